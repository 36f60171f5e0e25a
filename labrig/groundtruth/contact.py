"""Normal contact models for the ground truth: closed forms and a tabulated numerical solver.

Every model answers, for an indentation ``delta`` (mm, the indenter tip below
the undeformed surface) and points given relative to the contact centre in
the gel plane (mm): the normal surface displacement into the gel ``uz`` (mm;
negative where a bonded layer bulges), the contact mask, the normal force
(N) and the gross-slip shift (mm, how far the tip may move in-plane before
the contact slides, used to place the field during shear).

Closed forms (elastic half-space only; physics.md 2.3-2.6, Johnson 1985):

* ``hertz`` -- paraboloid of the sphere's radius R: a^2 = R delta,
  P = 4/3 E* R^1/2 delta^3/2, uz = delta - r^2/2R inside, and
  (delta/pi)[(2 - r^2/a^2) asin(a/r) + sqrt(r^2/a^2 - 1)] outside.
* ``sneddon`` -- any axisymmetric profile f(r) (Sneddon, Int. J. Eng. Sci.
  3:47, 1965): with g(t) = delta - t int_0^t f'(s) / sqrt(t^2 - s^2) ds, the
  contact radius a solves g(a) = 0 (or is the profile's edge: a punch),
  uz(r) = 2/pi int_0^min(r, a) g(t) / sqrt(r^2 - t^2) dt, P = 2 E* int_0^a g dt.
  The flat cylinder with its fillet is this case (the fillet is treated, not
  ignored); a flat punch without fillet gives Sneddon's delta and
  (2 delta / pi) asin(a / r).

Numerical (``numerical``, half-space or bonded layer, any indenter): the
virtual rig's influence coefficients and Polonsky-Keer solver
(:mod:`labrig.physics.mechanics`) on a local grid around the tip, solved over the
indentation depth once per (indenter, gel, mode, grid) and cached on disk like
the sim's contact tables (:class:`DepthTable`). Lookups interpolate linearly
in depth and bilinearly in space. Outside the tabulated square the layer's
field is taken as zero (it decays within a few thicknesses: +1 um at 8 mm for
the default gel) and the half-space's as the far field of the net force,
P / (pi E* r).

Inside the contact every model returns the indenter's own surface, delta - f:
the depth there is set by the rigid indenter, not by the elastic model.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from labrig.cache import cache_folder, cache_key
from labrig.config import GelConfig
from labrig.indenters import Indenter
from labrig.physics.mechanics import Box, Grid, SurfaceKernels, indenter_height_mm, solve_normal
from labrig.physics.mechanics.spectral import contact_modulus_mpa, shear_modulus_mpa

F64 = npt.NDArray[np.float64]

#: Elastic models of the gel.
ELASTIC_MODELS = ("layer", "halfspace")
#: Contact solutions.
CONTACT_METHODS = ("hertz", "sneddon", "numerical")
#: Bump when the numerical table's numerics or layout change.
DEPTH_TABLE_VERSION = 1

_GAUSS_X, _GAUSS_W = np.polynomial.legendre.leggauss(96)


class ContactModel(Protocol):
    """What the ground-truth generator needs from a contact model."""

    @property
    def elastic(self) -> str: ...

    @property
    def method(self) -> str: ...

    def fields(self, delta_mm: float, dx_mm: F64, dy_mm: F64) -> tuple[F64, npt.NDArray[np.bool_]]:
        """(uz mm, contact mask) at points (dx, dy) relative to the contact centre."""
        ...

    def force_n(self, delta_mm: float) -> float: ...

    def slip_shift_mm(self, delta_mm: float, direction: F64 | None = None) -> float: ...

    def describe(self) -> dict[str, Any]: ...


def _gel_dict(gel: GelConfig) -> dict[str, float]:
    return {k: float(getattr(gel, k)) for k in ("thickness_mm", "youngs_modulus_mpa", "poisson_ratio", "friction")}


# ------------------------------------------------------------------------------------- closed forms


@dataclass(frozen=True)
class HertzModel:
    """A rigid sphere (as a paraboloid) on an elastic half-space."""

    radius_mm: float
    gel: GelConfig
    elastic: str = "halfspace"
    method: str = "hertz"

    def contact_radius_mm(self, delta_mm: float) -> float:
        return float(np.sqrt(self.radius_mm * max(delta_mm, 0.0)))

    def uz_radial(self, delta_mm: float, r_mm: npt.ArrayLike) -> F64:
        r = np.abs(np.asarray(r_mm, dtype=np.float64))
        if delta_mm <= 0:
            return np.zeros_like(r)
        a = self.contact_radius_mm(delta_mm)
        inside = delta_mm - r**2 / (2 * self.radius_mm)
        ratio = np.maximum(r, a) / a
        outside = (delta_mm / np.pi) * ((2 - ratio**2) * np.arcsin(1 / ratio) + np.sqrt(ratio**2 - 1))
        return np.where(r <= a, inside, outside)

    def fields(self, delta_mm: float, dx_mm: F64, dy_mm: F64) -> tuple[F64, npt.NDArray[np.bool_]]:
        r = np.hypot(dx_mm, dy_mm)
        return self.uz_radial(delta_mm, r), r <= self.contact_radius_mm(delta_mm) if delta_mm > 0 else r < 0

    def force_n(self, delta_mm: float) -> float:
        d = max(delta_mm, 0.0)
        return float(4.0 / 3.0 * contact_modulus_mpa(self.gel) * np.sqrt(self.radius_mm) * d**1.5)

    def slip_shift_mm(self, delta_mm: float, direction: F64 | None = None) -> float:
        """Mindlin: the sphere's rigid shift at gross slip, 3 mu P (2 - nu) / (16 G a)."""
        a = self.contact_radius_mm(delta_mm)
        if a <= 0:
            return 0.0
        nu, mu = self.gel.poisson_ratio, self.gel.friction
        return float(3 * mu * self.force_n(delta_mm) * (2 - nu) / (16 * shear_modulus_mpa(self.gel) * a))

    def describe(self) -> dict[str, Any]:
        return {"elastic": self.elastic, "method": self.method, "radius_mm": self.radius_mm, "gel": _gel_dict(self.gel)}


class SneddonModel:
    """A rigid axisymmetric indenter of profile f(r) on a half-space (Sneddon's integrals).

    ``profile_mm(r)`` is the height above the tip (inf beyond the indenter);
    ``edge_mm`` the radius where it ends (a punch's contact cannot grow past it).
    """

    elastic = "halfspace"
    method = "sneddon"

    def __init__(self, profile_mm: Any, edge_mm: float, gel: GelConfig, name: str = "") -> None:
        self.profile_mm = profile_mm
        self.edge_mm = float(edge_mm)
        self.gel = gel
        self.name = name
        self._cache: dict[float, tuple[float, F64, F64]] = {}

    @classmethod
    def for_indenter(cls, indenter: Indenter, gel: GelConfig) -> SneddonModel:
        if not indenter.axisymmetric:
            raise ValueError(f"Sneddon's integrals need an axisymmetric indenter; {indenter.name} is a {indenter.kind}")
        return cls(lambda r: indenter.height_mm(r, np.zeros_like(r)), indenter.footprint_radius_mm, gel, indenter.name)

    def slope(self, s_mm: F64) -> F64:
        """f'(s) by central differences, limited to the indenter (a wall beyond its edge)."""
        h = 1e-5
        s = np.clip(np.asarray(s_mm, dtype=np.float64), 0, self.edge_mm - 2 * h)
        return (self.profile_mm(s + h) - self.profile_mm(np.abs(s - h))) / (2 * h)

    def _abel(self, t_mm: F64) -> F64:
        """t int_0^t f'(s) / sqrt(t^2 - s^2) ds = t int_0^(pi/2) f'(t sin phi) dphi (Gauss-Legendre)."""
        t = np.asarray(t_mm, dtype=np.float64)
        phi = (np.pi / 4) * (_GAUSS_X + 1)
        inner = self.slope(t[..., None] * np.sin(phi)) @ ((np.pi / 4) * _GAUSS_W)
        return t * inner

    def contact_radius_mm(self, delta_mm: float) -> float:
        """a with g(a) = 0 (bisection; delta(a) grows with a), at most the profile's edge."""
        if delta_mm <= 0:
            return 0.0
        hi = self.edge_mm * (1 - 1e-6)
        if float(self._abel(np.array(hi))) <= delta_mm:
            return hi
        lo = 0.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if float(self._abel(np.array(mid))) < delta_mm:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)

    def _solution(self, delta_mm: float) -> tuple[float, F64, F64]:
        """(a, t nodes, g(t)) for one depth, memoised to 0.1 um."""
        key = round(float(delta_mm), 4)
        hit = self._cache.get(key)
        if hit is None:
            a = self.contact_radius_mm(key)
            t = np.linspace(0.0, a, 257)
            hit = (a, t, key - self._abel(t))
            if len(self._cache) > 4096:
                self._cache.clear()
            self._cache[key] = hit
        return hit

    def uz_radial(self, delta_mm: float, r_mm: npt.ArrayLike) -> F64:
        """uz(r) = 2/pi int_0^(asin(min(1, a/r))) g(r sin theta) dtheta."""
        r = np.abs(np.asarray(r_mm, dtype=np.float64))
        if delta_mm <= 0:
            return np.zeros_like(r)
        a, t, g = self._solution(delta_mm)
        top = np.arcsin(np.minimum(1.0, a / np.maximum(r, 1e-12)))
        theta = 0.5 * top[..., None] * (_GAUSS_X + 1)
        values = np.interp(r[..., None] * np.sin(theta), t, g)
        return (2 / np.pi) * 0.5 * top * (values @ _GAUSS_W)

    def fields(self, delta_mm: float, dx_mm: F64, dy_mm: F64) -> tuple[F64, npt.NDArray[np.bool_]]:
        r = np.hypot(dx_mm, dy_mm)
        if delta_mm <= 0:
            return np.zeros_like(r), np.zeros(r.shape, bool)
        a = self._solution(delta_mm)[0]
        # radial profile on a fine grid, interpolated (the quadrature per point would be slower)
        rr = np.concatenate([np.linspace(0, a, 64), a + np.geomspace(1e-3, max(float(r.max()), 2 * a) - a + 1e-3, 192)])
        uz = np.interp(r, rr, self.uz_radial(delta_mm, rr))
        contact = r <= a
        uz = np.where(contact, delta_mm - self.profile_mm(np.minimum(r, a)), uz)
        return uz, contact

    def force_n(self, delta_mm: float) -> float:
        if delta_mm <= 0:
            return 0.0
        _, t, g = self._solution(delta_mm)
        return float(2 * contact_modulus_mpa(self.gel) * np.trapezoid(g, t))

    def slip_shift_mm(self, delta_mm: float, direction: F64 | None = None) -> float:
        """The bonded punch's rigid shift at Q = mu P: mu P (2 - nu) / (8 G a) (Mindlin; an upper bound)."""
        a = self._solution(delta_mm)[0] if delta_mm > 0 else 0.0
        if a <= 0:
            return 0.0
        nu, mu = self.gel.poisson_ratio, self.gel.friction
        return float(mu * self.force_n(delta_mm) * (2 - nu) / (8 * shear_modulus_mpa(self.gel) * a))

    def describe(self) -> dict[str, Any]:
        return {"elastic": self.elastic, "method": self.method, "indenter": self.name, "edge_mm": self.edge_mm,
                "gel": _gel_dict(self.gel)}


# ------------------------------------------------------------------------------------- numerical


def depth_table_dir(cache_dir: str | Path | None = None) -> Path:
    """``cache_dir``, else the cache root (:mod:`labrig.cache`); plus /groundtruth_tables."""
    return cache_folder("groundtruth_tables", cache_dir)


class DepthTable:
    """Normal contact of one indenter over depth on a local grid (numerical), cached on disk.

    Arrays: ``depths_mm`` (nd,), ``uz`` (nd, ny, nx) float32, ``contact`` (nd, ny, nx) uint8,
    ``force_n`` (nd,), ``slip_shift_mm`` (nd, 2) along gel x and y.
    """

    elastic: str
    method = "numerical"

    def __init__(self, meta: dict[str, Any], arrays: dict[str, np.ndarray], indenter: Indenter, gel: GelConfig) -> None:
        self.meta = meta
        self.elastic = meta["spec"]["mode"]
        self.indenter = indenter
        self.gel = gel
        self.depths_mm: F64 = arrays["depths_mm"]
        self.uz: npt.NDArray[np.float32] = arrays["uz"]
        self.contact: npt.NDArray[np.uint8] = arrays["contact"]
        self.force: F64 = arrays["force_n"]
        self.slip: F64 = arrays["slip_shift_mm"]
        self.grid = Grid(meta["spec"]["spacing_mm"], *meta["spec"]["grid_shape"])

    @classmethod
    def build(cls, indenter: Indenter, gel: GelConfig, *, mode: str = "layer", spacing_mm: float = 0.1,
              size_mm: float = 24.0, depth_step_mm: float = 0.05, max_depth_mm: float | None = None,
              cache_dir: str | Path | None = None, use_cache: bool = True) -> DepthTable:
        """From the cache, or solved (about 1-5 s per indenter at 0.1 mm) and cached."""
        if mode not in ELASTIC_MODELS:
            raise ValueError(f"elastic model must be one of {', '.join(ELASTIC_MODELS)}, not {mode!r}")
        spec: dict[str, Any] = {
            "version": DEPTH_TABLE_VERSION,
            "indenter": {"kind": indenter.kind, **{k: v for k, v in indenter.geometry.items() if k != "file"}},
            "gel": _gel_dict(gel),
            "mode": mode,
            "spacing_mm": float(spacing_mm),
            "grid_shape": list(Grid.centred(size_mm, spacing_mm).shape),
            "depth_step_mm": float(depth_step_mm),
            "max_depth_mm": float(indenter.max_depth_mm if max_depth_mm is None else max_depth_mm),
        }
        if indenter._heightmap is not None:
            spec["indenter"]["heightmap_sha256"] = hashlib.sha256(np.ascontiguousarray(indenter._heightmap).tobytes()).hexdigest()
        if indenter.axis_mm is not None:
            spec["indenter"]["axis_mm"] = list(indenter.axis_mm)
        key = cache_key(spec)
        path = depth_table_dir(cache_dir) / f"{indenter.name}-{mode}-{key}.npz"
        if use_cache and path.exists():
            try:
                with np.load(path) as data:
                    meta = json.loads(str(data["meta"]))
                    arrays = {k: data[k] for k in ("depths_mm", "uz", "contact", "force_n", "slip_shift_mm")}
                return cls(meta, arrays, indenter, gel)
            except (OSError, ValueError, KeyError):
                pass  # damaged: rebuild
        start = time.perf_counter()
        arrays = _solve_depths(indenter, gel, spec)
        meta = {"spec": spec, "key": key, "build_seconds": time.perf_counter() - start, "indenter": indenter.name}
        table = cls(meta, arrays, indenter, gel)
        if use_cache:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            with open(tmp, "wb") as f:
                np.savez(f, allow_pickle=True, meta=np.array(json.dumps(meta)), **arrays)
            os.replace(tmp, path)
        return table

    def _bracket(self, delta_mm: float) -> tuple[int, float]:
        d = self.depths_mm
        if delta_mm > d[-1] + 1e-9:
            raise ValueError(f"indentation {delta_mm:.3f} mm is beyond the table's {d[-1]:.3f} mm "
                             f"(the {self.indenter.name} indenter's max_depth_mm)")
        i = int(np.clip(np.searchsorted(d, delta_mm, side="right") - 1, 0, len(d) - 2))
        return i, float(np.clip((delta_mm - d[i]) / (d[i + 1] - d[i]), 0.0, 1.0))

    def fields(self, delta_mm: float, dx_mm: F64, dy_mm: F64) -> tuple[F64, npt.NDArray[np.bool_]]:
        dx, dy = np.asarray(dx_mm, np.float64), np.asarray(dy_mm, np.float64)
        if delta_mm <= 0:
            return np.zeros(dx.shape), np.zeros(dx.shape, bool)
        i, w = self._bracket(delta_mm)
        g = self.grid
        col = dx / g.spacing_mm + g.nx // 2
        row = dy / g.spacing_mm + g.ny // 2
        inside = ((col >= 0) & (col <= g.nx - 1) & (row >= 0) & (row <= g.ny - 1)).ravel()
        # Bilinear weights once for the two depth rows' maps (the points outside are replaced below).
        corners, weights = _bilinear(row.ravel(), col.ravel(), g.ny, g.nx)
        uz = np.zeros(dx.size)
        mask = np.zeros(dx.size)
        for k, weight in ((i, 1 - w), (i + 1, w)):
            if weight == 0:
                continue
            uz += weight * _gather(self.uz[k], corners, weights)
            mask += weight * _gather(self.contact[k], corners, weights)
        contact = (mask >= 0.5) & inside
        if self.elastic == "halfspace":  # far field of the net force beyond the table
            r = np.hypot(dx, dy).ravel()
            far = self.force_n(delta_mm) / (np.pi * contact_modulus_mpa(self.gel) * np.maximum(r, 1e-9))
            uz = np.where(inside, uz, far)
        else:
            uz = np.where(inside, uz, 0.0)
        if contact.any():  # the rigid indenter's surface where it touches
            height = self.indenter.height_mm(dx.ravel()[contact], dy.ravel()[contact])
            uz[contact] = np.where(np.isfinite(height), delta_mm - height, uz[contact])
        return uz.reshape(dx.shape), contact.reshape(dx.shape)

    def force_n(self, delta_mm: float) -> float:
        if delta_mm <= 0:
            return 0.0
        return float(np.interp(delta_mm, np.concatenate([[0.0], self.depths_mm]), np.concatenate([[0.0], self.force])))

    def slip_shift_mm(self, delta_mm: float, direction: F64 | None = None) -> float:
        if delta_mm <= 0:
            return 0.0
        d = np.concatenate([[0.0], self.depths_mm])
        sx = float(np.interp(delta_mm, d, np.concatenate([[0.0], self.slip[:, 0]])))
        sy = float(np.interp(delta_mm, d, np.concatenate([[0.0], self.slip[:, 1]])))
        if direction is None:
            return min(sx, sy)
        c2 = float(direction[0] ** 2 / max(float(direction @ direction), 1e-30))
        return c2 * sx + (1 - c2) * sy

    def describe(self) -> dict[str, Any]:
        spec = self.meta["spec"]
        return {"elastic": self.elastic, "method": self.method, "indenter": self.indenter.name,
                "table_key": self.meta["key"], "spacing_mm": spec["spacing_mm"], "grid_shape": spec["grid_shape"],
                "depth_step_mm": spec["depth_step_mm"], "gel": spec["gel"]}


def _solve_depths(indenter: Indenter, gel: GelConfig, spec: dict[str, Any]) -> dict[str, np.ndarray]:
    grid = Grid(spec["spacing_mm"], *spec["grid_shape"])
    kernels = SurfaceKernels(grid, gel, spec["mode"])
    height = indenter_height_mm(indenter, grid)
    step = spec["depth_step_mm"]
    depths = step * np.arange(1, int(np.ceil(spec["max_depth_mm"] / step - 1e-9)) + 1)
    uz = np.zeros((len(depths), *grid.shape), np.float32)
    contact = np.zeros((len(depths), *grid.shape), np.uint8)
    force = np.zeros(len(depths))
    slip = np.zeros((len(depths), 2))
    warm = None
    for k, depth in enumerate(depths):
        sol = solve_normal(kernels, height, float(depth), initial_pressure_mpa=warm)
        warm = sol.pressure_mpa if sol.force_n > 0 else None
        uz[k], contact[k], force[k] = sol.depth_mm, sol.contact_mask, sol.force_n
        if sol.contact_mask.any():  # gross-slip shift: the stick zone's largest shift under mu p
            box = Box.around(sol.contact_mask, margin=1)
            p = sol.pressure_mpa[box.slices]
            apply = kernels.tangential(box)
            inside = sol.contact_mask[box.slices]
            for axis in (0, 1):
                q = np.zeros((2, *box.shape))
                q[axis] = gel.friction * p
                slip[k, axis] = float(np.max(apply(q)[axis][inside]))
    return {"depths_mm": depths, "uz": uz, "contact": contact, "force_n": force, "slip_shift_mm": slip}


# ------------------------------------------------------------------------------------- choice


_TABLES: dict[tuple[Any, ...], DepthTable] = {}


def _cached_table(indenter: Indenter, gel: GelConfig, mode: str, options: dict[str, Any]) -> DepthTable:
    """Tables stay in memory per process (a campaign reuses one per indenter)."""
    key = (indenter.name, json.dumps(indenter.geometry, sort_keys=True, default=str), indenter.axis_mm, gel, mode,
           json.dumps(options, sort_keys=True, default=str))
    if key not in _TABLES:
        if len(_TABLES) >= 16:
            _TABLES.clear()
        _TABLES[key] = DepthTable.build(indenter, gel, mode=mode, **options)
    return _TABLES[key]


def choose_model(indenter: Indenter, gel: GelConfig, elastic: str = "layer", method: str = "auto",
                 **table_options: Any) -> ContactModel:
    """The contact model for an indenter: the scene decides.

    ``elastic`` "layer" (default): the numerical solver (no closed form exists
    for a bonded layer). "halfspace": Hertz for a sphere, Sneddon's integrals
    for a (filleted) cylinder, the numerical solver for square, ridge and
    height-map indenters. ``method`` forces "hertz", "sneddon" or "numerical".
    ``table_options`` go to :meth:`DepthTable.build` (spacing_mm, size_mm, cache_dir, ...).
    """
    if elastic not in ELASTIC_MODELS:
        raise ValueError(f"elastic model must be one of {', '.join(ELASTIC_MODELS)}, not {elastic!r}")
    if method == "auto":
        if elastic == "layer":
            method = "numerical"
        elif indenter.kind == "sphere":
            method = "hertz"
        elif indenter.kind == "cylinder":
            method = "sneddon"
        else:
            method = "numerical"
    if method in ("hertz", "sneddon") and elastic != "halfspace":
        raise ValueError(f"the {method} closed form is for an elastic half-space; the layer needs the numerical solver")
    if method == "hertz":
        if indenter.kind != "sphere":
            raise ValueError(f"Hertz is for a sphere; {indenter.name} is a {indenter.kind}")
        return HertzModel(float(indenter.geometry["radius_mm"]), gel)
    if method == "sneddon":
        return SneddonModel.for_indenter(indenter, gel)
    if method != "numerical":
        raise ValueError(f"contact method must be auto or one of {', '.join(CONTACT_METHODS)}, not {method!r}")
    return _cached_table(indenter, gel, elastic, table_options)


def _bilinear(row: F64, col: F64, ny: int, nx: int) -> tuple[npt.NDArray[np.intp], F64]:
    """Flat indices (4, N) of each point's four surrounding nodes on an (ny, nx) grid and their bilinear
    weights (4, N); points beyond the grid take its nearest edge."""
    r = np.clip(row, 0.0, ny - 1)
    c = np.clip(col, 0.0, nx - 1)
    r0 = np.minimum(r.astype(np.intp), ny - 2)
    c0 = np.minimum(c.astype(np.intp), nx - 2)
    fr, fc = r - r0, c - c0
    base = r0 * nx + c0
    corners = np.stack([base, base + 1, base + nx, base + nx + 1])
    weights = np.stack([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc])
    return corners, weights


def _gather(values: np.ndarray, corners: npt.NDArray[np.intp], weights: F64) -> F64:
    """Bilinear samples (N,) of a 2-D array at the points of :func:`_bilinear`."""
    return (values.ravel().take(corners) * weights).sum(axis=0)
