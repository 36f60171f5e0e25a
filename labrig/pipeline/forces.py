"""Forces from displacements: F = K U per marker, the net force, and the contact location.

Two force models: the paper's ``forces_from_displacements(K, U)`` (K at the markers only), and
:class:`SurfaceForces`, the dense surface operator of :func:`labrig.pipeline.ifem.build_surface_operator`
fed the whole depth map plus the markers' in-plane displacements (the default in the runtime).

Units: K in N/mm, U in mm (M, 3) -> F in N (M, 3), the force applied to the
gel at each marker, gel frame (pressing gives Fz < 0, as ``/truth/marker_forces``).
The contact location is the centre of mass of the depth map (positive depth
only) on the network grid, in sensor pixels and on the gel surface at rest (mm).

Silicone stiffens at large strain. The gel calibration (``labrig calibrate gel``) fits
E_eff = E (1 + stiffening * d / h) over indentation depth d and layer thickness h; forces
from the linear operator scale by that factor at the map's deepest point
(:func:`stiffening_factor`; stiffening 0 is the paper's linear gel).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from numba import njit

from labrig.config import Roi
from labrig.physics.camera import CameraModel
from labrig.pipeline.displacement import grid_sampling_matrix
from labrig.pipeline.ifem import SurfaceOperator
from labrig.pipeline.map_forces import MapForces, SolverCache, prepare
from labrig.pipeline.unobserved import condense_unobserved, fill_in_plane, in_plane_fill

Array = npt.NDArray[np.float64]


def forces_from_displacements(k_n_per_mm: npt.ArrayLike, displacements_mm: npt.ArrayLike,
                              observed: npt.ArrayLike | None = None) -> Array:
    """F (M, 3) N = K (3M x 3M, N/mm) @ U (M, 3) mm, marker-major DOFs.

    ``observed`` (M,): markers whose displacement is known; the others (missing markers, U may be
    NaN there) are condensed out like interior nodes (:func:`~labrig.pipeline.unobserved.condense_unobserved`)
    and get no force."""
    u = np.asarray(displacements_mm, np.float64)
    k = np.asarray(k_n_per_mm)
    if observed is not None and not np.all(observed):
        k = condense_unobserved(k, observed)
        u = np.where(np.asarray(observed, bool)[:, None], u, 0.0)
    return (k @ u.reshape(-1)).reshape(u.shape)


class SurfaceForces:
    """Per-marker forces from a depth map on the network grid and the markers' in-plane displacements.

    Binds a :class:`SurfaceOperator` to the camera and ROI: the operator's top nodes (gel frame, at
    rest) are projected once and the map is sampled bilinearly there (a sparse matrix), as the
    ground truth's maps are indexed by the surface point each cell saw at rest. ``observed`` (M,):
    markers with a tracked displacement; the in-plane displacements of the others (missing markers)
    are interpolated from their neighbours (:func:`~labrig.pipeline.unobserved.in_plane_fill`).
    """

    def __init__(self, operator: SurfaceOperator, camera: CameraModel, roi: Roi, grid_shape: tuple[int, int] = (90, 112),
                 observed: npt.ArrayLike | None = None):
        self.operator = operator
        self.fill = None if observed is None else in_plane_fill(operator, observed)
        self.grid_shape = grid_shape
        xy = operator.node_xy_mm
        self.node_px = camera.project(np.column_stack([xy, np.zeros(len(xy))]))
        self.sampler = grid_sampling_matrix(self.node_px, roi, grid_shape)
        self.solvers = SolverCache()

    def node_depths_mm(self, depth_map_mm: npt.ArrayLike) -> Array:
        d = np.asarray(depth_map_mm, np.float64)
        if d.shape != self.grid_shape:
            raise ValueError(f"depth map {d.shape}, expected {self.grid_shape}")
        return np.asarray(self.sampler @ d.ravel())

    def __call__(self, depth_map_mm: npt.ArrayLike, displacements_mm: npt.ArrayLike, mode: str = "contact",
                 threshold_mm: float = 0.01) -> Array:
        """(M, 3) N on the gel; ``depth_map_mm`` into the gel (pressing positive), ``displacements_mm`` (M, 2|3).

        ``mode`` "contact" (default): the map is used only where deeper than ``threshold_mm``,
        the rest of the surface is traction-free; "field": the whole map is prescribed."""
        u = fill_in_plane(self.fill, displacements_mm)
        return self.operator.forces_n(-self.node_depths_mm(depth_map_mm), u, mode, threshold_mm)

    def prepare(self, depth_map_mm: npt.ArrayLike, mode: str = "contact", threshold_mm: float = 0.01) -> MapForces:
        """The forces of one map for every window until it changes (:mod:`labrig.pipeline.map_forces`):
        ``prepare(d, mode, t)(u)`` is ``self(d, u, mode, t)`` to rounding, at a fraction of its cost per window."""
        return prepare(self.operator, -self.node_depths_mm(depth_map_mm), mode, threshold_mm, self.fill, self.solvers)


def stiffening_factor(depth_map_mm: npt.ArrayLike, thickness_mm: float, stiffening: float) -> float:
    """1 + stiffening * max(depth, 0) / thickness: the calibrated large-strain factor on the linear forces."""
    if stiffening == 0.0:
        return 1.0
    deepest_mm = max(float(np.max(depth_map_mm)), 0.0)
    return 1.0 + float(stiffening) * deepest_mm / float(thickness_mm)


def net_force_n(forces_n: npt.ArrayLike) -> Array:
    """The sum (3,) N of the per-marker forces."""
    return np.asarray(forces_n, np.float64).sum(axis=0)


#: Share of the peak depth below which :func:`contact_location` leaves the map out of the contact's centre.
CONTACT_CORE_FRACTION = 0.2


@dataclass(frozen=True)
class ContactLocation:
    position_px: Array  # (2,) sensor pixels (x, y)
    position_mm: Array  # (2,) gel frame x, y at rest
    weight_mm: float  # summed positive depth over the grid cells (0: no contact)


def contact_location(depth_map_mm: npt.ArrayLike, roi: Roi, camera: CameraModel,
                     threshold_mm: float = 0.0, core_fraction: float = CONTACT_CORE_FRACTION) -> ContactLocation | None:
    """The dent's core on the network grid: the centre of mass of ``depth - core_fraction * peak`` where positive.

    Only depth above ``threshold_mm`` counts as contact (None without any). Subtracting a fraction of
    the peak keeps a network's shallow skirt and far, faint residue out of the centre (docs/pipeline.md
    says how the fraction was chosen). ``weight_mm`` is the summed depth above the threshold.
    """
    d = np.ascontiguousarray(depth_map_mm, np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth map of shape {d.shape}, expected (rows, cols)")
    total, r, c = _contact_core(d, float(threshold_mm), float(core_fraction))
    if total <= 0:
        return None
    rows, cols = d.shape
    px = np.array([roi.x0_px - 0.5 + (c + 0.5) * roi.width_px / cols, roi.y0_px - 0.5 + (r + 0.5) * roi.height_px / rows])
    mm = camera.backproject_to_planes(px[None], 0.0)[0, :2]
    return ContactLocation(px, mm, total)


@njit(cache=True, nogil=True)
def _contact_core(d, threshold_mm, core_fraction):  # type: ignore[no-untyped-def]
    """(summed depth above ``threshold_mm``, core's centre row, core's centre column) of a float64 map; the
    core weighs each contact cell by ``max(depth - core_fraction * peak, 0)``; rows and columns are nan
    when the core is empty."""
    rows, cols = d.shape
    total = 0.0
    peak = 0.0
    for i in range(rows):
        for j in range(cols):
            v = d[i, j]
            if v > threshold_mm:
                total += v
                if v > peak:
                    peak = v
    floor = core_fraction * peak
    core = 0.0
    r = 0.0
    c = 0.0
    for i in range(rows):
        for j in range(cols):
            v = d[i, j]
            if v > threshold_mm and v > 0.0 and v > floor:
                w = v - floor
                core += w
                r += w * i
                c += w * j
    if core <= 0.0:
        return total, np.nan, np.nan
    return total, r / core, c / core
