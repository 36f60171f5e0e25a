"""``labrig calibrate rig`` and ``labrig calibrate gel``: rig registration and the gel's modulus.

Registered on the ``calibrate`` group by :func:`add_rig_calibration_commands`.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from rich.table import Table

from labrig.cli.console import (
    ForceOption,
    JsonOption,
    RigOption,
    calibration_file_rows,
    calibration_output,
    console,
    err_console,
    keep_backup,
    load_rig_and_indenters,
    output_file,
    print_json,
)

if TYPE_CHECKING:
    from labrig.config import RigConfig

IndentersOption = Annotated[Path | None, typer.Option("--indenters", help="Indenters TOML (default: protocols/indenters.toml).")]
SeedOption = Annotated[int, typer.Option(help="Seed of the virtual rig's noise (virtual rig only).")]


def _say_where(rig: RigConfig, as_json: bool) -> bool:
    from labrig.protocol.rigfile import device_config

    virtual = device_config(rig).virtual
    if virtual and not as_json:
        err_console.print("no hardware configured: calibrating on the virtual rig (embedded)")
    return virtual


def add_rig_calibration_commands(calibrate_app: typer.Typer) -> None:
    """Register ``rig`` and ``gel`` on the ``calibrate`` Typer group."""
    calibrate_app.command("rig")(rig_command)
    calibrate_app.command("gel")(gel_command)


def rig_command(
    out: Annotated[Path | None, typer.Option("--out", help="Registration file (default: rig-registration.toml next to the rig file).")] = None,  # noqa: E501
    force: ForceOption = False,
    plot: Annotated[Path | None, typer.Option(
        "--plot", help="Draw the touch-offs and residuals to this PNG.", callback=output_file)] = None,
    data: Annotated[Path, typer.Option("--data", help="Directory for the touch-off recordings.")] = Path("recordings/calibration"),  # noqa: E501
    points: Annotated[int, typer.Option(help="Touch-offs, 3 to 9: the corners of a 14 x 12 mm rectangle, its centre, "
                                        "its edges' midpoints (5 or more: a bad one can be dropped).")] = 5,
    gel: Annotated[Path | None, typer.Option("--gel", help="Gel calibration the surface fit models (default: gel.toml "
                                             "next to the rig file if any, else the rig file's [gel]).")] = None,
    shear_mm: Annotated[float, typer.Option(help="Shear at each touch-off for the F/T axes, mm.")] = 0.3,
    seed: SeedOption = 0,
    rig_path: RigOption = None,
    indenters_path: IndentersOption = None,
    as_json: JsonOption = False,
) -> None:
    """Where the gel is for the CNC (origin, yaw, tilt, surface height) and the F/T sensor's axes in the gel frame."""
    from labrig.calibration.plots import plot_registration
    from labrig.calibration.registration_file import default_registration_path
    from labrig.protocol.calibration_runs import register_rig, touchoff_locations

    rig, indenters, _ = load_rig_and_indenters(rig_path, indenters_path)
    target = calibration_output(out, default_registration_path(rig), force)
    _say_where(rig, as_json)
    locations = touchoff_locations(points)
    started = time.monotonic()

    def progress(message: str) -> None:
        if not as_json:
            err_console.print(f"[dim]{time.monotonic() - started:6.1f} s[/] {message}")

    reg = register_rig(rig, indenters, data_dir=data, locations=locations, shear_mm=shear_mm, gel_path=gel,
                       seed=seed, indenters_path=indenters_path, progress=progress)
    backup = keep_backup(target)
    path = reg.save(target)
    if plot is not None:
        plot_registration(reg, plot)
    summary = {"path": str(path), "plot": None if plot is None else str(plot),
               "backup": None if backup is None else str(backup), **reg.summary(),
               "wall_s": round(time.monotonic() - started, 2)}
    quality = reg.quality
    if quality.verdict != "good":
        err_console.print(f"[yellow]warning:[/] {quality.message()}")
    if as_json:
        print_json(summary)
        return
    yaw, tilt = reg.yaw_tilt_deg
    t = reg.gel_in_machine.translation_mm
    table = Table(title=f"rig registration -> {path}", show_header=False)
    table.add_column(style="dim")
    table.add_column()
    table.add_row("gel origin (machine)", f"{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f} mm (surface height {t[2]:.4f} mm)")
    table.add_row("yaw / tilt", f"{yaw:+.4f} deg / {tilt[0]:+.4f}, {tilt[1]:+.4f} deg")
    table.add_row("F/T axes", f"sensor x, y, z along gel {', '.join(reg.ft_axis_map)}; small rotation "
                  + " ".join(f"{v:+.5f}" for v in reg.ft_residual_rotvec_rad) + " rad")
    table.add_row("residuals", f"{reg.residual_rms_mm * 1e3:.1f} um rms over {quality.points_used} touch-offs "
                  f"(worst {quality.worst_residual_mm * 1e3:.1f} um, touch-off {quality.worst_index}; "
                  f"{quality.points_rejected} dropped; fit {quality.verdict}); F/T directions "
                  f"{reg.ft_angle_rms_deg:.2f} deg rms; surface fit {reg.surface_fit_rms_n * 1e3:.1f} mN rms")
    if reg.surface_gel is not None:
        g = reg.surface_gel
        table.add_row("gel modelled", f"{g.thickness_mm:g} mm, E {g.youngs_modulus_mpa:.3f} MPa, nu {g.poisson_ratio:g}, "
                      f"stiffening {g.stiffening:.2f} ({g.source})")
    table.add_row("camera", reg.camera_source)
    for i, p in enumerate(reg.points):
        dropped = f"; DROPPED ({p.rejected_residual_mm * 1e3:.0f} um from the others' pose)" if p.rejected else ""
        table.add_row(f"touch-off {i}", f"at {p.location_mm} -> gel {p.contact_gel_mm[0]:+.3f}, {p.contact_gel_mm[1]:+.3f} mm, "
                      f"contact {p.depth_offset_mm * 1e3:.0f} um below the surface, residual "
                      f"{float(np.linalg.norm(p.residual_mm)) * 1e3:.1f} um; {Path(p.recording).name}{dropped}")
    calibration_file_rows(table, summary)
    console.print(table)


def gel_command(
    out: Annotated[Path | None, typer.Option("--out", help="Gel file (default: gel.toml next to the rig file).")] = None,
    force: ForceOption = False,
    plot: Annotated[Path | None, typer.Option(
        "--plot", help="Draw force against depth with the fit to this PNG.", callback=output_file)] = None,
    stiffening: Annotated[bool, typer.Option("--stiffening/--linear", help="Fit a first-order strain stiffening with E "
                                             "(default), or a plain linear model.")] = True,
    max_depth: Annotated[float | None, typer.Option("--max-depth", help="Fit steps up to this depth below contact, mm.")] = None,
    registration: Annotated[Path | None, typer.Option("--registration", help="Rig registration for the gel pose "
                                                      "(default: rig-registration.toml next to the rig file, if any).")] = None,
    seed: SeedOption = 0,
    rig_path: RigOption = None,
    indenters_path: IndentersOption = None,
    as_json: JsonOption = False,
) -> None:
    """Young's modulus from stepped normal indentations with a sphere and a cylinder (nu: the rig's, a modelling choice)."""
    from labrig.calibration.gel import contact_table, fit_modulus
    from labrig.calibration.plots import plot_fit
    from labrig.protocol.calibration_runs import DEFAULT_PLAN, measure_curves

    rig, indenters, _ = load_rig_and_indenters(rig_path, indenters_path)
    target = calibration_output(out, rig.path.parent / "gel.toml", force)
    _say_where(rig, as_json)
    started = time.monotonic()

    def progress(message: str) -> None:
        if not as_json:
            err_console.print(f"[dim]{time.monotonic() - started:6.1f} s[/] {message}")

    curves = measure_curves(rig, indenters, DEFAULT_PLAN, seed=seed, indenters_path=indenters_path,
                            registration_path=registration, progress=progress)
    tables = {name: contact_table(indenters[name], rig) for name in DEFAULT_PLAN}
    fit = fit_modulus(curves, rig, indenters, stiffening=stiffening, max_depth_mm=max_depth, tables=tables)
    backup = keep_backup(target)
    path = fit.save(target)
    if plot is not None:
        plot_fit(fit, tables, plot)
    summary = {"path": str(path), "plot": None if plot is None else str(plot),
               "backup": None if backup is None else str(backup), **fit.summary(),
               "wall_s": round(time.monotonic() - started, 2)}
    if as_json:
        print_json(summary)
        return
    table = Table(title=f"gel modulus -> {path}", show_header=False)
    table.add_column(style="dim")
    table.add_column()
    table.add_row("Young's modulus", f"{fit.youngs_modulus_mpa:.4f} MPa (small strain)")
    table.add_row("Poisson ratio", f"{fit.poisson_ratio} (modelling choice, not fitted)")
    table.add_row("stiffening", f"{fit.stiffening:.3f} (E_eff = E (1 + b depth/h))" if fit.stiffening_fitted else "not fitted")
    if fit.linear_small_depth_mpa is not None:
        table.add_row(f"linear fit <= {fit.linear_small_depth_mm} mm", f"{fit.linear_small_depth_mpa:.4f} MPa (comparison)")
    table.add_row("residual", f"{fit.residual_rms_n * 1e3:.1f} mN rms ({fit.residual_rel * 100:.2f} % of the rms force)")
    for c, d0 in zip(fit.curves, fit.depth_offsets_mm, strict=True):
        table.add_row(c.source, f"{len(c.depth_mm)} steps to {c.depth_mm.max():.2f} mm, contact detected {d0 * 1e3:.0f} um deep")
    calibration_file_rows(table, summary)
    console.print(table)
