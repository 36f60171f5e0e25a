"""Fourier-space surface compliances of the gel (half-space and bonded layer).

A compliance ``f(k)`` maps the 2-D Fourier transform of a surface traction
(MPa) to that of the surface displacement it causes (mm): ``u~ = f(k) q~``, so
compliances are in mm/MPa times mm (i.e. mm^2/N per unit of wavenumber area);
``k`` is the wavenumber magnitude in rad/mm.

Sign conventions (this package): displacement "into the gel" is positive for
the normal part (``uz``), pressure is positive in compression; tangential
tractions and displacements share the gel frame's x, y axes.

Three scalar compliances describe an isotropic surface:

* ``normal``: uz / p (frictionless top surface, i.e. zero shear traction);
* ``longitudinal``: u / q for a tangential traction along k (P-SV motion);
* ``transverse``: u / q for a tangential traction across k (antiplane, SH).

Half-space (Johnson 1985; physics.md 2.7): normal = longitudinal =
(1 - nu) / (G k) = 2 / (E* k), transverse = 1 / (G k).

Bonded layer of thickness t on a rigid base (physics.md 2.9): normal from the
closed form C(kt) written without overflow; transverse = tanh(kt) / (G k)
(exact antiplane shear of a bonded layer); longitudinal from the exact
plane-strain transfer matrix of the layer (:func:`layer_plane_strain`), which
tends to the half-space for kt >> 1 and to simple shear t / G for k -> 0.
The normal-tangential coupling is ignored (Goodman approximation). On a
half-space it is ~(1 - 2 nu) (0.04 at nu = 0.48). On a thin bonded
near-incompressible layer it is *not* small at kt ~ 0.3..2 (coupling ratio
up to ~0.55 at nu = 0.48, see :func:`layer_coupling_ratio`): the physics.md
2.9 disc load (0.126 N on r = 2 mm, E = 0.3 MPa, nu = 0.49) would move the
surface outwards by 2-6 um at r = 1-8 mm through it (this transfer matrix
gives 2.2, 5.9, 3.1 um at r = 1, 4, 8 mm; the FE there says 2-6 um), next to
~60 um of normal displacement. So pure pressing here gives no in-plane
surface motion, and shear gives no normal surface motion.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.linalg import expm

from labrig.config import GelConfig

FloatArray = npt.NDArray[np.float64]

#: Above this kt the layer equals the half-space to ~1e-7 (relative): use the half-space.
LAYER_KT_MAX = 10.0


def shear_modulus_mpa(gel: GelConfig) -> float:
    """G = E / (2 (1 + nu)), MPa."""
    return gel.youngs_modulus_mpa / (2.0 * (1.0 + gel.poisson_ratio))


def contact_modulus_mpa(gel: GelConfig) -> float:
    """E* = E / (1 - nu^2) for a rigid indenter, MPa."""
    return gel.youngs_modulus_mpa / (1.0 - gel.poisson_ratio**2)


def confined_modulus_mpa(gel: GelConfig) -> float:
    """M = E (1 - nu) / ((1 + nu)(1 - 2 nu)), MPa (uniaxial strain)."""
    nu = gel.poisson_ratio
    return gel.youngs_modulus_mpa * (1 - nu) / ((1 + nu) * (1 - 2 * nu))


def halfspace_compliances(k_per_mm: npt.ArrayLike, gel: GelConfig) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(normal, longitudinal, transverse) half-space compliances; inf at k = 0."""
    k = np.asarray(k_per_mm, dtype=np.float64)
    g = shear_modulus_mpa(gel)
    with np.errstate(divide="ignore"):
        transverse = 1.0 / (g * k)
    longitudinal = (1.0 - gel.poisson_ratio) * transverse
    return longitudinal.copy(), longitudinal, transverse


def layer_normal_compliance(k_per_mm: npt.ArrayLike, gel: GelConfig) -> FloatArray:
    """uz / p of a bonded layer with a frictionless top (physics.md 2.9), mm^2/N.

    The stiffness (E* k / 2) C(kt) is inverted with every exponential written as
    exp(-2kt) <= 1, so large kt cannot overflow; k = 0 gives t / M.
    """
    k = np.asarray(k_per_mm, dtype=np.float64)
    nu, t = gel.poisson_ratio, gel.thickness_mm
    x = k * t
    e2 = np.exp(-2.0 * x)
    safe_x = np.where(x > 0, x, 1.0)
    # denominator / x, with (1 - exp(-4x)) / x -> 4 at x = 0
    den_over_x = (3 - 4 * nu) * np.where(x > 0, -np.expm1(-4.0 * x) / safe_x, 4.0) - 4.0 * e2
    num = (3 - 4 * nu) * (1.0 + e2**2) + 2.0 * (2.0 * x**2 + 8 * nu**2 - 12 * nu + 5) * e2
    return 2.0 * t / contact_modulus_mpa(gel) * den_over_x / num


def layer_transverse_compliance(k_per_mm: npt.ArrayLike, gel: GelConfig) -> FloatArray:
    """u / q across k (antiplane shear) of a bonded layer: tanh(kt) / (G k); t / G at k = 0."""
    k = np.asarray(k_per_mm, dtype=np.float64)
    t = gel.thickness_mm
    x = k * t
    ratio = np.where(x > 0, np.tanh(x) / np.where(x > 0, x, 1.0), 1.0)
    return ratio * t / shear_modulus_mpa(gel)


def layer_plane_strain(kt: npt.ArrayLike, nu: float) -> FloatArray:
    """Dimensionless plane-strain surface compliance matrix of a bonded layer.

    Returns ``c`` of shape (..., 2, 2) with, for a Fourier mode of wavenumber k
    and shear modulus G: longitudinal u/q = c[0, 0] t / (G kt), normal uz/p =
    c[1, 1] t / (G kt), and the coupling terms c[0, 1], c[1, 0] (pure imaginary
    in the physical mode; here as real magnitudes with sign).

    Method: state (V, W, s, n) = (in-plane and normal displacement, shear and
    normal traction / (G k)) obeys d/d(kz) = B state through the depth z; the
    base (z = t) is fixed; the 4x4 propagator is ``expm(B kt)``. B stays
    bounded as nu -> 0.5. Conditioning limits kt to ~10 (cond ~ e^(2 kt)).
    """
    x = np.atleast_1d(np.asarray(kt, dtype=np.float64))
    lam = 2 * nu / (1 - 2 * nu)  # lambda / G
    b = np.array(
        [
            [0.0, -1.0, 1.0, 0.0],
            [lam / (lam + 2), 0.0, 0.0, 1.0 / (lam + 2)],
            [4 * (lam + 1) / (lam + 2), 0.0, 0.0, -lam / (lam + 2)],
            [0.0, 0.0, 1.0, 0.0],
        ]
    )
    phi = expm(x[:, None, None] * b)
    # base: [V, W](t) = phi11 [V, W](0) + phi12 [s, n](0) = 0; surface tractions are -(s, n)
    return np.linalg.solve(phi[:, :2, :2], phi[:, :2, 2:]).reshape(*np.shape(kt), 2, 2)


def layer_longitudinal_compliance(k_per_mm: npt.ArrayLike, gel: GelConfig) -> FloatArray:
    """u / q along k (plane strain) of a bonded layer, mm^2/N; t / G at k = 0, half-space above kt = 10."""
    k = np.asarray(k_per_mm, dtype=np.float64)
    t, g = gel.thickness_mm, shear_modulus_mpa(gel)
    x = k * t
    out = np.empty_like(x)
    small = x <= 0
    big = x > LAYER_KT_MAX
    mid = ~(small | big)
    out[small] = t / g
    out[big] = (1.0 - gel.poisson_ratio) / (g * k[big])
    if np.any(mid):
        out[mid] = layer_plane_strain(x[mid], gel.poisson_ratio)[..., 0, 0] * t / (g * x[mid])
    return out


def layer_coupling_ratio(kt: npt.ArrayLike, nu: float) -> FloatArray:
    """|coupling| / sqrt(normal * longitudinal) of a bonded layer: the size of what Goodman ignores."""
    c = layer_plane_strain(kt, nu)
    return np.abs(c[..., 0, 1]) / np.sqrt(np.abs(c[..., 0, 0] * c[..., 1, 1]))
