"""The brightness change since rest: signed counts on the network grid, the leaky integrator, the channel,
its training track, and the depth source that feeds it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.config import RigConfig, Roi
from labrig.errors import LabrigError
from labrig.eventtypes import EVENT_DTYPE
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline import depth_sources, run_setup
from labrig.pipeline.brightness import BrightnessIntegrator, BrightnessParams, brightness_channel, map_median, signed_counts
from labrig.pipeline.depth_inputs import InputSpec, network_input
from labrig.pipeline.sae import sae_grid

ROI = Roi(276, 22, 1004, 694)


def _events(x: list[int], y: list[int], p: list[int], t: list[int] | None = None) -> np.ndarray:
    ev = np.zeros(len(x), EVENT_DTYPE)
    ev["x"], ev["y"], ev["p"] = x, y, p
    ev["t"] = t if t is not None else np.arange(1, len(x) + 1)  # after t0: the SAE scores an event at t0 as 0
    return ev


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_signed_counts_use_the_sae_cells_and_count_on_minus_off(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400))
    ev = _events(list(rng.integers(200, 1100, n)), list(rng.integers(0, 720, n)), list(rng.integers(0, 2, n)))
    counts = signed_counts(ev, ROI)
    inside = (ev["x"] >= ROI.x0_px) & (ev["x"] < ROI.x1_px) & (ev["y"] >= ROI.y0_px) & (ev["y"] < ROI.y1_px)
    assert counts.shape == GRID_SHAPE and counts.dtype == np.float32
    assert counts.sum() == (2 * ev["p"][inside].astype(int) - 1).sum()  # outside the ROI: dropped
    on = ev[inside & (ev["p"] == 1)]
    on_cells = sae_grid(on, 0, n + 2, ROI)[1] > 0  # the SAE's cells that saw an ON event
    on_counts = signed_counts(on, ROI)
    assert np.array_equal(on_cells, on_counts > 0)


def test_a_marker_that_moves_and_comes_back_leaves_no_count() -> None:
    integrator = BrightnessIntegrator(ROI)
    away = _events([500, 500, 520, 520], [300, 301, 300, 301], [0, 0, 1, 1])  # dark where it was, bright where it is
    back = _events([500, 500, 520, 520], [300, 301, 300, 301], [1, 1, 0, 0])
    integrator.add_events(away, 10_000)
    assert np.abs(integrator.counts).sum() == 4
    integrator.add_events(back, 20_000)
    assert np.allclose(integrator.counts, 0.0, atol=2e-3)  # what the 30 s leak took in 10 ms


def test_the_integrator_leaks_with_its_time_constant_and_resets() -> None:
    params = BrightnessParams(tau_s=2.0)
    integrator = BrightnessIntegrator(ROI, params)
    integrator.add_events(_events([600] * 10, [400] * 10, [1] * 10), 1_000_000)
    integrator.add(np.zeros(GRID_SHAPE, np.float32), 3_000_000)  # 2 s later: one time constant
    assert integrator.counts.max() == pytest.approx(10 * math.exp(-1.0), rel=1e-5)
    integrator.reset(3_000_000)
    assert not integrator.counts.any() and integrator.t_us == 3_000_000


def test_the_channel_removes_the_uniform_leak_drift_and_clips() -> None:
    params = BrightnessParams(scale_events_per_px=2.0, clip=3.0)
    ppc = 50.0
    counts = np.full(GRID_SHAPE, 0.5 * ppc, np.float32)  # every pixel's leak: half an ON event each
    counts[40:45, 50:55] += 2.0 * ppc  # a dent's shading: two events per pixel more
    counts[10, 10] += 1e4  # a hot pixel
    channel = brightness_channel(counts, ppc, params)
    assert np.allclose(channel[40:45, 50:55], 1.0) and abs(channel[0, 0]) < 1e-6
    assert channel[10, 10] == 3.0


def test_the_card_round_trips_the_brightness_settings() -> None:
    spec = InputSpec(("sae", "brightness"), brightness=BrightnessParams(tau_s=12.0, scale_events_per_px=1.5, clip=2.0))
    assert InputSpec.named("sae+bright").kinds == ("sae", "brightness") and spec.channels == 3 and spec.stateful
    assert InputSpec.from_card({"inputs": spec.to_card()}) == spec
    x = network_input(spec, np.zeros((2, *GRID_SHAPE), np.float32), brightness=np.full(GRID_SHAPE, 0.5, np.float32))
    assert x.shape == (3, 96, 112) and np.allclose(x[2, 3:93], 0.5) and not x[2, :3].any()
    with pytest.raises(LabrigError, match="brightness"):
        network_input(spec, np.zeros((2, *GRID_SHAPE), np.float32))
    with pytest.raises(LabrigError, match="positive"):
        BrightnessParams(tau_s=0.0)


def _stepped(rec, roi: Roi, params: BrightnessParams, windows: int) -> tuple[BrightnessIntegrator, int]:  # type: ignore[no-untyped-def]
    """An integrator stepped over the recording's first ``windows`` 10 ms windows, and the last one's end (us)."""
    from labrig.pipeline.windows import recording_windows

    integrator = BrightnessIntegrator(roi, params)
    for k, (_t0, t1, events) in enumerate(recording_windows(rec, window_us=10_000)):
        integrator.add_events(events, t1)
        if k == windows - 1:
            break
    return integrator, t1


def test_the_training_track_gives_the_run_time_channel(tmp_path, small_recording) -> None:  # type: ignore[no-untyped-def]
    """The cached 10 ms steps plus a window's own events equal the integrator stepped over the recording."""
    from labrig.recording import Recording
    from labrig.training.state_data import brightness_recording

    params = BrightnessParams()
    track = brightness_recording(small_recording, params, None, cache_root=tmp_path)
    again = brightness_recording(small_recording, params, None, cache_root=tmp_path)  # from the cache
    assert np.array_equal(np.asarray(track.counts), np.asarray(again.counts))
    with Recording(small_recording) as rec:
        integrator, t1 = _stepped(rec, track.roi, params, windows=151)
        t_mid = t1 + 4_000  # inside the next step: the track's step plus the window's own events
        window = rec.events_between(t_mid - 10_000, t_mid)
        integrator.add_events(rec.events_between(t1, t_mid), t_mid)
    assert np.abs(integrator.counts).sum() > 0
    expected = brightness_channel(integrator.counts, integrator.pixels_per_cell, params)
    assert np.allclose(track.channel_at(t_mid, window), expected, atol=2e-2)  # float16 steps


def test_with_the_dead_band_training_windows_end_on_the_tracks_steps(tmp_path, small_recording) -> None:  # type: ignore[no-untyped-def]
    """The pixels' polarity memory is not cached: a window ends on a step, where the track is the run-time state."""
    from labrig.recording import Recording
    from labrig.training.state_data import brightness_recording

    params = BrightnessParams(dead_band=True)
    track = brightness_recording(small_recording, params, None, cache_root=tmp_path)
    assert track.window_end(1_504_000.0) == 1_500_000.0 and track.window_end(1_506_000.0) == 1_510_000.0
    assert brightness_recording(small_recording, BrightnessParams(), None, cache_root=tmp_path).window_end(
        1_504_000.0) == 1_504_000.0
    with Recording(small_recording) as rec:
        integrator, t1 = _stepped(rec, track.roi, params, windows=151)
        end = track.window_end(t1 + 1_000)
        window = rec.events_between(end - 10_000, end)
    assert end == t1
    expected = brightness_channel(integrator.counts, integrator.pixels_per_cell, params)
    assert np.abs(expected).sum() > 0
    assert np.allclose(track.channel_at(end, window), expected, atol=2e-2)  # float16 steps


@pytest.fixture(scope="module")
def setup(rig: RigConfig) -> run_setup.PipelineSetup:
    return run_setup.setup_for_rig(rig, calibration_dir=None)


def test_a_brightness_network_answers_every_window_and_forgets_at_rest(tmp_path, setup) -> None:  # type: ignore[no-untyped-def]
    """No quiet hold and no rest gate by default (the state is in the input); a rest gate given clears the
    integrated change too."""
    from labrig.models import bundled_model_path
    from labrig.pipeline.model_card import ModelCard, write_card
    from labrig.pipeline.rest_gate import RestGateParams

    torch = pytest.importorskip("torch")
    from labrig.pipeline.depthnet import UNetConfig, build_unet, export_onnx

    spec = InputSpec.named("sae+bright")
    torch.manual_seed(0)
    net = build_unet(UNetConfig(width=4, in_channels=spec.channels)).eval()
    onnx = tmp_path / "bright.onnx"
    export_onnx(net, onnx)
    card = ModelCard.load(bundled_model_path().with_suffix(".json")).to_json()
    write_card({**card, "name": "bright", "inputs": spec.to_card()}, tmp_path / "bright.json")
    with pytest.raises(LabrigError, match="brightness"):
        depth_sources.model_depth(onnx)
    default = depth_sources.depth_source("model", setup, model_path=onnx)
    assert isinstance(default, depth_sources.ModelDepth) and default.hold is None and default.gate is None
    source = depth_sources.depth_source("model", setup, model_path=onnx, rest=RestGateParams())
    assert isinstance(source, depth_sources.ModelDepth) and source.hold is None and source.needs_counts
    rest = setup.rest_px
    source.counts(np.full(GRID_SHAPE, 40.0, np.float32), 10_000)
    source.markers(rest + 3.0, rest)
    source.depth_mm(np.zeros((2, *GRID_SHAPE), np.float32), 0, 10_000, 100)
    assert source.integrator is not None and source.integrator.counts.any()
    for k in range(5):  # back at rest: the gate fires after its windows and clears the count
        source.markers(rest, rest)
        depth = source.depth_mm(np.zeros((2, *GRID_SHAPE), np.float32), 0, 20_000 + k * 10_000, 100)
    assert not depth.any() and not source.integrator.counts.any()


#: How long after Normal Up's end the bundled network may still see a dent: the gel relaxes and the last events of the
#: release arrive over a few windows.
RELEASE_LAG_US = 100_000


@pytest.fixture(scope="module")
def virtual_press(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """A sphere pressed 1 mm at the gel centre, sheared 0.5 mm and back, released, retracted 1 mm
    (virtual time, with its sidecar)."""
    from labrig.evaluation.stress_scene import StressScene, record_scene

    path = tmp_path_factory.mktemp("press") / "press.h5"
    record_scene(StressScene(wait_s=0.3, approach_mm=1.0), path)  # a 0.33 s retract: windows after the release
    return path


def test_the_bundled_network_follows_a_press_and_returns_to_zero_after_normal_up(virtual_press) -> None:  # type: ignore[no-untyped-def]
    """The bundled default (SAE + brightness since rest) through the whole pipeline on a virtual press: the normal
    force follows the sim's while the gel is held still (where a 10 ms SAE shows nothing), and once the indenter
    has left the gel the depth and the force are back at zero: the brightness integrator's release, not the markers'
    rest gate, starts it again."""
    from labrig.evaluation.forces import ForceTask, evaluate_forces
    from labrig.models import bundled_model_path
    from labrig.pipeline.model_card import ModelCard
    from labrig.recording import Recording

    with Recording(virtual_press) as rec:
        phases = rec.phases()
    released_us = max(p.t_end_us for p in phases if p.name == "normal_up")
    waits = [(p.t_start_us, p.t_end_us) for p in phases if p.name == "wait"]
    result = evaluate_forces(ForceTask(str(virtual_press), str(bundled_model_path()), window_events=None,
                                       window_us=10_000, calibration_dir="calibration"))
    assert result.depth_source == f"model:{bundled_model_path().stem}"
    assert ModelCard.load(bundled_model_path().with_suffix(".json")).sees_brightness
    held = np.zeros(len(result.t1_us), bool)
    for a, b in waits:
        held |= (result.t1_us > a + 50_000) & (result.t1_us <= b)
    assert held.sum() >= 20
    fz_true = result.truth_n[held, 2]
    assert np.all(np.abs(result.predicted_n[held, 2] - fz_true) < 0.2 * np.abs(fz_true) + 0.2)
    after = result.t1_us > released_us + RELEASE_LAG_US
    assert after.sum() >= 10
    # the truth: 0; held 4.6 N; a stale SAE-only dent: 2-3 N; the dead band's remainder held by the gated leak without
    # the release: 0.3-0.4 N (docs/depthnet.md, The release)
    fz_after = np.abs(result.predicted_n[after, 2])
    released = result.t1_us[after] > released_us + 200_000  # the release has fired: settled for its 0.2 s
    assert fz_after.mean() < 0.2 and released.sum() >= 10 and fz_after[released].max() < 0.05, \
        f"a stale dent outlived the press: {np.round(fz_after, 2)} at {(result.t1_us[after] - released_us) // 1000} ms"


def test_a_stateful_networks_depth_table_uses_the_force_evaluations_windows(virtual_press, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A recording made through the drivers has events before host time 0, so its count windows start there; the
    depth table of a stateful network (run through the pipeline) must take the same windows, not the pipeline's
    own from 0 (it failed with a KeyError on every `make demo` recording)."""
    from labrig.evaluation import depth
    from labrig.models import bundled_model_path
    from labrig.pipeline import windows

    def from_before_zero(rec, *, window_events=None, window_us=None):  # type: ignore[no-untyped-def]
        t0, t1 = windows.window_ends_us(rec, window_events=window_events, window_us=window_us)
        return t0 - 4_321, t1 - 4_321  # as if the first events came before host time 0

    monkeypatch.setattr(depth, "window_ends_us", from_before_zero)
    result = depth.evaluate_depth(depth.DepthTask(str(virtual_press), str(bundled_model_path()), window_events=20_000))
    assert len(result.t_us) > 5 and np.isfinite(result.total_mm).all()


def test_the_noise_augmentation_adds_the_integrated_random_walk_of_that_noise() -> None:
    """Noise at r Hz per pixel, half ON and half OFF, integrated with the leak: per cell a random walk whose
    variance approaches r P tau / 2 events (P pixels per cell); zero mean, so no median is needed."""
    from labrig.training.state_data import BrightnessTrack, integrated_noise

    params = BrightnessParams(tau_s=30.0, scale_events_per_px=2.0)
    track = BrightnessTrack(np.array([10_000], np.int64), np.zeros((1, *GRID_SHAPE), np.float16), ROI, params)
    rng = np.random.default_rng(0)
    at_start = integrated_noise(track, 0.0, 1.0, rng)
    assert np.abs(at_start).max() < 1e-6  # nothing integrated yet
    late = integrated_noise(track, 600e6, 1.0, rng)  # 10 minutes in: the leak's steady state
    ppc = ROI.width_px * ROI.height_px / (GRID_SHAPE[0] * GRID_SHAPE[1])
    expected = math.sqrt(1.0 * ppc * params.tau_s / 2.0) / ppc / params.scale_events_per_px
    assert late.std() == pytest.approx(expected, rel=0.03) and abs(late.mean()) < 0.05 * expected


def _gated() -> BrightnessParams:
    return BrightnessParams(tau_s=3600.0, rest_tau_s=0.5, floor_events_per_px=0.3)


def _dent_events(n_per_px: int) -> np.ndarray:
    """ON events filling a 60 x 60 px square (about 25 cells) ``n_per_px`` times: a still dent's shading."""
    xs, ys = np.meshgrid(np.arange(600, 660), np.arange(300, 360))
    x, y = np.tile(xs.ravel(), n_per_px), np.tile(ys.ravel(), n_per_px)
    return _events(list(x), list(y), [1] * len(x))


def test_a_gated_leak_holds_a_still_dent_and_forgets_the_quiet_cells() -> None:
    """A dent two events per pixel deep is held for a minute (a one-leak integrator at 30 s keeps 13 %);
    a quiet cell's lone events decay within seconds; the uniform drift of the sensor's leak events is removed."""
    centres = np.rint(np.stack(np.meshgrid((np.arange(112) + 0.5) * ROI.width_px / 112 + ROI.x0_px - 0.5,
                                           (np.arange(90) + 0.5) * ROI.height_px / 90 + ROI.y0_px - 0.5), -1)).astype(int)
    every_cell = _events(list(centres[..., 0].ravel()), list(centres[..., 1].ravel()), [1] * centres[..., 0].size)
    gated, plain = BrightnessIntegrator(ROI, _gated()), BrightnessIntegrator(ROI)
    dent = _dent_events(2)
    for integrator in (gated, plain):
        integrator.add_events(dent, 10_000)
    cell = (int((330 - ROI.y0_px + 0.5) * 90 / ROI.height_px), int((630 - ROI.x0_px + 0.5) * 112 / ROI.width_px))
    pressed = float(gated.channel()[cell])  # about 1: 2 events per pixel / 2 per unit
    lone = _events([900, 900], [600, 600], [1, 1])  # a noise pair in a quiet cell
    gated.add_events(lone, 20_000)
    leak = np.zeros(0, dtype=EVENT_DTYPE)
    for k in range(3, 6001):  # 60 s of 10 ms windows; every pixel's leak fires ON now and then (uniform drift)
        window = leak
        if k % 200 == 0:  # one leak event in every cell every 2 s
            window = every_cell
        for integrator in (gated, plain):
            integrator.add_events(window, k * 10_000)
    held = gated.channel()[cell]
    assert pressed == pytest.approx(1.0, rel=0.05)
    assert held == pytest.approx(pressed * math.exp(-60 / 3600), rel=2e-3)  # only the loaded cells' own leak
    assert plain.channel()[cell] < 0.2
    lone_cell = (int((600 - ROI.y0_px + 0.5) * 90 / ROI.height_px), int((900 - ROI.x0_px + 0.5) * 112 / ROI.width_px))
    assert abs(gated.counts[lone_cell]) < 1e-3  # the lone pair, long forgotten
    assert abs(float(np.median(gated.counts))) < 0.5  # the leak's drift left every cell: no growing offset


def test_a_gated_leak_is_stepped_at_most_every_10_ms_and_round_trips_the_card() -> None:
    params = _gated()
    spec = InputSpec(("sae", "brightness"), brightness=params)
    assert InputSpec.from_card({"inputs": spec.to_card()}) == spec
    assert BrightnessParams.from_card(BrightnessParams().to_card()).rest_tau_s is None  # older cards: one leak
    integrator = BrightnessIntegrator(ROI, params)
    integrator.add_events(_events([600], [300], [1]), 1_000)
    for t in range(2_000, 11_000, 1_000):  # 1 ms windows: no step until 10 ms have passed
        integrator.add(np.zeros(GRID_SHAPE, np.float32), t)
    assert integrator.counts.sum() == pytest.approx(1.0)
    integrator.add(np.zeros(GRID_SHAPE, np.float32), 11_000)
    assert integrator.counts.sum() < 1.0
    with pytest.raises(LabrigError, match="rest_tau_s"):
        BrightnessParams(tau_s=1.0, rest_tau_s=2.0)


def _released() -> BrightnessParams:
    return BrightnessParams(tau_s=36_000.0, rest_tau_s=0.5, floor_events_per_px=0.3, release_fraction=0.5,
                            release_s=0.2)


def _dent_off_events(n_per_px: int) -> np.ndarray:
    off = _dent_events(n_per_px)
    off["p"] = 0
    return off


def _held_a_minute(step_us: int) -> tuple[BrightnessIntegrator, int]:
    """An integrator with the release, holding a dent of 8 events per pixel still for 60 s in steps of ``step_us``;
    and the time it has reached (us)."""
    integrator = BrightnessIntegrator(ROI, _released())
    integrator.add_events(_dent_events(8), 10_000)
    empty = np.zeros(0, dtype=EVENT_DTYPE)
    t = 10_000
    for _ in range(60_000_000 // step_us):
        t += step_us
        integrator.add_events(empty, t)
    return integrator, t


def test_the_release_starts_again_once_an_undone_press_has_settled() -> None:
    """A dent of 8 events per pixel held 60 s is kept; undone over 1 s down to the dead band's one event per pixel,
    it is not released while it still falls, and is released (zero) once it has stayed that low for 0.2 s."""
    integrator, t = _held_a_minute(10_000)
    empty = np.zeros(0, dtype=EVENT_DTYPE)
    held = integrator.held_total
    assert held > 0 and integrator.counts.max() > 0
    for _ in range(7):  # unloading: one event per pixel off every 150 ms
        for _ in range(15):
            t += 10_000
            integrator.add_events(empty, t)
            assert integrator.held_total > 0, "released while the press was still being undone"
        integrator.add_events(_dent_off_events(1), t)
    assert integrator.held_total < 0.5 * held
    for _ in range(25):  # settled at one event per pixel for 0.25 s
        t += 10_000
        integrator.add_events(empty, t)
    assert integrator.held_total == 0 and not integrator.counts.any()


def test_the_release_does_not_wait_on_the_window_length() -> None:
    """The same press seen in half-second steps (a gel at rest fills a fixed-count window slowly): its unloading,
    a quarter of the dent or more per step, is not a release; then a fall of a sixth over one step is settling, and
    the press is released."""
    integrator, t = _held_a_minute(500_000)
    for n_off in (2, 2, 2, 1):  # unloading down to the dead band's one event per pixel
        t += 500_000
        integrator.add_events(_dent_off_events(n_off), t)
        assert integrator.held_total > 0, "released while the press was still being undone"
    settling = _dent_off_events(1)
    settling = settling[settling["y"] < 310]  # a sixth of the dent's rows
    t += 500_000
    integrator.add_events(settling, t)
    assert integrator.held_total == 0 and not integrator.counts.any()


def test_a_press_undone_by_less_than_the_release_fraction_is_held() -> None:
    """Half of the dent taken back (a shallower hold, or the indenter sheared away from part of it) is not a release."""
    integrator = BrightnessIntegrator(ROI, _released())
    integrator.add_events(_dent_events(8), 10_000)
    integrator.add_events(_dent_off_events(3), 20_000)
    cell = (int((330 - ROI.y0_px + 0.5) * 90 / ROI.height_px), int((630 - ROI.x0_px + 0.5) * 112 / ROI.width_px))
    left = float(integrator.channel()[cell])  # about 5 events per pixel / 2 per unit
    empty = np.zeros(0, dtype=EVENT_DTYPE)
    for k in range(3, 1003):  # 10 s
        integrator.add_events(empty, k * 10_000)
    assert left > 2.4 and integrator.channel()[cell] == pytest.approx(left, rel=1e-3)


def test_the_release_round_trips_the_card_and_needs_the_gated_leak() -> None:
    spec = InputSpec(("sae", "brightness"), brightness=_released())
    assert InputSpec.from_card({"inputs": spec.to_card()}) == spec
    assert BrightnessParams.from_card(_gated().to_card()).release_fraction is None  # older cards: no release
    with pytest.raises(LabrigError, match="release"):
        BrightnessParams(release_fraction=0.5)  # no gated leak
    with pytest.raises(LabrigError, match="release"):
        BrightnessParams(rest_tau_s=0.5, release_fraction=1.5)



def _still_gated(moving_ratio: float | None = 2.0) -> BrightnessParams:
    return BrightnessParams(tau_s=36_000.0, rest_tau_s=0.5, floor_events_per_px=0.3, moving_ratio=moving_ratio)


def _shot_noise(rng: np.random.Generator, per_px_per_window: float) -> np.ndarray:
    """Shot noise over the whole ROI for one window: independent ON and OFF events, zero mean."""
    n = rng.poisson(per_px_per_window * ROI.width_px * ROI.height_px)
    return _events(list(rng.integers(ROI.x0_px, ROI.x0_px + ROI.width_px, n)),
                   list(rng.integers(ROI.y0_px, ROI.y0_px + ROI.height_px, n)), list(rng.integers(0, 2, n)))


def _dent_cells(channel: np.ndarray) -> np.ndarray:
    return channel > 0.5


def test_the_still_gate_keeps_a_still_press_from_random_walking() -> None:
    """A dent held 30 s under zero-mean shot noise (0.3 events per pixel per second everywhere): without the
    still gate its cells walk (the 10 h leak keeps the walk); with it they walk a third as far or less."""
    walked = {}
    for ratio in (2.0, None):
        integrator = BrightnessIntegrator(ROI, _still_gated(ratio))
        integrator.add_events(_dent_events(4), 10_000)
        integrator.add(np.zeros(GRID_SHAPE, np.float32), 20_000)
        pressed = integrator.channel().copy()
        rng = np.random.default_rng(7)
        for k in range(3, 3003):
            integrator.add_events(_shot_noise(rng, 0.003), k * 10_000)
        dent = _dent_cells(pressed)
        walked[ratio] = float(np.abs(integrator.channel() - pressed)[dent].mean())
    assert walked[None] > 0.05  # the walk the gate is for: events per pixel / 2 per unit
    assert walked[2.0] * 3 < walked[None]


def test_the_still_gate_lets_a_press_that_moves_through_whole() -> None:
    """A press that deepens while held (two more events per pixel over 50 ms, under the same noise) reaches
    the count whole: it gains what it gains without the gate, and only its steps are found moving."""
    gained, moved = {}, {}
    for ratio in (2.0, None):
        integrator = BrightnessIntegrator(ROI, _still_gated(ratio))
        t = 10_000
        integrator.add_events(_dent_events(4), t)
        t += 10_000
        integrator.add(np.zeros(GRID_SHAPE, np.float32), t)
        pressed = integrator.channel().copy()
        rng = np.random.default_rng(3)
        moved[ratio] = []
        for step in range(100):  # 1 s held, then 2 events per pixel more in five 10 ms steps
            t += 10_000
            window = _shot_noise(rng, 0.003)
            if 50 <= step < 55:
                window = np.concatenate([window, _dent_events(2)[::5]])
            integrator.add_events(window, t)
            moved[ratio].append(integrator.moving)
        gained[ratio] = (integrator.channel() - pressed)[_dent_cells(pressed)]
    assert np.median(gained[None]) > 0.5
    assert np.median(np.abs(gained[2.0] - gained[None])) < 0.05
    assert all(moved[2.0][50:55]) and sum(moved[2.0][:50]) <= 2


def test_the_still_gate_round_trips_the_card_and_needs_the_gated_leak() -> None:
    spec = InputSpec(("sae", "brightness"), brightness=_still_gated())
    assert InputSpec.from_card({"inputs": spec.to_card()}) == spec
    assert BrightnessParams.from_card(_gated().to_card()).moving_ratio is None  # older cards: no gate
    with pytest.raises(LabrigError, match="still gate"):
        BrightnessParams(moving_ratio=2.0)  # no gated leak
    with pytest.raises(LabrigError, match="still gate"):
        BrightnessParams(rest_tau_s=0.5, moving_ratio=0.5)


def test_a_light_too_dim_in_its_slope_response_is_warned_with_what_to_do() -> None:
    from labrig.pipeline.brightness import DIM_LIGHT_SLOPE_GAIN, dim_light_warning

    assert dim_light_warning(None) is None and dim_light_warning(DIM_LIGHT_SLOPE_GAIN) is None
    assert dim_light_warning(DIM_LIGHT_SLOPE_GAIN - 0.002) is None, "a light measured as the one checked, to print"
    assert dim_light_warning(DIM_LIGHT_SLOPE_GAIN - 0.01) is not None
    line = dim_light_warning(0.8)
    assert line is not None and "0.80" in line and "grazing" in line and "\n" not in line


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from([0.0, -1.5, 2.0, 3.25]) | st.floats(-1e3, 1e3, width=32), min_size=1, max_size=60))
def test_map_median_is_numpys_median(values: list[float]) -> None:
    """Odd and even sizes, ties and repeated zeros: the same float32 value as ``np.median``."""
    map_ = np.array(values, np.float32)
    assert map_median(map_) == np.float32(np.median(map_))
    assert map_median(map_.reshape(1, -1)) == np.float32(np.median(map_))
