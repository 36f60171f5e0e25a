"""Real-space influence coefficients on the grid, for DC-FFT convolution.

``coefficients[c, dy + ny - 1, dx + nx - 1]`` is the surface displacement (mm)
at a cell centre caused by a unit traction (1 MPa) uniform over another cell
whose centre is (dx, dy) cells away (offset = field point - load point).
Components ``c``: normal ``[zz]``; tangential ``[xx, xy, yy]`` (xy = yx).
Sign conventions as in :mod:`spectral` (uz positive into the gel).

Half-space: exact integrals of the Boussinesq and Cerruti point-load kernels
over a square cell (Love's rectangle formula and its Cerruti analogues; the
normal-tangential coupling ~(1 - 2 nu) is dropped, Goodman approximation).

Bonded layer: half-space coefficients plus a smooth correction, the inverse
Hankel transform of (layer - half-space) spectral compliance (physics.md 2.9
and :mod:`spectral`). That difference decays like exp(-2kt) at large k, so the
correction is smooth on the scale of t and is sampled at cell centres; at
small k it cancels the half-space's 1/r tail, so the layer kernel decays
exponentially beyond a few t and a window of the grid size holds all of it.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import numpy.typing as npt
from scipy.special import j0, jv

from labrig.config import GelConfig
from labrig.physics.mechanics.grid import Grid
from labrig.physics.mechanics.spectral import (
    LAYER_KT_MAX,
    contact_modulus_mpa,
    layer_longitudinal_compliance,
    layer_normal_compliance,
    layer_transverse_compliance,
    shear_modulus_mpa,
)

FloatArray = npt.NDArray[np.float64]
MODES = ("layer", "halfspace")


def check_mode(mode: str) -> str:
    if mode not in MODES:
        raise ValueError(f"mode must be 'layer' or 'halfspace', not {mode!r}")
    return mode


def normal_coefficients(grid: Grid, gel: GelConfig, mode: str) -> FloatArray:
    """(1, 2ny-1, 2nx-1) normal influence coefficients, mm/MPa (read-only, cached)."""
    return _normal_coefficients(grid, _elastic(gel), check_mode(mode))


def tangential_coefficients(grid: Grid, gel: GelConfig, mode: str) -> FloatArray:
    """(3, 2ny-1, 2nx-1) tangential influence coefficients [xx, xy, yy], mm/MPa (read-only, cached)."""
    return _tangential_coefficients(grid, _elastic(gel), check_mode(mode))


def _elastic(gel: GelConfig) -> GelConfig:
    """The gel with only what the kernels depend on (E, nu, thickness), so caches ignore the rest."""
    return GelConfig(gel.thickness_mm, 0.0, 0.0, gel.youngs_modulus_mpa, gel.poisson_ratio, 0.0)


@lru_cache(maxsize=8)
def _normal_coefficients(grid: Grid, gel: GelConfig, mode: str) -> FloatArray:
    x, y = _offsets_mm(grid)
    c = _rectangle(_f_inv_r, x, y, grid.spacing_mm) / (np.pi * contact_modulus_mpa(gel))
    if mode == "layer":
        a0, _ = _layer_correction(grid, gel, normal=True)
        c += a0(np.hypot(x, y)) * grid.cell_area_mm2
    return _freeze(c[None])


@lru_cache(maxsize=8)
def _tangential_coefficients(grid: Grid, gel: GelConfig, mode: str) -> FloatArray:
    x, y = _offsets_mm(grid)
    h, nu, g = grid.spacing_mm, gel.poisson_ratio, shear_modulus_mpa(gel)
    i_xx = _rectangle(_f_xx_r3, x, y, h)
    i_yy = _rectangle(_f_xx_r3, y, x, h)
    i_xy = _rectangle(_f_xy_r3, x, y, h)
    c = np.stack([(1 - nu) * (i_xx + i_yy) + nu * i_xx, nu * i_xy, (1 - nu) * (i_xx + i_yy) + nu * i_yy])
    c /= 2 * np.pi * g
    if mode == "layer":
        a0, a2 = _layer_correction(grid, gel, normal=False)
        r = np.hypot(x, y)
        safe_r2 = np.where(r > 0, r * r, 1.0)
        cos2, sin2 = (x * x - y * y) / safe_r2, 2 * x * y / safe_r2
        iso, dev = a0(r), a2(r) / 2
        c += np.stack([iso - dev * cos2, -dev * sin2, iso + dev * cos2]) * grid.cell_area_mm2
    return _freeze(c)


def _offsets_mm(grid: Grid) -> tuple[FloatArray, FloatArray]:
    dy = np.arange(-(grid.ny - 1), grid.ny) * grid.spacing_mm
    dx = np.arange(-(grid.nx - 1), grid.nx) * grid.spacing_mm
    x, y = np.meshgrid(dx, dy)
    return x, y


def _rectangle(f, x: FloatArray, y: FloatArray, h: float) -> FloatArray:  # type: ignore[no-untyped-def]
    """Integral over a cell of side h centred at offset (x, y), from the antiderivative f(x, y)."""
    a = h / 2  # corners sit at half-cell offsets, never at x = 0 or y = 0
    return f(x + a, y + a) - f(x + a, y - a) - f(x - a, y + a) + f(x - a, y - a)


def _f_inv_r(x: FloatArray, y: FloatArray) -> FloatArray:
    """Antiderivative of 1/r in x and y."""
    return x * np.arcsinh(y / np.abs(x)) + y * np.arcsinh(x / np.abs(y))


def _f_xx_r3(x: FloatArray, y: FloatArray) -> FloatArray:
    """Antiderivative of x^2 / r^3 in x and y (swap the arguments for y^2 / r^3)."""
    return y * np.arcsinh(x / np.abs(y))


def _f_xy_r3(x: FloatArray, y: FloatArray) -> FloatArray:
    """Antiderivative of x y / r^3 in x and y."""
    return -np.hypot(x, y)


def _layer_correction(grid: Grid, gel: GelConfig, normal: bool):  # type: ignore[no-untyped-def]
    """Point-load kernels (layer - half-space) as functions of r (mm -> mm/(MPa mm^2)).

    normal: returns (A, None) with dK_zz(r) = A(r).
    tangential: returns (A0, A2) with dK_ij = A0 delta_ij - A2 (r_i r_j / r^2 - delta_ij / 2).
    A_n(r) = 1/(2 pi) int_0^inf g(k) J_n(k r) dk with g = k (f_layer - f_halfspace), by the
    trapezoid rule on a k grid fine enough for the largest offset on the grid.
    """
    t = gel.thickness_mm
    r_max = float(np.hypot(grid.nx, grid.ny)) * grid.spacing_mm
    dk = min(0.1 / r_max, 0.02 / t)
    k = np.arange(0.0, 30.0 / t + dk, dk)
    weights = np.full(k.shape, dk / (2 * np.pi))
    weights[[0, -1]] /= 2
    dr = min(grid.spacing_mm / 2, t / 100)
    r = np.arange(0.0, r_max + 2 * dr, dr)
    kr = np.outer(r, k)
    if normal:
        g = k * layer_normal_compliance(k, gel) - 2.0 / contact_modulus_mpa(gel)
        a0 = (j0(kr) * g) @ weights
        return _interpolator(r, a0), None
    shear = shear_modulus_mpa(gel)
    g_long = k * layer_longitudinal_compliance(k, gel) - (1 - gel.poisson_ratio) / shear
    g_trans = k * layer_transverse_compliance(k, gel) - 1.0 / shear
    g_long[k * t > LAYER_KT_MAX] = 0.0
    a0 = (j0(kr) * ((g_long + g_trans) / 2)) @ weights
    a2 = (jv(2, kr) * (g_long - g_trans)) @ weights
    return _interpolator(r, a0), _interpolator(r, a2)


def _interpolator(r_table: FloatArray, values: FloatArray):  # type: ignore[no-untyped-def]
    return lambda r: np.interp(r, r_table, values)


def _freeze(a: FloatArray) -> FloatArray:
    a.setflags(write=False)
    return a
