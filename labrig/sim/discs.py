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
    a = np.asarray(axes_px, dtype=np.float64)
    o = np.asarray(origins_px, dtype=np.int64)
    side = 2 * half_px
    grid = np.arange(side, dtype=np.float64)
    qx = (o[:, 0] - c[:, 0])[:, None, None] + grid[None, None, :]
    qy = (o[:, 1] - c[:, 1])[:, None, None] + grid[None, :, None]
    # Q = (A A^T)^-1, symmetric 2x2: [[qa, qb], [qb, qc]].
    aat = a @ np.swapaxes(a, -1, -2)
    det = aat[:, 0, 0] * aat[:, 1, 1] - aat[:, 0, 1] ** 2
    qa, qb, qc = (aat[:, 1, 1] / det)[:, None, None], (-aat[:, 0, 1] / det)[:, None, None], (aat[:, 0, 0] / det)[:, None, None]
    gx = qa * qx + qb * qy
    gy = qb * qx + qc * qy
    f2 = qx * gx + qy * gy
    f = np.sqrt(f2)
    grad = np.sqrt(gx * gx + gy * gy)
    with np.errstate(invalid="ignore", divide="ignore"):
        distance = np.where(f2 > 0, (f - 1.0) * f / grad, -np.inf)
    return np.clip(0.5 - distance / edge_px, 0.0, 1.0)
