"""Tangential contact with Coulomb friction under a rigid tangential shift.

Model (quasi-static, monotonic loading from zero; Cattaneo-Mindlin type):

* Goodman approximation: the normal solution (pressure p, contact area) is
  fixed; tangential tractions do not change it, and the normal pressure
  causes no in-plane displacement here (see :mod:`spectral` for the size of
  what this neglects).
* The indenter is shifted rigidly by ``shift_mm`` = s (2-vector, gel frame x,
  y, mm) relative to the gel's rigid base. ``traction_mpa`` q is the traction
  the indenter applies to the gel (MPa); the gel surface moves by u = K q.
* Coulomb with friction coefficient mu, isotropic: |q| <= mu p. Stick where
  |q| < mu p: there u = s (no relative slip). Slip elsewhere: the slip
  w = s - u (indenter relative to the gel surface) is parallel to q and
  |q| = mu p (the indenter drags the gel along its slip).
* Monotonic loading from zero along a fixed direction makes the accumulated
  slip direction equal the incremental one, so the stateless law above holds;
  for reversals see :mod:`history` (Masing superposition).

Equivalently q minimises 1/2 q.Kq - s.sum(q) subject to |q_i| <= mu p_i (a
convex problem with a disc constraint per cell; its optimality conditions are
exactly the stick and slip conditions above). It is solved by an accelerated
projected gradient (FISTA with adaptive restart): each iteration is one
convolution and an exact projection onto the discs, so slip directions need
no special treatment (a Polonsky-Keer-type CG with frozen slip cells stalls on
the direction of slip near the stick boundary, where the slip vanishes).
Gross slip (every cell slipping) gives |Q| = mu P.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.physics.mechanics.kernels import Box, SurfaceKernels
from labrig.physics.mechanics.normal import NormalSolution

FloatArray = npt.NDArray[np.float64]

#: A cell is "stick" when |q| < (1 - STICK_MARGIN) mu p.
STICK_MARGIN = 1e-4


@dataclass(frozen=True)
class TangentialSolution:
    """Tangential contact at one shift. Fields on the grid; vectors are (x, y) in the gel frame."""

    shift_mm: FloatArray  # (2,) rigid shift of the indenter
    traction_mpa: FloatArray  # (2, ny, nx), applied by the indenter to the gel
    ux_mm: FloatArray  # (ny, nx) in-plane surface displacement of the gel
    uy_mm: FloatArray
    stick_mask: npt.NDArray[np.bool_]
    force_n: FloatArray  # (2,) = (Qx, Qy), the tangential force the indenter applies to the gel
    iterations: int
    residual: float  # rms violation of the stick/slip conditions / |s|

    @property
    def slip_mask(self) -> npt.NDArray[np.bool_]:
        """Cells in contact that slip (|q| = mu p)."""
        return (np.hypot(*self.traction_mpa) > 0) & ~self.stick_mask


def solve_tangential(
    kernels: SurfaceKernels,
    normal: NormalSolution,
    shift_mm: npt.ArrayLike,
    *,
    friction: float | None = None,
    tol: float = 1e-6,
    max_iter: int = 3000,
    initial_traction_mpa: FloatArray | None = None,
) -> TangentialSolution:
    """Tractions under the rigid shift ``shift_mm`` at the normal contact ``normal``.

    ``friction`` defaults to the gel's (``kernels.gel.friction``).
    ``initial_traction_mpa`` (2, ny, nx) warm-starts from a nearby solution.
    """
    grid = kernels.grid
    shift = np.asarray(shift_mm, dtype=np.float64).reshape(2)
    box, q, iterations, residual = solve_traction_in_box(
        kernels, normal, shift, friction=friction, tol=tol, max_iter=max_iter, initial_traction_mpa=initial_traction_mpa
    )
    mu = kernels.gel.friction if friction is None else float(friction)
    bound = mu * normal.pressure_mpa[box.slices]
    traction = np.zeros((2, *grid.shape))
    traction[(slice(None), *box.slices)] = q
    u = kernels.tangential(box, Box.full(grid.shape))(q)
    stick = np.zeros(grid.shape, dtype=bool)
    stick[box.slices] = (bound > 0) & (np.hypot(*q) < (1 - STICK_MARGIN) * bound)
    return TangentialSolution(
        shift_mm=shift,
        traction_mpa=traction,
        ux_mm=u[0],
        uy_mm=u[1],
        stick_mask=stick,
        force_n=q.sum(axis=(1, 2)) * grid.cell_area_mm2,
        iterations=iterations,
        residual=residual,
    )


def solve_traction_in_box(
    kernels: SurfaceKernels,
    normal: NormalSolution,
    shift_mm: npt.ArrayLike,
    *,
    friction: float | None = None,
    tol: float = 1e-6,
    max_iter: int = 3000,
    initial_traction_mpa: FloatArray | None = None,
) -> tuple[Box, FloatArray, int, float]:
    """The traction only, on the contact's bounding box: (box, q (2, *box.shape), iterations, residual).

    Same problem as :func:`solve_tangential`, without the surface displacement
    on the whole grid (for tables, which convolve later). ``initial_traction_mpa``
    is on the whole grid.
    """
    mu = kernels.gel.friction if friction is None else float(friction)
    shift = np.asarray(shift_mm, dtype=np.float64).reshape(2)
    box = Box.around(normal.contact_mask)
    if not normal.contact_mask.any() or not np.any(shift):
        return box, np.zeros((2, *box.shape)), 0, 0.0
    bound = mu * normal.pressure_mpa[box.slices]
    q0 = None if initial_traction_mpa is None else initial_traction_mpa[(slice(None), *box.slices)]
    q, iterations, residual = _projected_gradient(kernels.tangential(box), bound, shift, q0, tol, max_iter)
    return box, q, iterations, residual


def full_slip_traction_mpa(normal: NormalSolution, direction: npt.ArrayLike, friction: float) -> FloatArray:
    """Gross-slip traction mu p along the unit vector of ``direction``, (2, ny, nx)."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    return friction * normal.pressure_mpa[None] * d[:, None, None]


def _project(q: FloatArray, bound: FloatArray) -> FloatArray:
    """Scale every traction vector into its disc |q| <= bound."""
    magnitude = np.hypot(q[0], q[1])
    scale = np.where(magnitude > bound, bound / np.where(magnitude > 0, magnitude, 1.0), 1.0)
    return q * scale


def _projected_gradient(apply, bound: FloatArray, shift: FloatArray, q0: FloatArray | None, tol: float, max_iter: int):  # type: ignore[no-untyped-def]
    """Accelerated projected gradient for min 1/2 q.Kq - s.sum(q), |q| <= bound.

    FISTA with adaptive restart (O'Donoghue & Candes 2015), step 1/L with L the
    largest eigenvalue of the convolution operator. Returns (q, iterations,
    residual) with residual = rms gradient mapping / |s| (rms stick-zone
    displacement error relative to the shift, at convergence).
    """
    inside = bound > 0
    s = shift[:, None, None]
    lipschitz = apply.max_eigenvalue()
    q = np.zeros((2, *bound.shape)) if q0 is None else _project(np.where(inside, q0, 0.0), bound)
    y, momentum = q, 1.0
    scale = float(np.hypot(*shift)) * np.sqrt(max(int(inside.sum()), 1))
    residual, iteration = np.inf, 0
    for iteration in range(1, max_iter + 1):  # noqa: B007 - the count is returned
        grad = np.where(inside, apply(y) - s, 0.0)  # u - s = -slip
        q_new = _project(y - grad / lipschitz, bound)
        step = y - q_new
        residual = lipschitz * np.sqrt(float(np.sum(step * step))) / scale
        if residual < tol:
            q = q_new
            break
        if float(np.sum(step * (q_new - q))) > 0:  # the momentum points uphill: restart it
            momentum = 1.0
        momentum_new = (1 + np.sqrt(1 + 4 * momentum**2)) / 2
        y = q_new + ((momentum - 1) / momentum_new) * (q_new - q)
        q, momentum = q_new, momentum_new
    return q, iteration, float(residual)
