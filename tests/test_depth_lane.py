"""The depth lane: the network's jobs in their own thread, the newest finished map taken by each window."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from labrig.pipeline import depth_sources, run_setup, runtime
from labrig.pipeline.depth_lane import DepthLane
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
            assert any(np.array_equal(r.depth_mm, maps[t1]) for t1 in range(r.t1_us, 0, -1_000)[:40])
    assert pipe.lane is not None and pipe.lane.finished >= 50
    assert min(r.net_force_n[2] for r in results) < -1.0
