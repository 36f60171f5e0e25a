"""Contrast thresholds from events: every network-grid cell's ON and OFF threshold, in ln units.

The scene (``labrig calibrate events`` records it on the virtual rig; a lab drives its LED ring
the same way): the gel at rest, the LED ring dimmed from full to ``1 / ratio`` along a slow
ramp, held, brightened back, held, ``cycles`` times. Every pixel's log intensity falls and rises
by ``A = ln(ratio)`` whatever its brightness, slowly enough that the refractory period and the
photoreceptor's bandwidth lose no event. The recording names its light (``extra_led_ratio``,
``extra_led_cycles``, ``extra_led_ramps_json``: start, end and direction of each ramp, host us).

Model. A pixel fires OFF each time its log intensity falls ``C_off`` below its reference, ON each
time it rises ``C_on`` above it, and stays silent in between (the dead band ``C_on + C_off``
wide). Over a ramp of ``A`` the events cover ``A`` less the distance the pixel travels inside the
dead band, which on average over pixels at every phase of it is half the band:

    n_off C_off = A - (C_on + C_off) / 2,      n_on C_on = A - (C_on + C_off) / 2

(``n_on``, ``n_off``: events per pixel per brightening / dimming ramp). Solved per cell:

    C_on = A n_off / D,   C_off = A n_on / D,   D = n_on n_off + (n_on + n_off) / 2

(one threshold: ``n = A / C - 1``). The first cycle is left out (the pixels' references settle
into the cycle), and the background (leak and shot noise, counted per pixel and polarity in the
holds) is subtracted. Pixels that fire far more or far less than the median (hot, dead) are left
out of their cell; a cell with too few good pixels takes the median of the others.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.calibration.event_thresholds_file import ContrastThresholds
from labrig.config import Roi
from labrig.errors import CalibrationError
from labrig.physics.grid import GRID_SHAPE, grid_cells_of_pixels
from labrig.recording import Recording

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

#: Events after a ramp's end still belong to it for this long (us): the photoreceptor's settling.
SETTLE_US = 5_000
#: A pixel is left out when its ramp events are outside [1/HOT_DEAD_FACTOR, HOT_DEAD_FACTOR] x the median.
HOT_DEAD_FACTOR = 4.0
#: A cell needs this share of good pixels, and this many events per pixel per ramp of each polarity.
MIN_GOOD_SHARE = 0.25
MIN_EVENTS_PER_RAMP = 0.2


@dataclass(frozen=True)
class LedSchedule:
    """The scene's light: the LED's ratio between full and dimmed, the ramps (start us, end us, direction:
    -1 dims, +1 brightens), host time."""

    ratio: float
    ramps_us: tuple[tuple[int, int, int], ...]

    @property
    def amplitude_ln(self) -> float:
        return float(np.log(self.ratio))

    @classmethod
    def from_recording(cls, rec: Recording, ratio: float | None = None) -> LedSchedule:
        """The schedule a recording names (``extra_led_ratio``, ``extra_led_ramps_json``); ``ratio`` overrides."""
        attrs = rec.attrs
        raw = attrs.get("extra_led_ramps_json", "")
        if not raw:
            raise CalibrationError(f"{rec.path}: not an event-response recording (no extra_led_ramps_json: the LED "
                                   "ramps' times); record one with `labrig calibrate events` and no recording")
        try:
            ramps = tuple((int(a), int(b), int(d)) for a, b, d in json.loads(raw))
        except (ValueError, TypeError) as exc:
            raise CalibrationError(f"{rec.path}: extra_led_ramps_json is malformed ({exc})") from None
        value = ratio if ratio is not None else attrs.get("extra_led_ratio")
        if value is None or not float(value) > 1.0:
            raise CalibrationError(f"{rec.path}: the LED ratio must be above 1 (got {value!r}); give it with --led-ratio")
        if not ramps or any(d not in (-1, 1) or b <= a for a, b, d in ramps):
            raise CalibrationError(f"{rec.path}: extra_led_ramps_json needs ramps (start, end > start, direction +-1)")
        return cls(float(value), ramps)


@dataclass(frozen=True)
class EventThresholdFit:
    """The fitted thresholds and how well the scene measured them."""

    thresholds: ContrastThresholds
    schedule: LedSchedule
    ramps_used: int
    events_per_ramp_on: float  # median over cells, per pixel
    events_per_ramp_off: float
    background_rate_hz: float  # mean per pixel, both polarities
    pixels_rejected: int
    cells_filled: int
    recording: Path

    @property
    def on_ln_median(self) -> float:
        return float(np.median(self.thresholds.on_ln))

    @property
    def off_ln_median(self) -> float:
        return float(np.median(self.thresholds.off_ln))

    @property
    def on_off_ratio(self) -> float:
        """Median over cells of C_on / C_off."""
        return float(np.median(self.thresholds.on_ln / self.thresholds.off_ln))

    def summary(self) -> dict[str, Any]:
        """The file's and ``--json``'s figures, grouped as ``events.toml`` holds them."""
        on, off = self.thresholds.on_ln, self.thresholds.off_ln
        return {
            "thresholds": {
                "on_ln_median": round(self.on_ln_median, 5), "off_ln_median": round(self.off_ln_median, 5),
                "on_off_ratio": round(self.on_off_ratio, 4),
                "on_ln_cell_spread": round(float(np.std(on)), 5), "off_ln_cell_spread": round(float(np.std(off)), 5),
            },
            "scene": {"led_ratio": self.schedule.ratio, "amplitude_ln": round(self.schedule.amplitude_ln, 5),
                      "ramps": len(self.schedule.ramps_us), "ramps_used": self.ramps_used},
            "quality": {
                "events_per_ramp_on": round(self.events_per_ramp_on, 3),
                "events_per_ramp_off": round(self.events_per_ramp_off, 3),
                "background_rate_hz": round(self.background_rate_hz, 4),
                "pixels_rejected": self.pixels_rejected, "cells_filled": self.cells_filled,
            },
        }


def thresholds_from_counts(n_on: npt.ArrayLike, n_off: npt.ArrayLike, amplitude_ln: float) -> tuple[F64, F64]:
    """(C_on, C_off) ln from events per pixel per brightening (``n_on``) and dimming (``n_off``) ramp of
    ``amplitude_ln`` (the module docstring's model); nan where the counts cannot give them."""
    on, off = np.asarray(n_on, np.float64), np.asarray(n_off, np.float64)
    det = on * off + 0.5 * (on + off)
    with np.errstate(divide="ignore", invalid="ignore"):
        c_on = np.where(det > 0, amplitude_ln * off / det, np.nan)
        c_off = np.where(det > 0, amplitude_ln * on / det, np.nan)
    return c_on, c_off


def fit_event_thresholds(recording: str | Path, roi: Roi, *, ratio: float | None = None,
                         grid_shape: tuple[int, int] = GRID_SHAPE) -> EventThresholdFit:
    """Per-cell ON and OFF contrast thresholds (ln) over ``roi`` from an event-response recording."""
    path = Path(recording)
    with Recording(path) as rec:
        schedule = LedSchedule.from_recording(rec, ratio)
        events = rec.events_between(0, rec.end_us())
        end_us = rec.end_us()
    first_cycle_end = _first_cycle_end(schedule)
    used = [r for r in schedule.ramps_us if r[0] >= first_cycle_end] or list(schedule.ramps_us)
    n_pixels = roi.width_px * roi.height_px
    x = events["x"].astype(np.int64) - roi.x0_px
    y = events["y"].astype(np.int64) - roi.y0_px
    inside = (x >= 0) & (y >= 0) & (x < roi.width_px) & (y < roi.height_px)
    pixel = (y * roi.width_px + x)[inside]
    on = events["p"][inside] > 0
    t = events["t"][inside]

    in_ramp = np.zeros(len(t), bool)
    counted = {1: np.zeros(len(t), bool), -1: np.zeros(len(t), bool)}
    for t0, t1, direction in schedule.ramps_us:
        span = (t >= t0) & (t < t1 + SETTLE_US)
        in_ramp |= span
        if (t0, t1, direction) in used:
            counted[direction] |= span
    ramps_up = sum(1 for r in used if r[2] > 0)
    ramps_down = len(used) - ramps_up
    ramp_us_up = sum(r[1] - r[0] + SETTLE_US for r in used if r[2] > 0)
    ramp_us_down = sum(r[1] - r[0] + SETTLE_US for r in used if r[2] < 0)
    quiet_us = end_us - sum(r[1] - r[0] + SETTLE_US for r in schedule.ramps_us)
    if quiet_us <= 0 or ramps_up == 0 or ramps_down == 0:
        raise CalibrationError(f"{path}: the scene needs ramps both ways and quiet holds between them")

    on_up = np.bincount(pixel[counted[1] & on], minlength=n_pixels).astype(np.float64)
    off_down = np.bincount(pixel[counted[-1] & ~on], minlength=n_pixels).astype(np.float64)
    quiet = ~in_ramp
    bg_on = np.bincount(pixel[quiet & on], minlength=n_pixels) / (quiet_us * 1e-6)
    bg_off = np.bincount(pixel[quiet & ~on], minlength=n_pixels) / (quiet_us * 1e-6)
    per_ramp_on = (on_up - bg_on * ramp_us_up * 1e-6) / ramps_up
    per_ramp_off = (off_down - bg_off * ramp_us_down * 1e-6) / ramps_down

    total = per_ramp_on + per_ramp_off
    median = float(np.median(total))
    if not median > 0:
        raise CalibrationError(f"{path}: the pixels did not fire on the LED ramps; is the LED ring wired and the "
                               "camera looking at the gel?")
    good = (total > median / HOT_DEAD_FACTOR) & (total < median * HOT_DEAD_FACTOR)
    xs, ys = np.meshgrid(np.arange(roi.width_px), np.arange(roi.height_px))
    cell, _ = grid_cells_of_pixels(xs.ravel() + roi.x0_px, ys.ravel() + roi.y0_px, roi.x0_px, roi.y0_px,
                                   roi.width_px, roi.height_px, grid_shape)
    n_cells = grid_shape[0] * grid_shape[1]
    pixels_per_cell = np.bincount(cell, minlength=n_cells)
    good_per_cell = np.bincount(cell[good], minlength=n_cells)
    cell_on = np.bincount(cell[good], weights=per_ramp_on[good], minlength=n_cells) / np.maximum(good_per_cell, 1)
    cell_off = np.bincount(cell[good], weights=per_ramp_off[good], minlength=n_cells) / np.maximum(good_per_cell, 1)
    c_on, c_off = thresholds_from_counts(cell_on, cell_off, schedule.amplitude_ln)
    ok = ((good_per_cell >= MIN_GOOD_SHARE * pixels_per_cell) & (cell_on >= MIN_EVENTS_PER_RAMP)
          & (cell_off >= MIN_EVENTS_PER_RAMP) & np.isfinite(c_on) & np.isfinite(c_off))
    if ok.sum() < 0.5 * n_cells:
        raise CalibrationError(f"{path}: only {int(ok.sum())} of {n_cells} grid cells fired enough on the LED ramps "
                               f"(median {median / 2:.2f} events per pixel per ramp); use a larger LED ratio or more cycles")
    c_on = np.where(ok, c_on, np.median(c_on[ok]))
    c_off = np.where(ok, c_off, np.median(c_off[ok]))
    thresholds = ContrastThresholds(c_on.reshape(grid_shape).astype(np.float32),
                                    c_off.reshape(grid_shape).astype(np.float32), roi, str(path))
    return EventThresholdFit(
        thresholds, schedule, len(used), float(np.median(cell_on[ok])), float(np.median(cell_off[ok])),
        float(np.mean(bg_on + bg_off)), int((~good).sum()), int((~ok).sum()), path,
    )


def _first_cycle_end(schedule: LedSchedule) -> int:
    """The end of the first ramp of each direction (the references settle into the cycle over it)."""
    ends: dict[int, int] = {}
    for _t0, t1, direction in schedule.ramps_us:
        ends.setdefault(direction, t1)
    return max(ends.values())
