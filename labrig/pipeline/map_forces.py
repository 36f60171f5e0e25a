"""The forces of one depth map, prepared once and applied to every window's in-plane displacements.

Between two runs of the depth source (1 ms windows, depth every 10 ms) the map does not change, and
neither does anything the surface operator derives from it alone: the prescribed (pressed) nodes, their
normal forces, and the factorisation of the in-plane system on those nodes. :func:`prepare` does that
work once per map; :meth:`MapForces.__call__` then costs two small products and one triangular solve
per window; the factorisation of a pressed set is kept for the maps that press the same nodes
(:class:`SolverCache`). The arithmetic is :meth:`labrig.pipeline.ifem.SurfaceOperator.node_forces_n`'s, reordered
only where a sum skips nodes that carry no force (the result agrees to rounding).

Units and frames as :mod:`labrig.pipeline.forces`: displacements mm, forces N on the gel (pressing:
Fz < 0), gel frame; M markers, N top nodes, P pressed nodes.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.linalg import cho_factor
from scipy.linalg.lapack import dpotrs

from labrig.pipeline.ifem import FORCE_MODES, SurfaceOperator
from labrig.pipeline.unobserved import fill_in_plane

Array = npt.NDArray[np.float64]
HeldSolve = Callable[[Array], Array]


def held_solver(operator: SurfaceOperator, name: str, held: npt.NDArray[np.int64]) -> HeldSolve:
    """Forces (H,) N on the ``held`` DOFs of ``operator.<name>`` from displacements (H,) mm there, the others
    free: :meth:`SurfaceOperator._mixed_solve` with its factorisation done here, once (small held sets: the
    Cholesky factor of C_hh, C = K^-1; large ones: that of K_ff for the Schur complement)."""
    k = getattr(operator, name)
    if 2 * held.size <= len(k):
        c_hh, lower = cho_factor(operator.compliance(name)[np.ix_(held, held)], check_finite=False)
        return lambda u: _cholesky_solve(c_hh, lower, u)
    free = np.setdiff1d(np.arange(len(k)), held)
    k_hh = k[np.ix_(held, held)]
    if free.size == 0:
        return lambda u: np.asarray(k_hh @ u)
    k_fh = k[np.ix_(free, held)]
    k_ff, lower = cho_factor(k[np.ix_(free, free)], check_finite=False)
    return lambda u: np.asarray(k_hh @ u - k_fh.T @ _cholesky_solve(k_ff, lower, k_fh @ u))


def _cholesky_solve(factor: Array, lower: bool, b: Array) -> Array:
    """x with A x = b, ``factor`` A's Cholesky factor from ``cho_factor``: LAPACK's potrs called directly
    (scipy's ``cho_solve`` checks its arguments at several times the cost of a solve this small)."""
    x, info = dpotrs(factor, b, lower=lower)
    if info != 0:
        raise ValueError(f"potrs: argument {-info} is invalid")
    return np.asarray(x)


@dataclass(frozen=True)
class MapForces:
    """Per-marker forces (M, 3) N of one depth map from the markers' displacements (M, 2|3) mm.

    ``normal_n`` (M,): the map's normal forces per marker cell; ``interp_held`` (P, M) and ``cells_held``
    (M, P): the operator's spline and cell weights restricted to the pressed nodes (all N in "field" mode);
    ``tangential``: the pressed nodes' in-plane forces (2P,) from their displacements (x of every node,
    then y); ``fill``: the missing markers' in-plane completion (None: every marker observed)."""

    normal_n: Array
    interp_held: Array
    cells_held: Array
    tangential: HeldSolve
    fill: Array | None

    def __call__(self, displacements_mm: npt.ArrayLike) -> Array:
        out = np.empty((len(self.normal_n), 3))
        out[:, 2] = self.normal_n
        p = self.interp_held.shape[0]
        if p == 0:
            out[:, :2] = 0.0
            return out
        u = fill_in_plane(self.fill, displacements_mm)
        ut = self.interp_held @ u[:, :2]
        ft = self.tangential(np.ascontiguousarray(ut.T).reshape(-1))
        out[:, 0] = self.cells_held @ ft[:p]
        out[:, 1] = self.cells_held @ ft[p:]
        return out


class SolverCache:
    """The factorised systems of the last ``size`` pressed sets (a held press keeps its set from map to map, so
    its factorisation is done once), least recently used dropped first."""

    def __init__(self, size: int = 8) -> None:
        self.size = size
        self._solvers: OrderedDict[bytes, tuple[HeldSolve, HeldSolve]] = OrderedDict()
        self.hits = 0
        self.misses = 0

    def solvers(self, operator: SurfaceOperator, held: npt.NDArray[np.int64]) -> tuple[HeldSolve, HeldSolve]:
        """(normal, in-plane) solvers of the pressed nodes ``held``."""
        key = held.tobytes()
        found = self._solvers.get(key)
        if found is not None:
            self._solvers.move_to_end(key)
            self.hits += 1
            return found
        self.misses += 1
        n = len(operator.node_xy_mm)
        found = (held_solver(operator, "k_zz", held), held_solver(operator, "k_tt", np.concatenate([held, held + n])))
        self._solvers[key] = found
        if len(self._solvers) > self.size:
            self._solvers.popitem(last=False)
        return found


def prepare(operator: SurfaceOperator, uz_nodes_mm: npt.ArrayLike, mode: str = "contact", threshold_mm: float = 0.01,
            fill: Array | None = None, cache: SolverCache | None = None) -> MapForces:
    """The :class:`MapForces` of one map: ``uz_nodes_mm`` (N,) the top nodes' normal displacement (up positive,
    pressed in: negative); ``mode`` and ``threshold_mm`` as :meth:`SurfaceOperator.node_forces_n`; ``cache``: the
    factorisations of recent pressed sets (one operator per cache)."""
    if mode not in FORCE_MODES:
        raise ValueError(f"mode must be one of {FORCE_MODES}, not {mode!r}")
    uz = np.asarray(uz_nodes_mm, np.float64)
    if mode == "field":
        normal = operator.cells @ (operator.k_zz @ uz)
        k_tt = operator.k_tt
        return MapForces(normal, operator.interp, operator.cells, lambda u: np.asarray(k_tt @ u), fill)
    held = np.flatnonzero(uz < -threshold_mm)
    if held.size == 0:
        return MapForces(np.zeros(operator.n_markers), operator.interp[:0], operator.cells[:, :0],
                         lambda u: u, fill)
    cells_held = np.ascontiguousarray(operator.cells[:, held])
    normal_solve, tangential = (cache or SolverCache(0)).solvers(operator, held)
    return MapForces(cells_held @ normal_solve(uz[held]), np.ascontiguousarray(operator.interp[held]), cells_held,
                     tangential, fill)
