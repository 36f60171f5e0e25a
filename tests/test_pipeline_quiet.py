"""Quiet windows keep the last active depth map; the network sees its own window; the calibrated gel stiffens."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.models import bundled_model_path
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline import depth_sources, forces, run_setup, runtime
from labrig.pipeline.model_card import ModelCard
from labrig.pipeline.quiet import NoiseFloor, QuietHold, QuietParams, TileActivity, active_cells_per_tile
from labrig.pipeline.sae import sae_grid
from labrig.recording import EVENT_DTYPE

NOISE, MOTION = 470, 2500  # events per 10 ms window over the ROI: the virtual rig at rest and in a press


def _noise(rig: RigConfig, t0_us: int, t1_us: int, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    r = rig.roi
    ev = np.zeros(n, EVENT_DTYPE)
    ev["x"] = rng.integers(r.x0_px, r.x1_px, n)
    ev["y"] = rng.integers(r.y0_px, r.y1_px, n)
    ev["p"] = rng.integers(0, 2, n)
    ev["t"] = np.sort(rng.integers(t0_us, t1_us, n))
    return ev


def test_the_noise_floor_tells_rest_from_motion_and_a_stream_starts_quiet() -> None:
    rng = np.random.default_rng(1)
    counts = np.concatenate([rng.poisson(NOISE, 50), rng.poisson(MOTION, 30), rng.poisson(NOISE, 40),
                             rng.poisson(900, 5)])  # a slow movement: twice the noise
    stream = NoiseFloor()
    quiet = np.array([stream.is_quiet(int(n), 10_000) for n in counts])
    assert quiet[:50].all() and not quiet[50:80].any() and quiet[80:120].all() and not quiet[120:].any()
    floor = NoiseFloor()
    assert floor.is_quiet(MOTION, 10_000)  # the first window defines the floor
    assert floor.is_quiet(0, 10_000)


def test_the_noise_floor_forgets_a_quieter_past() -> None:
    floor = NoiseFloor(QuietParams(history_windows=20))
    for _ in range(20):
        floor.is_quiet(100, 10_000)
    for _ in range(20):
        floor.is_quiet(NOISE, 10_000)  # the light came on: more noise
    assert floor.is_quiet(NOISE, 10_000) and not floor.is_quiet(MOTION, 10_000)


class _Spy(depth_sources.DepthSource):
    """A depth source with its own 30 ms window that remembers what it was given."""

    name = "spy"
    needs_sae = True

    def __init__(self, window_us: float | None) -> None:
        self.window_us = window_us
        self.calls: list[tuple[int, int, int, float]] = []

    def depth_mm(self, sae_grid: Any, t0_us: int, t1_us: int, n_events: int) -> np.ndarray:
        self.calls.append((t0_us, t1_us, n_events, float(sae_grid.sum())))
        return np.zeros((90, 112), np.float32)


@pytest.fixture(scope="module")
def setup(rig: RigConfig) -> run_setup.PipelineSetup:
    return run_setup.setup_for_rig(rig, calibration_dir=None)


def test_the_depth_source_sees_its_own_window_ending_at_each_window_end(rig: RigConfig,
                                                                       setup: run_setup.PipelineSetup) -> None:
    spy = _Spy(30_000.0)
    pipe = runtime.Pipeline(setup, spy)
    bounds = [(0, 10_000), (10_000, 12_000), (12_000, 14_000), (14_000, 60_000)]  # count windows: short, then long
    per_window = [300, 300, 300, 300]
    for (t0, t1), n in zip(bounds, per_window):
        pipe.process(t0, t1, _noise(rig, t0, t1, n, seed=t0))
    starts = [c[0] for c in spy.calls]
    assert starts == [-20_000, -18_000, -16_000, 30_000]
    assert [c[2] for c in spy.calls] == [300, 600, 900, pytest.approx(300 * 30 / 46, abs=40)]
    default = _Spy(None)
    runtime.Pipeline(setup, default).process(0, 10_000, _noise(rig, 0, 10_000, 300))
    assert default.calls[0][:3] == (0, 10_000, 300)


def test_depth_every_10_ms_with_tracking_and_forces_every_1_ms(rig: RigConfig, setup: run_setup.PipelineSetup) -> None:
    """1 ms windows, depth every 10 ms: the source sees its own 30 ms window ending at every tenth window's
    end, the others keep its map, and every window is tracked and gets forces."""
    spy = _Spy(30_000.0)
    pipe = runtime.Pipeline(setup, spy, depth_every_us=10_000)
    results = [pipe.process(k * 1_000, (k + 1) * 1_000, _noise(rig, k * 1_000, (k + 1) * 1_000, 40, seed=k))
               for k in range(35)]
    assert [c[1] for c in spy.calls] == [1_000, 11_000, 21_000, 31_000]
    assert [c[0] for c in spy.calls] == [-29_000, -19_000, -9_000, 1_000]
    assert len(results) == 35 and all(r.forces_n.shape == (len(setup.rest_px), 3) for r in results)
    assert all(np.shares_memory(results[k].depth_mm, results[1].depth_mm) for k in range(1, 10))
    with pytest.raises(ValueError, match="depth_every_us"):
        runtime.Pipeline(setup, spy, depth_every_us=0)


def test_the_network_holds_its_last_active_map_through_quiet_windows(rig: RigConfig,
                                                                     setup: run_setup.PipelineSetup) -> None:
    network = depth_sources.model_depth(bundled_model_path("sae-only"))
    unheld = depth_sources.model_depth(bundled_model_path("sae-only"), quiet=None)
    held_pipe, raw_pipe = runtime.Pipeline(setup, network), runtime.Pipeline(setup, unheld)
    counts = [NOISE] * 20 + [MOTION] * 3 + [NOISE] * 10
    held, raw = [], []
    for k, n in enumerate(counts):
        ev = _noise(rig, k * 10_000, (k + 1) * 10_000, n, seed=k)
        held.append(held_pipe.process(k * 10_000, (k + 1) * 10_000, ev))
        raw.append(raw_pipe.process(k * 10_000, (k + 1) * 10_000, ev))
    assert all(not r.depth_mm.any() and not r.net_force_n.any() for r in held[:20])  # at rest: nothing, not a dimple
    assert any(np.abs(r.depth_mm).max() > 0 for r in raw[:20])  # what the network alone answers to noise
    assert all(np.array_equal(r.depth_mm, held[22].depth_mm) for r in held[23:])


def test_the_calibrated_stiffening_scales_the_linear_forces(rig: RigConfig, tmp_path: Path) -> None:
    assert forces.stiffening_factor(np.array([[0.0, 2.0]]), 4.0, 0.6) == pytest.approx(1.3)
    assert forces.stiffening_factor(np.array([[-1.0]]), 4.0, 0.6) == 1.0
    assert forces.stiffening_factor(np.array([[2.0]]), 4.0, 0.0) == 1.0
    (tmp_path / "gel.toml").write_text("youngs_modulus_mpa = 0.4\npoisson_ratio = 0.48\nstiffening = 0.6\n")
    fitted = run_setup.setup_for_rig(rig, calibration_dir=tmp_path)
    assert fitted.stiffening == 0.6 and fitted.sources["stiffening"].endswith("gel.toml")
    assert run_setup.setup_for_rig(rig, calibration_dir=tmp_path, stiffening=0.0).stiffening == 0.0
    assert run_setup.setup_for_rig(rig, calibration_dir=None).stiffening == 0.0
    depth = np.zeros((90, 112), np.float32)
    depth[40:50, 50:60] = 2.0
    linear = runtime.Pipeline(run_setup.setup_for_rig(rig, calibration_dir=tmp_path, stiffening=0.0),
                              _Fixed(depth)).process(0, 10_000, _noise(rig, 0, 10_000, 10))
    stiff = runtime.Pipeline(fitted, _Fixed(depth)).process(0, 10_000, _noise(rig, 0, 10_000, 10))
    factor = 1 + 0.6 * 2.0 / rig.gel.thickness_mm
    assert linear.net_force_n[2] < -1.0
    np.testing.assert_allclose(stiff.net_force_n, factor * linear.net_force_n, rtol=1e-9, atol=1e-12)  # x, y: float noise


class _Fixed(depth_sources.DepthSource):
    name = "fixed"
    needs_sae = False
    window_us = None

    def __init__(self, depth_mm: np.ndarray) -> None:
        self.map = depth_mm

    def depth_mm(self, sae_grid: Any, t0_us: int, t1_us: int, n_events: int) -> np.ndarray:
        return self.map


def test_active_cells_are_summed_per_tile() -> None:
    sae = np.zeros((2, 6, 8), np.float32)
    sae[0, 0, 0] = sae[1, 0, 0] = 0.5  # one cell, both polarities: counted once
    sae[1, 5, 7] = 0.9
    sae[0, 2:4, 4:6] = 0.1
    np.testing.assert_array_equal(active_cells_per_tile(sae, (2, 2)), [[1, 2], [0, 3]])
    with pytest.raises(ValueError, match="tiles"):
        QuietParams(tiles=(0, 3))


def _grid(rig: RigConfig, rate_hz: float, seed: int, press: bool = False) -> tuple[np.ndarray, int]:
    """One 10 ms window's SAE and event count: uniform noise at ``rate_hz`` per pixel, plus a local press."""
    r = rig.roi
    n = np.random.default_rng(seed).poisson(rate_hz * r.width_px * r.height_px * 0.01)
    ev = _noise(rig, 0, 10_000, n, seed)
    if press:  # 3,000 events in a 160 px (about 6 mm) square: the markers around a slow press
        local = _noise(rig, 0, 10_000, 3_000, seed + 1)
        local["x"] = r.x0_px + 280 + local["x"] % 160
        local["y"] = r.y0_px + 250 + local["y"] % 160
        ev = np.sort(np.concatenate([ev, local]), order="t")
    return sae_grid(ev, 0, 10_000, r, GRID_SHAPE), len(ev)


def test_tiles_find_a_local_press_the_total_rate_misses_in_heavy_noise(rig: RigConfig) -> None:
    rate_only = QuietHold(GRID_SHAPE, QuietParams())
    tiled = QuietHold(GRID_SHAPE, QuietParams(tiles=(6, 7)))
    for k in range(40):  # 2 Hz per pixel: about 9,800 noise events per window
        grid, n = _grid(rig, 2.0, k)
        assert rate_only(n, 10_000) and tiled(n, 10_000, grid), k
    grid, n = _grid(rig, 2.0, 99, press=True)
    assert rate_only(n, 10_000)  # 3,000 more events on 9,800 is within 1.6x the floor: "quiet"
    assert not tiled(n, 10_000, grid)  # one tile far above its own floor: motion
    quiet_windows = sum(tiled(n, 10_000, g) for g, n in (_grid(rig, 2.0, 200 + k) for k in range(200)))
    assert quiet_windows >= 198  # noise alone rarely looks like motion (6 sigma on one of 42 tiles)


def test_a_hot_pixel_raises_only_its_own_tile_floor(rig: RigConfig) -> None:
    tiles = TileActivity(QuietParams(tiles=(6, 7), refresh_windows=4))
    for k in range(40):
        grid, _ = _grid(rig, 0.05, k)
        grid[0, 10, 10] = 0.5  # a hot pixel: active in every window
        grid[1, 11, 10] = 0.7
        assert not tiles.is_active(grid), k
    grid, _ = _grid(rig, 0.05, 77, press=True)
    assert tiles.is_active(grid)


def test_the_gate_follows_the_network_card() -> None:
    assert depth_sources.model_depth("sae-only").hold.tiles is None  # type: ignore[union-attr]
    noisy = depth_sources.quiet_params_for(_card({"augmentation": {"background_noise": {"max_hz": 2.0}}}))
    assert noisy is not None and noisy.tiles is not None  # a noise-trained SAE network: the tiles too
    assert depth_sources.quiet_params_for(_card({"augmentation": None})).tiles is None  # type: ignore[union-attr]
    bright = {"inputs": {"kinds": ["sae", "brightness"]}, "augmentation": {"background_noise": {"max_hz": 2.0}}}
    assert depth_sources.quiet_params_for(_card(bright)) is None  # the state is in its input: no hold
    assert depth_sources.model_depth("sae-only", quiet=None).hold is None


def _card(sections: dict[str, Any]) -> ModelCard:
    """A model card with these sections (and the scale every card has)."""
    return ModelCard.from_json({"format": "labrig.depthnet", "scale_mm": 2.5, **sections})
