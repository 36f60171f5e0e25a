"""Rotating tangential fields of axisymmetric contacts about the tip.

For an axisymmetric indenter the solution for a shift along angle phi is the
solution along x rotated: q_phi(x) = R(phi) q_0(R(-phi) x). Fields live on a
square box centred on the tip (odd size). Multiples of 90 degrees are exact
array rotations; other angles resample bilinearly (tables resample the
friction utilisation q / (mu p), see :func:`rotate_contact_traction`).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import numpy.typing as npt
from numba import njit

Array = npt.NDArray[np.floating]
F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


def rotate_vector_field(field: Array, angle_rad: float, valid: npt.NDArray[np.bool_] | None = None) -> Array:
    """(2, n, n) vector field on a tip-centred square box, rotated by ``angle_rad`` (counter-clockwise).

    With ``valid`` (n, n), the bilinear weights are renormalised over valid
    source cells (a normalised convolution), so values next to the edge of the
    valid region are not diluted by the invalid cells beyond it.
    """
    _, ny, nx = field.shape
    if ny != nx or ny % 2 == 0:
        raise ValueError("rotation needs a square, odd-sized box centred on the tip")
    quarter = angle_rad / (np.pi / 2)
    turns = round(quarter)
    if abs(quarter - turns) < 1e-9:
        return _rotate_quarter(field, turns % 4)
    index, weight = _sampler(ny, round(angle_rad, 12))
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    if valid is not None and field.dtype == np.float32:  # the traction's utilisation, at every solve: compiled
        out = np.empty((2, ny * nx), np.float32)
        _rotate_masked(np.ascontiguousarray(field).reshape(2, -1), index, weight,
                       np.ascontiguousarray(valid, dtype=bool).ravel(), float(c), float(s), out)
        return out.reshape(field.shape)
    if valid is not None:
        masked = weight * valid.ravel()[index]
        total = masked.sum(axis=0)
        weight = (masked / np.where(total > 0, total, 1)).astype(np.float32)
    flat = field.reshape(2, -1)
    sampled = np.einsum("kn,ckn->cn", weight, flat[:, index]).reshape(field.shape)
    return np.stack([c * sampled[0] - s * sampled[1], s * sampled[0] + c * sampled[1]]).astype(field.dtype)


@njit(cache=True, nogil=True)
def _rotate_masked(field, index, weight, valid, c, s, out):  # type: ignore[no-untyped-def]
    """:func:`rotate_vector_field` with ``valid``, float32, in one pass and numpy's arithmetic: the weights of
    the valid taps summed in tap order and divided by their sum (float32), the taps accumulated in order
    (float32), the rotation in float64 rounded to float32."""
    zero, one = np.float32(0.0), np.float32(1.0)
    for i in range(field.shape[1]):
        m0 = weight[0, i] if valid[index[0, i]] else zero
        m1 = weight[1, i] if valid[index[1, i]] else zero
        m2 = weight[2, i] if valid[index[2, i]] else zero
        m3 = weight[3, i] if valid[index[3, i]] else zero
        total = m0 + m1
        total += m2
        total += m3
        if not total > 0:
            total = one
        w0, w1, w2, w3 = m0 / total, m1 / total, m2 / total, m3 / total
        a = w0 * field[0, index[0, i]]
        a += w1 * field[0, index[1, i]]
        a += w2 * field[0, index[2, i]]
        a += w3 * field[0, index[3, i]]
        b = w0 * field[1, index[0, i]]
        b += w1 * field[1, index[1, i]]
        b += w2 * field[1, index[2, i]]
        b += w3 * field[1, index[3, i]]
        a64, b64 = np.float64(a), np.float64(b)
        out[0, i] = np.float32(c * a64 - s * b64)
        out[1, i] = np.float32(s * a64 + c * b64)


def rotate_contact_traction(traction: F32, bound: F32, angle: float, force_n: F64, area: float) -> tuple[F32, F64]:
    """Rotate an axisymmetric contact's traction (2, n, n) MPa by ``angle`` rad: (field, net shear force (2,) N).

    ``bound`` is mu p (MPa) on the same box, ``area`` the cell area (mm^2).

    The force rotates exactly. The field is resampled as the utilisation
    q / (mu p) (bounded by 1, constant in slip zones) over the contact, times
    mu p; what the resampling lost of the net force is added back spread over
    the contact as mu p, and the field clipped to mu p again (its sum then
    misses the force by the clipped part, < 0.1 %). The correction is as small
    as the resampling's error wherever the net force is: a residual traction
    whose opposite zones nearly cancel (after Shear and Shear Opposite) keeps
    its shape, where scaling the field to the force's magnitude would blow it up.
    """
    in_contact = bound > 0
    utilisation = traction / np.where(in_contact, bound, 1)
    rotated = rotate_vector_field(utilisation, angle, valid=in_contact) * bound
    c, s = np.cos(angle), np.sin(angle)
    force = np.array([c * force_n[0] - s * force_n[1], s * force_n[0] + c * force_n[1]])
    total_bound = float(bound.sum(dtype=np.float64))
    if total_bound > 0:
        missing = force / area - rotated.sum(axis=(1, 2), dtype=np.float64)  # MPa, summed over the cells
        rotated = clip_to_friction_disc(rotated + (missing / total_bound).astype(np.float32)[:, None, None] * bound,
                                        bound)
    return rotated, force


def clip_to_friction_disc(traction: F32, bound: F32) -> F32:
    """Scale each traction vector into its Coulomb disc |q| <= bound."""
    magnitude = np.hypot(traction[0], traction[1])
    over = magnitude > bound
    if not over.any():
        return traction
    scale = np.where(over, bound / np.where(over, magnitude, 1), 1).astype(traction.dtype)
    return traction * scale


def _rotate_quarter(field: Array, turns: int) -> Array:
    # rows are +y and columns +x, so a counter-clockwise turn is np.rot90's clockwise one
    out = np.rot90(field, k=-turns, axes=(1, 2))
    vx, vy = out[0], out[1]
    for _ in range(turns):
        vx, vy = -vy, vx
    return np.ascontiguousarray(np.stack([vx, vy]))


@lru_cache(maxsize=16)
def _sampler(n: int, angle_rad: float) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.float32]]:
    """Bilinear gather (4, n*n) indices and weights: value at x from the unrotated field at R(-angle) x."""
    half = n // 2
    j, i = np.meshgrid(np.arange(n) - half, np.arange(n) - half)
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    src_x, src_y = c * j + s * i + half, -s * j + c * i + half
    x0, y0 = np.floor(src_x).astype(int), np.floor(src_y).astype(int)
    fx, fy = src_x - x0, src_y - y0
    index, weight = [], []
    for dy, dx, w in ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)), (1, 0, (1 - fx) * fy), (1, 1, fx * fy)):
        yy, xx = y0 + dy, x0 + dx
        valid = (yy >= 0) & (yy < n) & (xx >= 0) & (xx < n)
        index.append(np.where(valid, yy * n + xx, 0).ravel())
        weight.append(np.where(valid, w, 0.0).ravel())
    return np.array(index), np.array(weight, dtype=np.float32)
