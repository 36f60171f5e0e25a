"""The tracking evaluation (Table I and the true error) on short virtual-rig recordings, through run_tasks.

Three shallow sphere presses (about 1 s each, different places, depths and shear directions),
tracked in 10 ms windows. Also: the same results from in-process, process-pool and Dask runs.
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.errors import LabrigError
from labrig.evaluation.tracking import (
    LOST_PX,
    TrackingResult,
    TrackingTask,
    table_lost_tracks,
    table_tasks,
    track_recording,
    truth_at,
    truth_errors,
)
from labrig.executor import run_tasks
from labrig.indenters import Indenter
from labrig.sim.live import record_live
from labrig.sim.motion import probing_path

PRESSES = (  # location (mm), depth (mm), shear (mm), shear direction (deg)
    ((0.0, 0.0), 0.8, 0.4, 0.0),
    ((3.0, -2.0), 1.0, 0.5, 90.0),
    ((-3.0, 2.0), 0.6, 0.3, 225.0),
)
TIMING_KEYS = ("track_ms_median", "track_ms_p95")


@pytest.fixture(scope="session")
def presses(tmp_path_factory: pytest.TempPathFactory, rig: RigConfig, sphere: Indenter) -> list[str]:
    folder = tmp_path_factory.mktemp("tracking-eval")
    paths = []
    for k, (location, depth, shear, direction) in enumerate(PRESSES):
        tool = probing_path(rig, sphere, location_mm=location, depth_mm=depth, shear_mm=shear, shear_direction_deg=direction,
                            normal_speed_mm_s=4.0, shear_speed_mm_s=4.0, wait_s=0.05)
        path = folder / f"press{k}.h5"
        record_live(path, rig, sphere, tool, seed=k, realtime=False)
        paths.append(str(path))
    return paths


@pytest.fixture(scope="session")
def table_results(presses: list[str], tmp_path_factory: pytest.TempPathFactory) -> list[TrackingResult]:
    """1x and 3x patches, with and without refinement, for the bundled and the published tracker."""
    tasks = [t for kind in ("paper", "paper-published") for t in table_tasks(presses, patch_scales=(1.0, 3.0), tracker=kind)]
    results = run_tasks(track_recording, tasks, workers=1, cache_dir=tmp_path_factory.mktemp("cache"))
    return list(results)


def pick(results: list[TrackingResult], **settings: Any) -> list[TrackingResult]:
    chosen = [r for r in results if all(getattr(r, k) == v for k, v in settings.items())]
    assert chosen, settings
    return chosen


def without_timing(result: TrackingResult) -> dict[str, Any]:
    return {f.name: getattr(result, f.name) for f in fields(result) if f.name not in TIMING_KEYS}


def assert_same(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], np.ndarray):
            np.testing.assert_array_equal(a[k], b[k])
        else:
            assert a[k] == b[k], k


def test_default_tracker_loses_nothing_and_errs_little(table_results: list[TrackingResult]) -> None:
    for r in pick(table_results, tracker="paper", patch_scale=3.0, refine=True):
        print(f"{Path(r.recording).name}: lost {r.lost_tracks}, by truth {r.lost_by_truth}, error median "
              f"{r.error_median_px:.2f} p95 {r.error_p95_px:.2f} max {r.error_max_px:.1f} px, "
              f"drift max {r.drift_max_px:.1f} px, {r.track_ms_median:.2f} ms/window, {r.n_windows} windows")
        assert r.has_truth and r.n_markers == 156 and r.drift_px.shape == (156,)
        assert r.lost_tracks == 0 and r.lost_by_truth == 0
        assert r.error_median_px < 1.0 and r.error_p95_px < 3.5 and r.error_max_px < LOST_PX
        assert r.truth_end_offset_max_px < 0.5  # the sequences end at rest: the start-end proxy's premise
        assert r.t1_us.shape == r.window_error_p95_px.shape == (r.n_windows,)
        assert 80 <= r.n_windows <= 130 and 0 < r.track_ms_median < 5.0
        assert r.rest_source.endswith("extrinsics.toml")


def test_published_tracker_loses_tracks_in_plausible_numbers(table_results: list[TrackingResult]) -> None:
    lost = [r.lost_tracks for r in pick(table_results, tracker="paper-published", refine=False)]
    by_truth = [r.lost_by_truth for r in pick(table_results, tracker="paper-published", refine=False)]
    assert 0 < max(lost) < 60 and max(by_truth) < 100  # of 156 markers
    # A track that ends off its rest position was off the (resting) truth too: the truth sees every start-end
    # loss (1 px of slack for the calibrated rest positions), and also those that were lost and came back.
    for r in pick(table_results, tracker="paper-published"):
        assert np.all(r.error_max_per_marker_px[r.drift_px > LOST_PX + 1.0] > LOST_PX)
    assert sum(r.lost_by_truth for r in table_results) > sum(r.lost_tracks for r in table_results)


@pytest.mark.parametrize("tracker", ["paper", "paper-published"])
def test_refinement_is_never_worse_at_1x(table_results: list[TrackingResult], tracker: str) -> None:
    refined = pick(table_results, tracker=tracker, patch_scale=1.0, refine=True)
    plain = pick(table_results, tracker=tracker, patch_scale=1.0, refine=False)
    for a, b in zip(refined, plain):
        assert a.recording == b.recording
        assert a.lost_tracks <= b.lost_tracks and a.lost_by_truth <= b.lost_by_truth
    assert np.mean([a.error_p95_px for a in refined]) <= np.mean([b.error_p95_px for b in plain])


def test_a_1x_patch_errs_more_than_3x(table_results: list[TrackingResult]) -> None:
    for refine in (True, False):
        small = pick(table_results, tracker="paper", patch_scale=1.0, refine=refine)
        usual = pick(table_results, tracker="paper", patch_scale=3.0, refine=refine)
        for a, b in zip(small, usual):
            assert a.lost_tracks > b.lost_tracks or a.error_p95_px > 1.3 * b.error_p95_px


def test_table_rows(table_results: list[TrackingResult]) -> None:
    rows = table_lost_tracks([*table_results, None])  # a failed task is skipped
    assert len(rows) == 8
    for row in rows:
        print(f"{row['tracker']:16s} {'refined' if row['refine'] else 'plain  '} {row['patch_scale']:.0f}x: lost "
              f"{row['lost_mean']:.1f} +/- {row['lost_std']:.1f}, by truth {row['lost_by_truth_mean']:.1f} +/- "
              f"{row['lost_by_truth_std']:.1f}, p95 {row['error_p95_px_mean']:.2f} px, {row['track_ms_median']:.2f} ms")
    first = rows[0]
    assert (first["tracker"], first["refine"], first["patch_scale"], first["recordings"]) == ("paper", True, 1.0, 3)
    assert [r["refine"] for r in rows[:4]] == [True, True, False, False]
    lost = [r.lost_tracks for r in pick(table_results, tracker="paper-published", patch_scale=3.0, refine=False)]
    published = next(r for r in rows if (r["tracker"], r["refine"], r["patch_scale"]) == ("paper-published", False, 3.0))
    assert published["lost_mean"] == pytest.approx(np.mean(lost)) and published["lost_std"] == pytest.approx(np.std(lost))


def test_table_of_hand_made_results() -> None:
    def result(lost: int, by_truth: int | None, scale: float = 2.0) -> SimpleNamespace:
        return SimpleNamespace(tracker="paper", window_us=10_000, window_events=None, refine=False, patch_scale=scale,
                               lost_tracks=lost, has_truth=by_truth is not None, lost_by_truth=by_truth,
                               error_p95_px=2.0 if by_truth is not None else None, track_ms_median=0.1)

    rows = table_lost_tracks([result(2, 4), result(4, None), result(0, 0, scale=1.0)])
    assert [r["patch_scale"] for r in rows] == [1.0, 2.0]
    assert rows[1]["lost_mean"] == 3.0 and rows[1]["lost_std"] == 1.0 and rows[1]["lost_by_truth_mean"] == 4.0
    assert table_lost_tracks([result(1, None)])[0]["lost_by_truth_mean"] is None


def test_truth_helpers() -> None:
    t = np.array([0.0, 1000.0, 2000.0])
    truth = np.array([[[0.0, 0.0]], [[10.0, 0.0]], [[10.0, 20.0]]])
    np.testing.assert_allclose(truth_at(t, truth, np.array([-5.0, 500.0, 1500.0, 9000.0]))[:, 0],
                               [[0, 0], [5, 0], [10, 10], [10, 20]])
    track = np.zeros((2, 1, 2))
    errors = truth_errors(track, np.array([500.0, 2000.0]), (t, truth), LOST_PX)
    assert errors.error_max_px == pytest.approx(np.hypot(10, 20)) and errors.lost_by_truth == 1
    missing = truth_errors(track, np.array([500.0, 2000.0]), None, LOST_PX)
    assert missing.has_truth is False and missing.error_p95_px is None and missing.lost_by_truth is None


def test_truth_errors_leave_missing_markers_out_and_count_them() -> None:
    """A marker never printed has NaN truth: it is neither an error nor a lost track, only counted."""
    t = np.array([0.0, 1000.0])
    truth = np.array([[[0.0, 0.0], [np.nan, np.nan], [50.0, 0.0]], [[2.0, 0.0], [np.nan, np.nan], [50.0, 0.0]]])
    track = np.array([[[0.0, 0.0], [90.0, 90.0], [50.0, 3.0]]])  # the missing marker's estimate is far off: ignored
    errors = truth_errors(track, np.array([1000.0]), (t, truth), LOST_PX)
    assert errors.markers_missing == 1 and errors.lost_by_truth == 0
    assert errors.error_max_px == pytest.approx(3.0) and errors.error_median_px == pytest.approx(2.5)
    assert np.isnan(errors.error_max_per_marker_px[1]) and errors.error_max_per_marker_px[2] == pytest.approx(3.0)
    assert np.isfinite(errors.truth_end_offset_max_px) and errors.truth_end_offset_max_px == pytest.approx(2.0)
    with pytest.raises(LabrigError, match="no marker with a finite position"):
        truth_errors(track, np.array([1000.0]), (t, np.full_like(truth, np.nan)), LOST_PX)


def test_settings_are_checked(presses: list[str]) -> None:
    with pytest.raises(LabrigError, match="tracker must be one of"):
        track_recording(TrackingTask(presses[0], tracker="kalman"))
    with pytest.raises(LabrigError, match="rest must be one of"):
        track_recording({"recording": presses[0], "rest": "guess"})
    with pytest.raises(LabrigError, match="unknown tracking settings"):
        table_tasks(presses, window="10ms")


def test_other_settings_run(presses: list[str]) -> None:
    circle = track_recording(TrackingTask(presses[0], tracker="circle-fit", patch_scale=2.0))
    evetac = track_recording(TrackingTask(presses[0], tracker="evetac", patch_scale=2.0))
    counted = track_recording({"recording": presses[0], "window_us": None, "window_events": 20_000, "rest": "rig"})
    assert circle.lost_tracks == 0 and circle.error_p95_px < 5.0
    assert evetac.lost_tracks == 0 and evetac.lost_by_truth == 0 and evetac.error_p95_px < 3.0
    assert counted.window_events == 20_000 and 5 <= counted.n_windows <= 40 and counted.lost_tracks == 0
    assert counted.rest_source == "rig camera (the recording's rig)"


def test_pool_and_dask_agree_with_in_process(presses: list[str], tmp_path: Path) -> None:
    distributed = pytest.importorskip("dask.distributed")
    tasks = [TrackingTask(p, patch_scale=2.0, refine=k % 2 == 0) for k, p in enumerate(presses)]
    local = run_tasks(track_recording, tasks, workers=1, use_cache=False)
    pooled = run_tasks(track_recording, tasks, workers=2, use_cache=False)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None,
                                  local_directory=str(tmp_path / "dask")) as cluster:
        on_dask = run_tasks(track_recording, tasks, scheduler=cluster.scheduler_address, cache_dir=tmp_path)
        failing = run_tasks(track_recording, [TrackingTask(presses[0], tracker="kalman")], scheduler=cluster.scheduler_address,
                            use_cache=False, raise_on_error=False)
    for a, b, c in zip(local, pooled, on_dask):
        assert_same(without_timing(a), without_timing(b))
        assert_same(without_timing(a), without_timing(c))
    assert on_dask.misses == 3 and failing.failures[0].error == "LabrigError"
    assert run_tasks(track_recording, tasks, workers=2, cache_dir=tmp_path).hits == 3  # the Dask run filled the cache
