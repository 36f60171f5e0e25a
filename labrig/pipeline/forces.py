"""Forces from displacements: F = K U per marker, the net force, and the contact location.

Units: K in N/mm, U in mm (M, 3) -> F in N (M, 3), the force applied to the
gel at each marker, gel frame (pressing gives Fz < 0, as ``/truth/marker_forces``).
The contact location is the centre of mass of the depth map (positive depth
only) on the network grid, in sensor pixels and on the gel surface at rest (mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.config import Roi
from labrig.sim.camera import CameraModel

Array = npt.NDArray[np.float64]


def forces_from_displacements(k_n_per_mm: npt.ArrayLike, displacements_mm: npt.ArrayLike) -> Array:
    """F (M, 3) N = K (3M x 3M, N/mm) @ U (M, 3) mm, marker-major DOFs."""
    u = np.asarray(displacements_mm, np.float64)
    return (np.asarray(k_n_per_mm) @ u.reshape(-1)).reshape(u.shape)


def net_force_n(forces_n: npt.ArrayLike) -> Array:
    """The sum (3,) N of the per-marker forces."""
    return np.asarray(forces_n, np.float64).sum(axis=0)


@dataclass(frozen=True)
class ContactLocation:
    position_px: Array  # (2,) sensor pixels (x, y)
    position_mm: Array  # (2,) gel frame x, y at rest
    weight_mm: float  # summed positive depth over the grid cells (0: no contact)


def contact_location(depth_map_mm: npt.ArrayLike, roi: Roi, camera: CameraModel,
                     threshold_mm: float = 0.0) -> ContactLocation | None:
    """Centre of mass of the depth above ``threshold_mm`` on the network grid; None without contact."""
    d = np.asarray(depth_map_mm, np.float64)
    w = np.where(d > threshold_mm, d, 0.0)
    total = float(w.sum())
    if total <= 0:
        return None
    rows, cols = d.shape
    r = float((w.sum(axis=1) * np.arange(rows)).sum() / total)
    c = float((w.sum(axis=0) * np.arange(cols)).sum() / total)
    px = np.array([roi.x0_px - 0.5 + (c + 0.5) * roi.width_px / cols, roi.y0_px - 0.5 + (r + 0.5) * roi.height_px / rows])
    mm = camera.backproject_to_plane(px[None], 0.0)[0, :2]
    return ContactLocation(px, mm, total)
