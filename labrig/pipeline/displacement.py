"""3D marker displacements from tracked image positions, normal displacements and the camera.

Each marker's pixel ray (through the calibrated camera, distortion included) is
intersected with its displaced surface, the plane z = -depth (depth: normal
displacement into the gel, mm, positive when pressed), and its rest position is
subtracted: U (M, 3) mm in the gel frame. Normal displacements come per marker,
or as a depth map on the network grid (the ROI resized, e.g. 90 x 112) sampled
bilinearly at the markers' tracked pixels.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from labrig.config import Roi
from labrig.physics.camera import CameraModel

Array = npt.NDArray[np.float64]


def grid_coordinates(positions_px: npt.ArrayLike, roi: Roi, grid_shape: tuple[int, int]) -> Array:
    """Fractional (row, col) of sensor pixels on the network grid (cell centres at integers)."""
    xy = np.asarray(positions_px, np.float64)
    rows, cols = grid_shape
    col = (xy[..., 0] - roi.x0_px + 0.5) * cols / roi.width_px - 0.5
    row = (xy[..., 1] - roi.y0_px + 0.5) * rows / roi.height_px - 0.5
    return np.stack([row, col], axis=-1)


def sample_grid(grid: npt.ArrayLike, positions_px: npt.ArrayLike, roi: Roi) -> Array:
    """Bilinear samples (N,) of a (rows, cols) map over the ROI at sensor pixels (N, 2); edges clamp."""
    g = np.asarray(grid, np.float64)
    rc = grid_coordinates(positions_px, roi, g.shape)
    r = np.clip(rc[..., 0], 0, g.shape[0] - 1)
    c = np.clip(rc[..., 1], 0, g.shape[1] - 1)
    r0 = np.minimum(np.floor(r).astype(np.int64), g.shape[0] - 2)
    c0 = np.minimum(np.floor(c).astype(np.int64), g.shape[1] - 2)
    fr, fc = r - r0, c - c0
    return ((1 - fr) * ((1 - fc) * g[r0, c0] + fc * g[r0, c0 + 1])
            + fr * ((1 - fc) * g[r0 + 1, c0] + fc * g[r0 + 1, c0 + 1]))


def grid_sampling_matrix(positions_px: npt.ArrayLike, roi: Roi, grid_shape: tuple[int, int]) -> sp.csr_matrix:
    """(N, rows * cols) sparse: ``matrix @ grid.ravel()`` equals :func:`sample_grid` at the N pixels."""
    rows, cols = grid_shape
    rc = grid_coordinates(positions_px, roi, grid_shape).reshape(-1, 2)
    r = np.clip(rc[:, 0], 0, rows - 1)
    c = np.clip(rc[:, 1], 0, cols - 1)
    r0 = np.minimum(np.floor(r).astype(np.int64), rows - 2)
    c0 = np.minimum(np.floor(c).astype(np.int64), cols - 2)
    fr, fc = r - r0, c - c0
    n = len(r)
    index = np.concatenate([r0 * cols + c0, r0 * cols + c0 + 1, (r0 + 1) * cols + c0, (r0 + 1) * cols + c0 + 1])
    weight = np.concatenate([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc])
    return sp.csr_matrix((weight, (np.tile(np.arange(n), 4), index)), shape=(n, rows * cols))


def marker_depths_mm(depth: npt.ArrayLike, positions_px: npt.ArrayLike, roi: Roi) -> Array:
    """Per-marker normal displacements (M,) mm: ``depth`` is already per marker (M,) or a grid map."""
    d = np.asarray(depth, np.float64)
    n = len(np.asarray(positions_px))
    if d.ndim == 1:
        if len(d) != n:
            raise ValueError(f"{len(d)} depths for {n} markers")
        return d
    if d.ndim == 0:
        return np.full(n, float(d))
    return sample_grid(d, positions_px, roi)


def marker_positions_mm(positions_px: npt.ArrayLike, depth_mm: npt.ArrayLike, camera: CameraModel) -> Array:
    """Gel-frame points (M, 3) mm where each marker's pixel ray meets its plane z = -depth."""
    frame = camera.gel_to_camera.inverse()
    rays = frame.rotate(camera.pixel_rays(positions_px))
    origin = frame.translation_mm
    z = -np.asarray(depth_mm, np.float64)
    s = (z - origin[2]) / rays[:, 2]
    return origin + s[:, None] * rays


def displacements_mm(positions_px: npt.ArrayLike, depth: npt.ArrayLike, camera: CameraModel, rest_mm: npt.ArrayLike,
                     roi: Roi, sample_px: npt.ArrayLike | None = None) -> Array:
    """U (M, 3) mm: tracked pixels + normal displacement (per marker or grid map) -> 3D, minus rest.

    A map is sampled at ``sample_px`` (default: the tracked pixels). The ground truth's maps (and
    so the network's) hold each grid cell's displacement of the surface point it saw at rest, so
    pass the markers' rest pixels to read a marker's own depth there (under 0.5 mm of shear the
    tracked pixel is a quarter of a millimetre off near the dimple's edge).
    """
    d = marker_depths_mm(depth, positions_px if sample_px is None else sample_px, roi)
    return marker_positions_mm(positions_px, d, camera) - np.asarray(rest_mm, np.float64)
