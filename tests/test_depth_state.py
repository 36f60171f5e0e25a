"""Depth that carries state: the input contract, the displacement raster, the rest gate and the one depth-source builder."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.config import RigConfig
from labrig.errors import LabrigError
from labrig.models import bundled_model_path
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline import depth_sources, run_setup, runtime
from labrig.pipeline.depth_inputs import DisplacementRaster, InputSpec, gel_plane_displacement_mm, network_input
from labrig.pipeline.rest_gate import RestGate, RestGateParams
from labrig.pipeline.sae import UNET_SHAPE
from labrig.training.state_data import PreviousAugment, Tracks

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def setup(rig: RigConfig) -> run_setup.PipelineSetup:
    return run_setup.setup_for_rig(rig, calibration_dir=None)


# ------------------------------------------------------------------------------------ the input contract


def test_the_input_sets_and_the_card() -> None:
    assert InputSpec.named("sae").channels == 2 and not InputSpec.named("sae").stateful
    full = InputSpec.named("sae+disp+prev")
    assert full.channels == 5 and full.stateful and full.name == "sae+disp+prev"
    assert InputSpec.from_card({"inputs": full.to_card()}) == full
    assert InputSpec.from_card({"name": "old"}) == InputSpec()  # cards written before inputs were named: the SAE
    for bad in ("disp", "sae+prev+x"):
        with pytest.raises(LabrigError, match="--inputs"):
            InputSpec.named(bad)
    with pytest.raises(LabrigError, match="start with sae"):
        InputSpec(("displacement", "sae"))
    with pytest.raises(LabrigError, match="kinds"):
        InputSpec.from_card({"inputs": ["sae"]})


def test_the_network_input_stacks_padded_channels_in_the_card_order() -> None:
    spec = InputSpec(("sae", "displacement", "previous"), displacement_scale_mm=0.5)
    sae = np.full((2, *GRID_SHAPE), 0.25, np.float32)
    field = np.full((2, *GRID_SHAPE), 0.1, np.float32)
    previous = np.full(GRID_SHAPE, 0.7, np.float32)
    x = network_input(spec, sae, field, previous)
    assert x.shape == (5, *UNET_SHAPE) and x.dtype == np.float32
    inner = x[:, 3:93]  # the 90 rows inside the zero padding
    assert np.allclose(inner[:2], 0.25) and np.allclose(inner[2:4], 0.2) and np.allclose(inner[4], 0.7)
    assert not x[:, :3].any() and not x[:, 93:].any()
    with pytest.raises(LabrigError, match="previous depth"):
        network_input(spec, sae, field, None)
    with pytest.raises(LabrigError, match="displacement"):
        network_input(spec, sae, None, previous)


@settings(max_examples=20, deadline=None)
@given(st.floats(-3, 3), st.floats(-3, 3))
def test_a_uniform_displacement_rasterises_to_a_uniform_field(setup: run_setup.PipelineSetup, dx: float, dy: float) -> None:
    raster = DisplacementRaster(setup.rest_px, None, setup.rig.roi)
    field = raster(np.tile([dx, dy], (len(setup.rest_px), 1)))
    assert field.shape == (2, *GRID_SHAPE)
    np.testing.assert_allclose(field[0], dx, atol=1e-4)
    np.testing.assert_allclose(field[1], dy, atol=1e-4)


def test_missing_markers_are_filled_from_their_neighbours(setup: run_setup.PipelineSetup) -> None:
    roi = setup.rig.roi
    ramp = np.stack([(setup.rest_px[:, 0] - roi.x0_px) / roi.width_px, np.zeros(len(setup.rest_px))], axis=1)
    observed = np.ones(len(setup.rest_px), bool)
    hole = int(np.argmin(np.linalg.norm(setup.rest_px - setup.rest_px.mean(0), axis=1)))  # the centre marker
    observed[hole] = False
    values = ramp.copy()
    values[hole] = 50.0  # a missing marker's value (whatever the tracker left there) must not count
    full = DisplacementRaster(setup.rest_px, None, roi)(ramp)
    holed = DisplacementRaster(setup.rest_px, observed, roi)(values)
    assert np.abs(holed).max() < 2.0
    from labrig.pipeline.displacement import grid_coordinates

    r, c = np.round(grid_coordinates(setup.rest_px[hole], roi, GRID_SHAPE)).astype(int)
    assert holed[0, r, c] == pytest.approx(full[0, r, c], abs=0.02)  # the ramp goes on through the hole
    with pytest.raises(LabrigError, match="observed"):
        DisplacementRaster(setup.rest_px, np.zeros(len(setup.rest_px), bool), roi)


def test_gel_plane_displacement_is_zero_at_rest_and_follows_the_markers(setup: run_setup.PipelineSetup) -> None:
    assert not gel_plane_displacement_mm(setup.camera, setup.rest_px, setup.rest_px).any()
    # every marker moved onto its lattice neighbour's rest pixel: the gel-plane displacement is the pitch (mm)
    moved = gel_plane_displacement_mm(setup.camera, setup.rest_px[1:], setup.rest_px[:-1])
    rest_mm = setup.rest_mm()
    np.testing.assert_allclose(moved, (rest_mm[1:] - rest_mm[:-1])[:, :2], atol=1e-6)
    assert np.median(np.linalg.norm(moved, axis=1)) == pytest.approx(setup.rig.markers.pitch_mm, rel=0.05)


def test_the_previous_map_is_perturbed_not_copied() -> None:
    previous = np.zeros(GRID_SHAPE, np.float32)
    previous[40:50, 50:60] = 0.5
    rng = np.random.default_rng(3)
    augment = PreviousAugment(p_zero=0.25)
    draws = [augment(previous, rng) for _ in range(200)]
    zeroed = sum(not d.any() for d in draws)
    assert 30 <= zeroed <= 75  # about a quarter
    kept = [d for d in draws if d.any()]
    assert all(d.min() >= 0.0 and d.max() <= 1.0 for d in kept)
    assert not any(np.array_equal(d, previous) for d in kept)
    peaks = np.array([d[38:52, 48:62].mean() for d in kept])
    assert peaks.std() > 0.01  # scaled differently each time
    lags = [PreviousAugment(p_stale=0.5, max_lag_windows=5).lag_windows(rng) for _ in range(400)]
    assert set(lags) == {1, 2, 3, 4, 5} and 150 <= lags.count(1) <= 250  # a stale map half the time
    shifted = PreviousAugment(p_zero=0.0, scale=0.0, shift_cells=2, noise=0.0)
    moved = [shifted(previous, rng) for _ in range(50)]
    assert any(not np.array_equal(m, previous) for m in moved) and all(m.sum() == pytest.approx(previous.sum()) for m in moved)


def test_tracks_interpolate_between_windows() -> None:
    tracks = Tracks(np.array([10, 20]), np.array([[[0.0, 0.0]], [[2.0, 4.0]]]), np.array([[-1.0, -1.0]]))
    np.testing.assert_allclose(tracks.at(15), [[1.0, 2.0]])
    np.testing.assert_allclose(tracks.at(5), [[-1.0, -1.0]])  # before the first window: the rest
    np.testing.assert_allclose(tracks.at(99), [[2.0, 4.0]])


# ------------------------------------------------------------------------------------ the rest state


def test_the_rest_gate_needs_every_marker_at_rest_for_some_windows() -> None:
    rest = np.zeros((4, 2))
    gate = RestGate(params=RestGateParams(threshold_px=0.3, windows=3))
    moved = rest.copy()
    moved[2] = [0.0, 0.5]
    assert [gate(rest, rest) for _ in range(3)] == [False, False, True]
    assert not gate(moved, rest) and gate.displacement_px == pytest.approx(0.5)  # one marker off: not at rest
    assert [gate(rest + 0.1, rest) for _ in range(3)] == [False, False, True]
    masked = RestGate(observed=[True, True, False, True], params=RestGateParams(windows=1))
    assert masked(moved, rest)  # a missing marker does not count
    p75 = RestGate(params=RestGateParams(windows=1, statistic="p50"))
    assert p75(moved, rest)
    for bad in ({"threshold_px": 0.0}, {"windows": 0}, {"statistic": "mean"}, {"statistic": "p0"}):
        with pytest.raises(LabrigError):
            RestGateParams(**bad)  # type: ignore[arg-type]


def _press_sae(rng: np.random.Generator, active: bool) -> np.ndarray:
    """A window's SAE: a ring of fresh events round the centre while pressing, sparse noise when quiet."""
    sae = np.zeros((2, *GRID_SHAPE), np.float32)
    noise = rng.random(GRID_SHAPE) < 0.005
    sae[1][noise] = rng.random(int(noise.sum()))
    if active:
        rows, cols = np.mgrid[0:GRID_SHAPE[0], 0:GRID_SHAPE[1]]
        ring = np.abs(np.hypot(rows - 45, cols - 56) - 12) < 3
        sae[0][ring] = 0.5 + 0.5 * rng.random(int(ring.sum()))
        sae[1][ring] = 0.5 + 0.5 * rng.random(int(ring.sum()))
    return sae


def test_a_virtual_press_returns_to_zero_depth_and_force_after_normal_up(setup: run_setup.PipelineSetup) -> None:
    """Rest, press (markers move, events), hold (markers still displaced, no events), Normal Up (markers back,
    no events): the quiet hold keeps the dent while the gel is held, and the depth is exactly zero and Fz 0
    once every marker is back at rest; without the gate the stale dent and its force would stay."""
    source = depth_sources.depth_source("model", setup, model_path=bundled_model_path("sae-only"))
    stale = depth_sources.depth_source("model", setup, model_path=bundled_model_path("sae-only"), rest=None)
    pipes = [runtime.Pipeline(setup, s) for s in (source, stale)]
    rest = setup.rest_px
    centre = setup.rest_px.mean(0)
    pressed = rest + 1.5 * (rest - centre) / (np.linalg.norm(rest - centre, axis=1, keepdims=True) + 1.0)
    script = [("rest", 20), ("press", 4), ("hold", 10), ("release", 6)]
    results: list[list[runtime.WindowResult]] = [[], []]
    rng = np.random.default_rng(0)
    k = 0
    for phase, n in script:
        for _ in range(n):
            sae = _press_sae(rng, phase == "press")
            positions = pressed if phase in ("press", "hold") else rest
            tracked = runtime.TrackedWindow(k, k * 10_000, (k + 1) * 10_000, 5000 if phase == "press" else 400,
                                            positions.copy(), np.ones(len(rest), bool), k * 10_000,
                                            5000 if phase == "press" else 400, sae, {}, rest)
            for pipe, out in zip(pipes, results):
                out.append(pipe.back(tracked))
            k += 1
    gated, ungated = results
    assert all(not r.depth_mm.any() and not r.net_force_n.any() for r in gated[:20])
    dent = gated[23].depth_mm
    assert dent.max() > 0.05 and gated[23].net_force_n[2] < -0.1  # the network drew the press
    assert all(np.array_equal(r.depth_mm, dent) for r in gated[24:34])  # the hold keeps it while the gel is held
    released = gated[34 + RestGateParams().windows - 1:]
    assert released and all(not r.depth_mm.any() and r.net_force_n[2] == 0.0 for r in released)
    assert ungated[-1].depth_mm.max() > 0.05 and ungated[-1].net_force_n[2] < -0.1  # the stale dent the gate removes


def test_a_stateful_network_needs_the_setup(tmp_path: Path) -> None:
    import shutil

    from labrig.pipeline.model_card import ModelCard, write_card

    onnx = tmp_path / "disp.onnx"
    shutil.copy(bundled_model_path("sae-only"), onnx)
    card = ModelCard.load(bundled_model_path("sae-only").with_suffix(".json")).to_json()
    write_card({**card, "inputs": InputSpec.named("sae+disp").to_card()}, tmp_path / "disp.json")
    with pytest.raises(LabrigError, match="takes 2 channels but its card names 4"):
        depth_sources.model_depth(onnx)


# ------------------------------------------------------------------------------------ one code path


@pytest.mark.parametrize("module", ["labrig/cli/run.py", "labrig/cli/run_live.py", "labrig/evaluation/forces.py"])
def test_run_live_and_evaluate_build_their_depth_source_in_one_place(module: str) -> None:
    tree = ast.parse((ROOT / module).read_text())
    calls = [node.func for node in ast.walk(tree) if isinstance(node, ast.Call)]
    names = {f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "") for f in calls}
    assert "depth_source" in names, f"{module} must build its depth source with depth_sources.depth_source"
    assert not names & {"ModelDepth", "TruthDepth"}, f"{module} builds a depth source of its own"


def test_the_builder_refuses_truth_without_a_recording(setup: run_setup.PipelineSetup) -> None:
    with pytest.raises(LabrigError, match="truth"):
        depth_sources.depth_source("truth", setup)
    with pytest.raises(LabrigError, match="'truth' or 'model'"):
        depth_sources.depth_source("sim", setup)
    source = depth_sources.depth_source("model", setup, model_path="default")
    assert isinstance(source, depth_sources.ModelDepth) and source.needs_counts
    assert source.hold is None and source.gate is None  # the default sees the brightness change: no hold, no gate
    baseline = depth_sources.depth_source("model", setup, model_path="sae-only")
    assert isinstance(baseline, depth_sources.ModelDepth) and not baseline.needs_counts
    assert baseline.hold is not None and baseline.gate is not None


def test_self_feed_replaces_only_the_previous_channel_with_the_networks_own_padded_answer() -> None:
    import torch

    from labrig.pipeline.depthnet import UNetConfig, build_unet
    from labrig.pipeline.sae import crop_from_unet
    from labrig.training.state_data import self_feed

    spec = InputSpec.named("sae+disp+prev")
    assert (spec.channel_of("sae"), spec.channel_of("displacement"), spec.channel_of("previous")) == (0, 2, 4)
    assert InputSpec().channel_of("previous") is None
    torch.manual_seed(0)
    model = build_unet(UNetConfig(width=2, pools=2, in_channels=5))
    x = torch.rand(3, 5, *UNET_SHAPE)
    assert self_feed(model, x, 4, 0) is x
    fed = self_feed(model, x, 4, 1)
    assert torch.equal(fed[:, :4], x[:, :4]) and not torch.equal(fed[:, 4], x[:, 4])
    assert not fed[:, 4, :3].any() and not fed[:, 4, 93:].any()  # the padding rows stay empty, as at run time
    with torch.no_grad():
        own = crop_from_unet(model(x)[:, 0]).clamp(0.0, 1.0)
    torch.testing.assert_close(fed[:, 4, 3:93], own)
    assert float(fed[:, 4].min()) >= 0.0 and float(fed[:, 4].max()) <= 1.0
