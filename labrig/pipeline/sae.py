"""Polarity-separated Surface of Active Events (SAE) over a time window.

An SAE holds, per pixel and polarity, the latest event timestamp in the window
``[t0_us, t1_us)``, normalised to [0, 1] over the window ((t - t0) / (t1 - t0));
pixels without an event are 0. Arrays are (2, rows, cols) float32, channel 0 OFF
(p = 0) and channel 1 ON (p = 1), row = image y.

Three resolutions: the sensor (or any pixel rectangle, e.g. the ROI) for
tracking and display; the network grid (:mod:`labrig.physics.grid`: the ROI
resized to 90 x 112, each cell holding the latest event among its pixels, the
grid of ``/truth/depth``); and
the grid zero-padded to 96 x 112 for the U-Net's down-sampling.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import numpy.typing as npt
from numba import njit

from labrig.config import Roi
from labrig.physics.grid import GRID_SHAPE

if TYPE_CHECKING:
    import torch

#: The network grid zero-padded for the U-Net's down-sampling.
UNET_SHAPE = (96, 112)

Sae = npt.NDArray[np.float32]
#: A network output: numpy's (ONNX Runtime) or torch's (training).
NetworkOutput = TypeVar("NetworkOutput", npt.NDArray[Any], "torch.Tensor")


@njit(cache=True, nogil=True)
def _scatter_latest(x, y, p, t, x0, y0, sx, sy, t0, inv_span, out):  # pragma: no cover - compiled
    rows, cols = out.shape[1], out.shape[2]
    for i in range(x.shape[0]):
        c = int((x[i] - x0 + 0.5) * sx)
        r = int((y[i] - y0 + 0.5) * sy)
        if x[i] < x0 or y[i] < y0 or c >= cols or r >= rows:
            continue
        v = (t[i] - t0) * inv_span
        v = min(max(v, 0.0), 1.0)
        ch = 1 if p[i] else 0
        if v > out[ch, r, c]:
            out[ch, r, c] = v


def _scatter(events: npt.NDArray, t0_us: float, t1_us: float, x0: int, y0: int, sx: float, sy: float,
             out: Sae) -> Sae:
    if t1_us <= t0_us:
        raise ValueError("the window must have t1_us > t0_us")
    out[...] = 0.0
    if len(events):
        _scatter_latest(events["x"], events["y"], events["p"], events["t"], x0, y0, sx, sy,
                        float(t0_us), 1.0 / (float(t1_us) - float(t0_us)), out)
    return out


def sae_pixels(events: npt.NDArray, t0_us: float, t1_us: float, *, x0_px: int = 0, y0_px: int = 0,
               width_px: int = 1280, height_px: int = 720, out: Sae | None = None) -> Sae:
    """SAE (2, height, width) at pixel resolution over the rectangle starting at (x0, y0).

    Events outside the rectangle are ignored; pass ``out`` to reuse a buffer.
    """
    if out is None:
        out = np.zeros((2, height_px, width_px), np.float32)
    return _scatter(events, t0_us, t1_us, x0_px, y0_px, 1.0, 1.0, out)


def sae_roi(events: npt.NDArray, t0_us: float, t1_us: float, roi: Roi, out: Sae | None = None) -> Sae:
    """SAE over the ROI, at pixel resolution."""
    return sae_pixels(events, t0_us, t1_us, x0_px=roi.x0_px, y0_px=roi.y0_px, width_px=roi.width_px,
                      height_px=roi.height_px, out=out)


def sae_grid(events: npt.NDArray, t0_us: float, t1_us: float, roi: Roi,
             grid_shape: tuple[int, int] = GRID_SHAPE, out: Sae | None = None) -> Sae:
    """SAE on the network grid: the ROI divided into ``grid_shape`` cells, latest event per cell.

    Cell (r, c) covers the pixels whose centres map into it under the ROI-to-grid
    scaling (:func:`labrig.physics.grid.network_grid_pixels` gives the cell centres).
    """
    rows, cols = grid_shape
    if out is None:
        out = np.zeros((2, rows, cols), np.float32)
    return _scatter(events, t0_us, t1_us, roi.x0_px, roi.y0_px, cols / roi.width_px, rows / roi.height_px, out)


def resize_to_grid(sae: Sae, grid_shape: tuple[int, int] = GRID_SHAPE) -> Sae:
    """Max-pool a pixel-resolution SAE (e.g. :func:`sae_roi`) onto the grid; equals :func:`sae_grid`."""
    rows, cols = grid_shape
    h, w = sae.shape[1:]
    r = ((np.arange(h) + 0.5) * rows / h).astype(np.int64)
    c = ((np.arange(w) + 0.5) * cols / w).astype(np.int64)
    row_max = np.maximum.reduceat(sae, np.searchsorted(r, np.arange(rows)), axis=1)
    return np.maximum.reduceat(row_max, np.searchsorted(c, np.arange(cols)), axis=2).astype(np.float32)


def pad_for_unet(sae: Sae, shape: tuple[int, int] = UNET_SHAPE) -> Sae:
    """Zero-pad (..., 90, 112) to ``shape`` (rows split evenly top and bottom)."""
    dr, dc = shape[0] - sae.shape[-2], shape[1] - sae.shape[-1]
    if dr < 0 or dc < 0:
        raise ValueError(f"cannot pad {sae.shape[-2:]} to {shape}")
    pad = [(0, 0)] * (sae.ndim - 2) + [(dr // 2, dr - dr // 2), (dc // 2, dc - dc // 2)]
    return np.pad(sae, pad)


def crop_from_unet(array: NetworkOutput, shape: tuple[int, int] = GRID_SHAPE) -> NetworkOutput:
    """Undo :func:`pad_for_unet` on a network output (..., 96, 112) -> (..., 90, 112)."""
    dr, dc = array.shape[-2] - shape[0], array.shape[-1] - shape[1]
    return array[..., dr // 2: dr // 2 + shape[0], dc // 2: dc // 2 + shape[1]]
