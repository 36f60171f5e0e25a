"""``labrig sim ...``: the virtual rig's probing runs, its devices served to other processes, its contact tables."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.progress import TextColumn, TimeElapsedColumn

from labrig.cli.console import (
    IndentersOption,
    JsonOption,
    RigOption,
    console,
    err_console,
    load_rig_and_indenters,
    print_json,
    print_json_line,
    progress_bar,
)
from labrig.errors import LabrigError

if TYPE_CHECKING:
    from labrig.config import RigConfig
    from labrig.indenters import Indenter

sim_app = typer.Typer(help="The virtual rig: simulated probing runs and its precomputed contact tables.", no_args_is_help=True)


def _rig_and_indenter(rig_path: Path | None, indenters_path: Path | None, name: str) -> tuple[RigConfig, Indenter]:
    from labrig.config import DEFAULT_RIG, load_rig
    from labrig.indenters import DEFAULT_INDENTERS, load_indenter

    return load_rig(rig_path or DEFAULT_RIG), load_indenter(name, indenters_path or DEFAULT_INDENTERS)


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
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    rig, ind = _rig_and_indenter(rig_path, indenters_path, indenter)
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
    with progress_bar(TextColumn("{task.completed:.2f}/{task.total:.2f} s"), TimeElapsedColumn(), disable=as_json) as bar:
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
        print_json(summary)
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
    import sys
    import threading

    from labrig.sim.serve import DeviceServer

    rig, ind = _rig_and_indenter(rig_path, indenters_path, indenter)
    if seconds is not None and seconds <= 0:
        raise LabrigError("--seconds must be positive")
    if camera_socket is not None and not camera_socket.parent.is_dir():
        raise LabrigError(f"--camera-socket {camera_socket}: its directory does not exist")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with err_console.status("loading the contact tables"):
        server = DeviceServer(rig, ind, seed=seed, homed=homed, camera_socket=camera_socket, links=links)
    with server:
        for name, path in server.paths.items():
            if as_json:
                print_json_line({"device": name, "path": path})
            else:
                sys.stdout.write(f"{name} {path}\n")
                sys.stdout.flush()
        server.serve(stop=stop, seconds=seconds)
    if as_json:
        print_json_line({"stats": server.stats})
    else:
        err_console.print(f"served {server.served_s:.1f} s; renderer max lag {server.stats['max_lag_ms']} ms")


@sim_app.command("tables")
def sim_tables(
    rig_path: RigOption = None,
    indenters_path: IndentersOption = None,
    as_json: JsonOption = False,
) -> None:
    """Build (or load from cache) the contact tables of every indenter."""
    import time

    from rich.progress import MofNCompleteColumn, TimeElapsedColumn

    from labrig.physics.mechanics import table_cache_dir
    from labrig.sim.truth_config import true_contact_table

    rig, indenters, _ = load_rig_and_indenters(rig_path, indenters_path)
    rows = []
    with progress_bar(MofNCompleteColumn(), TimeElapsedColumn(), disable=as_json) as bar:
        task = bar.add_task("contact tables", total=len(indenters))
        for name, ind in indenters.items():
            bar.update(task, description=f"contact table: {name} (a new one takes a minute or two)")
            t0 = time.perf_counter()
            table = true_contact_table(ind, rig)
            rows.append({"indenter": name, "seconds": time.perf_counter() - t0,
                         "max_depth_mm": float(table.depths_mm[-1]), "footprint_yaw_deg": table.yaw_deg})
            bar.advance(task)
    if as_json:
        print_json({"cache_dir": str(table_cache_dir()), "tables": rows})
        return
    for row in rows:
        turn = f", footprint turned {row['footprint_yaw_deg']:+.2f} deg from the gel" if row["footprint_yaw_deg"] else ""
        console.print(f"{row['indenter']:>10}: up to {row['max_depth_mm']:.2f} mm in {row['seconds']:.1f} s{turn}")
    console.print(f"cache: {table_cache_dir()}")


def add_sim_commands(app: typer.Typer) -> None:
    """Mount the ``sim`` group on the main app."""
    app.add_typer(sim_app, name="sim")
