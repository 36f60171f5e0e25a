"""The membrane's shading response: how much brighter it looks per unit of surface slope, from a known press.

Under a ring of grazing LEDs a dented membrane scatters more light towards the camera where it
slopes, whatever the slope's direction. The response is modelled as

    I / I_rest = 1 + g |grad d|,    so    delta ln I = ln(1 + g |grad d|)

with ``d`` the surface depth (mm), ``|grad d|`` its slope (mm/mm, dimensionless) and ``g`` the
**slope gain** (dimensionless), set by the light's geometry and the membrane's finish: one lab's
gel and ring are not another's. A press of known depth gives ``|grad d|`` per grid cell (the
ground-truth maps of ``labrig groundtruth``), the events give ``delta ln I`` per grid cell
(their polarities integrated, weighted by the calibrated contrast thresholds:
:mod:`labrig.pipeline.brightness`), and :func:`fit_slope_gain` finds ``g`` by least squares
over the cells that slope. A log-intensity change is a ratio of intensities, so the fit does
not see the light's strength or the membrane's level, only the shading's shape.
:func:`slope_response_of` reads a press recording: its events summed per cell since its start (no
leak: the press lasts seconds) less the map's median (the sensor's leak events, a uniform drift) at
each ground-truth map at least ``min_indentation_mm`` deep.

A moved marker leaves an OFF patch where it was and an ON patch where it is: the model does not
hold there, which the fit's residual (``rms_ln``) shows; its sign averages out over a press.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from scipy.optimize import minimize_scalar

from labrig.calibration.event_counts import signed_counts
from labrig.calibration.event_thresholds_file import NOMINAL_THRESHOLD_LN, ContrastThresholds
from labrig.config import Roi
from labrig.errors import CalibrationError
from labrig.physics.grid import GRID_SHAPE
from labrig.recording import Recording

F64 = npt.NDArray[np.float64]

#: Cells whose surface slope is below this (mm/mm) are left out of the fit: flat membrane carries noise only.
MIN_SLOPE = 0.05
#: The fit needs at least this many sloped cells over all maps.
MIN_CELLS = 200
#: The slope gains the fit searches (dimensionless).
GAIN_BOUNDS = (0.05, 20.0)
#: The maps of a press that feed the fit: at least this deep (mm).
MIN_INDENTATION_MM = 0.3
#: The events are summed in slices this long (us).
SLICE_US = 100_000


@dataclass(frozen=True)
class SlopeResponse:
    """The fitted slope gain ``slope_gain`` (dimensionless), the fit's rms residual ``rms_ln`` (ln intensity),
    the sloped cells ``cells`` it used over ``maps`` ground-truth maps."""

    slope_gain: float
    rms_ln: float
    cells: int
    maps: int

    def summary(self) -> dict[str, float | int]:
        return {"slope_gain": round(self.slope_gain, 4), "rms_ln": round(self.rms_ln, 4), "cells": self.cells,
                "maps": self.maps}


def surface_slope(depth_mm: npt.ArrayLike, grid_gel_mm: npt.ArrayLike) -> F64:
    """(rows, cols) surface slope |grad d| (mm/mm) of a depth map (rows, cols) in mm, on a grid whose cells sit
    at ``grid_gel_mm`` (rows, cols, 2) (gel frame x, y in mm; any smooth, non-degenerate grid): the
    derivatives along the grid's rows and columns, turned into x and y by the grid's Jacobian."""
    d = np.asarray(depth_mm, np.float64)
    xy = np.asarray(grid_gel_mm, np.float64)
    if xy.shape != (*d.shape, 2):
        raise CalibrationError(f"the grid's gel coordinates must be {(*d.shape, 2)}, not {xy.shape}")
    d_i, d_j = np.gradient(d)
    x_i, x_j = np.gradient(xy[..., 0])
    y_i, y_j = np.gradient(xy[..., 1])
    det = x_i * y_j - x_j * y_i
    if not np.all(np.abs(det) > 1e-12):
        raise CalibrationError("the grid's gel coordinates are degenerate (two cells at one point)")
    # [d_i, d_j] = J^T [d_x, d_y] with J = [[x_i, x_j], [y_i, y_j]]
    d_x = (y_j * d_i - y_i * d_j) / det
    d_y = (-x_j * d_i + x_i * d_j) / det
    return np.hypot(d_x, d_y)


def fit_slope_gain(change_ln: npt.ArrayLike, depth_mm: npt.ArrayLike, grid_gel_mm: npt.ArrayLike,
                   min_slope: float = MIN_SLOPE, min_cells: int = MIN_CELLS) -> SlopeResponse:
    """The slope gain ``g`` minimising ``sum (delta ln I - ln(1 + g |grad d|))^2`` over the cells whose slope is
    at least ``min_slope``, from ``change_ln`` (N, rows, cols) the log-intensity change since rest per cell
    (ln, less the map's uniform drift) and ``depth_mm`` (N, rows, cols) the known depth at the same instants."""
    change = np.asarray(change_ln, np.float64)
    depth = np.asarray(depth_mm, np.float64)
    if change.shape != depth.shape or change.ndim != 3:
        raise CalibrationError(f"the brightness changes {change.shape} and depth maps {depth.shape} must be "
                               "(maps, rows, cols) of one shape")
    slope = np.stack([surface_slope(d, grid_gel_mm) for d in depth]) if len(depth) else depth
    sloped = (slope >= min_slope) & np.isfinite(change)
    cells = int(sloped.sum())
    if cells < min_cells:
        raise CalibrationError(f"the press sloped the membrane in {cells} cells, the slope fit needs {min_cells}; "
                               "press deeper (a sphere 1 mm or more) or give a recording with more of its press")
    s, c = slope[sloped], change[sloped]

    def cost(g: float) -> float:
        return float(np.mean((c - np.log1p(g * s)) ** 2))

    best = minimize_scalar(cost, bounds=GAIN_BOUNDS, method="bounded", options={"xatol": 1e-4})
    gain = float(best.x)
    if not GAIN_BOUNDS[0] * 1.01 < gain < GAIN_BOUNDS[1] * 0.99:
        raise CalibrationError(f"the slope fit ran to its bound ({gain:.3g}): the events do not follow the press "
                               "(is the LED ring on, are the ground-truth maps of this recording?)")
    return SlopeResponse(gain, float(np.sqrt(best.fun)), cells, len(depth))


def change_at_times(recording: Recording, roi: Roi, times_us: npt.ArrayLike,
                    thresholds: ContrastThresholds | None = None, grid_shape: tuple[int, int] = GRID_SHAPE
                    ) -> npt.NDArray[np.float32]:
    """(N, rows, cols) float32: the log-intensity change (ln) per grid cell since the recording's start, per
    pixel and less the map's median, at each of ``times_us`` (N,) host us, ascending: the events up to each
    time summed (:func:`~labrig.calibration.event_counts.signed_counts`, weighted by ``thresholds``)."""
    times = np.asarray(times_us, np.int64)
    if len(times) and (np.diff(times) < 0).any():
        raise CalibrationError("the slope fit's map times must ascend")
    pixels_per_cell = roi.width_px * roi.height_px / float(grid_shape[0] * grid_shape[1])
    total = np.zeros(grid_shape, np.float64)
    out = np.zeros((len(times), *grid_shape), np.float32)
    t = 0
    for k, t_map in enumerate(times):
        while t < t_map:
            t1 = min(t + SLICE_US, int(t_map))
            total += signed_counts(recording.events_between(t, t1), roi, grid_shape, thresholds)
            t = t1
        per_px = total / pixels_per_cell
        out[k] = (per_px - np.median(per_px)) * NOMINAL_THRESHOLD_LN
    return out


def slope_response_of(recording: str | Path, roi: Roi, thresholds: ContrastThresholds | None, t_us: npt.ArrayLike,
                      depth_mm: npt.ArrayLike, indentation_mm: npt.ArrayLike, grid_gel_mm: npt.ArrayLike,
                      min_indentation_mm: float = MIN_INDENTATION_MM) -> SlopeResponse:
    """The slope gain of the light that recorded the press ``recording``, from its ground-truth maps (``t_us``
    (N,) host us, ``depth_mm`` (N, rows, cols), ``indentation_mm`` (N,), ``grid_gel_mm`` (rows, cols, 2)) and
    its events weighted by ``thresholds`` (None: nominal) over the network grid on ``roi``; the maps at
    least ``min_indentation_mm`` deep."""
    picked = np.flatnonzero(np.asarray(indentation_mm) >= min_indentation_mm)
    if picked.size == 0:
        raise CalibrationError(f"{recording}: the press never reached {min_indentation_mm} mm; the slope fit needs a "
                               "press of known depth (protocols/slope-press.toml: a sphere 1.2 mm below contact)")
    depth = np.asarray(depth_mm)[picked]
    with Recording(recording) as rec:
        change = change_at_times(rec, roi, np.asarray(t_us)[picked], thresholds, depth.shape[1:])
    return fit_slope_gain(change, depth, grid_gel_mm)
