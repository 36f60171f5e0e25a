"""The dead band undone: signed counts that read a pixel's log-intensity change since rest without the half band
a pixel whose last event was OFF reads high."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.calibration.event_thresholds_file import NOMINAL_THRESHOLD_LN, ContrastThresholds
from labrig.config import Roi
from labrig.eventtypes import EVENT_DTYPE
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.brightness import BrightnessIntegrator, BrightnessParams, signed_counts
from labrig.pipeline.dead_band import PolarityMemory
from labrig.sim.events import EventParams, EventSensor

# 2 x 2 pixels per grid cell
ROI = Roi(100, 50, 100 + 2 * GRID_SHAPE[1], 50 + 2 * GRID_SHAPE[0])


def _events(x: list[int], y: list[int], p: list[int]) -> np.ndarray:
    ev = np.zeros(len(x), EVENT_DTYPE)
    ev["x"], ev["y"], ev["p"] = x, y, p
    ev["t"] = np.arange(1, len(x) + 1)
    return ev


def test_a_pixel_whose_last_event_is_off_gives_back_half_its_band() -> None:
    memory = PolarityMemory(ROI)
    x, y = ROI.x0_px, ROI.y0_px
    assert memory.counts(_events([x, x], [y, y], [1, 1]))[0, 0] == 2.0  # ON, ON: as counted
    assert memory.counts(_events([x], [y], [0]))[0, 0] == -2.0  # turns OFF: -1, and the half band -1
    assert memory.counts(_events([x], [y], [0]))[0, 0] == -1.0  # OFF again: as counted
    assert memory.counts(_events([x], [y], [1]))[0, 0] == 2.0  # back ON: +1, and the half band back
    assert memory.counts(_events([x + 1], [y], [0]))[0, 0] == -2.0  # another pixel of the cell, its own memory


def test_reset_forgets_from_the_next_window() -> None:
    memory = PolarityMemory(ROI)
    x, y = ROI.x0_px, ROI.y0_px
    memory.counts(_events([x], [y], [0]))
    memory.reset()
    assert memory.counts(_events([x], [y], [1]))[0, 0] == 1.0  # no OFF remembered: no half band given back


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_it_differs_from_signed_counts_only_by_the_half_bands(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 300))
    x = rng.integers(ROI.x0_px - 5, ROI.x0_px + 12, n)
    y = rng.integers(ROI.y0_px - 5, ROI.y0_px + 12, n)
    ev = _events(list(x), list(y), list(rng.integers(0, 2, n)))
    on = rng.uniform(0.15, 0.4, GRID_SHAPE).astype(np.float32)
    off = rng.uniform(0.15, 0.4, GRID_SHAPE).astype(np.float32)
    thresholds = ContrastThresholds(on, off, ROI)
    memory = PolarityMemory(ROI, thresholds=thresholds)
    got = memory.counts(ev)
    expected = signed_counts(ev, ROI, thresholds=thresholds).astype(np.float64)
    inside = (ev["x"] >= ROI.x0_px) & (ev["x"] < ROI.x1_px) & (ev["y"] >= ROI.y0_px) & (ev["y"] < ROI.y1_px)
    pixel = (ev["y"][inside] - ROI.y0_px) * ROI.width_px + ev["x"][inside] - ROI.x0_px
    last_off = np.zeros(ROI.width_px * ROI.height_px, bool)
    last_off[pixel] = True  # touched ...
    for px, p in zip(pixel, ev["p"][inside]):
        last_off[px] = p == 0  # ... and whose last event is OFF
    cells = ((ev["y"][inside] - ROI.y0_px) // 2) * GRID_SHAPE[1] + (ev["x"][inside] - ROI.x0_px) // 2
    touched_off = np.zeros(GRID_SHAPE[0] * GRID_SHAPE[1])
    for px, c in set(zip(pixel.tolist(), cells.tolist())):
        touched_off[c] += last_off[px]
    half_band = 0.5 * (on + off).ravel() / NOMINAL_THRESHOLD_LN
    np.testing.assert_allclose(got.ravel(), expected.ravel() - touched_off * half_band, atol=1e-4)


def _sensor_round_trip(rise_ln: float, fall_ln: float, seed: int = 3) -> tuple[float, float]:
    """A block of the sim's pixels (leak, threshold spread, no shot noise) at rest, brightened by ``rise_ln`` and
    darkened by ``fall_ln``: the mean change per pixel (ln) as signed counts and as the memory read it."""
    params = replace(EventParams(), shot_noise_rate_hz=0.0, refractory_us=0.0)
    width, height = ROI.width_px, ROI.height_px
    n = width * height
    sensor = EventSensor(params, width, height, np.full(n, 0.05), x0=ROI.x0_px, y0=ROI.y0_px, seed=seed)
    memory = PolarityMemory(ROI)
    plain = np.zeros(GRID_SHAPE, np.float64)
    band = np.zeros(GRID_SHAPE, np.float64)
    level = np.log(0.05 + params.eps)
    t = 0
    for target in (level + rise_ln, level + rise_ln - fall_ln):
        for k in range(1, 11):
            value = np.exp(level + (target - level) * k / 10) - params.eps
            ev = sensor.step(t, t + 1000, np.arange(n), np.full(n, value))
            t += 1000
            plain += signed_counts(ev, ROI)
            band += memory.counts(ev)
        level = target
    per_px = NOMINAL_THRESHOLD_LN / n
    return float(plain.sum() * per_px), float(band.sum() * per_px)


@pytest.mark.parametrize(("rise_ln", "fall_ln"), [(0.9, 0.9), (1.5, 1.5), (0.1, 0.0), (0.5, 0.0), (0.0, 0.5),
                                                   (0.3, 0.6)])
def test_the_sims_pixels_read_true_through_the_memory(rise_ln: float, fall_ln: float) -> None:
    plain, band = _sensor_round_trip(rise_ln, fall_ln)
    true = rise_ln - fall_ln
    assert band == pytest.approx(true, abs=0.04)
    if fall_ln >= 0.5:  # the way back crossed bands: signed counts keep about one band more (less when it ends low)
        assert abs(plain - true) > 0.15


def test_a_partial_fall_reads_closer_than_signed_counts() -> None:
    """Pixels that fell back less than a band since their last ON event are where the memory cannot tell."""
    plain, band = _sensor_round_trip(0.6, 0.3)
    assert abs(band - 0.3) < abs(plain - 0.3) - 0.04


def test_an_integrator_with_the_dead_band_counts_through_its_memory_and_resets_it() -> None:
    params = replace(BrightnessParams(), dead_band=True)
    integrator = BrightnessIntegrator(ROI, params)
    assert integrator.memory is not None
    x, y = ROI.x0_px, ROI.y0_px
    integrator.add_events(_events([x, x], [y, y], [1, 0]), 1000.0)
    assert integrator.counts[0, 0] == -1.0  # +1, -1, and the half band
    integrator.reset(2000.0)
    integrator.add_events(_events([x], [y], [1]), 3000.0)
    assert integrator.counts[0, 0] == 1.0
    assert BrightnessParams.from_card(params.to_card()).dead_band
    assert not BrightnessParams.from_card(BrightnessParams().to_card()).dead_band
