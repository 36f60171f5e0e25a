"""The run's animation (``labrig run --view``): which windows it shows, bounded memory, one palette, progress."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.errors import LabrigError
from labrig.pipeline import run_setup
from labrig.pipeline.runtime import WindowResult
from labrig.pipeline.view import MAX_VIEW_FRAMES, ViewFrames, write_view


def window(index: int, setup: run_setup.PipelineSetup, rng: np.random.Generator) -> WindowResult:
    m = len(setup.rest_px)
    forces = rng.normal(0.0, 0.1, (m, 3))
    return WindowResult(index, index * 10_000, (index + 1) * 10_000, 1000, setup.rest_px + rng.normal(0, 1, (m, 2)),
                        np.ones(m, bool), np.zeros((m, 3)), forces, forces.sum(0), np.zeros(2), np.zeros(2),
                        rng.random((90, 112)).astype(np.float32), rng.random((2, 90, 112)).astype(np.float32))


@pytest.fixture(scope="module")
def setup(rig: RigConfig) -> run_setup.PipelineSetup:
    return run_setup.setup_for_rig(rig, calibration_dir=None)


def test_the_view_keeps_the_probing_span_thinned_as_it_comes(setup: run_setup.PipelineSetup) -> None:
    rng = np.random.default_rng(0)
    shown = ViewFrames(span_us=(1_000_000, 9_000_000), every=1, max_frames=50)
    held = 0
    for i in range(2000):  # 20 s of 10 ms windows; the span holds 800 of them
        shown.offer(window(i, setup, rng))
        held = max(held, len(shown._kept))
    frames = shown.frames
    assert 25 <= len(frames) <= 50 and held < 100  # never more than twice the cap in memory
    assert all(1_000_000 <= f.t1_us <= 9_000_000 for f in frames)
    steps = np.diff([f.index for f in frames])
    assert len(set(steps.tolist())) == 1  # evenly spaced
    every = ViewFrames(every=7)
    kept = [every.offer(window(i, setup, rng)) for i in range(30)]
    assert [i for i, k in enumerate(kept) if k] == [0, 7, 14, 21, 28]
    with pytest.raises(LabrigError, match="at least 1"):
        ViewFrames(every=0)
    assert ViewFrames().max_frames == MAX_VIEW_FRAMES
    by_time = ViewFrames()
    kept = [by_time.offer(window(i, setup, rng)) for i in range(30)]  # 10 ms windows, a frame per 100 ms
    assert [i for i, k in enumerate(kept) if k] == [0, 10, 20]


def test_the_gif_has_one_frame_per_window_and_reports_progress(setup: run_setup.PipelineSetup, tmp_path: Path) -> None:
    from PIL import Image

    rng = np.random.default_rng(1)
    frames = [window(i, setup, rng) for i in range(12)]
    frames[5].net_force_n[:] = (1.5, -0.25, -6.0)
    done: list[int] = []
    path = write_view(frames, setup, tmp_path / "view.gif", progress=lambda k, n: done.append(k))
    assert done == list(range(1, 13))
    gif = Image.open(path)
    assert gif.n_frames == 12 and gif.size == (792, 446)  # 11 x 6.2 in at 72 dpi
    gif.seek(5)
    still = np.asarray(gif.convert("RGB"))
    gif.seek(6)
    assert np.abs(still.astype(int) - np.asarray(gif.convert("RGB")).astype(int)).sum() > 0  # frames differ
    with pytest.raises(LabrigError, match="nothing to animate"):
        write_view([], setup, tmp_path / "none.gif")
