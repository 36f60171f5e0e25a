"""``labrig calibrate``: camera intrinsics, gel-to-camera extrinsics and contrast thresholds from event recordings.

Mount on the main app with :func:`add_calibrate_commands`, which also registers the rig
calibrations (``rig``, ``gel``: :mod:`labrig.cli.calibrate_rig`) on :data:`calibrate_app`.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
import typer
from rich.table import Table

from labrig.cli.calibrate_rig import add_rig_calibration_commands
from labrig.cli.console import (
    ForceOption,
    JsonOption,
    RigOption,
    calibration_file_rows,
    calibration_output,
    console,
    err_console,
    keep_backup,
    output_file,
    print_json,
)

if TYPE_CHECKING:
    from labrig.calibration.marker_map import MarkerMap

calibrate_app = typer.Typer(
    help="Calibration from events: camera intrinsics, gel-to-camera extrinsics, contrast thresholds (and rig "
         "registration, gel modulus).",
    no_args_is_help=True,
)

PlotOption = Annotated[Path | None, typer.Option(
    "--plot", help="Draw detections and reprojection residuals to this PNG.", callback=output_file)]
SeedOption = Annotated[int, typer.Option(help="Seed of the virtual rig's scene (when no recording is given).")]


def add_calibrate_commands(app: typer.Typer) -> None:
    """Mount the ``calibrate`` group (intrinsics, extrinsics, events, rig, gel) on the main app."""
    add_rig_calibration_commands(calibrate_app)
    app.add_typer(calibrate_app, name="calibrate")


def _scratch(name: str) -> Path:
    return Path(tempfile.mkdtemp(prefix="labrig-calibrate-")) / name


@calibrate_app.command("intrinsics")
def intrinsics_command(
    recording: Annotated[Path | None, typer.Argument(help="Recording of a blinking dot-grid target (default: record one on the virtual rig).")] = None,  # noqa: E501
    out: Annotated[Path | None, typer.Option("--out", help="Intrinsics file to write (default: intrinsics.toml beside the rig file).")] = None,  # noqa: E501
    force: ForceOption = False,
    rows: Annotated[int | None, typer.Option(help="Target dot rows (default: from the recording, else 9).")] = None,
    cols: Annotated[int | None, typer.Option(help="Target dot columns (default: from the recording, else 15).")] = None,
    pitch_mm: Annotated[float | None, typer.Option(help="Target dot pitch, mm (default: from the recording, else 2).")] = None,
    fit_k3: Annotated[bool, typer.Option("--fit-k3", help="Also fit k3 (fixed at 0 by default).")] = False,
    views: Annotated[int, typer.Option(help="Views to record on the virtual rig (when no recording is given).")] = 12,
    seed: SeedOption = 0,
    rig_path: RigOption = None,
    plot: PlotOption = None,
    as_json: JsonOption = False,
) -> None:
    """Camera matrix and distortion from a recording of a blinking dot-grid target at many poses."""
    from labrig.calibration.intrinsics import calibrate_intrinsics, write_intrinsics
    from labrig.calibration.plots import plot_intrinsics
    from labrig.config import DEFAULT_RIG, load_rig
    from labrig.physics.target import DotGridTarget

    rig = load_rig(rig_path or DEFAULT_RIG)
    target_file = calibration_output(out, rig.path.parent / "intrinsics.toml", force)
    if recording is None:
        from labrig.sim.calibration_scenes import record_target_scene

        recording = _scratch("target-scene.h5")
        err_console.print(f"no recording given: recording a {views}-view dot-grid target scene on the virtual rig ({recording})")
        record_target_scene(recording, rig, n_views=views, seed=seed)
    target = None
    if rows is not None or cols is not None or pitch_mm is not None:
        base = DotGridTarget()
        target = DotGridTarget(rows=rows or base.rows, cols=cols or base.cols, pitch_mm=pitch_mm or base.pitch_mm)
    result = calibrate_intrinsics(recording, target, fix_k3=not fit_k3)
    backup = keep_backup(target_file)
    path = write_intrinsics(result, target_file)
    k = result.camera_matrix
    summary: dict[str, Any] = {
        "path": str(path), "recording": str(recording), "fx_px": float(k[0, 0]), "fy_px": float(k[1, 1]),
        "cx_px": float(k[0, 2]), "cy_px": float(k[1, 2]), "distortion": [float(d) for d in result.distortion],
        "rms_px": result.rms_px, "views_found": len(result.views), "views_used": len(result.used),
        "views_rejected": {str(v.index): v.rejected for v in result.views if v.rejected},
        "per_view_rms_px": result.per_view_rms_px, "backup": None if backup is None else str(backup),
    }
    if plot is not None:
        summary["plot"] = str(plot_intrinsics(result, plot))
    if as_json:
        print_json(summary)
        return
    table = Table(title=f"intrinsics -> {path}", show_header=False)
    table.add_column(style="dim")
    table.add_column()
    table.add_row("fx, fy", f"{k[0, 0]:.2f}, {k[1, 1]:.2f} px")
    table.add_row("cx, cy", f"{k[0, 2]:.2f}, {k[1, 2]:.2f} px")
    table.add_row("k1 k2 p1 p2 k3", " ".join(f"{d:+.5f}" for d in result.distortion))
    table.add_row("RMS", f"{result.rms_px:.3f} px")
    table.add_row("views", f"{len(result.used)} used of {len(result.views)}")
    for index, reason in summary["views_rejected"].items():
        table.add_row(f"view {index}", f"[yellow]rejected[/]: {reason}")
    calibration_file_rows(table, summary)
    console.print(table)


@calibrate_app.command("extrinsics")
def extrinsics_command(
    recording: Annotated[Path | None, typer.Argument(help="Recording of the LED ring blinking, gel at rest (default: record one on the virtual rig).")] = None,  # noqa: E501
    intrinsics: Annotated[Path | None, typer.Option("--intrinsics", help="Intrinsics file (default: calibration/intrinsics.toml).")] = None,  # noqa: E501
    out: Annotated[Path | None, typer.Option("--out", help="Extrinsics file to write (default: extrinsics.toml beside the rig file).")] = None,  # noqa: E501
    force: ForceOption = False,
    seed: SeedOption = 0,
    rig_path: RigOption = None,
    plot: PlotOption = None,
    residual_map: Annotated[Path | None, typer.Option("--residual-map", help="Per-marker residual map PNG (default: OUT's name + -residuals.png, beside it).")] = None,  # noqa: E501
    worst: Annotated[int, typer.Option(help="Markers listed with the largest residuals.", min=0)] = 5,
    as_json: JsonOption = False,
) -> None:
    """Gel-to-camera pose and marker rest positions from a recording of the LED ring blinking.

    Also finds missing markers and each marker's residual (measured less the nominal lattice through the
    pose), drawn as a map beside the calibration file: a badly printed gel shows at a glance."""
    from labrig.calibration.extrinsics import calibrate_extrinsics, write_extrinsics
    from labrig.calibration.files import DEFAULT_INTRINSICS, load_intrinsics
    from labrig.calibration.plots import plot_extrinsics, plot_marker_residuals
    from labrig.config import DEFAULT_RIG, load_rig

    rig = load_rig(rig_path or DEFAULT_RIG)
    target_file = calibration_output(out, rig.path.parent / "extrinsics.toml", force)
    intr = load_intrinsics(intrinsics or DEFAULT_INTRINSICS)
    if recording is None:
        from labrig.sim.calibration_scenes import record_led_blink

        recording = _scratch("led-blink.h5")
        err_console.print(f"no recording given: recording the LED ring blinking on the virtual rig ({recording})")
        record_led_blink(recording, rig, seed=seed)
    result = calibrate_extrinsics(recording, intr, rig.markers, nominal_rotvec_rad=rig.camera.nominal_rotvec_rad)
    backup = keep_backup(target_file)
    path = write_extrinsics(result, target_file, intr)
    summary: dict[str, Any] = {
        "path": str(path), "recording": str(recording), "intrinsics": str(intr.path),
        "rotation_rotvec_rad": result.rotvec_rad.tolist(), "translation_mm": result.translation_mm.tolist(),
        "reprojection_mean_px": result.mean_error_px, "reprojection_std_px": result.std_error_px,
        "reprojection_max_px": result.max_error_px, "markers_detected": int(result.detected.sum()),
        "markers": len(result.rest_gel_mm), "blobs_spurious": result.spurious, "blinks": result.blinks,
        **result.marker_map.summary(worst), "backup": None if backup is None else str(backup),
    }
    residual_map = residual_map or path.with_name(path.stem + "-residuals.png")
    summary["residual_map"] = str(plot_marker_residuals(result.marker_map, residual_map, f"{path.name}"))
    if plot is not None:
        summary["plot"] = str(plot_extrinsics(result, plot))
    if as_json:
        print_json(summary)
        return
    table = Table(title=f"extrinsics -> {path}", show_header=False)
    table.add_column(style="dim")
    table.add_column()
    table.add_row("rotation (Rodrigues)", " ".join(f"{v:+.5f}" for v in result.rotvec_rad) + " rad"
                  f"  ({np.degrees(np.linalg.norm(result.rotvec_rad)):.3f} deg)")
    table.add_row("translation", " ".join(f"{v:+.4f}" for v in result.translation_mm) + " mm")
    table.add_row("reprojection", f"{result.mean_error_px:.3f} +/- {result.std_error_px:.3f} px "
                  f"(max {result.max_error_px:.3f})")
    table.add_row("markers", f"{int(result.detected.sum())} of {len(result.rest_gel_mm)} detected, "
                  f"{result.spurious} spurious blob(s) ignored, {result.blinks} blink(s)")
    _marker_rows(table, result.marker_map, worst)
    calibration_file_rows(table, summary)
    console.print(table)


@calibrate_app.command("events")
def events_command(
    recording: Annotated[Path | None, typer.Argument(help="Recording of the LED ring dimmed and brightened along ramps, gel at rest (default: record one on the virtual rig, and the calibration press).")] = None,  # noqa: E501
    press: Annotated[Path | None, typer.Option("--press", help="A probing recording of the standard sphere pressed 1 mm or more (protocols/slope-press.toml): the light's slope response is fitted against its ground truth.")] = None,  # noqa: E501
    out: Annotated[Path | None, typer.Option("--out", help="Thresholds file to write (default: events.toml beside the rig file).")] = None,  # noqa: E501
    force: ForceOption = False,
    led_ratio: Annotated[float | None, typer.Option("--led-ratio", help="The LED's full / dimmed light (default: what the recording names).", min=1.0)] = None,  # noqa: E501
    seed: SeedOption = 0,
    rig_path: RigOption = None,
    plot: Annotated[Path | None, typer.Option(
        "--plot", help="Draw the threshold maps and histograms to this PNG.", callback=output_file)] = None,
    as_json: JsonOption = False,
) -> None:
    """Contrast thresholds, ON and OFF, per cell of the network grid, from the LED ring dimmed and brightened;
    with a press of known depth, the light's slope response too.

    Every command that reads the calibration folder uses them: the depth network's brightness input is
    then the change of log intensity under the reference light, not a count of events, whatever the
    camera's biases and the light."""
    from labrig.cache import sha256_of
    from labrig.calibration.event_thresholds import fit_event_thresholds
    from labrig.calibration.event_thresholds_file import EVENTS_FILE, write_event_thresholds
    from labrig.calibration.files import provenance
    from labrig.calibration.plots import plot_event_thresholds
    from labrig.config import DEFAULT_RIG, load_rig
    from labrig.errors import CalibrationError
    from labrig.indenters import load_indenters
    from labrig.pipeline.brightness import dim_light_warning
    from labrig.protocol.light_calibration import measure_slope_response, record_slope_press

    rig = load_rig(rig_path or DEFAULT_RIG)
    target = calibration_output(out, rig.path.parent / EVENTS_FILE, force)
    if press is not None and not press.exists():
        raise CalibrationError(f"--press {press}: no such recording; record the calibration press first "
                               "(labrig record --protocol protocols/slope-press.toml)")
    if recording is None:
        from labrig.sim.calibration_scenes import record_led_ramps

        recording = _scratch("led-ramps.h5")
        err_console.print(f"no recording given: recording the LED ring's ramps on the virtual rig ({recording})")
        record_led_ramps(recording, rig, seed=seed)
        if press is None:
            press = _scratch("slope-press.h5")
            err_console.print(f"and the calibration press on the virtual rig ({press})")
            record_slope_press(press, rig, load_indenters()["sphere"], seed=seed)
    fit = fit_event_thresholds(recording, rig.roi, ratio=led_ratio)
    summary = fit.summary()
    response = None
    if press is not None:
        response = measure_slope_response(press, rig.roi, fit.thresholds, rig.path.parent, rig.path)
        summary["shading"] = {**response.summary(), "press": str(press)}
    else:
        err_console.print("no --press: the light's slope response is not measured; networks trained under the "
                          "reference light will assume it")
    backup = keep_backup(target)
    path = write_event_thresholds(target, fit.thresholds, summary, provenance(recording, sha256_of(recording)))
    result: dict[str, Any] = {"path": str(path), "recording": str(recording), "backup": None if backup is None else str(backup),
                              **summary["thresholds"], **summary["scene"], **summary["quality"],
                              "slope_gain": None if response is None else response.slope_gain,
                              "slope_rms_ln": None if response is None else response.rms_ln,
                              "press": None if press is None else str(press)}
    if plot is not None:
        result["plot"] = str(plot_event_thresholds(fit, plot))
    result["dim_light_warning"] = dim_light_warning(result["slope_gain"])
    if as_json:
        print_json(result)
        return
    table = Table(title=f"contrast thresholds -> {path}", show_header=False)
    table.add_column(style="dim")
    table.add_column()
    t, q = summary["thresholds"], summary["quality"]
    table.add_row("ON threshold", f"{t['on_ln_median']:.4f} ln (median; spread over cells {t['on_ln_cell_spread']:.4f})")
    table.add_row("OFF threshold", f"{t['off_ln_median']:.4f} ln (median; spread over cells {t['off_ln_cell_spread']:.4f})")
    table.add_row("ON / OFF", f"{t['on_off_ratio']:.3f}")
    table.add_row("events per ramp", f"ON {q['events_per_ramp_on']:.2f}, OFF {q['events_per_ramp_off']:.2f} per pixel "
                  f"({fit.ramps_used} ramps of ln {fit.schedule.ratio:g})")
    table.add_row("background", f"{q['background_rate_hz']:.3f} Hz per pixel")
    table.add_row("left out", f"{q['pixels_rejected']} pixels (hot or dead), {q['cells_filled']} cells given the median")
    table.add_row("slope gain", "not measured (no --press)" if response is None else
                  f"{response.slope_gain:.3f} (ln(1 + g |grad d|) fitted over {response.cells} cells of "
                  f"{response.maps} maps, rms {response.rms_ln:.3f} ln)")
    calibration_file_rows(table, result)
    console.print(table)
    if (dim := dim_light_warning(result["slope_gain"])) is not None:
        err_console.print(f"[yellow]warning:[/] {dim}")


def _marker_rows(table: Table, marker_map: MarkerMap, worst: int) -> None:
    """The markers as printed: missing ones, the residual spread and the worst markers (row, col)."""
    missing = [marker_map.row_col(i) for i in marker_map.missing_indices]
    table.add_row("missing markers", ("[red]" + ", ".join(f"({r},{c})" for r, c in missing) + "[/]") if missing else "none")
    found = ~marker_map.missing
    if found.any():
        mm, px = marker_map.residual_norm_mm[found], marker_map.residual_norm_px[found]
        table.add_row("residual to nominal", f"rms {np.sqrt(np.nanmean(mm**2)) * 1e3:.1f} um "
                      f"({np.sqrt(np.mean(px**2)):.2f} px), max {np.nanmax(mm) * 1e3:.1f} um ({px.max():.2f} px)")
    for r in marker_map.worst(worst):
        table.add_row(f"  marker ({r.row},{r.col})", f"{r.residual_mm * 1e3:.1f} um, {r.residual_px:.2f} px")
