"""Figures of the calibrations: the camera's intrinsics and extrinsics (detections and reprojection
residuals), the registration's touch-offs and residuals, the gel modulus fit, the contrast thresholds.

matplotlib (Agg) is imported by each function: only a plot needs it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from labrig.calibration.event_thresholds import EventThresholdFit
from labrig.calibration.gel import GelFit
from labrig.calibration.marker_map import MarkerMap
from labrig.calibration.registration_file import RigRegistration
from labrig.physics.mechanics import ContactTable

if TYPE_CHECKING:  # the camera calibrations import OpenCV; their figures need only their results
    from labrig.calibration.extrinsics import ExtrinsicsResult
    from labrig.calibration.intrinsics import IntrinsicsResult


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
        left.annotate(f"{p.location_mm}{' dropped' if p.rejected else ''}", g, fontsize=7, xytext=(4, 4),
                      textcoords="offset points")
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


def _residual_axes(frame: npt.NDArray[np.float64], measured: npt.NDArray[np.float64], projected: npt.NDArray[np.float64],
                   title: str, path: Path) -> Path:
    """The accumulated frame with detected and reprojected points (px) beside the residual arrows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(14, 4.6))
    ax0.imshow(frame, cmap="gray", vmax=np.percentile(frame[frame > 0], 99.5) if (frame > 0).any() else 1)
    ax0.plot(measured[:, 0], measured[:, 1], "+", color="tab:red", ms=6, label="detected")
    ax0.plot(projected[:, 0], projected[:, 1], "o", mfc="none", color="tab:cyan", ms=5, label="reprojected")
    ax0.set_title(f"{title}: accumulated frame")
    ax0.legend(loc="upper right", fontsize=8)
    residual = measured - projected
    ok = np.isfinite(residual).all(axis=1)
    scale = float(np.nanmax(np.linalg.norm(residual[ok], axis=1))) if ok.any() else 1.0
    ax1.quiver(projected[ok, 0], projected[ok, 1], residual[ok, 0], residual[ok, 1], angles="xy", color="tab:red")
    ax1.set_xlim(0, frame.shape[1])
    ax1.set_ylim(frame.shape[0], 0)
    ax1.set_aspect("equal")
    ax1.set_title(f"reprojection residuals (arrows autoscaled; longest {scale:.2f} px)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_intrinsics(result: IntrinsicsResult, path: str | Path) -> Path:
    """The first used view's frame and points with its residuals; beside it (``PATH-residuals.png``) every used view's."""
    path = Path(path)
    measured, projected = [], []
    for view in result.used:
        m, p = result.residuals(view)
        measured.append(m)
        projected.append(p)
    frame = result.preview if result.preview is not None else np.zeros((result.height_px, result.width_px))
    first = result.used[0]
    # Left: the first view's frame with its points; right: residuals of every used view.
    m0, p0 = result.residuals(first)
    out = _residual_axes(frame, m0, p0, f"intrinsics view {first}", path)
    if len(measured) > 1:
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(8, 4.6))
        allm, allp = np.concatenate(measured), np.concatenate(projected)
        r = allm - allp
        ax.quiver(allp[:, 0], allp[:, 1], r[:, 0], r[:, 1], angles="xy", color="tab:red")
        ax.set_xlim(0, result.width_px)
        ax.set_ylim(result.height_px, 0)
        ax.set_aspect("equal")
        ax.set_title(f"residuals of all {len(result.used)} views (RMS {result.rms_px:.3f} px)")
        fig.tight_layout()
        fig.savefig(path.with_name(path.stem + "-residuals" + path.suffix), dpi=110)
        plt.close(fig)
    return out


def plot_extrinsics(result: ExtrinsicsResult, path: str | Path) -> Path:
    """The LED-blink frame with detected and reprojected marker centres (px) and the residual arrows."""
    path = Path(path)
    return _residual_axes(result.frame, result.measured_px, result.rest_px, "extrinsics", path)


def plot_marker_residuals(marker_map: MarkerMap, path: str | Path, title: str = "markers as printed") -> Path:
    """Per-marker residual map: each marker at its nominal site (sensor px), coloured by how far its measured
    centre is from that site on the gel (um), an arrow to the measured centre (exaggerated), missing markers
    as red crosses and the five worst labelled by (row, col)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nominal, missing = marker_map.nominal_px, marker_map.missing
    found = ~missing
    norm_um = np.nan_to_num(marker_map.residual_norm_mm, nan=0.0) * 1e3
    residual = np.nan_to_num(marker_map.residual_px, nan=0.0)
    longest = float(marker_map.residual_norm_px[found].max()) if found.any() else 0.0
    pitch = float(np.median(np.linalg.norm(np.diff(nominal[: marker_map.cols], axis=0), axis=1)))
    gain = 0.6 * pitch / max(longest, 1e-3)  # the longest arrow 0.6 of a pitch
    fig, ax = plt.subplots(figsize=(9, 6))
    dots = ax.scatter(nominal[found, 0], nominal[found, 1], c=norm_um[found], cmap="viridis", s=40,
                      vmin=0.0, vmax=max(float(norm_um.max()), 1.0))
    fig.colorbar(dots, ax=ax, label="measured - nominal on the gel (um)")
    ax.quiver(nominal[found, 0], nominal[found, 1], gain * residual[found, 0], gain * residual[found, 1],
              angles="xy", scale_units="xy", scale=1.0, color="tab:red", width=0.003, zorder=3)
    ax.plot(nominal[missing, 0], nominal[missing, 1], "x", color="red", ms=12, mew=2.5,
            label=f"missing ({int(missing.sum())})")
    for worst in marker_map.worst(5):
        ax.annotate(f"({worst.row},{worst.col}) {worst.residual_mm * 1e3:.0f} um", nominal[worst.index], fontsize=7,
                    xytext=(5, 5), textcoords="offset points")
    ax.set_aspect("equal")
    ax.invert_yaxis()
    ax.set_xlabel("sensor x (px)")
    ax.set_ylabel("sensor y (px)")
    rms_um = float(np.sqrt(np.mean(norm_um[found] ** 2))) if found.any() else float("nan")
    ax.set_title(f"{title}: residual rms {rms_um:.0f} um, max {float(norm_um.max()):.0f} um; arrows x{gain:.0f}")
    if missing.any():
        ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_event_thresholds(fit: EventThresholdFit, path: str | Path) -> Path:
    """The ON and OFF contrast thresholds per grid cell over the ROI (sensor px), on one colour scale,
    and their histograms with the medians."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    on, off, roi = fit.thresholds.on_ln, fit.thresholds.off_ln, fit.thresholds.roi
    low, high = (float(v) for v in np.percentile(np.concatenate([on.ravel(), off.ravel()]), [0.5, 99.5]))
    extent = (roi.x0_px, roi.x1_px, roi.y1_px, roi.y0_px)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), gridspec_kw={"width_ratios": [1, 1, 0.9]})
    for ax, values, name in ((axes[0], on, "ON"), (axes[1], off, "OFF")):
        image = ax.imshow(values, extent=extent, vmin=low, vmax=high, cmap="viridis")
        ax.set_title(f"{name}: median {float(np.median(values)):.3f} ln")
        ax.set_xlabel("sensor x (px)")
        ax.set_ylabel("sensor y (px)")
    fig.colorbar(image, ax=axes[:2].tolist(), label="contrast threshold (ln intensity per event)", shrink=0.85)
    bins = np.linspace(low, high, 60)
    axes[2].hist(on.ravel(), bins=bins, alpha=0.6, color="tab:red", label=f"ON, median {fit.on_ln_median:.3f}")
    axes[2].hist(off.ravel(), bins=bins, alpha=0.6, color="tab:blue", label=f"OFF, median {fit.off_ln_median:.3f}")
    axes[2].set_xlabel("contrast threshold (ln)")
    axes[2].set_ylabel("cells")
    axes[2].set_title(f"ON / OFF = {fit.on_off_ratio:.3f}; {fit.ramps_used} ramps of ln {fit.schedule.ratio:g}")
    axes[2].legend(fontsize=8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
