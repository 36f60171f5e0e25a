"""Missing markers in the inverse FEM: their displacements are unknowns, condensed out like interior nodes.

A marker that was never printed (or that the calibration did not find) has no tracked
displacement. The inverse FEM then treats its degrees of freedom as it treats the gel's
interior and its unmarked surface: unknown and free of applied force, so they follow the
observed markers through the gel's own stiffness. With K the stiffness over the markers'
DOFs, split into observed (o) and unobserved (u) ones, zero force on the unobserved DOFs
gives ``u_u = -K_uu^-1 K_uo u_o`` and the observed forces ``f_o = (K_oo - K_ou K_uu^-1 K_uo) u_o``:
static condensation (:func:`condense_unobserved`, the paper's K at the markers).

The dense surface operator (:class:`~labrig.pipeline.ifem.SurfaceOperator`) takes the
normal displacement from the depth map (unchanged: the depth network sees the whole
image) and the in-plane one from the markers through spline weights. There a missing
marker may sit under the contact, where the zero-force assumption is wrong: condensed, a
missing marker under a press took no shear traction and the net force error grew 1.4x
(three markers missing at the press, the stress suite's printed gel). The surface
operator's missing markers are therefore interpolated from their neighbours
(:func:`in_plane_fill`: biharmonic, so a smooth peak under the contact is followed rather than
flattened to its neighbours' mean: on a Gaussian bump one pitch wide with its three central
markers missing, the harmonic fill loses 47 % of their displacement, the biharmonic 27 %),
which holds under a contact (the in-plane field is smooth where the indenter sticks) as away
from it.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from labrig.pipeline.ifem import SurfaceOperator

Array = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def _dof_mask(observed: npt.ArrayLike, dofs_per_marker: int, marker_major: bool) -> BoolArray:
    o = np.asarray(observed, bool).reshape(-1)
    return np.repeat(o, dofs_per_marker) if marker_major else np.tile(o, dofs_per_marker)


def completion_matrix(k: npt.ArrayLike, observed_dofs: npt.ArrayLike) -> Array:
    """(n, n): ``u_full = C @ u`` keeps the observed DOFs and sets the others to ``-K_uu^-1 K_uo u_o``
    (zero force on them); columns of unobserved DOFs are zero, so their input values never count."""
    kk = np.asarray(k, np.float64)
    o = np.asarray(observed_dofs, bool)
    n = len(kk)
    if kk.shape != (n, n) or o.shape != (n,):
        raise ValueError(f"stiffness {kk.shape} and observed mask {o.shape} do not match")
    out = np.zeros((n, n))
    io, iu = np.flatnonzero(o), np.flatnonzero(~o)
    out[io, io] = 1.0
    if iu.size:
        if not io.size:
            raise ValueError("no observed degree of freedom")
        from scipy.linalg import solve

        out[np.ix_(iu, io)] = -solve(kk[np.ix_(iu, iu)], kk[np.ix_(iu, io)], assume_a="sym")
    return out


def condense_unobserved(k_n_per_mm: npt.ArrayLike, observed: npt.ArrayLike) -> Array:
    """The paper's K (3M x 3M, N/mm, marker-major) with the unobserved markers condensed out, kept full size:
    ``K' @ U`` gives the observed markers' forces from their displacements alone (the unobserved rows and
    columns are zero: no force there, and their displacements, e.g. NaN-free placeholders, never count)."""
    k = np.asarray(k_n_per_mm, np.float64)
    o = _dof_mask(observed, 3, marker_major=True)
    c = completion_matrix(k, o)
    out = k @ c
    out[~o] = 0.0
    return (out + out.T) / 2


def in_plane_fill(operator: SurfaceOperator, observed: npt.ArrayLike) -> Array | None:
    """(2M, 2M) completion of the markers' in-plane displacements (x of every marker, then y) for
    ``operator``: observed markers kept, unobserved ones biharmonic over the marker graph (neighbours:
    markers whose cells share a node, the 8 around each), x and y apart. None when every marker is observed."""
    o = np.asarray(observed, bool).reshape(-1)
    m = operator.n_markers
    if o.shape != (m,):
        raise ValueError(f"observed mask of {o.size} for {m} markers")
    if o.all():
        return None
    adjacency = (operator.cells @ operator.cells.T) > 0
    np.fill_diagonal(adjacency, False)
    laplacian = np.diag(adjacency.sum(axis=1)).astype(np.float64) - adjacency
    bending = laplacian @ laplacian
    zeros = np.zeros_like(bending)
    return completion_matrix(np.block([[bending, zeros], [zeros, bending]]), _dof_mask(o, 2, marker_major=False))


def fill_in_plane(fill: Array | None, displacements_mm: npt.ArrayLike) -> Array:
    """Displacements (M, 2|3) with the unobserved markers' x, y completed by ``fill`` (NaN there is fine)."""
    u = np.array(displacements_mm, np.float64)
    if fill is None:
        return u
    m = len(u)
    flat = np.nan_to_num(np.concatenate([u[:, 0], u[:, 1]]), nan=0.0)
    done = fill @ flat
    u[:, 0], u[:, 1] = done[:m], done[m:]
    return u
