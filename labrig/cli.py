"""The ``labrig`` command line: parses, calls the library, prints with rich."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.table import Table

from labrig import __version__
from labrig.cli_calibrate import add_calibrate_commands
from labrig.cli_camera import add_camera_commands
from labrig.cli_devices import add_device_commands
from labrig.cli_evaluate import add_evaluate_commands
from labrig.cli_groundtruth import add_groundtruth_commands
from labrig.cli_protocol import add_protocol_commands
from labrig.cli_run import add_run_commands
from labrig.cli_train import add_train_commands
from labrig.errors import LabrigError

app = typer.Typer(
    name="labrig",
    help="Collect and evaluate datasets for dense 3D force estimation with an event-based tactile sensor.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
err_console = Console(stderr=True)

JsonOption = Annotated[bool, typer.Option("--json", help="Print the summary as JSON (stable keys, units in names).")]


def _print_json(data: Any) -> None:
    sys.stdout.write(json.dumps(data, indent=2, default=_json_default) + "\n")


def _json_default(value: Any) -> Any:
    if hasattr(value, "item"):  # numpy scalars
        return value.item()
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


def _version(value: bool) -> None:
    if value:
        console.print(f"labrig {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version.")] = False,
) -> None:
    """labrig: probing rig, virtual rig, calibration, ground truth and evaluation."""


@app.command()
def inspect(
    file: Annotated[Path, typer.Argument(help="Recording file (.h5) or a crashed NAME.h5.partial.")],
    plot: Annotated[Path | None, typer.Option("--plot", help="Also draw event rate, forces and CNC Z to this PNG.")] = None,
    as_json: JsonOption = False,
) -> None:
    """Summarize a recording: duration, events, forces, phases, clocks, warnings."""
    from labrig.recording import Recording
    from labrig.recording.plot import plot_overview
    from labrig.recording.summary import summarize

    with Recording(file) as rec:
        summary = summarize(rec)
        if plot is not None:
            summary["plot"] = str(plot_overview(rec, plot))
    if as_json:
        _print_json(summary)
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
        forces = Table(title="force-torque range", title_justify="left")
        for col in ("axis", "min", "max"):
            forces.add_column(col, justify="right")
        for axis in "xyz":
            forces.add_row(f"F{axis} (N)", f"{s[f'f{axis}_min_n']:.3f}", f"{s[f'f{axis}_max_n']:.3f}")
        for axis in "xyz":
            forces.add_row(f"T{axis} (N m)", f"{s[f't{axis}_min_nm']:.4f}", f"{s[f't{axis}_max_nm']:.4f}")
        console.print(forces)

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


@app.command()
def recover(
    file: Annotated[Path, typer.Argument(help="The crashed NAME.h5.partial (or NAME.h5 if its partial file is beside it).")],
    keep_partial: Annotated[bool, typer.Option("--keep-partial", help="Keep the partial file after recovering.")] = False,
    as_json: JsonOption = False,
) -> None:
    """Finalize a recording whose recorder stopped unexpectedly (crash, kill, disk full)."""
    from labrig.recording import recover as recover_file

    result = recover_file(file, keep_partial=keep_partial)
    if as_json:
        _print_json({"path": str(result.path), "rows": result.rows, "lost_rows": result.lost_rows})
        return
    console.print(f"[green]recovered[/] {result.path}")
    for stream, rows in result.rows.items():
        if rows:
            console.print(f"  {stream}: {rows:,} rows")
    for stream, rows in result.lost_rows.items():
        console.print(f"  [yellow]{stream}: {rows:,} rows past the last commit were not trusted[/]")


@app.command()
def devices(as_json: JsonOption = False) -> None:
    """List serial ports and USB devices, and recognise the rig's instruments."""
    from labrig.devices.discovery import discover

    found = discover()
    if as_json:
        _print_json(found.to_dict())
        return
    ports = Table(title="serial ports", title_justify="left")
    for col in ("port", "what", "role", "usb id", "description"):
        ports.add_column(col)
    for p in found.serial_ports:
        usb_id = f"{p.vid:04x}:{p.pid:04x}" if p.vid is not None and p.pid is not None else "-"
        ports.add_row(p.device, p.kind, p.role, usb_id, p.description)
    console.print(ports if found.serial_ports else "no serial ports found")
    for p in found.serial_ports:
        for warning in p.warnings:
            console.print(f"[yellow]warning:[/] {p.device}: {warning}")
    if found.usb_error:
        console.print(f"[yellow]USB:[/] {found.usb_error}")
    cameras = [d for d in found.usb_devices if d.role == "camera"]
    for d in cameras:
        console.print(f"camera: {d.kind} (USB {d.vid:04x}:{d.pid:04x}, bus {d.bus}, address {d.address})")
    if not found.usb_error and not cameras:
        console.print("no event camera on USB (the virtual rig is used when no hardware is configured)")
    sdk = found.metavision_sdk
    if sdk is not None and sdk.importable:
        console.print(f"Metavision SDK: metavision_hal imports ({sdk.module_path}); plugins: "
                      f"{', '.join(sdk.plugins) or 'none found'} in {', '.join(sdk.plugin_dirs) or 'no plugin folder'}; "
                      f"cameras it sees: {', '.join(sdk.cameras) or 'none'}" + (f"; [yellow]{sdk.error}[/]" if sdk.error else ""))
    elif sdk is not None:
        console.print(f"Metavision SDK: not importable ({sdk.error}); the camera = \"metavision\" backend needs it "
                      "(README, 'Metavision SDK')")


sim_app = typer.Typer(help="The virtual rig: simulated probing runs and its precomputed contact tables.", no_args_is_help=True)
app.add_typer(sim_app, name="sim")
add_device_commands(app)
add_camera_commands(app)
add_protocol_commands(app)
add_calibrate_commands(app)
add_groundtruth_commands(app)
add_train_commands(app)
add_evaluate_commands(app)
add_run_commands(app)

RigOption = Annotated[Path | None, typer.Option("--rig", help="Rig TOML (default: calibration/rig.toml).")]
IndentersOption = Annotated[Path | None, typer.Option("--indenters", help="Indenter TOML (default: protocols/indenters.toml).")]


def _load_rig_and_indenters(rig_path: Path | None, indenters_path: Path | None) -> tuple[Any, dict[str, Any]]:
    from labrig.config import DEFAULT_RIG, load_rig
    from labrig.indenters import DEFAULT_INDENTERS, load_indenters

    return load_rig(rig_path or DEFAULT_RIG), load_indenters(indenters_path or DEFAULT_INDENTERS)


@sim_app.command("probe")
def sim_probe(
    out: Annotated[Path, typer.Argument(help="Recording to write (.h5).")],
    indenter: Annotated[str, typer.Option(help="Indenter name from the indenter file.")] = "sphere",
    depth_mm: Annotated[float, typer.Option(help="Indentation depth below the gel surface, mm.")] = 1.5,
    shear_mm: Annotated[float, typer.Option(help="Shear distance at depth, mm (0: none).")] = 1.0,
    direction_deg: Annotated[float, typer.Option(help="Shear direction in the gel frame, degrees from +x.")] = 0.0,
    x_mm: Annotated[float, typer.Option(help="Contact location, gel frame x, mm.")] = 0.0,
    y_mm: Annotated[float, typer.Option(help="Contact location, gel frame y, mm.")] = 0.0,
    speed_mm_s: Annotated[float, typer.Option(help="Normal and shear speed, mm/s.")] = 1.5,
    wait_s: Annotated[float, typer.Option(help="Each Wait phase, s.")] = 0.3,
    seed: Annotated[int, typer.Option(help="Seed of the event sensor's noise and thresholds.")] = 0,
    realtime: Annotated[
        bool, typer.Option("--realtime/--fast", help="Pace to the host clock (as live devices) or run as fast as possible.")
    ] = False,
    overwrite: Annotated[bool, typer.Option(help="Replace OUT if it exists.")] = False,
    rig_path: RigOption = None,
    indenters_path: IndentersOption = None,
    as_json: JsonOption = False,
) -> None:
    """Record one probing run (the paper's sequence) on the virtual rig, with its truth."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from labrig.errors import LabrigError
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    rig, indenters = _load_rig_and_indenters(rig_path, indenters_path)
    if indenter not in indenters:
        raise LabrigError(f"unknown indenter {indenter!r}; known: {', '.join(indenters)}")
    ind = indenters[indenter]
    if not 0 < depth_mm <= ind.max_depth_mm:
        raise LabrigError(f"--depth-mm must be in (0, {ind.max_depth_mm}] for the {indenter} indenter (its max_depth_mm)")
    if speed_mm_s <= 0 or wait_s < 0 or shear_mm < 0:
        raise LabrigError("--speed-mm-s must be positive; --wait-s and --shear-mm must not be negative")
    half_x, half_y = rig.gel.size_x_mm / 2, rig.gel.size_y_mm / 2
    if abs(x_mm) > half_x or abs(y_mm) > half_y:
        raise LabrigError(f"location ({x_mm}, {y_mm}) mm is off the gel (|x| <= {half_x}, |y| <= {half_y})")
    if out.exists() and overwrite:
        out.unlink()
    path = probing_path(rig, ind, location_mm=(x_mm, y_mm), depth_mm=depth_mm, shear_mm=shear_mm,
                        shear_direction_deg=direction_deg, normal_speed_mm_s=speed_mm_s, shear_speed_mm_s=speed_mm_s,
                        wait_s=wait_s)
    total_s = path.duration_us / 1e6
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed:.2f}/{task.total:.2f} s"),
                  TimeElapsedColumn(), console=err_console, disable=as_json) as bar:
        task = bar.add_task(f"simulating {indenter}", total=total_s)
        result = record_live(out, rig, ind, path, seed=seed, realtime=realtime,
                             progress=lambda done_s: bar.update(task, completed=done_s))
    summary = {
        "path": str(result.recording.path),
        "indenter": indenter,
        "sim_duration_s": result.sim_duration_s,
        "wall_s": result.wall_s,
        "real_time_factor": result.wall_s / result.sim_duration_s,
        "events": result.events,
        "event_rate_hz": result.events / result.sim_duration_s,
        "realtime": realtime,
        "max_lag_ms": result.max_lag_ms,
        "late_chunks": result.late_chunks,
        "exit_status": result.recording.exit_status,
    }
    if as_json:
        _print_json(summary)
        return
    console.print(f"[green]recorded[/] {summary['path']}: {summary['events']:,} events over {total_s:.2f} s "
                  f"(real-time factor {summary['real_time_factor']:.2f})")
    if realtime:
        style = "green" if result.late_chunks == 0 else "red"
        console.print(f"[{style}]max lag behind real time: {result.max_lag_ms:.1f} ms, late chunks: {result.late_chunks}[/]")


@sim_app.command("serve")
def sim_serve(
    indenter: Annotated[str, typer.Option(help="Indenter mounted on the virtual CNC.")] = "sphere",
    seed: Annotated[int, typer.Option(help="Seed of the event sensor's and the F/T sensor's noise.")] = 0,
    seconds: Annotated[float | None, typer.Option(help="Serve this long, then stop (default: until Ctrl-C).")] = None,
    homed: Annotated[
        bool, typer.Option("--homed/--unhomed", help="Power the CNC up as if homed (machine coordinates valid) or not.")
    ] = True,
    camera_socket: Annotated[
        Path | None, typer.Option("--camera-socket", help="Unix socket of the EVK4 twin (default: in a fresh temp directory).")
    ] = None,
    links: Annotated[
        Path | None, typer.Option("--links", help="Also symlink DIR/grbl, DIR/bota, DIR/evk4 to the devices (stable names).")
    ] = None,
    rig_path: RigOption = None,
    indenters_path: IndentersOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="JSON lines: one per device, then the statistics.")] = False,
) -> None:
    """Serve the virtual rig's devices until interrupted: GRBL and Bota on pseudo-terminals,
    the EVK4 as EVT3 on a Unix socket.

    Prints one line per device, name first (``grbl /dev/pts/5``, ``evk4 /tmp/.../evk4.sock``);
    real drivers and any other GRBL sender or Bota client open them as serial ports, the
    camera's ``sim`` backend reads the socket.
    """
    import signal
    import tempfile
    import threading

    from labrig.sim.world import LiveWorld

    rig, indenters = _load_rig_and_indenters(rig_path, indenters_path)
    if indenter not in indenters:
        raise LabrigError(f"unknown indenter {indenter!r}; known: {', '.join(indenters)}")
    if seconds is not None and seconds <= 0:
        raise LabrigError("--seconds must be positive")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    socket_dir = None
    if camera_socket is None:
        socket_dir = tempfile.TemporaryDirectory(prefix="labrig-")
        camera_socket = Path(socket_dir.name) / "evk4.sock"
    elif not camera_socket.parent.is_dir():
        raise LabrigError(f"--camera-socket {camera_socket}: its directory does not exist")
    with err_console.status("loading the contact tables"):
        world = LiveWorld(rig, indenters[indenter], seed=seed, camera_socket=camera_socket, homed=homed)
    made: list[Path] = []
    with world:
        for name, path in world.paths.items():
            if links is not None:
                made.append(_link(links, name, path))
            if as_json:
                sys.stdout.write(json.dumps({"device": name, "path": path}) + "\n")
            else:
                sys.stdout.write(f"{name} {path}\n")
        sys.stdout.flush()
        try:
            while not stop.wait(0.2):
                if world.error is not None or world.server.error is not None:
                    raise LabrigError(f"the virtual rig stopped: {world.error or world.server.error!r}")
                if seconds is not None and world.now_world_us() >= seconds * 1e6:
                    break
        except KeyboardInterrupt:
            pass
        finally:
            for link in made:
                link.unlink(missing_ok=True)
    if socket_dir is not None:
        socket_dir.cleanup()
    stats = world.stats.as_dict()
    if as_json:
        sys.stdout.write(json.dumps({"stats": stats}) + "\n")
    else:
        err_console.print(f"served {world.now_world_us() / 1e6:.1f} s; renderer max lag {stats['max_lag_ms']} ms")


def _link(directory: Path, name: str, target: str) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    link = directory / name
    if link.is_symlink() or link.exists():
        if not link.is_symlink():
            raise LabrigError(f"{link} exists and is not a symlink; choose another --links directory")
        link.unlink()
    link.symlink_to(target)
    return link


@sim_app.command("tables")
def sim_tables(
    rig_path: RigOption = None,
    indenters_path: IndentersOption = None,
    as_json: JsonOption = False,
) -> None:
    """Build (or load from cache) the contact tables of every indenter."""
    import time

    from labrig.physics.mechanics import ContactTable, table_cache_dir

    rig, indenters = _load_rig_and_indenters(rig_path, indenters_path)
    rows = []
    for name, ind in indenters.items():
        t0 = time.perf_counter()
        with err_console.status(f"contact table for {name}"):
            table = ContactTable.from_rig(ind, rig)
        rows.append({"indenter": name, "seconds": time.perf_counter() - t0, "max_depth_mm": float(table.depths_mm[-1])})
    if as_json:
        _print_json({"cache_dir": str(table_cache_dir()), "tables": rows})
        return
    for row in rows:
        console.print(f"{row['indenter']:>10}: up to {row['max_depth_mm']:.2f} mm in {row['seconds']:.1f} s")
    console.print(f"cache: {table_cache_dir()}")


def main() -> None:
    """Console entry point: user errors print one line and exit 2, no traceback."""
    from labrig.recording.writer import exit_process

    code = 0
    try:
        app()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except LabrigError as exc:
        err_console.print(f"[red]error:[/] {exc}", soft_wrap=True, highlight=False)
        code = exc.exit_code
    except KeyboardInterrupt:
        err_console.print("[yellow]interrupted[/]")
        code = 130
    exit_process(code)


if __name__ == "__main__":
    main()
