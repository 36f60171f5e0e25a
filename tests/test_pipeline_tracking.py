"""Marker trackers on a simulated recording, against the sim's true marker positions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.indenters import Indenter
from labrig.pipeline.tracking import (
    EvetacParams,
    EvetacTracker,
    Tracker,
    TrackerParams,
    grid_neighbours,
    marker_diameter_px,
    rest_positions_px,
)
from labrig.recording import Recording
from labrig.sim.live import record_live
from labrig.sim.motion import probing_path

WINDOW_US = 10_000
LOST_PX = 15.0  # the paper's metric: start-end drift above this is a lost track


@pytest.fixture(scope="module")
def probe_recording(tmp_path_factory: pytest.TempPathFactory, rig: RigConfig, sphere: Indenter) -> Path:
    path = probing_path(rig, sphere, depth_mm=1.0, shear_mm=0.5, normal_speed_mm_s=3.0, shear_speed_mm_s=3.0, wait_s=0.1)
    out = tmp_path_factory.mktemp("pipeline") / "probe.h5"
    record_live(out, rig, sphere, path, seed=5, realtime=False)
    return out


def track(recording: Path, tracker: Tracker | EvetacTracker) -> tuple[np.ndarray, np.ndarray]:
    """Per-window tracking errors (windows, M) px against the truth at each window's end, and the final drift."""
    with Recording(recording) as rec:
        truth = rec.stream("truth/markers")
        t_truth, true_px = truth["t_host_us"], truth["position_px"].astype(np.float64)
        errors = []
        for t0 in range(0, rec.end_us() - WINDOW_US + 1, WINDOW_US):
            positions, _ = tracker.update(rec.events_between(t0, t0 + WINDOW_US))
            k = min(int(np.searchsorted(t_truth, t0 + WINDOW_US)), len(t_truth) - 1)
            errors.append(np.linalg.norm(positions - true_px[k], axis=1))
        drift = np.linalg.norm(positions - tracker.rest_px, axis=1)
    return np.array(errors), drift


def test_rest_positions_match_the_truth_at_rest(rig: RigConfig, probe_recording: Path) -> None:
    with Recording(probe_recording) as rec:
        first = rec.column("truth/markers", "position_px", 0, 1)[0]
    assert np.abs(rest_positions_px(rig) - first).max() < 0.05
    assert 12 < marker_diameter_px(rig) < 16


def test_paper_tracker_follows_the_markers(rig: RigConfig, probe_recording: Path) -> None:
    tracker = Tracker(rest_positions_px(rig), TrackerParams(marker_diameter_px=marker_diameter_px(rig)))
    errors, drift = track(probe_recording, tracker)
    median, p95 = np.median(errors), np.percentile(errors, 95)
    print(f"paper tracker: median {median:.2f} px, p95 {p95:.2f} px, max {errors.max():.1f} px, "
          f"lost {(drift > LOST_PX).sum()}, end drift max {drift.max():.2f} px")
    assert median < 1.0 and p95 < 3.5  # the paper's localisation error, 2.47 px, for scale
    assert (drift > LOST_PX).sum() == 0 and drift.max() < 6.0


def test_plain_paper_tracker_is_worse_without_the_gates(rig: RigConfig, probe_recording: Path) -> None:
    plain = TrackerParams(marker_diameter_px=marker_diameter_px(rig), gate_diameters=None, min_each_polarity=0)
    errors, _ = track(probe_recording, Tracker(rest_positions_px(rig), plain))
    gated, _ = track(probe_recording, Tracker(rest_positions_px(rig), TrackerParams(marker_diameter_px=plain.marker_diameter_px)))
    assert np.percentile(errors, 95) > np.percentile(gated, 95)


def test_evetac_baseline_follows_the_markers(rig: RigConfig, probe_recording: Path) -> None:
    tracker = EvetacTracker(rest_positions_px(rig), EvetacParams(marker_diameter_px=marker_diameter_px(rig)))
    errors, drift = track(probe_recording, tracker)
    print(f"evetac baseline: median {np.median(errors):.2f} px, p95 {np.percentile(errors, 95):.2f} px, "
          f"lost {(drift > LOST_PX).sum()}")
    assert np.median(errors) < 1.0 and np.percentile(errors, 95) < 5.0
    assert (drift > LOST_PX).sum() == 0


def test_tracker_ignores_sparse_noise_and_follows_a_translated_grid(rig: RigConfig) -> None:
    rest = rest_positions_px(rig)
    tracker = Tracker(rest, TrackerParams(marker_diameter_px=14.0))
    rng = np.random.default_rng(0)
    noise = np.zeros(300, dtype=[("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("t", "<i8")])
    noise["x"], noise["y"] = rng.integers(0, 1280, 300), rng.integers(0, 720, 300)
    noise["p"] = rng.integers(0, 2, 300)
    positions, updated = tracker.update(noise)
    assert not updated.any() and np.array_equal(positions, rest)
    # Every dot moves +1.5 px in x: ON events on its leading rim, OFF on its trailing rim.
    angles = np.linspace(-np.pi / 2, np.pi / 2, 12)
    shift = np.array([1.5, 0.0])
    ev = []
    for centre in rest:
        for sign, pol in ((1, 1), (-1, 0)):
            xy = centre + 0.5 * shift + np.stack([sign * 7 * np.cos(angles), 7 * np.sin(angles)], 1)
            ev.append([(x, y, pol) for x, y in np.rint(xy)])
    arr = np.concatenate([np.array(e) for e in ev])
    events = np.zeros(len(arr), dtype=noise.dtype)
    events["x"], events["y"], events["p"] = arr[:, 0], arr[:, 1], arr[:, 2]
    positions, updated = tracker.update(events)
    assert updated.all()
    assert np.abs(positions - (rest + 0.5 * shift)).max() < 0.6


def test_grid_neighbours_and_parameter_checks(rig: RigConfig) -> None:
    n4 = grid_neighbours(12, 13, 4)
    assert (n4[0] >= 0).sum() == 2 and (n4[13 + 1] >= 0).sum() == 4
    assert (grid_neighbours(12, 13, 8)[13 + 1] >= 0).sum() == 8
    with pytest.raises(ValueError):
        Tracker(np.zeros((10, 2)))
    with pytest.raises(ValueError):
        grid_neighbours(3, 3, 6)
