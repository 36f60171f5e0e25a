"""Displacement-controlled normal contact of a rigid indenter: Polonsky-Keer CG.

Problem (gel frame, units mm and MPa): the indenter tip is pressed
``indentation_mm`` (delta) into the gel. With the indenter height map g
(height above the tip, inf where the indenter has no surface) and the surface
displacement into the gel ``uz = K p`` (see :mod:`kernels`), find the pressure
p >= 0 (compression positive) such that

    gap = g - delta + uz >= 0 everywhere, gap = 0 where p > 0.

Solved by the constrained conjugate gradient of Polonsky & Keer (Wear 231:206,
1999) in its displacement-controlled form: CG on the contact set, pressure
clipped at zero, cells that penetrate re-enter the set (and the CG restarts).
The pressure is only sought inside a box around the cells the indenter can
touch; afterwards ``uz`` is computed on the whole grid and, if the gel would
penetrate the indenter outside the box (the layer's bulge lifting the gel into
a fillet, say), the box grows and the solve resumes.

Outside the contact, ``depth_mm`` is the free surface: positive where the
surface is pushed in, negative where it bulges out (a bonded layer bulges
next to the contact; a half-space does not).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.indenters import Indenter
from labrig.physics.mechanics.grid import Grid
from labrig.physics.mechanics.kernels import Box, SurfaceKernels

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class NormalSolution:
    """Normal contact at one indentation. Fields are (ny, nx) on the grid."""

    indentation_mm: float
    pressure_mpa: FloatArray
    depth_mm: FloatArray  # uz, positive into the gel, everywhere on the grid
    contact_mask: npt.NDArray[np.bool_]
    force_n: float  # sum of p times the cell area (MPa mm^2 = N), pressing
    contact_area_mm2: float
    iterations: int
    residual: float  # max complementarity violation / indentation

    @property
    def box(self) -> Box:
        """Bounding box of the contact (cells)."""
        return Box.around(self.contact_mask)


def indenter_height_mm(indenter: Indenter, grid: Grid, yaw_deg: float = 0.0) -> FloatArray:
    """Height map of ``indenter`` on ``grid`` (tip at the grid centre), mm; inf outside it.

    ``yaw_deg``: the indenter's turn relative to the grid's (gel) axes."""
    x, y = grid.mesh_mm()
    return indenter.height_in_gel_mm(x, y, yaw_deg)


def solve_normal(
    kernels: SurfaceKernels,
    height_mm: FloatArray,
    indentation_mm: float,
    *,
    tol: float = 1e-6,
    max_iter: int = 2000,
    initial_pressure_mpa: FloatArray | None = None,
) -> NormalSolution:
    """Pressure and surface of a rigid indenter (height map ``height_mm``) pressed ``indentation_mm`` in.

    ``tol`` bounds the relative change of the pressure per iteration (the
    Polonsky-Keer stopping rule) and the rms gap in contact relative to the
    indentation. ``initial_pressure_mpa`` warm-starts from a nearby solution.
    """
    grid = kernels.grid
    g = np.asarray(height_mm, dtype=np.float64)
    if g.shape != grid.shape:
        raise ValueError(f"height map shape {g.shape} does not match the grid {grid.shape}")
    delta = float(indentation_mm)
    reachable = np.isfinite(g)
    if delta <= 0 or not np.any(g[reachable] < delta):
        zeros = np.zeros(grid.shape)
        return NormalSolution(delta, zeros, zeros.copy(), zeros > 0, 0.0, 0.0, 0, 0.0)
    full = Box.full(grid.shape)
    p = np.zeros(grid.shape) if initial_pressure_mpa is None else np.clip(initial_pressure_mpa, 0, None)
    candidates = reachable & (g < delta * 1.05 + grid.spacing_mm)
    iterations = 0
    for _ in range(8):  # grow the box until no penetration is left outside it
        box = Box.around(candidates | (p > 0), margin=2)
        p_box, its = _polonsky_keer(kernels, box, g[box.slices], delta, p[box.slices], tol, max_iter)
        iterations += its
        p = np.zeros(grid.shape)
        p[box.slices] = p_box
        uz = kernels.normal(box, full)(p_box[None])[0]
        gap = np.where(reachable, g - delta + uz, np.inf)
        outside = np.ones(grid.shape, dtype=bool)
        outside[box.slices] = False
        penetrating = outside & (gap < -tol * delta)
        if not penetrating.any():
            break
        candidates = candidates | penetrating
    contact = p > 0
    violation = max(float(np.abs(gap[contact]).max(initial=0.0)), float(-gap.min(initial=0.0)))
    area = grid.cell_area_mm2
    return NormalSolution(
        indentation_mm=delta,
        pressure_mpa=p,
        depth_mm=uz,
        contact_mask=contact,
        force_n=float(p.sum() * area),
        contact_area_mm2=float(contact.sum() * area),
        iterations=iterations,
        residual=violation / delta,
    )


def _polonsky_keer(
    kernels: SurfaceKernels, box: Box, g: FloatArray, delta: float, p: FloatArray, tol: float, max_iter: int
) -> tuple[FloatArray, int]:
    """Polonsky-Keer CG on one box; returns (pressure, iterations)."""
    apply = kernels.normal(box)
    reachable = np.isfinite(g)
    target = np.where(reachable, delta - g, 0.0)  # uz wanted in contact
    p = np.where(reachable, p, 0.0)
    if not np.any(p > 0):  # cold start: a pressure of the right order where the indenter overlaps
        scale = 2.0 / (kernels.normal_coefficients.max() * max(np.sqrt(np.count_nonzero(target > 0)), 1.0))
        p = np.where(target > 0, target * scale, 0.0)
    direction = np.zeros_like(p)
    g_old, restart = 1.0, True
    iteration = 0
    for iteration in range(1, max_iter + 1):  # noqa: B007 - the count is returned
        gap = apply(p[None])[0] - target  # g - delta + uz
        active = p > 0
        norm = float(np.sum(gap[active] ** 2))
        direction = np.where(active, gap + (0.0 if restart else norm / g_old) * direction, 0.0)
        g_old = norm
        response = apply(direction[None])[0]
        curvature = float(np.sum(response[active] * direction[active]))
        if curvature <= 0 or norm == 0:
            break
        step = float(np.sum(gap[active] * direction[active])) / curvature
        p_old = p
        p = np.where(active, p - step * direction, 0.0)
        p[p < 0] = 0.0
        entering = (p == 0) & reachable & (gap < 0)
        restart = bool(entering.any())
        p[entering] -= step * gap[entering]
        total = float(p.sum())
        change = float(np.abs(p - p_old).sum()) / total if total > 0 else 0.0
        rms_gap = np.sqrt(norm / max(int(active.sum()), 1)) / delta
        if change < tol and rms_gap < tol and not restart:
            break
    return p, iteration
