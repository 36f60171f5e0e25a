"""Anti-aliased ellipses in small square pixel patches (the image of a small disc).

A disc of radius r on a plane images, to first order, as the ellipse
``{c + A s : |s| <= 1}`` with ``A = J r`` (J: the 2x2 pixel-per-mm Jacobian
of the projection at the disc's centre). Its coverage at a pixel centre q is
a linear ramp of ``edge_px`` across the boundary, using the first-order
signed distance ``(f - 1) / |grad f|`` with ``f(q) = |A^-1 (q - c)|``. The
coverage is point-symmetric about c, so its centroid is c (up to pixel
sampling). Pixel coordinates have the origin at the top-left pixel's centre.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]


def patch_half_px(axes_px: npt.ArrayLike, edge_px: float = 1.0, margin: float = 1.25) -> int:
    """Half the side of a patch that holds ellipses with these axes (K, 2, 2), grown by ``margin``."""
    semi_major = np.linalg.norm(np.asarray(axes_px, dtype=np.float64), ord=2, axis=(-2, -1))
    return int(np.ceil(margin * float(np.max(semi_major, initial=0.0)) + edge_px / 2 + 1.0))


def patch_origins(centres_px: npt.ArrayLike, half_px: int) -> npt.NDArray[np.int64]:
    """Top-left pixel (x, y) of the 2*half_px square patch around each centre (K, 2)."""
    return np.floor(np.asarray(centres_px, dtype=np.float64)).astype(np.int64) - half_px + 1


def ellipse_coverage(
    centres_px: npt.ArrayLike, axes_px: npt.ArrayLike, origins_px: npt.ArrayLike, half_px: int, edge_px: float = 1.0
) -> Array:
    """Coverage in [0, 1] of K ellipses on their (K, S, S) patches, S = 2 * half_px.

    ``centres_px`` (K, 2) and ``axes_px`` (K, 2, 2) as in the module docstring;
    ``origins_px`` (K, 2) the patch's top-left pixel (x, y), e.g. from :func:`patch_origins`.
    Patch element [k, i, j] is pixel (x, y) = origin_k + (j, i).
    """
    c = np.asarray(centres_px, dtype=np.float64)
    o = np.asarray(origins_px, dtype=np.int64)
    side = 2 * half_px
    # Flat (K, S*S) patches: long contiguous rows for numpy's inner loops.
    cols = np.tile(np.arange(side, dtype=np.float64), side)
    rows = np.repeat(np.arange(side, dtype=np.float64), side)
    qx = (o[:, 0] - c[:, 0])[:, None] + cols[None, :]
    qy = (o[:, 1] - c[:, 1])[:, None] + rows[None, :]
    qa, qb, qc = inverse_shape(axes_px)
    return coverage_at(qx, qy, qa[:, None], qb[:, None], qc[:, None], edge_px).reshape(-1, side, side)


def inverse_shape(axes_px: npt.ArrayLike) -> tuple[Array, Array, Array]:
    """(qa, qb, qc), each (K,): the symmetric Q = (A A^T)^-1 = [[qa, qb], [qb, qc]] of each ellipse."""
    a = np.asarray(axes_px, dtype=np.float64)
    aat = a @ np.swapaxes(a, -1, -2)
    det = aat[:, 0, 0] * aat[:, 1, 1] - aat[:, 0, 1] ** 2
    return aat[:, 1, 1] / det, -aat[:, 0, 1] / det, aat[:, 0, 0] / det


def coverage_at(qx: Array, qy: Array, qa: Array, qb: Array, qc: Array, edge_px: float = 1.0) -> Array:
    """Coverage at pixel offsets (qx, qy) from an ellipse centre, for its Q = [[qa, qb], [qb, qc]] (broadcast)."""
    gx = qa * qx + qb * qy
    gy = qb * qx + qc * qy
    f = qx * gx
    f += qy * gy  # f^2 = q^T Q q
    np.sqrt(f, out=f)
    gx *= gx
    gy *= gy
    gx += gy
    grad = np.sqrt(gx, out=gx)  # |grad f^2| / 2
    # Signed distance (f - 1) f / |grad f^2 / 2|; at the centre it is 0/0 = NaN, which fmin turns into full coverage.
    with np.errstate(invalid="ignore", divide="ignore"):
        distance = f - 1.0
        distance *= f
        distance /= grad
    if edge_px != 1.0:
        distance /= edge_px
    coverage = np.subtract(0.5, distance, out=distance)
    np.fmin(coverage, 1.0, out=coverage)
    np.fmax(coverage, 0.0, out=coverage)
    return coverage


def rim_radii(axes_px: npt.ArrayLike, edge_px: float = 1.0) -> tuple[Array, Array]:
    """(inner, outer) radii (K,), px: coverage is exactly 1 closer than ``inner`` to the centre, exactly 0 beyond ``outer``.

    With s1 >= s2 the singular values of A, f = |A^-1 q| and |grad f^2 / 2| = |Q q|
    lie within [|q| / s1, |q| / s2] and [|q| / s1^2, |q| / s2^2], which bounds the
    signed distance: <= -edge/2 (full) for |q| <= s2 - edge/2 s1 / s2, >= edge/2
    (empty) for |q| >= s1 + edge/2 (s1 / s2)^2.
    """
    a = np.asarray(axes_px, dtype=np.float64)
    aat = a @ np.swapaxes(a, -1, -2)
    mean = (aat[:, 0, 0] + aat[:, 1, 1]) / 2
    spread = np.sqrt(((aat[:, 0, 0] - aat[:, 1, 1]) / 2) ** 2 + aat[:, 0, 1] ** 2)
    s1, s2 = np.sqrt(mean + spread), np.sqrt(np.maximum(mean - spread, 1e-300))
    return s2 - edge_px / 2 * s1 / s2, s1 + edge_px / 2 * (s1 / s2) ** 2
