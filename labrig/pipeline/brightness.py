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
:func:`brightness_channel` turns it into the network's channel: events per pixel
(the count over the cell's pixel area) minus the map's median (the uniform drift of the
sensor's leak events, which fire ON at a steady rate on every pixel), over
``scale_events_per_px`` (reference events), clipped (a hot pixel's count grows without bound).

Training and run time build the channel with these functions (:mod:`labrig.training.state_data`,
:mod:`labrig.pipeline.depth_sources`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.ndimage import uniform_filter

from labrig.calibration.event_thresholds_file import ContrastThresholds
from labrig.config import Roi
from labrig.errors import LabrigError
from labrig.physics.grid import GRID_SHAPE, grid_cells_of_pixels

F32 = npt.NDArray[np.float32]
#: A gated leak (``rest_tau_s``) is applied at most this often (us of stream time).
LEAK_STEP_US = 10_000


@dataclass(frozen=True)
class BrightnessParams:
    """The integrator's leak ``tau_s`` (s), the channel's unit ``scale_events_per_px`` (reference events per
    pixel for one unit: ``scale_events_per_px * 0.22`` ln of log-intensity change) and its clip ``clip``
    (units, either sign).

    ``rest_tau_s`` (s; None: one leak for every cell): the leak of the cells that hold no change (the
    gel at rest there), which bounds their noise; a cell whose change since rest, averaged over it and
    its 8 neighbours, is at least ``floor_events_per_px`` (reference events per pixel) holds it and
    leaks only with ``tau_s``, so a press is kept as long as it lasts."""

    tau_s: float = 30.0
    scale_events_per_px: float = 2.0
    clip: float = 4.0
    rest_tau_s: float | None = None
    floor_events_per_px: float = 0.3

    def __post_init__(self) -> None:
        if not (self.tau_s > 0 and self.scale_events_per_px > 0 and self.clip > 0 and self.floor_events_per_px > 0):
            raise LabrigError("the brightness channel's tau_s, scale_events_per_px, clip and floor_events_per_px must "
                              "be positive")
        if self.rest_tau_s is not None and not 0 < self.rest_tau_s <= self.tau_s:
            raise LabrigError("the brightness channel's rest_tau_s must be positive and at most tau_s")

    def to_card(self) -> dict[str, float]:
        card = {"tau_s": self.tau_s, "scale_events_per_px": self.scale_events_per_px, "clip": self.clip}
        if self.rest_tau_s is not None:
            card.update(rest_tau_s=self.rest_tau_s, floor_events_per_px=self.floor_events_per_px)
        return card

    @classmethod
    def from_card(cls, section: dict[str, float] | None) -> BrightnessParams:
        keys = ("tau_s", "scale_events_per_px", "clip", "rest_tau_s", "floor_events_per_px")
        return cls(**{k: float(v) for k, v in (section or {}).items() if k in keys})


def signed_counts(events: npt.NDArray, roi: Roi, grid_shape: tuple[int, int] = GRID_SHAPE,
                  thresholds: ContrastThresholds | None = None) -> F32:
    """(rows, cols) float32: the log-intensity change per grid cell (the cells of ``sae_grid``) in reference
    events, summed over its pixels: ON minus OFF events, each weighted by its cell's threshold over
    :data:`~labrig.calibration.event_thresholds_file.NOMINAL_THRESHOLD_LN` when ``thresholds`` are given
    (else 1); events outside the ROI are dropped."""
    rows, cols = grid_shape
    if len(events) == 0:
        return np.zeros(grid_shape, np.float32)
    cell, inside = grid_cells_of_pixels(events["x"], events["y"], roi.x0_px, roi.y0_px, roi.width_px, roi.height_px,
                                        grid_shape)
    cell, on = cell[inside], events["p"][inside] > 0
    if thresholds is None:
        weight = np.where(on, 1.0, -1.0)
    else:
        if thresholds.on_ln.shape != grid_shape:
            raise LabrigError(f"{thresholds.source}: thresholds on a {thresholds.on_ln.shape} grid, the channel's is "
                              f"{grid_shape}")
        on_weight, off_weight = thresholds.reference_weights
        weight = np.where(on, on_weight[cell], off_weight[cell])
    counts = np.bincount(cell, weights=weight, minlength=rows * cols)
    return counts.reshape(grid_shape).astype(np.float32)


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
        self.t_us: float | None = None

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
        map's median and averaged with its 8 neighbours, is under ``floor_events_per_px``."""
        change = self.counts - np.float32(np.median(self.counts))
        floor = np.float32(self.params.floor_events_per_px * self.pixels_per_cell)
        quiet = np.abs(uniform_filter(change, 3, mode="nearest")) < floor
        drift = np.float32(self._added[quiet].mean() if quiet.any() else np.median(self._added))
        self.counts -= drift
        rest = np.float32(math.exp(-dt_s / rest_tau_s))
        hold = np.float32(math.exp(-dt_s / self.params.tau_s))
        self.counts *= np.where(quiet, rest, hold)
        self._added[...] = 0.0

    def add_events(self, events: npt.NDArray, t1_us: float) -> F32:
        return self.add(signed_counts(events, self.roi, self.grid_shape, self.thresholds), t1_us)

    def reset(self, t_us: float | None = None) -> None:
        """Forget the count (the gel is at rest)."""
        self.counts[...] = 0.0
        self._added[...] = 0.0
        self.t_us = t_us

    def channel(self) -> F32:
        return brightness_channel(self.counts, self.pixels_per_cell, self.params)


def brightness_channel(counts: F32, pixels_per_cell: float, params: BrightnessParams) -> F32:
    """(rows, cols) float32: integrated counts per pixel less their median, in units of ``scale_events_per_px``, clipped."""
    per_px = np.asarray(counts, np.float32) / np.float32(pixels_per_cell)
    out = (per_px - np.float32(np.median(per_px))) / np.float32(params.scale_events_per_px)
    return np.clip(out, -params.clip, params.clip).astype(np.float32)
