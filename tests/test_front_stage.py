"""The front stage: SAE, signed counts and markers per window; a skipped window's events still count."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labrig.pipeline import brightness, run_setup, sae
from labrig.pipeline.front_stage import FrontStage
from labrig.pipeline.marker_stage import MarkerStage
from labrig.pipeline.windows import recording_windows
from labrig.recording import Recording


def _stage(setup: run_setup.PipelineSetup) -> FrontStage:
    return FrontStage(setup, MarkerStage.for_setup(setup), depth_window_us=10_000, needs_sae=True, needs_counts=True)


def test_a_skipped_window_is_tracked_and_counted_into_the_next(sphere_press: Path) -> None:
    """Skipping the back stage of every other 5 ms window during the press leaves the markers, the
    next window's SAE and the counts summed over the windows handed on exactly as with none skipped."""
    with Recording(sphere_press) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=None)
        windows = list(recording_windows(rec, window_us=5_000))
    every, skipping = _stage(setup), _stage(setup)
    total_every = np.zeros((90, 112), np.float32)
    total_skipping = np.zeros((90, 112), np.float32)
    handed = 0
    for k, (t0, t1, events) in enumerate(windows):
        a = every.window(t0, t1, events)
        assert a.counts is not None
        total_every += a.counts
        if k % 2 and k < len(windows) - 1:
            skipping.skip(t0, t1, events)
            continue
        b = skipping.window(t0, t1, events)
        assert b.counts is not None and b.sae is not None and a.sae is not None
        total_skipping += b.counts
        handed += 1
        np.testing.assert_array_equal(b.positions_px, a.positions_px)
        np.testing.assert_array_equal(b.sae, a.sae)  # the span reaches back into the skipped window's events
        np.testing.assert_allclose(total_skipping, total_every, atol=1e-3)
    assert handed < len(windows) and np.abs(total_every).sum() > 1000  # the press moved the brightness
    moved = np.linalg.norm(every.markers.tracker.positions_px - setup.rest_px, axis=1).max()
    assert moved > 0.3


def test_the_counts_and_the_sae_are_the_pipeline_functions(sphere_press: Path) -> None:
    with Recording(sphere_press) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=None)
        t0, t1, events = list(recording_windows(rec, window_us=10_000))[40]
    tracked = _stage(setup).window(t0, t1, events)
    np.testing.assert_array_equal(tracked.counts, brightness.signed_counts(events, setup.rig.roi))
    np.testing.assert_array_equal(tracked.sae, sae.sae_grid(events, t1 - 10_000, t1, setup.rig.roi))
