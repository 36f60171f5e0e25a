"""The membrane's brightness change since rest, integrated from the events' polarities: the gel's state.

An event camera reports changes of log intensity: a pixel fires ON each time its log
intensity rises by its contrast threshold C_on, OFF each time it falls by C_off. Summed over
time, ``C_on`` times its ON events less ``C_off`` times its OFF events is a pixel's
log-intensity change since counting began, to within one threshold. The thresholds are the
camera's (its biases, each pixel's mismatch): measured per grid cell by ``labrig calibrate
events`` (:class:`~labrig.calibration.event_thresholds_file.ContrastThresholds`), they turn the
counts into a unit that no camera setting moves. The unit here is the **reference event**: the
change of log intensity over :data:`~labrig.calibration.event_thresholds_file.NOMINAL_THRESHOLD_LN`
(0.22 ln, the IMX636's nominal 25 %), the events a reference sensor would have fired; an ON event
counts ``C_on / 0.22`` of them, an OFF event ``-C_off / 0.22``. Uncalibrated, every event counts
one (the nominal sensor). Under the LED ring a dented membrane is brighter where it slopes (the
slope shading of :mod:`labrig.sim.shading`; a real gel does the same), and a marker that moved
leaves an OFF patch where it was and an ON patch where it is. So the integrated count is the
image's change since rest: a still dent, which a 10 ms SAE cannot see, stays in it.

:class:`BrightnessIntegrator` keeps it on the network grid (:mod:`labrig.physics.grid`, the
cells of :func:`labrig.pipeline.sae.sae_grid`), per window:

    A(t1) = A(t_prev) exp(-(t1 - t_prev) / tau) + sum of the window's signed events per cell

(the leak's decay within one window is neglected: windows are 3-400 ms, ``tau`` tens of
seconds). The leak forgets what a pixel's threshold mismatch and background noise add up over
minutes, and with them a press held that long. The gated leak (``BrightnessParams.rest_tau_s``)
leaks only where the gel is at rest: each 10 ms step removes the uniform drift and decays the
quiet cells quickly, while the cells that hold a change keep it (:meth:`BrightnessIntegrator._gated_leak`).
A DVS pixel is silent inside its dead band, so a press that is undone leaves about one event per
pixel where it was; with ``BrightnessParams.release_fraction`` the integrator starts again from zero
once the change its held cells keep has fallen under that fraction of its peak and stopped falling
(the release: the image says the press is undone; a press hardly moves the markers at the gel's
centre, so they cannot say it).
:func:`brightness_channel` turns it into the network's channel: events per pixel
(the count over the cell's pixel area) minus the map's median (the uniform drift of the
sensor's leak events, which fire ON at a steady rate on every pixel), over
``scale_events_per_px`` (reference events), clipped (a hot pixel's count grows without bound).

**The light, in reference units.** The membrane brightens by ``1 + g |grad d|`` where it slopes
(:mod:`labrig.calibration.slope_response`), and ``g``, the slope gain, is the lab's light and
membrane. With ``BrightnessParams.reference_slope_gain`` set (the network was trained so) and the
camera's slope gain measured (``events.toml`` ``[shading]``), :func:`reference_light` turns every
cell's change ``L`` into what the reference light would have made of the same slope,
``ln(1 + (g_ref / g)(e^L - 1))``, before the unit and the clip.

Training and run time build the channel with these functions (:mod:`labrig.training.state_data`,
:mod:`labrig.pipeline.depth_sources`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.calibration.event_counts import signed_counts
from labrig.calibration.event_thresholds_file import NOMINAL_THRESHOLD_LN, ContrastThresholds
from labrig.config import Roi
from labrig.errors import LabrigError
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.dead_band import PolarityMemory

F32 = npt.NDArray[np.float32]
#: A gated leak (``rest_tau_s``) is applied at most this often (us of stream time).
LEAK_STEP_US = 10_000
#: The reference light's slope gain (dimensionless): the light a channel under the reference light is expressed
#: in. Any fixed value would serve; this one is the reference sensor's as the calibration press measures it
#: (:mod:`labrig.protocol.light_calibration`), so that sensor's channel is about unchanged.
REFERENCE_SLOPE_GAIN = 2.4
#: A light whose slope gain is under this (dimensionless) is dimmer than any the brightness networks were checked on
#: (the stress grid's LED slope gain axis, docs/depthnet.md, from 1.0, where the bundled network's normal force error
#: is already 1.9x the reference light's): a dent's shallow flanks brighten the membrane by less than one contrast
#: threshold. Warned, not refused.
DIM_LIGHT_SLOPE_GAIN = 1.0


def dim_light_warning(slope_gain: float | None) -> str | None:
    """One line for a light too dim in its slope response for the brightness channel (None: fine or not measured)."""
    if slope_gain is None or round(slope_gain, 2) >= DIM_LIGHT_SLOPE_GAIN:  # as printed: 0.998 is the 1.0 checked
        return None
    return (f"the light's slope gain is {slope_gain:.2f}, under {DIM_LIGHT_SLOPE_GAIN:g}: dimmer than any light the "
            "estimator was checked on, and a dent's shallow flanks brighten the membrane by less than one contrast "
            "threshold (docs/depthnet.md); light the gel at a more grazing angle or lower the contrast thresholds (biases)")


#: The release waits while the held change still falls by more than this fraction of itself per ``release_s``
#: (the gel unloading), averaged over the time it has been under the release fraction.
RELEASE_SETTLE = 0.1


#: The brightness settings that are switches (true or false on a card), the others being numbers.
BOOLEAN_KEYS = ("dead_band", "brightening_only")


@dataclass(frozen=True)
class BrightnessParams:
    """The integrator's leak ``tau_s`` (s), the channel's unit ``scale_events_per_px`` (reference events per
    pixel for one unit: ``scale_events_per_px * 0.22`` ln of log-intensity change) and its clip ``clip``
    (units, either sign).

    ``rest_tau_s`` (s; None: one leak for every cell): the leak of the cells that hold no change (the
    gel at rest there), which bounds their noise; a cell whose change since rest, averaged over it and
    its 8 neighbours, is at least ``floor_events_per_px`` (reference events per pixel) holds it and
    leaks only with ``tau_s``, so a press is kept as long as it lasts.

    ``release_fraction`` (dimensionless; None: off; needs ``rest_tau_s``): the release. The press is
    undone, and the integrator starts again from zero, once the change the held cells keep, summed, has
    stayed under this fraction of the most it has been since the last start for ``release_s`` (s): an
    undone press leaves about one event per pixel where it was (each pixel's dead band), which the
    gate would otherwise hold as a shallow dent.

    ``moving_ratio`` (dimensionless; None: off; needs ``rest_tau_s``): the still gate. A step's held cells
    count their events only when the press moves: when their mean |change| over the step is more than
    ``moving_ratio`` times the quiet cells' (the sensor's noise, measured live). In a still step their
    events are the same noise, which a 10 h leak would otherwise keep for the whole press as a random walk
    (shot noise, the leak's mismatch from pixel to pixel), and are left out.

    ``reference_slope_gain`` (dimensionless; None: the light as it is): the slope gain the channel is
    expressed in (:func:`reference_light`).

    ``brightening_only``: under the reference light, only a brightening is converted (:func:`reference_light`): a
    darkening is a marker leaving its place, which the light's shape does not scale.

    ``dead_band``: count the events through :class:`~labrig.pipeline.dead_band.PolarityMemory`, which takes off
    the half dead band a pixel whose last event was OFF reads high (an undone press's ghost)."""

    tau_s: float = 30.0
    scale_events_per_px: float = 2.0
    clip: float = 4.0
    rest_tau_s: float | None = None
    floor_events_per_px: float = 0.3
    release_fraction: float | None = None
    release_s: float = 0.2
    moving_ratio: float | None = None
    reference_slope_gain: float | None = None
    dead_band: bool = False
    brightening_only: bool = False

    def __post_init__(self) -> None:
        if not (self.tau_s > 0 and self.scale_events_per_px > 0 and self.clip > 0 and self.floor_events_per_px > 0):
            raise LabrigError("the brightness channel's tau_s, scale_events_per_px, clip and floor_events_per_px must "
                              "be positive")
        if self.rest_tau_s is not None and not 0 < self.rest_tau_s <= self.tau_s:
            raise LabrigError("the brightness channel's rest_tau_s must be positive and at most tau_s")
        if self.release_fraction is not None and (self.rest_tau_s is None or not 0 < self.release_fraction < 1
                                                  or not self.release_s >= 0):
            raise LabrigError("the brightness channel's release needs rest_tau_s, a release_fraction between 0 and 1 "
                              "and a release_s of zero or more")
        if self.moving_ratio is not None and (self.rest_tau_s is None or not self.moving_ratio >= 1):
            raise LabrigError("the brightness channel's still gate needs rest_tau_s and a moving_ratio of 1 or more")
        if self.reference_slope_gain is not None and not self.reference_slope_gain > 0:
            raise LabrigError("the brightness channel's reference_slope_gain must be positive")

    def to_card(self) -> dict[str, float | bool]:
        card: dict[str, float | bool] = {"tau_s": self.tau_s, "scale_events_per_px": self.scale_events_per_px, "clip": self.clip}
        if self.rest_tau_s is not None:
            card.update(rest_tau_s=self.rest_tau_s, floor_events_per_px=self.floor_events_per_px)
        if self.release_fraction is not None:
            card.update(release_fraction=self.release_fraction, release_s=self.release_s)
        if self.moving_ratio is not None:
            card["moving_ratio"] = self.moving_ratio
        if self.reference_slope_gain is not None:
            card["reference_slope_gain"] = self.reference_slope_gain
        for flag in BOOLEAN_KEYS:
            if getattr(self, flag):
                card[flag] = True
        return card

    @classmethod
    def from_card(cls, section: dict[str, float | bool] | None) -> BrightnessParams:
        keys = ("tau_s", "scale_events_per_px", "clip", "rest_tau_s", "floor_events_per_px", "release_fraction",
                "release_s", "moving_ratio", "reference_slope_gain")
        section = section or {}
        numbers: dict[str, Any] = {k: float(v) for k, v in section.items() if k in keys}
        switches: dict[str, Any] = {k: bool(section.get(k)) for k in BOOLEAN_KEYS}
        return cls(**numbers, **switches)


class BrightnessIntegrator:
    """The leaky log-intensity change per grid cell in reference events (:func:`signed_counts`) since
    :meth:`reset`; ``thresholds``: the camera's, else nominal."""

    def __init__(self, roi: Roi, params: BrightnessParams | None = None, grid_shape: tuple[int, int] = GRID_SHAPE,
                 thresholds: ContrastThresholds | None = None) -> None:
        self.roi = roi
        self.params = params or BrightnessParams()
        self.thresholds = thresholds
        self.grid_shape = grid_shape
        self.pixels_per_cell = roi.width_px * roi.height_px / float(grid_shape[0] * grid_shape[1])
        self.counts = np.zeros(grid_shape, np.float32)
        self._added = np.zeros(grid_shape, np.float32)  # gated leak: the counts since its last step
        self.moving = True  # still gate: whether the last step found the press moving
        self.held_total = 0.0  # release: the change the held cells keep, summed (reference events)
        self._held_peak = 0.0  # the most it has been since the last start
        self._undone_s = 0.0  # how long it has stayed under release_fraction of that, without falling further
        self._undone_from = 0.0  # the held change when that began
        self.t_us: float | None = None
        self.memory = PolarityMemory(roi, grid_shape, thresholds) if self.params.dead_band else None

    def count(self, events: npt.NDArray) -> F32:
        """One window's events as :meth:`add` takes them: :func:`signed_counts`, or through :attr:`memory`
        (``dead_band``), which must then see every event once and in order."""
        if self.memory is not None:
            return self.memory.counts(events)
        return signed_counts(events, self.roi, self.grid_shape, self.thresholds)

    def add(self, counts: F32, t1_us: float) -> F32:
        """Fold in one window's :func:`signed_counts` ending at ``t1_us``; returns the integrated counts.

        One leak (``rest_tau_s`` None): the counts decay before the window's are added. Gated leak: a step
        of :meth:`_gated_leak` at most every :data:`LEAK_STEP_US` (a step reads the whole map)."""
        if self.params.rest_tau_s is None:
            if self.t_us is not None and t1_us > self.t_us:
                self.counts *= np.float32(math.exp(-(t1_us - self.t_us) * 1e-6 / self.params.tau_s))
            self.counts += counts
            self.t_us = t1_us if self.t_us is None else max(self.t_us, t1_us)
            return self.counts
        self.counts += counts
        self._added += counts
        if self.t_us is None:
            self.t_us = t1_us
        elif t1_us - self.t_us >= LEAK_STEP_US:
            self._gated_leak((t1_us - self.t_us) * 1e-6, self.params.rest_tau_s)
            self.t_us = t1_us
        return self.counts

    def _gated_leak(self, dt_s: float, rest_tau_s: float) -> None:
        """One step of the gated leak over ``dt_s``: the step's uniform drift (the mean of what the quiet cells
        gained: the sensor's leak events, a change of the light) leaves every cell, then the quiet cells
        decay with ``rest_tau_s`` and the others with ``tau_s``. A cell is quiet when its change, less the
        map's median and averaged with its 8 neighbours, is under ``floor_events_per_px``. With
        ``release_fraction`` set, a step that finds the press undone (:meth:`_released`) starts again from zero;
        with ``moving_ratio``, the held cells' changes pass :meth:`_still_gate`."""
        change = self.counts - map_median(self.counts)
        smoothed = np.abs(box_mean_3x3(change))
        quiet = smoothed < np.float32(self.params.floor_events_per_px * self.pixels_per_cell)
        if self.params.release_fraction is not None and self._released(float(smoothed[~quiet].sum()), dt_s):
            self.reset(self.t_us)
            return
        drift = np.float32(self._added[quiet].mean() if quiet.any() else map_median(self._added))
        self.counts -= drift
        if self.params.moving_ratio is not None:
            self._still_gate(quiet, self._added - drift)
        rest = np.float32(math.exp(-dt_s / rest_tau_s))
        hold = np.float32(math.exp(-dt_s / self.params.tau_s))
        self.counts *= np.where(quiet, rest, hold)
        self._added[...] = 0.0

    def _still_gate(self, quiet: npt.NDArray[np.bool_], step: F32) -> None:
        """Take the held cells' ``step`` (their change over this step, less the drift) back out of their counts
        unless they are more active than ``moving_ratio`` times the quiet cells (the press moves)."""
        assert self.params.moving_ratio is not None
        held = ~quiet
        if not held.any():
            self.moving = True
            return
        noise = float(np.abs(step[quiet]).mean()) if quiet.any() else 0.0
        self.moving = float(np.abs(step[held]).mean()) > self.params.moving_ratio * noise
        if not self.moving:
            self.counts[held] -= step[held]

    def _released(self, held_total: float, dt_s: float) -> bool:
        """Whether the held change, ``held_total`` (reference events) now, has stayed under ``release_fraction``
        of its peak for ``release_s``, falling meanwhile by no more than :data:`RELEASE_SETTLE` of itself per
        ``release_s`` (faster: the gel still unloading), ``dt_s`` being the time since the last step.

        The allowed fall grows with the time spent under the fraction, so the answer does not depend on how
        long the steps are: a window of half a second at rest carries the same slow fall as fifty of 10 ms."""
        self.held_total = held_total
        self._held_peak = max(self._held_peak, held_total)
        assert self.params.release_fraction is not None
        allowed = RELEASE_SETTLE * max(1.0, (self._undone_s + dt_s) / self.params.release_s) \
            if self.params.release_s > 0 else RELEASE_SETTLE
        if not held_total < self.params.release_fraction * self._held_peak:
            self._undone_s = self._undone_from = 0.0
        elif self._undone_from == 0.0 or held_total < (1.0 - allowed) * self._undone_from:
            self._undone_s, self._undone_from = 0.0, held_total
        else:
            self._undone_s += dt_s
        return self._undone_s >= self.params.release_s

    def add_events(self, events: npt.NDArray, t1_us: float) -> F32:
        return self.add(self.count(events), t1_us)

    def reset(self, t_us: float | None = None) -> None:
        """Forget the count (the gel is at rest)."""
        self.counts[...] = 0.0
        self._added[...] = 0.0
        self.moving = True
        self.held_total = self._held_peak = self._undone_s = self._undone_from = 0.0
        self.t_us = t_us
        if self.memory is not None:
            self.memory.reset()

    def channel(self) -> F32:
        slope_gain = None if self.thresholds is None else self.thresholds.slope_gain
        return brightness_channel(self.counts, self.pixels_per_cell, self.params, slope_gain)


def change_per_px(counts: npt.ArrayLike, pixels_per_cell: float) -> F32:
    """(rows, cols) float32: integrated counts (reference events per cell) per pixel, less their median (the
    uniform drift), in reference events; times ``NOMINAL_THRESHOLD_LN`` it is the log-intensity change (ln)."""
    per_px = np.asarray(counts, np.float32) / np.float32(pixels_per_cell)
    return per_px - map_median(per_px)


def map_median(values: F32) -> np.float32:
    """The median of a float32 map (``np.median``'s value; the maps hold no NaN, so none is looked for)."""
    flat = values.ravel()
    k = flat.size // 2
    ordered = np.partition(flat, k)
    if flat.size % 2:
        return np.float32(ordered[k])
    # the lower middle is the largest of the k below: numpy's partition at two kth values costs ten times one
    return np.float32((ordered[:k].max() + ordered[k]) / 2)


def box_mean_3x3(values: F32) -> F32:
    """(rows, cols) float32: each cell's mean with its 8 neighbours, the edge cells repeated outwards (scipy's
    ``uniform_filter(values, 3, mode="nearest")`` to float32 rounding)."""
    import cv2  # deferred: OpenCV is heavy to import

    return np.asarray(cv2.blur(np.asarray(values, np.float32), (3, 3), borderType=cv2.BORDER_REPLICATE))


def reference_light(change_ln: npt.ArrayLike, slope_gain: float, reference_slope_gain: float,
                    floor_ln: float = -4.0, brightening_only: bool = False) -> F32:
    """(rows, cols) float32: a log-intensity change (ln) under a light of ``slope_gain`` expressed under the
    reference light's ``reference_slope_gain``: ``ln(1 + (g_ref / g)(e^L - 1))``, exact for the slope
    shading ``1 + g |grad d|``; an argument at or below zero (a darkening the reference light cannot make)
    gives ``floor_ln``. ``brightening_only``: a darkening (L < 0), which the shading cannot make (a marker
    that left its place), stays as it is."""
    change = np.asarray(change_ln, np.float64)
    inside = 1.0 + (reference_slope_gain / slope_gain) * np.expm1(change)
    converted = np.log(np.maximum(inside, math.exp(floor_ln)))
    if brightening_only:
        converted = np.where(change < 0.0, change, converted)
    return converted.astype(np.float32)


def brightness_channel(counts: F32, pixels_per_cell: float, params: BrightnessParams,
                       slope_gain: float | None = None) -> F32:
    """(rows, cols) float32: integrated counts per pixel less their median, under the reference light when
    ``params.reference_slope_gain`` and the camera's ``slope_gain`` are both known (:func:`reference_light`),
    in units of ``scale_events_per_px``, clipped."""
    change = change_per_px(counts, pixels_per_cell)
    if params.reference_slope_gain is not None and slope_gain is not None:
        floor_ln = -2.0 * params.clip * params.scale_events_per_px * NOMINAL_THRESHOLD_LN
        change = reference_light(change * np.float32(NOMINAL_THRESHOLD_LN), slope_gain, params.reference_slope_gain,
                                 floor_ln, params.brightening_only) / np.float32(NOMINAL_THRESHOLD_LN)
    out = change / np.float32(params.scale_events_per_px)
    return np.clip(out, -params.clip, params.clip).astype(np.float32)
