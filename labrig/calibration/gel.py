"""Gel modulus: fit Young's modulus E to force-depth curves of normal indentations.

Model. The normal force of a rigid indenter pressed ``delta`` into the gel is
the tabulated bonded-layer contact (:class:`~labrig.physics.mechanics.ContactTable`,
Polonsky-Keer with the layer kernel: the model the ground truth uses), built
once at a reference modulus E_ref and the rig's Poisson ratio. At fixed nu a
linear-elastic solution scales with E, so

    F(delta) = (E / E_ref) * F_table(delta) * (1 + b * delta / h),

where ``delta = d + d0``: ``d`` is the depth below the point where the
approach detected contact and ``d0`` (fitted per curve) the depth at which it
did (contact is detected at a small force, slightly below the true surface).
``1 + b * delta / h`` (h the gel thickness) is a first-order large-strain
stiffening of the silicone: a linear model fitted over deep indentations reads
it as a higher modulus, so ``b`` is fitted with E (it is identifiable because
the indenters' curves have different shapes: a flat punch is nearly linear in
depth, a sphere is not). ``b = 0`` (``stiffening=False``) gives the plain
linear fit, which should then be restricted to modest depths (``max_depth_mm``).
E is then the small-strain modulus; nu stays a modelling choice (the rig's,
stated in the output): E and nu are not separately identifiable from a few
normal indentations.

Inputs: :class:`ForceDepthCurve` s from quasi-static stepped indentations
(:func:`labrig.protocol.touchoff.press`, run by
:func:`labrig.protocol.calibration_runs.measure_curves`), at least two indenter
kinds. Output: ``calibration/gel.toml`` (:meth:`GelFit.to_toml`, read back by
:func:`load_gel`); :func:`labrig.calibration.plots.plot_fit` draws it.
"""

from __future__ import annotations

import datetime as _dt
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.optimize import OptimizeResult, least_squares

from labrig.calibration.files import save_text_atomic
from labrig.config import RigConfig
from labrig.errors import CalibrationError
from labrig.indenters import Indenter
from labrig.physics.mechanics import ContactTable

F64 = npt.NDArray[np.float64]

#: Fewest points per curve, and curves, a fit accepts.
MIN_POINTS = 5
MIN_INDENTER_KINDS = 2


@dataclass(frozen=True)
class ForceDepthCurve:
    """Normal force (N, pressing > 0) against depth below the detected contact (mm), one indentation."""

    indenter: str
    depth_mm: F64
    force_n: F64
    source: str = ""
    location_mm: tuple[float, float] = (0.0, 0.0)


@dataclass
class GelFit:
    """The fitted modulus and what it came from."""

    youngs_modulus_mpa: float
    poisson_ratio: float
    stiffening: float
    stiffening_fitted: bool
    depth_offsets_mm: list[float]
    residual_rms_n: float
    residual_rel: float
    residuals_n: list[F64]
    curves: list[ForceDepthCurve]
    reference_modulus_mpa: float
    thickness_mm: float
    max_depth_mm: float | None
    linear_small_depth_mpa: float | None = None
    linear_small_depth_mm: float | None = None
    date: str = field(default_factory=lambda: _dt.datetime.now().astimezone().isoformat(timespec="seconds"))
    sources: list[dict[str, str]] = field(default_factory=list)

    def model_force_n(self, curve_index: int, depth_mm: npt.ArrayLike, tables: dict[str, ContactTable]) -> F64:
        """The fitted model's normal force (N) of curve ``curve_index`` at depths below its detected contact (mm)."""
        curve = self.curves[curve_index]
        delta = np.asarray(depth_mm, dtype=np.float64) + self.depth_offsets_mm[curve_index]
        return _model(tables[curve.indenter], delta, self.youngs_modulus_mpa / self.reference_modulus_mpa,
                      self.stiffening, self.thickness_mm)

    def summary(self) -> dict[str, Any]:
        return {
            "youngs_modulus_mpa": round(self.youngs_modulus_mpa, 5),
            "poisson_ratio": self.poisson_ratio,
            "stiffening": round(self.stiffening, 4),
            "stiffening_fitted": self.stiffening_fitted,
            "linear_small_depth_mpa": None if self.linear_small_depth_mpa is None else round(self.linear_small_depth_mpa, 5),
            "linear_small_depth_mm": self.linear_small_depth_mm,
            "residual_rms_n": round(self.residual_rms_n, 5),
            "residual_rel": round(self.residual_rel, 5),
            "curves": [{"indenter": c.indenter, "location_mm": list(c.location_mm), "points": len(c.depth_mm),
                        "max_depth_mm": round(float(c.depth_mm.max()), 4), "depth_offset_mm": round(d0, 5),
                        "residual_rms_n": round(float(np.sqrt(np.mean(r ** 2))), 5), "source": c.source}
                       for c, d0, r in zip(self.curves, self.depth_offsets_mm, self.residuals_n, strict=True)],
        }

    def to_toml(self) -> str:
        lines = [
            "# Gel modulus fitted by `labrig calibrate gel` (labrig.calibration.gel).",
            "# Model: F = (E/E_ref) F_table(d + d0) (1 + stiffening (d + d0)/h), bonded-layer contact tables;",
            "# poisson_ratio is a modelling choice (not fitted).",
            f"date = {_q(self.date)}",
            f"youngs_modulus_mpa = {self.youngs_modulus_mpa:.6g}",
            f"poisson_ratio = {self.poisson_ratio:.6g}",
            f"thickness_mm = {self.thickness_mm:.6g}",
            f"stiffening = {self.stiffening:.6g}              # E_eff = E (1 + stiffening * depth / thickness)",
            f"stiffening_fitted = {str(self.stiffening_fitted).lower()}",
            f"residual_rms_n = {self.residual_rms_n:.6g}",
            f"residual_rel = {self.residual_rel:.6g}          # rms residual / rms force",
            f"reference_modulus_mpa = {self.reference_modulus_mpa:.6g}",
        ]
        if self.max_depth_mm is not None:
            lines.append(f"max_depth_mm = {self.max_depth_mm:.6g}")
        if self.linear_small_depth_mpa is not None:
            lines.append(f"linear_small_depth_mpa = {self.linear_small_depth_mpa:.6g}   "
                         f"# plain linear fit up to {self.linear_small_depth_mm} mm, for comparison")
        for curve, d0, res in zip(self.curves, self.depth_offsets_mm, self.residuals_n, strict=True):
            lines += ["", "[[data]]", f"indenter = {_q(curve.indenter)}",
                      f"location_mm = [{curve.location_mm[0]:.4g}, {curve.location_mm[1]:.4g}]",
                      f"points = {len(curve.depth_mm)}", f"max_depth_mm = {float(curve.depth_mm.max()):.5g}",
                      f"depth_offset_mm = {d0:.6g}", f"residual_rms_n = {float(np.sqrt(np.mean(res ** 2))):.6g}",
                      f"source = {_q(curve.source)}",
                      "depth_mm = [" + ", ".join(f"{v:.5f}" for v in curve.depth_mm) + "]   # below the detected contact",
                      "force_n = [" + ", ".join(f"{v:.5f}" for v in curve.force_n) + "]"]
        for source in self.sources:
            lines += ["", "[[recordings]]"] + [f"{k} = {_q(v)}" for k, v in source.items()]
        return "\n".join(lines) + "\n"

    def save(self, path: str | Path) -> Path:
        return save_text_atomic(path, self.to_toml())


def _q(text: str) -> str:
    return '"' + str(text).replace("\\", "\\\\").replace('"', '\\"') + '"'


def contact_table(indenter: Indenter, rig: RigConfig, poisson_ratio: float | None = None) -> ContactTable:
    """The normal-contact table the fit uses: the rig's gel (its E as reference, nu as chosen),
    the rig file's ``[mechanics]`` mode and grid, no stiffening (cached on disk like the virtual rig's)."""
    gel = rig.gel if poisson_ratio is None else replace(rig.gel, poisson_ratio=float(poisson_ratio))
    return ContactTable.build(indenter, gel, mode=rig.mechanics.mode, spacing_mm=rig.mechanics.grid_spacing_mm,
                              stiffening=0.0)


#: The gel calibration's file name, next to the rig file.
GEL_FILE = "gel.toml"


@dataclass(frozen=True)
class GelModel:
    """The gel a contact model is built for: thickness (mm), Young's modulus (MPa, small strain),
    Poisson ratio, first-order stiffening b (``E_eff = E (1 + b depth / thickness)``) and where
    these came from (the gel calibration's file, or the rig file's ``[gel]`` with b = 0)."""

    thickness_mm: float
    youngs_modulus_mpa: float
    poisson_ratio: float
    stiffening: float
    source: str

    def summary(self) -> dict[str, Any]:
        return {"thickness_mm": self.thickness_mm, "youngs_modulus_mpa": round(self.youngs_modulus_mpa, 5),
                "poisson_ratio": self.poisson_ratio, "stiffening": round(self.stiffening, 4), "source": self.source}


def gel_model(rig: RigConfig, gel_path: str | Path | None = None) -> GelModel:
    """The gel as the lab knows it: the gel calibration (``gel_path``, default ``gel.toml`` next to
    the rig file, when it exists: its E, nu, thickness and stiffening), else the rig file's ``[gel]``
    (nominal E, nu, thickness; no stiffening known). A ``gel_path`` given but missing is an error."""
    path = Path(gel_path) if gel_path is not None else rig.path.parent / GEL_FILE
    if gel_path is None and not path.exists():
        return GelModel(rig.gel.thickness_mm, rig.gel.youngs_modulus_mpa, rig.gel.poisson_ratio, 0.0,
                        f"{rig.path} [gel] (no gel calibration next to it)")
    data = load_gel(path)
    try:
        return GelModel(float(data.get("thickness_mm", rig.gel.thickness_mm)), float(data["youngs_modulus_mpa"]),
                        float(data.get("poisson_ratio", rig.gel.poisson_ratio)), float(data.get("stiffening", 0.0)),
                        str(path))
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: a gel calibration needs youngs_modulus_mpa (and thickness_mm, poisson_ratio, "
                               f"stiffening); rerun `labrig calibrate gel` ({exc})") from None


def model_contact_table(indenter: Indenter, rig: RigConfig, gel: GelModel) -> ContactTable:
    """The normal-contact table of ``indenter`` on the gel ``gel`` (its thickness, E and nu; the rig's
    ``[mechanics]`` mode and grid; no stiffening: models apply ``gel.stiffening`` themselves)."""
    nominal = replace(rig.gel, thickness_mm=gel.thickness_mm, youngs_modulus_mpa=gel.youngs_modulus_mpa,
                      poisson_ratio=gel.poisson_ratio)
    return ContactTable.build(indenter, nominal, mode=rig.mechanics.mode, spacing_mm=rig.mechanics.grid_spacing_mm,
                              stiffening=0.0)


def _model(table: ContactTable, delta: F64, scale: float, stiffening: float, thickness_mm: float) -> F64:
    d = np.clip(delta, 0.0, float(table.depths_mm[-1]))
    base = np.interp(d, table.depths_mm, table.normal_force_n)
    return scale * base * (1.0 + stiffening * d / thickness_mm)


def fit_modulus(
    curves: list[ForceDepthCurve],
    rig: RigConfig,
    indenters: dict[str, Indenter],
    *,
    stiffening: bool = True,
    max_depth_mm: float | None = None,
    poisson_ratio: float | None = None,
    tables: dict[str, ContactTable] | None = None,
    compare_small_depth_mm: float | None = 0.3,
) -> GelFit:
    """Fit E (and the stiffening b, unless ``stiffening`` is False) and one depth offset per curve.

    ``max_depth_mm``: use only points up to this depth below contact. Raises
    :class:`CalibrationError` with fewer than MIN_POINTS points in a curve or
    fewer than MIN_INDENTER_KINDS indenter shapes.
    """
    if not curves:
        raise CalibrationError("no force-depth curves: press at least one sphere and one cylinder (flat punch)")
    use = []
    for curve in curves:
        keep = np.isfinite(curve.force_n) & np.isfinite(curve.depth_mm)
        if max_depth_mm is not None:
            keep &= curve.depth_mm <= max_depth_mm + 1e-9
        if int(keep.sum()) < MIN_POINTS:
            raise CalibrationError(
                f"the {curve.indenter} curve {curve.source or ''} has {int(keep.sum())} usable points"
                f"{'' if max_depth_mm is None else f' up to {max_depth_mm} mm'}; the fit needs at least {MIN_POINTS}: "
                "press deeper or in finer steps")
        use.append((curve.depth_mm[keep], curve.force_n[keep]))
    kinds = {indenters[c.indenter].kind if c.indenter in indenters else c.indenter for c in curves}
    if len(kinds) < MIN_INDENTER_KINDS:
        raise CalibrationError(
            f"force-depth curves of {len(kinds)} indenter shape ({', '.join(sorted(kinds))}); the fit needs at least "
            f"{MIN_INDENTER_KINDS} (e.g. a sphere and a cylinder): E and the depth offset trade off on one shape")
    nu = rig.gel.poisson_ratio if poisson_ratio is None else float(poisson_ratio)
    if tables is None:
        tables = {}
    for curve in curves:
        if curve.indenter not in tables:
            if curve.indenter not in indenters:
                raise CalibrationError(f"unknown indenter {curve.indenter!r} in the force-depth data")
            tables[curve.indenter] = contact_table(indenters[curve.indenter], rig, nu)
    h = rig.gel.thickness_mm
    e_ref = rig.gel.youngs_modulus_mpa
    n = len(curves)

    def solve(fit_b: bool, data: list[tuple[F64, F64]]) -> tuple[F64, OptimizeResult]:
        def residuals(p: F64) -> F64:
            scale, b = p[0], (p[1] if fit_b else 0.0)
            offsets = p[2:] if fit_b else p[1:]
            return np.concatenate([_model(tables[c.indenter], d + d0, scale, b, h) - f
                                   for c, (d, f), d0 in zip(curves, data, offsets, strict=True)])

        start = np.array(([1.0, 0.0] if fit_b else [1.0]) + [0.05] * n)
        lower = np.array(([1e-3, -2.0] if fit_b else [1e-3]) + [-0.5] * n)
        upper = np.array(([1e3, 5.0] if fit_b else [1e3]) + [1.0] * n)
        result = least_squares(residuals, start, bounds=(lower, upper), x_scale="jac")
        return result.x, result

    params, result = solve(stiffening, use)
    b = float(params[1]) if stiffening else 0.0
    offsets = [float(v) for v in (params[2:] if stiffening else params[1:])]
    residuals = []
    at = 0
    for d, _ in use:
        residuals.append(result.fun[at: at + len(d)].copy())
        at += len(d)
    all_f = np.concatenate([f for _, f in use])
    rms = float(np.sqrt(np.mean(result.fun ** 2)))
    fit = GelFit(
        youngs_modulus_mpa=float(params[0]) * e_ref, poisson_ratio=nu, stiffening=b, stiffening_fitted=stiffening,
        depth_offsets_mm=offsets, residual_rms_n=rms, residual_rel=rms / max(float(np.sqrt(np.mean(all_f ** 2))), 1e-12),
        residuals_n=residuals, curves=[replace(c, depth_mm=d, force_n=f) for c, (d, f) in zip(curves, use, strict=True)],
        reference_modulus_mpa=e_ref, thickness_mm=h, max_depth_mm=max_depth_mm,
    )
    if compare_small_depth_mm is not None:
        small = [(d[d <= compare_small_depth_mm], f[d <= compare_small_depth_mm]) for d, f in use]
        if all(len(d) >= 3 for d, _ in small):
            p_small, _ = solve(False, small)
            fit.linear_small_depth_mpa = float(p_small[0]) * e_ref
            fit.linear_small_depth_mm = compare_small_depth_mm
    return fit


def load_gel(path: str | Path) -> dict[str, Any]:
    """The fitted values of a gel.toml (youngs_modulus_mpa, poisson_ratio, stiffening, ...)."""
    try:
        return tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CalibrationError(f"{path}: no gel calibration; run `labrig calibrate gel`") from None
