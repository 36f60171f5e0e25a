"""The depth lanes: the network's jobs in their own thread, or in steps in the windows' thread, the newest finished
map taken by each window."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from labrig.pipeline import depth_sources, run_setup, runtime
from labrig.pipeline.depth_lane import DepthLane, SteppedLane, one_step
from labrig.recording import Recording


def _wait_for(lane: DepthLane, timeout_s: float = 5.0) -> tuple[np.ndarray, int]:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        done = lane.poll()
        if done is not None:
            return done
        time.sleep(0.001)
    raise AssertionError("no map from the lane")


def test_a_newer_job_replaces_one_still_waiting_and_maps_come_back_with_their_window() -> None:
    release = threading.Event()
    ran: list[int] = []

    def job(k: int):  # type: ignore[no-untyped-def]
        def run() -> np.ndarray:
            if k == 0:
                release.wait(5)
            ran.append(k)
            return np.full((2, 2), k, np.float32)
        return run

    with DepthLane() as lane:
        lane.submit(job(0), 10)
        time.sleep(0.05)  # job 0 is running
        lane.submit(job(1), 20)
        lane.submit(job(2), 30)  # replaces job 1, which never started
        assert lane.poll() is None
        release.set()
        first = _wait_for(lane)
        later = first if first[1] == 30 else _wait_for(lane)
    assert ran == [0, 2] and lane.replaced == 1 and lane.finished == 2
    assert later[1] == 30 and np.all(later[0] == 2)


def test_a_failing_job_is_raised_in_the_caller() -> None:
    def boom() -> np.ndarray:
        raise ValueError("network failed")

    with DepthLane() as lane:
        lane.submit(boom, 10)
        with pytest.raises(ValueError, match="network failed"):
            end = time.monotonic() + 5
            while time.monotonic() < end:
                lane.poll()
                time.sleep(0.001)


class _SlowTruth(depth_sources.TruthDepth):
    """The recording's truth, taking 3 ms a map in the job (as a network would)."""

    def depth_job(self, sae_grid, t0_us, t1_us, n_events):  # type: ignore[no-untyped-def]
        depth = self.depth_mm(sae_grid, t0_us, t1_us, n_events)

        def run() -> np.ndarray:
            time.sleep(0.003)
            return depth
        return run


def test_a_pipeline_with_a_depth_lane_uses_the_newest_finished_map(sphere_press: Path) -> None:
    """1 ms windows, depth every 10 ms in the lane: every window's map is one the source made for an earlier or the
    same due window (flat before the first), and the forces follow the press."""
    with Recording(sphere_press) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=None)
        source = _SlowTruth(rec)
        pipe = runtime.Pipeline(setup, source, depth_every_us=10_000, depth_lane=True)
        results = list(pipe.run(rec, window_us=1_000, concurrent=False, end_us=600_000))
        pipe.close()
        maps = {t1: source.depth_mm(None, 0, t1, 0) for t1 in range(1_000, 601_000, 1_000)}
    assert not results[0].depth_mm.any()
    for r in results[1:]:
        if r.depth_mm.any():
            assert any(np.array_equal(r.depth_mm, maps[t1]) for t1 in range(r.t1_us, 0, -1_000))
    # how far behind depends on the windows' pace against the job's 3 ms: offline they run faster than real time
    assert pipe.lane is not None and pipe.lane.finished >= 10
    assert min(r.net_force_n[2] for r in results) < -1.0


def _counted(k: int, steps: int, log: list[tuple[int, int]]):  # type: ignore[no-untyped-def]
    for step in range(steps):
        log.append((k, step))
        if step < steps - 1:
            yield
    return np.full((2, 2), k, np.float32)


def test_a_stepped_lane_runs_one_step_per_call_and_a_newer_job_replaces_one_waiting() -> None:
    lane: SteppedLane[np.ndarray] = SteppedLane()
    log: list[tuple[int, int]] = []
    lane.step()  # nothing to run
    lane.submit(_counted(0, 3, log), 10)
    lane.step()
    lane.submit(_counted(1, 3, log), 20)  # waits: job 0 runs
    lane.submit(_counted(2, 2, log), 30)  # replaces job 1 before it started
    assert lane.poll() is None
    lane.step()
    lane.step()
    done = lane.poll()
    assert done is not None and done[1] == 10 and done[0][0, 0] == 0
    lane.step()
    lane.step()
    assert lane.poll()[1] == 30  # type: ignore[index]
    assert log == [(0, 0), (0, 1), (0, 2), (2, 0), (2, 1)]
    assert (lane.submitted, lane.replaced, lane.finished, lane.steps) == (3, 1, 2, 5)
    lane.submit(one_step(lambda: np.zeros((2, 2), np.float32)), 40)
    lane.step()
    assert lane.poll()[1] == 40  # type: ignore[index]


def test_a_failing_step_is_raised_and_the_lane_goes_on() -> None:
    def failing():  # type: ignore[no-untyped-def]
        yield
        raise RuntimeError("network failed")

    lane: SteppedLane[np.ndarray] = SteppedLane()
    lane.submit(failing(), 10)
    lane.step()
    with pytest.raises(RuntimeError, match="network failed"):
        lane.step()
    lane.submit(one_step(lambda: np.ones((2, 2), np.float32)), 20)
    lane.step()
    assert lane.poll()[1] == 20  # type: ignore[index]


def test_a_pipeline_with_the_network_in_steps_gives_the_serial_maps_three_windows_later(sphere_press: Path) -> None:
    """1 ms windows, depth every 10 ms, the bundled network cut in three parts: each window runs one part, the map's
    work in the fourth, so every map is the one the serial pipeline made three windows before (the same parts, the
    same output), and the forces follow the press."""
    from labrig.models import bundled_model_path

    with Recording(sphere_press) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=None)
        runs = []
        for parts in (None, 3):
            source = depth_sources.depth_source("model", setup, rec, bundled_model_path(), threads=1)
            pipe = runtime.Pipeline(setup, source, depth_every_us=10_000, depth_parts=parts)
            runs.append(list(pipe.run(rec, window_us=1_000, concurrent=False, end_us=600_000)))
            pipe.close()
    serial, stepped = runs
    assert pipe.stepped is not None and pipe.stepped.finished == 60
    assert not any(r.depth_mm.any() for r in stepped[:3])
    for k in range(3, len(stepped)):
        assert np.array_equal(stepped[k].depth_mm, serial[k - 3].depth_mm)
    assert sum(r.depth_mm.any() for r in serial) > 100
    assert min(r.net_force_n[2] for r in stepped) < -1.0


def test_depth_parts_are_checked(sphere_press: Path) -> None:
    with Recording(sphere_press) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=None)
        source = depth_sources.TruthDepth(rec)
        with pytest.raises(ValueError, match="exclude each other"):
            runtime.Pipeline(setup, source, depth_lane=True, depth_parts=2)
        with pytest.raises(ValueError, match="at least 1"):
            runtime.Pipeline(setup, source, depth_parts=0)
