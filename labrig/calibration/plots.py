"""Figures of the rig calibrations: the registration's touch-offs and residuals, the gel modulus fit.

matplotlib (Agg) is imported by each function: only a plot needs it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labrig.calibration.gel import GelFit
from labrig.calibration.registration_file import RigRegistration
from labrig.physics.mechanics import ContactTable


def plot_registration(reg: RigRegistration, path: str | Path) -> Path:
    """Touch-off points on the gel and their residual arrows (in-plane, and height)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4.5))
    gel = np.array([p.contact_gel_mm for p in reg.points])
    res = np.array([reg.gel_in_machine.inverse().rotate(p.residual_mm) for p in reg.points]) * 1e3
    left.plot(gel[:, 0], gel[:, 1], "o")
    left.quiver(gel[:, 0], gel[:, 1], res[:, 0], res[:, 1], angles="xy", scale_units="xy", scale=1 / 0.2, color="r")
    for p, g in zip(reg.points, gel, strict=True):
        left.annotate(f"{p.location_mm}", g, fontsize=7, xytext=(4, 4), textcoords="offset points")
    left.set_aspect("equal")
    left.set_xlabel("gel x (mm)")
    left.set_ylabel("gel y (mm)")
    left.set_title("contacts; residual arrows: 1 um = 0.2 mm")
    right.bar(range(len(res)), res[:, 2])
    right.set_xlabel("touch-off")
    right.set_ylabel("height residual (um)")
    yaw, tilt = reg.yaw_tilt_deg
    right.set_title(f"yaw {yaw:.3f} deg, tilt {tilt[0]:.3f}/{tilt[1]:.3f} deg, rms {reg.residual_rms_mm * 1e3:.1f} um")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


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
