"""Marker trackers on a simulated recording, against the sim's true marker positions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.indenters import Indenter
from labrig.pipeline.evetac import EvetacParams, EvetacTracker
from labrig.pipeline.tracking import (
    CircleFitParams,
    CircleFitTracker,
    Tracker,
    TrackerParams,
    grid_neighbours,
    marker_diameter_px,
)
from labrig.recording import Recording
from labrig.sim.live import record_live
from labrig.sim.motion import probing_path
from labrig.sim.truth_config import true_camera


def true_rest_px(rig: RigConfig) -> np.ndarray:
    """The markers' rest pixels through the virtual rig's true camera."""
    return true_camera(rig).project(rig.markers.rest_positions_mm())


def true_diameter_px(rig: RigConfig) -> float:
    """The markers' image diameter through the virtual rig's true camera."""
    return marker_diameter_px(rig, true_camera(rig))


WINDOW_US = 10_000
LOST_PX = 15.0  # the paper's metric: start-end drift above this is a lost track


@pytest.fixture(scope="module")
def probe_recording(tmp_path_factory: pytest.TempPathFactory, rig: RigConfig, sphere: Indenter) -> Path:
    path = probing_path(rig, sphere, depth_mm=1.0, shear_mm=0.5, normal_speed_mm_s=3.0, shear_speed_mm_s=3.0, wait_s=0.1)
    out = tmp_path_factory.mktemp("pipeline") / "probe.h5"
    record_live(out, rig, sphere, path, seed=5, realtime=False)
    return out


def track(recording: Path, tracker: Tracker | CircleFitTracker | EvetacTracker) -> tuple[np.ndarray, np.ndarray]:
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
    assert np.abs(true_rest_px(rig) - first).max() < 0.05
    assert 12 < true_diameter_px(rig) < 16


def test_paper_tracker_follows_the_markers(rig: RigConfig, probe_recording: Path) -> None:
    tracker = Tracker(true_rest_px(rig), TrackerParams(marker_diameter_px=true_diameter_px(rig)))
    errors, drift = track(probe_recording, tracker)
    median, p95 = np.median(errors), np.percentile(errors, 95)
    print(f"paper tracker: median {median:.2f} px, p95 {p95:.2f} px, max {errors.max():.1f} px, "
          f"lost {(drift > LOST_PX).sum()}, end drift max {drift.max():.2f} px")
    assert median < 1.0 and p95 < 3.5  # the paper's localisation error, 2.47 px, for scale
    assert (drift > LOST_PX).sum() == 0 and drift.max() < 6.0


def test_plain_paper_tracker_is_worse_without_the_gates(rig: RigConfig, probe_recording: Path) -> None:
    plain = TrackerParams(marker_diameter_px=true_diameter_px(rig), gate_diameters=None, min_each_polarity=0)
    errors, _ = track(probe_recording, Tracker(true_rest_px(rig), plain))
    gated, _ = track(probe_recording, Tracker(true_rest_px(rig), TrackerParams(marker_diameter_px=plain.marker_diameter_px)))
    assert np.percentile(errors, 95) > np.percentile(gated, 95)


def test_circle_fit_baseline_follows_the_markers(rig: RigConfig, probe_recording: Path) -> None:
    tracker = CircleFitTracker(true_rest_px(rig), CircleFitParams(marker_diameter_px=true_diameter_px(rig)))
    errors, drift = track(probe_recording, tracker)
    print(f"circle-fit baseline: median {np.median(errors):.2f} px, p95 {np.percentile(errors, 95):.2f} px, "
          f"lost {(drift > LOST_PX).sum()}")
    assert np.median(errors) < 1.0 and np.percentile(errors, 95) < 5.0
    assert (drift > LOST_PX).sum() == 0


def test_evetac_published_tracker_follows_the_markers(rig: RigConfig, probe_recording: Path) -> None:
    tracker = EvetacTracker(true_rest_px(rig), EvetacParams(marker_diameter_px=true_diameter_px(rig)))
    errors, drift = track(probe_recording, tracker)
    print(f"evetac (published): median {np.median(errors):.2f} px, p95 {np.percentile(errors, 95):.2f} px, "
          f"max {errors.max():.1f} px, lost {(drift > LOST_PX).sum()}")
    assert np.median(errors) < 0.5 and np.percentile(errors, 95) < 2.0 and errors.max() < 8.0
    assert (drift > LOST_PX).sum() == 0
    unsprung = EvetacTracker(true_rest_px(rig), EvetacParams(marker_diameter_px=true_diameter_px(rig), springs=False))
    assert track(probe_recording, unsprung)[0].max() > errors.max()  # the springs hold dots the events lose


def test_tracker_ignores_sparse_noise_and_follows_a_translated_grid(rig: RigConfig) -> None:
    rest = true_rest_px(rig)
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


def test_the_polarity_guard_keeps_a_dot_from_a_band_of_slope_shading(rig: RigConfig) -> None:
    """Every dot moves +1.5 px in y (ON on its leading rim, OFF on its trailing one) while a pressing
    edge's slope shading brightens a band 11-14 px below the dots of one row (under the edge): many ON
    events and no OFF. Without the guard their ON centroid follows the band; with it, only as many ON
    events count as OFF ones, the nearest the dot."""
    rest = true_rest_px(rig)
    angles = np.linspace(0.0, np.pi, 12)
    shift = np.array([0.0, 1.5])
    rows = []
    for k, centre in enumerate(rest):
        c = centre + 0.5 * shift
        rows += [(x, y, 1) for x, y in np.rint(c + np.stack([7 * np.cos(angles), 7 * np.sin(angles)], 1))]
        rows += [(x, y, 0) for x, y in np.rint(c + np.stack([7 * np.cos(angles), -7 * np.sin(angles)], 1))]
        if k // rig.markers.cols == 6:
            rows += [(x, y, 1) for x in np.arange(c[0] - 10, c[0] + 11) for y in np.rint(c[1] - np.array([11, 12, 13, 14]))]
    arr = np.array(rows)
    events = np.zeros(len(arr), dtype=[("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("t", "<i8")])
    events["x"], events["y"], events["p"] = arr[:, 0], arr[:, 1], arr[:, 2]
    errors = {}
    for guard in (2.0, None):
        tracker = Tracker(rest, TrackerParams(marker_diameter_px=14.0, refine_lambda=0.0, polarity_guard=guard))
        positions, updated = tracker.update(events)
        assert updated.all()
        errors[guard] = np.abs(positions - (rest + 0.5 * shift)).max()
    assert errors[2.0] < 0.6 < 3.0 < errors[None]


def test_grid_neighbours_and_parameter_checks(rig: RigConfig) -> None:
    n4 = grid_neighbours(12, 13, 4)
    assert (n4[0] >= 0).sum() == 2 and (n4[13 + 1] >= 0).sum() == 4
    assert (grid_neighbours(12, 13, 8)[13 + 1] >= 0).sum() == 8
    with pytest.raises(ValueError):
        Tracker(np.zeros((10, 2)))
    with pytest.raises(ValueError):
        grid_neighbours(3, 3, 6)


def _with_noise(events: np.ndarray, rig: RigConfig, t0_us: int, rate_hz: float, rng: np.random.Generator) -> np.ndarray:
    from labrig.training.data import background_noise

    noise = background_noise(rig.roi, t0_us, t0_us + WINDOW_US, rate_hz, rng).astype(events.dtype)
    return np.sort(np.concatenate([events, noise]), order="t")


def test_background_subtraction_keeps_the_gated_tracker_on_its_markers_in_noise(rig: RigConfig,
                                                                               probe_recording: Path) -> None:
    """At 2 Hz per pixel (6 noise events per polarity in a gate per 10 ms) the noise alone passes the
    event minimums: without subtraction the tracks random-walk and lag; with it they follow. (The flood test, off
    here to show the subtraction alone, also keeps a dot whose gate holds only noise still: with both, below.)"""
    base = TrackerParams(marker_diameter_px=true_diameter_px(rig), flood_ratio=None)
    results = {}
    for subtract, flood in ((True, None), (False, None), (True, TrackerParams().flood_ratio)):
        params = {**base.__dict__, "noise_subtraction": subtract, "flood_ratio": flood}
        tracker = Tracker(true_rest_px(rig), TrackerParams(**params))
        rng = np.random.default_rng(11)
        with Recording(probe_recording) as rec:
            truth = rec.stream("truth/markers")
            errors = []
            for t0 in range(0, rec.end_us() - WINDOW_US + 1, WINDOW_US):
                positions, _ = tracker.update(_with_noise(rec.events_between(t0, t0 + WINDOW_US), rig, t0, 2.0, rng))
                k = min(int(np.searchsorted(truth["t_host_us"], t0 + WINDOW_US)), len(truth) - 1)
                errors.append(np.linalg.norm(positions - truth["position_px"][k], axis=1))
        results[subtract, flood] = np.array(errors)
    subtracted, plain, both = results.values()
    assert np.percentile(subtracted, 95) < 0.6 * np.percentile(plain, 95)
    assert np.percentile(subtracted, 95) < 4.0  # 8.1 px without
    assert (subtracted[-1] < LOST_PX).all()  # no track lost at the end
    assert np.percentile(both, 95) < 4.0 and (both[-1] < LOST_PX).all()


def test_subtract_background_recovers_the_signal_centroid() -> None:
    from labrig.pipeline.tracking import subtract_background

    gate2 = 14.0**2
    centre = np.array([[100.0, 100.0], [300.0, 100.0], [500.0, 100.0]])
    patches = np.array([[c[0] - 21, c[0] + 21, c[1] - 21, c[1] + 21] for c in centre], np.int64)
    rho = 0.02  # noise events per px per polarity: 12.3 in a gate, 23 in the ring outside it
    ring = 42 * 42 - np.pi * gate2
    outside = np.full((3, 2), rho * ring)
    expected = rho * np.pi * gate2
    sums = np.zeros((3, 2, 3))
    sums[:, :, 0] = expected + 20.0  # 20 signal events per polarity at (x + 5, y - 3) on top of the noise
    sums[:, :, 1] = expected * centre[:, None, 0] + 20.0 * (centre[:, None, 0] + 5.0)
    sums[:, :, 2] = expected * centre[:, None, 1] + 20.0 * (centre[:, None, 1] - 3.0)
    sums[2, 1, :] = [expected + 5.0, (expected + 5.0) * 500.0, (expected + 5.0) * 100.0]  # 5 events: under 3 sigma
    subtract_background(sums, outside, patches, gate2, centre)
    np.testing.assert_allclose(sums[:2, :, 1] / sums[:2, :, 0], np.repeat(centre[:2, 0:1] + 5.0, 2, axis=1))
    np.testing.assert_allclose(sums[:2, :, 2] / sums[:2, :, 0], np.repeat(centre[:2, 1:2] - 3.0, 2, axis=1))
    assert np.all(sums[2, 1] == 0.0) and sums[2, 0, 0] == pytest.approx(20.0)


def _ring_events(centres: np.ndarray, t_us: np.ndarray, direction: np.ndarray, radius: float = 7.0) -> np.ndarray:
    """A dot's rim events as it moves along ``direction``: at each time ``t_us`` (per dot, (M, K)) one ON event
    on the leading half of the rim and one OFF on the trailing half, around ``centres`` (M, K, 2) px."""
    m, k = t_us.shape
    angle = np.arctan2(direction[1], direction[0]) + np.linspace(-np.pi / 2, np.pi / 2, k)
    rim = radius * np.stack([np.cos(angle), np.sin(angle)], -1)  # (K, 2) the leading half
    lead, trail = np.rint(centres + rim), np.rint(centres - rim)
    events = np.zeros(2 * m * k, dtype=[("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("t", "<i8")])
    events["x"] = np.r_[lead[..., 0].ravel(), trail[..., 0].ravel()]
    events["y"] = np.r_[lead[..., 1].ravel(), trail[..., 1].ravel()]
    events["p"] = np.r_[np.ones(m * k), np.zeros(m * k)]
    events["t"] = np.r_[t_us.ravel(), t_us.ravel()]
    return np.sort(events, order="t")


def test_the_lag_correction_reports_a_moving_dot_at_the_windows_end(rig: RigConfig) -> None:
    """Every dot moves at 0.1 px/ms (3.6 mm/s on the default rig) for six 20 ms windows. A window's
    centroid is where the dot was at its events' mean time, 1 px behind its end; the correction moves
    it on by the velocity of the last two centroids."""
    rest = true_rest_px(rig)
    velocity = np.array([0.0, 1e-4])  # px / us
    rng = np.random.default_rng(0)
    errors: dict[float | None, float] = {}
    for noise in (1.0, None):
        tracker = Tracker(rest, TrackerParams(marker_diameter_px=14.0, lag_noise_px=noise))
        for w in range(6):
            t0, t1 = 20_000 * w, 20_000 * (w + 1)
            times = np.sort(rng.integers(t0, t1, (len(rest), 16)), axis=1)
            events = _ring_events(rest[:, None, :] + times[..., None] * velocity, times, velocity)
            positions, _ = tracker.update(events, t1)
        errors[noise] = float(np.median(np.linalg.norm(positions - (rest + t1 * velocity), axis=1)))
    assert errors[None] > 0.8  # half a window behind
    assert errors[1.0] < 0.3


def test_a_still_dot_is_not_moved_by_the_lag_correction(rig: RigConfig) -> None:
    """The dots stay put while their rims flicker with 0.3 px of jitter: the velocity of two noisy centroids
    is shrunk away (without the shrinkage the extrapolation would add half the jitter again)."""
    rest = true_rest_px(rig)
    errors: dict[float | None, float] = {}
    for noise in (1.0, 0.01, None):
        rng = np.random.default_rng(1)
        tracker = Tracker(rest, TrackerParams(marker_diameter_px=14.0, lag_noise_px=noise))
        error = []
        for w in range(20):
            t0, t1 = 20_000 * w, 20_000 * (w + 1)
            times = np.sort(rng.integers(t0, t1, (len(rest), 16)), axis=1)
            centres = np.broadcast_to(rest[:, None, :] + rng.normal(0.0, 0.3, (len(rest), 1, 2)), (len(rest), 16, 2))
            positions, _ = tracker.update(_ring_events(centres, times, np.array([1.0, 0.0])), t1)
            error.append(np.linalg.norm(positions - rest, axis=1))
        errors[noise] = float(np.mean(error))
    assert errors[1.0] < 1.05 * errors[None]
    assert errors[0.01] > 1.2 * errors[None]


def test_a_dot_under_one_polarity_shading_follows_its_neighbours(rig: RigConfig) -> None:
    """Every dot moves +1.5 px in y; one dot in the middle is covered by a pressing edge's slope shading,
    300 ON events across its middle and its own rim's (12 ON, 12 OFF). The polarity guard keeps the 12
    ON events nearest the centre, which are the shading's: the dot is dragged down. A gate this lopsided
    cannot place its dot, so it takes its neighbours' displacement."""
    rest = true_rest_px(rig)
    shift = np.array([0.0, 1.5])
    angles = np.linspace(0.0, np.pi, 12)
    shaded = 6 * rig.markers.cols + 6
    rows = []
    for k, centre in enumerate(rest):
        c = centre + 0.5 * shift
        rows += [(x, y, 1) for x, y in np.rint(c + np.stack([7 * np.cos(angles), 7 * np.sin(angles)], 1))]
        rows += [(x, y, 0) for x, y in np.rint(c + np.stack([7 * np.cos(angles), -7 * np.sin(angles)], 1))]
        if k == shaded:
            rows += [(x, y, 1) for x in np.arange(c[0] - 7, c[0] + 8) for y in np.rint(c[1] + np.arange(-1, 4))] * 4
    arr = np.array(rows)
    events = np.zeros(len(arr), dtype=[("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("t", "<i8")])
    events["x"], events["y"], events["p"] = arr[:, 0], arr[:, 1], arr[:, 2]
    errors = {}
    for ratio in (10.0, None):
        params = TrackerParams(marker_diameter_px=14.0, refine_lambda=0.0, lopsided_ratio=ratio, lag_noise_px=None)
        positions, updated = Tracker(rest, params).update(events)
        errors[ratio] = float(np.linalg.norm(positions[shaded] - (rest[shaded] + 0.5 * shift)))
        assert updated[shaded] == (ratio is None)
    assert errors[10.0] < 0.2 < 1.5 < errors[None]


def test_a_still_dot_swept_by_a_translating_edge_stays(rig: RigConfig) -> None:
    """A sliding flat punch's rim crosses a dot that stands still: a band of ON events ahead of the edge and OFF
    behind it, across the whole patch, and none of the dot's own. Both polarities alike, so neither the guard nor the
    lopsided test sees it, and the gate follows the band; the patch around the gate holds the band's events about as
    densely as the gate, which a dot's own events never do, so the dot takes its neighbours' moves (none: it stays)."""
    rest = true_rest_px(rig)
    swept = 6 * rig.markers.cols + 6
    c = rest[swept]
    ys = np.arange(c[1] - 20, c[1] + 21)
    rows = [(x, y, 1) for x in (c[0] + 5, c[0] + 6) for y in ys] + [(x, y, 0) for x in (c[0] + 3, c[0] + 4) for y in ys]
    arr = np.rint(np.array(rows * 2))
    events = np.zeros(len(arr), dtype=[("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("t", "<i8")])
    events["x"], events["y"], events["p"] = arr[:, 0], arr[:, 1], arr[:, 2]
    errors = {}
    for ratio in (0.3, None):
        params = TrackerParams(marker_diameter_px=14.0, flood_ratio=ratio, lag_noise_px=None)
        positions, updated = Tracker(rest, params).update(events)
        errors[ratio] = float(np.linalg.norm(positions[swept] - c))
        assert updated[swept] == (ratio is None)
    assert errors[0.3] < 0.1 and errors[None] > 2.0, errors
