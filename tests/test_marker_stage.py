"""The markers' front stage: one tracker-and-rest loop for the runtime, the training's tracks and the tracker evaluation."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from labrig.pipeline import depth_sources, run_setup, runtime, tracking
from labrig.pipeline.marker_stage import MarkerStage
from labrig.pipeline.rest import RestParams
from labrig.pipeline.windows import recording_windows
from labrig.recording import Recording

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def press(sphere_press: Path) -> Path:
    return sphere_press


def test_the_runtime_and_the_training_tracks_see_the_same_markers(press: Path, tmp_path: Path) -> None:
    """The runtime's tracked positions, window by window, are the training's cached tracks, and its rest is theirs."""
    from labrig.training.state_data import track_recording

    tracks = track_recording(press, calibration_dir=None, cache_root=tmp_path)
    with Recording(press) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=None)
        pipe = runtime.Pipeline(setup, depth_sources.depth_source("truth", setup, rec), cache_dir=tmp_path)
        results = list(pipe.run(rec, window_us=10_000, concurrent=False))
    assert len(results) == len(tracks.t_us) > 50
    np.testing.assert_array_equal([r.t1_us for r in results], tracks.t_us)
    np.testing.assert_array_equal(np.stack([r.positions_px for r in results]), tracks.positions_px)
    np.testing.assert_array_equal(pipe.markers.rest_px, tracks.rest_px)
    moved = np.linalg.norm(tracks.positions_px - tracks.rest_px, axis=2).max()
    assert moved > 1.0  # the press moved the markers: the comparison is not of still markers


def test_the_stage_feeds_the_rest_refinement_until_it_freezes(press: Path) -> None:
    with Recording(press) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=None)
        stage = MarkerStage.for_setup(setup, rest_params=RestParams(windows=5))
        alone = tracking.Tracker(setup.rest_px, stage.tracker.params, observed=setup.observed)
        held = MarkerStage(tracking.Tracker(setup.rest_px, stage.tracker.params, observed=setup.observed))
        for k, (t0, t1, events) in enumerate(recording_windows(rec, window_us=10_000)):
            stage.update(events, t0, t1)
            q, _ = held.update(events, t0, t1)
            np.testing.assert_array_equal(q, alone.update(events, t1)[0])  # no refinement: the tracker alone
            if k == 10:
                break
    assert stage.rest is not None and stage.rest.frozen and stage.rest.summary().windows == 5
    assert stage.tracker.rest_px is stage.rest.rest_px and held.rest_px is held.tracker.rest_px
    assert not np.array_equal(stage.rest_px, setup.rest_px)  # the quiet start's average, not the calibration's


def test_no_other_module_runs_its_own_tracker_and_rest_loop() -> None:
    """Only the markers' stage builds a rest refinement; the trackers' own modules define them."""
    builders = []
    for path in sorted((ROOT / "labrig").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", None)) == "RestRefiner":
                builders.append(path.relative_to(ROOT).as_posix())
    assert builders == ["labrig/pipeline/marker_stage.py"]
