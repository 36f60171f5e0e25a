"""Signed event counts that undo the pixels' dead band: the log-intensity change since rest, unbiased both ways.

A DVS pixel remembers the log intensity of its last event, its reference ``R``, and fires again only
when the intensity leaves the dead band ``(R - C_off, R + C_on)``. Where the intensity ``L`` sits in
that band is lost, so ON minus OFF events (weighted by their thresholds, :func:`signed_counts`) tell
``L - L_rest`` only up to the distance ``D = L - R`` the pixel has travelled inside its band:

    L - L_rest = (R - R_rest) + D - D_rest

Averaged over the pixels of a cell, ``D`` is uniform over the part of the band the last crossing left
the pixel in: ``[0, C_on)`` after an ON event (a rise carries it on towards ``C_on``), ``(-C_off, 0]``
after an OFF event. At rest a pixel sits in its leak's steady state, ``D_rest`` uniform in ``[0, C_on)``
(the background activity drifts every pixel up to its next ON event). So a pixel whose last event
since rest was ON reads true on average, and one whose last event was OFF reads
``(C_on + C_off) / 2`` high: a dent pressed and released leaves about one event per pixel it touched
(the band the way back had to cross first), which the integrated change would keep as a ghost dent, and
which a dim light, expressed under the reference light (:func:`labrig.pipeline.brightness.reference_light`),
magnifies. :class:`PolarityMemory` keeps each pixel's last polarity since rest and takes that half band
off when a pixel's last event turns OFF (and gives it back when it turns ON again).

What it assumes of the sensor: each pixel's thresholds are its cell's (``events.toml``); the background
activity is ON-going leak (the IMX636's is); shot noise that does not move the reference is counted as
a change, as :func:`signed_counts` counts it.
"""

from __future__ import annotations

import threading

import numpy as np
import numpy.typing as npt
from numba import njit

from labrig.calibration.event_thresholds_file import ContrastThresholds
from labrig.config import Roi
from labrig.errors import LabrigError
from labrig.physics.grid import GRID_SHAPE

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

#: A pixel's last polarity since rest: none yet, ON, OFF.
NONE, ON, OFF = 0, 1, -1


@njit(cache=True, nogil=True)
def _count(x_px, y_px, polarity, x0_px, y0_px, width_px, height_px, rows, cols, on_weight, off_weight, half_band,  # type: ignore[no-untyped-def]
           last, out):
    """Add each event inside the ROI to its grid cell of ``out`` (:func:`~labrig.physics.grid.grid_cells_of_pixels`'s
    cell): its polarity's weight, and the half band when its pixel's last polarity turns OFF (subtracted) or turns
    back ON from OFF (added); ``last`` (ROI pixels, row-major) is updated in place. ``off_weight`` is negative."""
    col_scale = cols / width_px
    row_scale = rows / height_px
    for i in range(x_px.shape[0]):
        x = np.int64(x_px[i]) - x0_px
        y = np.int64(y_px[i]) - y0_px
        if x < 0 or y < 0:
            continue
        c_col = np.int64((x + 0.5) * col_scale)
        c_row = np.int64((y + 0.5) * row_scale)
        if c_col >= cols or c_row >= rows:
            continue
        c = c_row * cols + c_col
        pixel = y * width_px + x
        was_off = last[pixel] == OFF
        if polarity[i] > 0:
            out[c] += on_weight[c]
            last[pixel] = ON
            if was_off:
                out[c] += half_band[c]
        else:
            out[c] += off_weight[c]
            last[pixel] = OFF
            if not was_off:
                out[c] -= half_band[c]


class PolarityMemory:
    """Each ROI pixel's last event polarity since rest, and the signed counts per grid cell less the dead band it
    implies (module docstring), in reference events.

    :meth:`counts` takes each window's events in time order; :meth:`reset` (the gel at rest again) may come from
    another thread: it takes effect before the next window is counted."""

    def __init__(self, roi: Roi, grid_shape: tuple[int, int] = GRID_SHAPE,
                 thresholds: ContrastThresholds | None = None) -> None:
        self.roi = roi
        self.grid_shape = grid_shape
        cells = grid_shape[0] * grid_shape[1]
        if thresholds is None:
            self.on_weight, self.off_weight = np.ones(cells), -np.ones(cells)
        else:
            if thresholds.on_ln.shape != grid_shape:
                raise LabrigError(f"{thresholds.source}: thresholds on a {thresholds.on_ln.shape} grid, the "
                                  f"channel's is {grid_shape}")
            self.on_weight, self.off_weight = thresholds.reference_weights
        self.half_band = 0.5 * (self.on_weight - self.off_weight)
        self.last = np.zeros(roi.width_px * roi.height_px, np.int8)
        self._reset = threading.Event()

    def counts(self, events: npt.NDArray) -> F32:
        """(rows, cols) float32: this window's change per cell in reference events, the dead band undone."""
        if self._reset.is_set():
            self._reset.clear()
            self.last[...] = NONE
        out = np.zeros(self.grid_shape[0] * self.grid_shape[1], np.float64)
        if len(events):
            roi = self.roi
            _count(events["x"], events["y"], events["p"], roi.x0_px, roi.y0_px, roi.width_px, roi.height_px,
                   self.grid_shape[0], self.grid_shape[1], self.on_weight, self.off_weight, self.half_band, self.last,
                   out)
        return out.reshape(self.grid_shape).astype(np.float32)

    def reset(self) -> None:
        """Forget every pixel's polarity (from the next window on)."""
        self._reset.set()

