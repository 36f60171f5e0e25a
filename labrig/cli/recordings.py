"""``labrig inspect`` (a recording's summary) and ``labrig recover`` (finalize a crashed recording)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from labrig.cli.console import JsonOption, calibration_folder, console, output_file, print_json


def inspect(
    file: Annotated[Path, typer.Argument(help="Recording file (.h5) or a crashed NAME.h5.partial.")],
    plot: Annotated[Path | None, typer.Option(
        "--plot", help="Also draw event rate, forces and CNC Z to this PNG.", callback=output_file)] = None,
    calibration: Annotated[Path | None, typer.Option(
        help="Calibration folder whose rig-registration.toml turns the F/T axes into the gel frame (default: the "
             "folder of labrig's default rig; the registration the recording names comes first).")] = None,
    as_json: JsonOption = False,
) -> None:
    """Summarize a recording: duration, events, forces (on the gel, gel frame), phases, clocks, data quality."""
    from labrig.calibration.ft_frame import force_on_gel_ranges
    from labrig.recording import Recording
    from labrig.recording.plot import plot_overview
    from labrig.recording.summary import summarize

    with Recording(file) as rec:
        summary = summarize(rec)
        summary.update(force_on_gel_ranges(rec, calibration_folder(calibration)))
        if plot is not None:
            summary["plot"] = str(plot_overview(rec, plot))
    if as_json:
        print_json(summary)
    else:
        _print_summary(summary)


def _print_summary(s: dict[str, Any]) -> None:
    status_style = {"complete": "green", "aborted": "yellow"}.get(s["exit_status"], "red")
    console.print(f"[bold]{s['file']}[/]  format {s['schema_version']}  [{status_style}]{s['exit_status']}[/]"
                  + ("" if s["finalized"] else " [red](not finalized)[/]"))
    overview = Table(show_header=False, box=None, pad_edge=False)
    overview.add_column(style="dim")
    overview.add_column()
    overview.add_row("indenter", s["indenter"] or "-")
    overview.add_row("duration", f"{s['duration_s']:.3f} s")
    rates = f"{s['event_rate_hz'] / 1e6:.3f} Mev/s mean, {s['event_rate_peak_hz'] / 1e6:.3f} peak"
    overview.add_row("events", f"{s['events']:,}  ({rates})")
    overview.add_row("triggers", str(s["triggers"]))
    overview.add_row("F/T", f"{s['ft_samples']:,} samples at {s['ft_rate_hz']:.0f} Hz")
    overview.add_row("CNC", f"{s['cnc_samples']:,} status samples, {s['gcode_lines']} G-code lines")
    console.print(overview)

    if s["ft_samples"]:
        forces = Table(title=f"force on the gel, gel frame (F/T axes: {s['force_on_gel_ft_axes']}; a press: Fz < 0)",
                       title_justify="left")
        for col in ("axis", "min", "max"):
            forces.add_column(col, justify="right")
        for axis in "xyz":
            forces.add_row(f"F{axis} (N)", f"{s[f'force_on_gel_{axis}_min_n']:.3f}", f"{s[f'force_on_gel_{axis}_max_n']:.3f}")
        console.print(forces)
        sensor = Table(title="F/T sensor reading: the force on the indenter, sensor axes", title_justify="left")
        for col in ("axis", "min", "max"):
            sensor.add_column(col, justify="right")
        for axis in "xyz":
            sensor.add_row(f"F{axis} (N)", f"{s[f'ft_sensor_f{axis}_min_n']:.3f}", f"{s[f'ft_sensor_f{axis}_max_n']:.3f}")
        for axis in "xyz":
            sensor.add_row(f"T{axis} (N m)", f"{s[f'ft_sensor_t{axis}_min_nm']:.4f}", f"{s[f'ft_sensor_t{axis}_max_nm']:.4f}")
        console.print(sensor)
    console.print(f"data quality: {s['quality']}" + (f" ({'; '.join(s['quality_reasons'])})" if s["quality_reasons"] else ""))

    if s["phases"]:
        phases = Table(title="phases", title_justify="left")
        for col in ("phase", "start (s)", "end (s)", "duration (s)"):
            phases.add_column(col, justify="right" if col != "phase" else "left")
        for p in s["phases"]:
            phases.add_row(p["name"], f"{p['start_s']:.3f}", f"{p['end_s']:.3f}", f"{p['duration_s']:.3f}")
        console.print(phases)

    if s["clock"]:
        clocks = Table(title="clock models (device to host)", title_justify="left")
        for col in ("device", "method", "drift ppm", "pairs", "trig", "lat p50 us", "p99 us", "max us"):
            clocks.add_column(col, justify="right" if col not in ("device", "method") else "left")
        for device, c in s["clock"].items():
            clocks.add_row(device, c["method"], f"{c['drift_ppm']:.2f}", str(c["pairs"]), str(c["triggers"]),
                           f"{c['residual_p50_us']:.0f}", f"{c['residual_p99_us']:.0f}", f"{c['residual_max_us']:.0f}")
        console.print(clocks)

    for warning in s["warnings"]:
        console.print(f"[yellow]warning:[/] {warning}")
    if "plot" in s:
        console.print(f"plot written to {s['plot']}")


def recover(
    file: Annotated[Path, typer.Argument(help="The crashed NAME.h5.partial (or NAME.h5 if its partial file is beside it).")],
    keep_partial: Annotated[bool, typer.Option("--keep-partial", help="Keep the partial file after recovering.")] = False,
    as_json: JsonOption = False,
) -> None:
    """Finalize a recording whose recorder stopped unexpectedly (crash, kill, disk full)."""
    from labrig.recording import recover as recover_file

    result = recover_file(file, keep_partial=keep_partial)
    if as_json:
        print_json({"path": str(result.path), "rows": result.rows, "lost_rows": result.lost_rows})
        return
    console.print(f"[green]recovered[/] {result.path}")
    for stream, rows in result.rows.items():
        if rows:
            console.print(f"  {stream}: {rows:,} rows")
    for stream, rows in result.lost_rows.items():
        console.print(f"  [yellow]{stream}: {rows:,} rows past the last commit were not trusted[/]")


def add_recording_commands(app: typer.Typer) -> None:
    """Mount ``inspect`` and ``recover`` on the main app."""
    app.command("inspect")(inspect)
    app.command("recover")(recover)
