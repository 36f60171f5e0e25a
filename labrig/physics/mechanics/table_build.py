"""Computing a contact table's arrays (see :mod:`tables` for what they hold and how they are used).

Normal solutions run in depth order, each warm-started from the previous one.
Tangential sweeps (one per depth, over the shift fractions) run on
``BUILD_THREADS`` threads; each thread takes every n-th depth and warm-starts
every solve from a first-order guess built from its previous depth's sweep.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.config import GelConfig
from labrig.indenters import Indenter
from labrig.physics.mechanics.grid import Grid
from labrig.physics.mechanics.kernels import Box, SurfaceKernels
from labrig.physics.mechanics.normal import NormalSolution, indenter_height_mm, solve_normal
from labrig.physics.mechanics.tangential import solve_traction_in_box

#: Tolerance of the tangential solves in a table (rms stick-zone displacement error / shift).
SHEAR_TOL = 1e-5

#: Threads for the tangential sweeps of a table build (one sweep per depth).
BUILD_THREADS = 2

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


def compute_table(indenter: Indenter, gel: GelConfig, spec: dict[str, Any]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(meta, arrays) of a table described by ``spec`` (the cache-key dictionary of :meth:`ContactTable.build`)."""
    grid = Grid(spec["spacing_mm"], *spec["grid_shape"])
    kernels = SurfaceKernels(grid, gel, spec["mode"])
    height = indenter_height_mm(indenter, grid, spec.get("yaw_deg", 0.0))
    step = spec["depth_step_mm"]
    depths = step * np.arange(int(np.ceil(spec["max_depth_mm"] / step - 1e-9)) + 1)
    normals = _normal_solutions(kernels, height, depths)
    box = _symmetric_box([n.contact_mask for n in normals], grid, square=indenter.axisymmetric)
    rows = list(range(0, len(depths), spec["shear_depth_stride"]))
    if rows[-1] != len(depths) - 1:
        rows.append(len(depths) - 1)
    fractions = from_mindlin(np.arange(spec["shear_steps"] + 1) / spec["shear_steps"])
    angle = np.deg2rad(spec["direction_deg"])
    direction = np.array([np.cos(angle), np.sin(angle)])
    traction = np.zeros((len(rows), len(fractions), 2, *box.shape), dtype=np.float32)
    slip_shift = np.zeros(len(rows))
    workers = max(min(os.cpu_count() or 1, BUILD_THREADS), 1)

    def chain(first: int) -> None:  # every workers-th depth, each warm-started from the one before
        previous = None
        for j in range(first, len(rows), workers):
            slip_shift[j], traction[j] = _shear_sweep(kernels, normals[rows[j]], box, direction, fractions, previous)
            previous = traction[j]

    with ThreadPoolExecutor(max_workers=workers) as pool:  # FFTs and large numpy ops release the GIL
        list(pool.map(chain, range(workers)))
    shear_force = traction.sum(axis=(-2, -1), dtype=np.float64) * grid.cell_area_mm2
    arrays = {
        "depths_mm": depths,
        "depth_fields": np.array([n.depth_mm for n in normals], dtype=np.float32),
        "pressure": np.array([n.pressure_mpa[box.slices] for n in normals], dtype=np.float32),
        "normal_force_n": np.array([n.force_n for n in normals]),
        "shear_rows": np.array(rows),
        "slip_shift_mm": slip_shift,
        "fractions": fractions,
        "traction": traction,
        "shear_force_n": shear_force,
        "window": kernels.tangential_window(box, Box.full(grid.shape)),
    }
    meta = {
        "indenter": indenter.name,
        "spacing_mm": grid.spacing_mm,
        "grid_shape": list(grid.shape),
        "box": [box.y0, box.y1, box.x0, box.x1],
        "direction_deg": spec["direction_deg"],
        "yaw_deg": spec.get("yaw_deg", 0.0),
        "normal_iterations": int(sum(n.iterations for n in normals)),
    }
    return meta, arrays


def _normal_solutions(kernels: SurfaceKernels, height: F64, depths: F64) -> list[NormalSolution]:
    out: list[NormalSolution] = []
    for depth in depths:
        warm = out[-1].pressure_mpa if out and out[-1].force_n > 0 else None
        out.append(solve_normal(kernels, height, float(depth), initial_pressure_mpa=warm))
    return out


def _symmetric_box(masks: list[npt.NDArray[np.bool_]], grid: Grid, square: bool) -> Box:
    """Bounding box of every contact, made symmetric about the tip (and square for rotations)."""
    union = np.logical_or.reduce(masks)
    b = Box.around(union)
    cy, cx = grid.ny // 2, grid.nx // 2
    half_y = max(cy - b.y0, b.y1 - 1 - cy, 0)
    half_x = max(cx - b.x0, b.x1 - 1 - cx, 0)
    if square:
        half_y = half_x = min(max(half_y, half_x), cy, cx)
    return Box(cy - half_y, cy + half_y + 1, cx - half_x, cx + half_x + 1)


def _shear_sweep(
    kernels: SurfaceKernels,
    normal: NormalSolution,
    box: Box,
    direction: F64,
    fractions: F64,
    previous: F32 | None = None,
) -> tuple[float, F32]:
    """(gross-slip shift, tractions (nk, 2, *box.shape)) of one depth's monotonic sweep.

    Each solve starts from q(k - 1) plus the step q(k) - q(k - 1) of the
    ``previous`` (shallower) depth's sweep, if given: a first-order guess that
    saves about half of the iterations.
    """
    out = np.zeros((len(fractions), 2, *box.shape), dtype=np.float32)
    if not normal.contact_mask.any():
        return 0.0, out
    mu = kernels.gel.friction
    full_slip = mu * normal.pressure_mpa[box.slices][None] * direction[:, None, None]
    u = kernels.tangential(box)(full_slip)
    slip_shift = float(np.max(np.where(normal.contact_mask[box.slices], u[0] * direction[0] + u[1] * direction[1], -np.inf)))
    guess = np.zeros((2, *kernels.grid.shape))
    for k, fraction in enumerate(fractions):
        if fraction <= 0:
            continue
        if fraction >= 1:
            out[k] = full_slip
            continue
        if previous is not None:
            guess[(slice(None), *box.slices)] = out[k - 1] + previous[k] - previous[k - 1]
        sub, q, _, _ = solve_traction_in_box(
            kernels, normal, fraction * slip_shift * direction, tol=SHEAR_TOL, initial_traction_mpa=guess
        )
        guess = np.zeros((2, *kernels.grid.shape))
        guess[(slice(None), *sub.slices)] = q
        out[k] = guess[(slice(None), *box.slices)]
    return slip_shift, out


def to_mindlin(fraction: npt.ArrayLike) -> np.ndarray:
    """Shift fraction s / s_gs -> Mindlin's Q / (mu P) = 1 - (1 - s / s_gs)^(3/2), the interpolation coordinate."""
    return 1.0 - (1.0 - np.asarray(fraction, dtype=np.float64)) ** 1.5


def from_mindlin(force_fraction: npt.ArrayLike) -> np.ndarray:
    """Inverse of :func:`to_mindlin`."""
    return 1.0 - (1.0 - np.asarray(force_fraction, dtype=np.float64)) ** (2.0 / 3.0)
