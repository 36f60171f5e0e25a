"""The DVS pixel model: event counts, timing, refractory period, noise rates, determinism."""

from __future__ import annotations

import dataclasses
from itertools import pairwise

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.recording.reader import EVENT_DTYPE as RECORDING_EVENT_DTYPE
from labrig.sim.events import EVENT_DTYPE, EventParams, EventSensor
from labrig.sim.optics import Renderer
from labrig.sim.pixels import PixelBlock


def translate_marker(
    rig: RigConfig, params: EventParams, seed: int, shift_px: float = 5.0, steps: int = 100
) -> tuple[np.ndarray, float]:
    """Move marker 70 by shift_px along image x in 1 ms steps, then let the pixels settle.

    Returns the events and the summed |change of log(eps + I)| / threshold over every pixel and step.
    """
    renderer = Renderer(rig)
    sensor = EventSensor.from_rig(rig, renderer.image, seed=seed, params=params)
    rest = rig.markers.rest_positions_mm()
    jac = renderer.camera.jacobian_px_per_mm(rest[70:71])[0]
    dx_mm = shift_px / np.linalg.norm(jac[:, 0])
    log_now = np.log(params.eps + renderer.image.ravel())
    total_change, events, t = 0.0, [], 0
    for k in range(1, steps + 1):
        xyz = rest.copy()
        xyz[70, 0] += dx_mm * k / steps
        update = renderer.render(xyz)
        new = np.log(params.eps + update.intensity)
        total_change += np.abs(new - log_now[update.indices]).sum()
        log_now[update.indices] = new
        events.append(sensor.step(t, t + 1000, update.indices, update.intensity))
        t += 1000
    for _ in range(10):
        events.append(sensor.step(t, t + 1000, [], []))
        t += 1000
    return np.concatenate(events), total_change / params.threshold_on


def test_event_count_matches_log_intensity_change(rig: RigConfig) -> None:
    params = EventParams.from_rig(rig).noiseless()
    events, expected = translate_marker(rig, params, seed=1)
    assert expected > 500
    assert events.size / expected == pytest.approx(1.0, abs=0.1)
    assert events.dtype == EVENT_DTYPE == RECORDING_EVENT_DTYPE
    assert np.all(np.diff(events["t"]) >= 0)
    # Leading edge brightens, trailing edge darkens: both polarities, about equally.
    assert 0.4 < events["p"].mean() < 0.6


def test_event_count_for_a_global_brightness_ramp() -> None:
    params = EventParams(threshold_sigma=0.03).noiseless()
    n = 5000
    sensor = EventSensor(params, 100, 50, np.full(n, 0.02), seed=4)
    levels = 0.02 * np.exp(np.linspace(0.0, 3.0, 31))  # +3 ln units in 30 steps
    pixels = np.arange(n)
    events = [sensor.step(10 * k, 10 * (k + 1), pixels, np.full(n, level)) for k, level in enumerate(levels[1:])]
    events.append(sensor.step(300, 5000, [], []))
    all_events = np.concatenate(events)
    expected = n * np.log((params.eps + levels[-1]) / (params.eps + levels[0])) / params.threshold_on
    assert all_events.size / expected == pytest.approx(1.0, abs=0.1)
    assert np.all(all_events["p"] == 1)
    assert all_events["x"].max() == 99 and all_events["y"].max() == 49


def test_crossings_within_a_step_are_spread_linearly_in_time() -> None:
    params = dataclasses.replace(EventParams(threshold_sigma=0.0).noiseless(), cutoff_hz=0.0)
    sensor = EventSensor(params, 1, 1, [0.1], t_us=1000, seed=0)
    events = sensor.step(1000, 2000, [0], [0.1 * np.exp(10 * 0.22)])  # ten thresholds in 1 ms
    assert 9 <= events.size <= 10
    gaps = np.diff(events["t"])
    assert np.all(np.abs(gaps - 100) <= 1)  # one crossing per 100 us
    assert events["t"].min() >= 1000 and events["t"].max() <= 2000


def test_low_pass_delays_a_step(rig: RigConfig) -> None:
    params = dataclasses.replace(EventParams(threshold_sigma=0.0).noiseless(), cutoff_hz=800.0)
    sensor = EventSensor(params, 200, 1, np.full(200, 0.01), seed=0)
    sensor.step(0, 1, np.arange(200), np.full(200, 0.01 * np.exp(2.2)))  # +10 thresholds at t = 0
    events = np.concatenate([sensor.step(t, t + 10, [], []) for t in range(1, 4000, 10)])
    tau_us = 1e6 / (2 * np.pi * 800.0)
    # Mean time of the k-th crossing of 1 - exp(-t / tau) = k / 10, k = 1..9 (the 10th waits on the reference phase).
    median = np.median(events["t"])
    assert events.size == pytest.approx(200 * 9.5, rel=0.1)
    assert median == pytest.approx(tau_us * np.log(1 / (1 - 0.5)), rel=0.15)
    assert events["t"].max() < 12 * tau_us


def test_dense_block_and_pixel_list_give_the_same_events(rig: RigConfig) -> None:
    # The same brightening of a rectangle, given as a dense PixelBlock or as flat pixel indices.
    params = EventParams.from_rig(rig)
    width, height = 64, 48
    base = np.full((height, width), 0.08)
    rng = np.random.default_rng(5)
    gain = np.exp(rng.normal(0.0, 0.3, (20, 30)))
    outs = []
    for dense in (True, False):
        sensor = EventSensor(params, width, height, base, x0=10, y0=20, seed=7)
        image = base.copy()
        events, t = [], 0
        for k in range(1, 6):
            values = image[10:30, 5:35].copy()
            changed = np.ones(values.shape, bool)
            changed[::3, ::4] = False
            values[changed] = (0.08 * gain ** (k / 5))[changed]
            image[10:30, 5:35] = values
            block = PixelBlock(10, 5, changed, values)
            if dense:
                events.append(sensor.step(t, t + 700, [], [], block=block))
            else:
                events.append(sensor.step(t, t + 700, block.flat_indices(width), block.changed_values()))
            t += 700
        events.append(sensor.step(t, t + 5000, [], []))
        outs.append(np.concatenate(events))
    assert outs[0].size > 100
    assert outs[0].tobytes() == outs[1].tobytes()


def test_same_seed_same_events(rig: RigConfig) -> None:
    params = EventParams.from_rig(rig)
    a, _ = translate_marker(rig, params, seed=7, steps=30)
    b, _ = translate_marker(rig, params, seed=7, steps=30)
    c, _ = translate_marker(rig, params, seed=8, steps=30)
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()


def test_refractory_period_spaces_each_pixels_events(rig: RigConfig) -> None:
    params = dataclasses.replace(EventParams.from_rig(rig), shot_noise_rate_hz=2000.0, leak_rate_hz=50.0)
    n = 400
    sensor = EventSensor(params, 20, 20, np.full(n, 0.01), seed=2)
    rng = np.random.default_rng(0)
    events = []
    for k in range(200):  # fast flicker: many crossings per step
        events.append(sensor.step(100 * k, 100 * (k + 1), np.arange(n), rng.uniform(0.01, 0.9, n)))
    ev = np.concatenate(events)
    pixel = ev["y"].astype(np.int64) * 20 + ev["x"]
    order = np.lexsort((ev["t"], pixel))
    same = np.diff(pixel[order]) == 0
    gaps = np.diff(ev["t"][order])[same]
    assert gaps.size > 5000
    assert gaps.min() >= params.refractory_us
    free = EventSensor(dataclasses.replace(params, refractory_us=0.0), 20, 20, np.full(n, 0.01), seed=2)
    rng = np.random.default_rng(0)
    n_free = sum(free.step(100 * k, 100 * (k + 1), np.arange(n), rng.uniform(0.01, 0.9, n)).size for k in range(200))
    assert n_free > 2 * ev.size


def quiet_run(rig: RigConfig, params: EventParams, seconds: float, step_us: int = 20_000) -> tuple[np.ndarray, int]:
    renderer = Renderer(rig)
    sensor = EventSensor.from_rig(rig, renderer.image, seed=5, params=params)
    events = [sensor.step(t, t + step_us, [], []) for t in range(0, int(seconds * 1e6), step_us)]
    return np.concatenate(events), sensor.size


def test_leak_rate_over_a_quiet_run(rig: RigConfig) -> None:
    params = dataclasses.replace(EventParams.from_rig(rig), shot_noise_rate_hz=0.0)
    events, pixels = quiet_run(rig, params, seconds=30.0)
    assert events["p"].min() == 1  # leak makes ON events only
    assert events.size / (pixels * 30.0) == pytest.approx(params.leak_rate_hz, rel=0.02)
    assert np.all(np.diff(events["t"]) >= 0)


def test_shot_noise_is_uniform_in_time_whatever_the_steps() -> None:
    from labrig.sim.events import NOISE_HORIZON_US

    params = dataclasses.replace(EventParams(), leak_rate_hz=0.0, refractory_us=0.0, shot_noise_rate_hz=50.0)
    n = 100 * 100
    steps = [0]
    rng = np.random.default_rng(1)
    while steps[-1] < 2_000_000:  # short steps, steps across the horizon's end, a step of several horizons
        steps.append(steps[-1] + int(rng.choice([7, 1_000, 33_333, NOISE_HORIZON_US - 1, 3 * NOISE_HORIZON_US + 5])))
    sensor = EventSensor(params, 100, 100, np.full(n, 0.5), seed=4)
    events = [sensor.step(t0, t1, [], []) for t0, t1 in pairwise(steps)]
    for (t0, t1), ev in zip(pairwise(steps), events):
        assert ev.size == 0 or (t0 <= ev["t"].min() and ev["t"].max() < t1)  # each event in its own step
    t = np.concatenate(events)["t"]
    expected = n * params.shot_noise_rate_hz * steps[-1] * 1e-6  # ~1e6 events
    assert t.size / expected == pytest.approx(1.0, rel=0.01)
    per_ms = np.bincount(t // 1000)  # uniform: Poisson counts per ms, no step or horizon in sight
    assert per_ms.mean() == pytest.approx(n * params.shot_noise_rate_hz * 1e-3, rel=0.01)
    assert per_ms.var() / per_ms.mean() == pytest.approx(1.0, abs=0.1)
    at_horizons = per_ms[np.arange(NOISE_HORIZON_US // 1000 - 1, per_ms.size, NOISE_HORIZON_US // 1000)]
    assert at_horizons.mean() == pytest.approx(per_ms.mean(), rel=0.1)
    again = EventSensor(params, 100, 100, np.full(n, 0.5), seed=4)
    assert np.concatenate([again.step(t0, t1, [], []) for t0, t1 in pairwise(steps)]).tobytes() == (
        np.concatenate(events).tobytes())


def test_shot_noise_rate_over_a_quiet_run(rig: RigConfig) -> None:
    params = dataclasses.replace(EventParams.from_rig(rig), leak_rate_hz=0.0)
    events, pixels = quiet_run(rig, params, seconds=10.0)
    expected = pixels * 10.0 * params.shot_noise_rate_hz  # ~245k: Poisson sd 0.2 %
    assert events.size / expected == pytest.approx(1.0, rel=0.02)
    assert events["p"].mean() == pytest.approx(0.5, abs=0.01)
    roi = rig.roi
    assert events["x"].min() >= roi.x0_px and events["x"].max() < roi.x1_px
    assert events["y"].min() >= roi.y0_px and events["y"].max() < roi.y1_px


def test_step_checks_time(rig: RigConfig) -> None:
    sensor = EventSensor(EventParams(), 4, 4, np.full(16, 0.1), t_us=100)
    with pytest.raises(ValueError):
        sensor.step(0, 200, [], [])
    with pytest.raises(ValueError):
        sensor.step(100, 100, [], [])
