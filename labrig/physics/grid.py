"""The network grid: the camera's ROI resized to the depth network's grid.

Cell centres map linearly to sensor pixels over the ROI (``rig.roi``; pixel
coordinates with the origin at the top-left pixel's centre), and from there
to the gel surface at rest through a camera model. The SAE, the depth
network, the ground-truth labels and the sim's truth all live on this grid.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig
from labrig.physics.camera import CameraModel

#: (rows, cols) of the network grid.
GRID_SHAPE = (90, 112)


def network_grid_pixels(rig: RigConfig, grid_shape: tuple[int, int] = GRID_SHAPE) -> npt.NDArray[np.float64]:
    """Sensor-pixel coordinates (rows, cols, 2) of the network grid's cell centres over the ROI."""
    roi = rig.roi
    rows, cols = grid_shape
    x = roi.x0_px - 0.5 + (np.arange(cols) + 0.5) * roi.width_px / cols
    y = roi.y0_px - 0.5 + (np.arange(rows) + 0.5) * roi.height_px / rows
    xx, yy = np.meshgrid(x, y)
    return np.stack([xx, yy], axis=-1)


def network_grid_gel_mm(rig: RigConfig, camera: CameraModel, grid_shape: tuple[int, int] = GRID_SHAPE) -> npt.NDArray[np.float64]:
    """Gel-surface points (rows, cols, 2) mm, gel frame, at rest seen by each network-grid cell through ``camera``."""
    px = network_grid_pixels(rig, grid_shape).reshape(-1, 2)
    return camera.backproject_to_plane(px, 0.0)[:, :2].reshape(*grid_shape, 2)


def grid_cells_of_pixels(x_px: npt.ArrayLike, y_px: npt.ArrayLike, x0_px: int, y0_px: int, width_px: int, height_px: int,
                         grid_shape: tuple[int, int] = GRID_SHAPE) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
    """(flat cell index, inside) of sensor pixels on the network grid over the ROI whose top-left pixel is
    (``x0_px``, ``y0_px``): the cell whose span holds the pixel's centre (the cells of the SAE grid); pixels
    outside the ROI are marked False (their index is meaningless)."""
    rows, cols = grid_shape
    x = np.asarray(x_px).astype(np.int64) - x0_px
    y = np.asarray(y_px).astype(np.int64) - y0_px
    c = ((x + 0.5) * (cols / width_px)).astype(np.int64)
    r = ((y + 0.5) * (rows / height_px)).astype(np.int64)
    inside = (x >= 0) & (y >= 0) & (c < cols) & (r < rows)
    return r * cols + c, inside
