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
(:func:`labrig.calibration.registration.press`), at least two indenter kinds.
Output: ``calibration/gel.toml`` (:meth:`GelFit.to_toml`).
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig
from labrig.errors import LabrigError
from labrig.indenters import Indenter
from labrig.physics.mechanics import ContactTable

F64 = npt.NDArray[np.float64]

#: Fewest points per curve, and curves, a fit accepts.
MIN_POINTS = 5
MIN_INDENTER_KINDS = 2


class CalibrationError(LabrigError):
    """Calibration could not be done from the data given; the message says what to change."""


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
        from labrig.calibration.files import save_text_atomic

        return save_text_atomic(path, self.to_toml())


def _q(text: str) -> str:
    return '"' + str(text).replace("\\", "\\\\").replace('"', '\\"') + '"'


def contact_table(indenter: Indenter, rig: RigConfig, poisson_ratio: float | None = None) -> ContactTable:
    """The normal-contact table the fit uses: the rig's gel (its E as reference, nu as chosen),
    the rig's mechanics mode and grid, no stiffening (cached on disk like the virtual rig's)."""
    gel = rig.gel if poisson_ratio is None else replace(rig.gel, poisson_ratio=float(poisson_ratio))
    return ContactTable.build(indenter, gel, mode=rig.sim.mechanics.mode, spacing_mm=rig.sim.mechanics.grid_spacing_mm,
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
    from scipy.optimize import least_squares

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

    def solve(fit_b: bool, data: list[tuple[F64, F64]]) -> tuple[F64, Any]:
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


def plot_fit(fit: GelFit, tables: dict[str, ContactTable], path: str | Path) -> Path:
    """Force against depth per curve with the fitted model, and the residuals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 7), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    for i, curve in enumerate(fit.curves):
        d0 = fit.depth_offsets_mm[i]
        line = top.plot(curve.depth_mm + d0, curve.force_n, "o", ms=3, label=f"{curve.indenter} {curve.location_mm}")[0]
        grid = np.linspace(0.0, float(curve.depth_mm.max()) + d0, 200)
        top.plot(grid, fit.model_force_n(i, grid - d0, tables), "-", color=line.get_color(), lw=1)
        bottom.plot(curve.depth_mm + d0, fit.residuals_n[i], "o", ms=3, color=line.get_color())
    top.set_ylabel("normal force (N)")
    top.set_title(f"E = {fit.youngs_modulus_mpa:.4f} MPa (nu = {fit.poisson_ratio} chosen), stiffening b = "
                  f"{fit.stiffening:.3f}, rms {fit.residual_rms_n * 1e3:.1f} mN")
    top.legend(fontsize=8)
    bottom.axhline(0, color="k", lw=0.5)
    bottom.set_xlabel("depth below the fitted surface (mm)")
    bottom.set_ylabel("residual (N)")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def load_gel(path: str | Path) -> dict[str, Any]:
    """The fitted values of a gel.toml (youngs_modulus_mpa, poisson_ratio, stiffening, ...)."""
    import tomllib

    try:
        return tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CalibrationError(f"{path}: no gel calibration; run `labrig calibrate gel`") from None


#: Default indentations for the modulus: indenter -> (locations in gel mm, depths below contact in mm).
DEFAULT_PLAN: dict[str, tuple[tuple[tuple[float, float], ...], tuple[float, ...]]] = {
    "sphere": (((0.0, 0.0),), (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0)),
    "cylinder": (((0.0, 0.0),), (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8)),
}


def measure_curves(
    rig: RigConfig,
    indenters: dict[str, Indenter],
    plan: dict[str, tuple[tuple[tuple[float, float], ...], tuple[float, ...]]] | None = None,
    *,
    seed: int = 0,
    indenters_path: Path | None = None,
    registration_path: str | Path | None = None,
    progress: Any = None,
    **press_options: Any,
) -> list[ForceDepthCurve]:
    """Stepped normal indentations per indenter (one rig session each; on hardware the operator
    mounts each indenter when asked), at the registered gel pose (or the nominal one)."""
    from labrig.calibration.registration import gel_pose, lift, press, rig_clearance
    from labrig.protocol.rigfile import device_config, safety_limits
    from labrig.protocol.session import RigSession

    plan = plan if plan is not None else DEFAULT_PLAN
    pose = gel_pose(rig, registration_path)
    curves = []
    for name, (locations, depths) in plan.items():
        if name not in indenters:
            raise CalibrationError(f"unknown indenter {name!r}; known: {', '.join(sorted(indenters))}")
        indenter = indenters[name]
        if progress:
            progress(f"{name}: opening the rig")
        with RigSession(rig, device_config(rig), safety_limits(rig), seed=seed, indenter=indenter,
                        indenters_path=indenters_path) as session:
            for loc in locations:
                if progress:
                    progress(f"{name}: pressing at {loc} mm")
                result = press(session, rig, indenter, pose, loc, depths, **press_options)
                curves.append(ForceDepthCurve(name, result.depth_mm, result.force_n[:, 2], f"{name}@{loc[0]:g},{loc[1]:g}",
                                              (float(loc[0]), float(loc[1]))))
            lift(session, pose, indenter, rig_clearance(rig))
    return curves
