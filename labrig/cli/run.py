"""``labrig run REC`` / ``labrig run --live``: stream a recording, or the rig's camera, through the
inference pipeline and write the force fields.

Mount on the main app with :func:`add_run_commands`. The live path is in
:mod:`labrig.cli.run_live` (its work in :mod:`labrig.live`). User errors are
:class:`LabrigError` s, printed as one line by ``labrig``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from labrig.cli.console import (
    JsonOption,
    WindowEventsOption,
    WindowMsOption,
    calibration_folder,
    output_file,
    print_json,
    progress_bar,
)
from labrig.cli.run_report import check_out, check_view, depth_every_option, print_run
from labrig.errors import LabrigError


def run(
    recording: Annotated[Path | None, typer.Argument(help="A recording (.h5); or --live.")] = None,
    live: Annotated[bool, typer.Option("--live", help=(
        "Stream the camera of the rig file's \\[devices] instead of a recording; with a probing run "
        "(--indenter/--protocol, always on the embedded virtual rig) for as long as the run lasts."))] = False,
    seconds: Annotated[float | None, typer.Option(help="--live, camera only: stop after this long (default: Ctrl-C).")] = None,
    indenter: Annotated[str | None, typer.Option(help="--live: run one probing run with this indenter meanwhile.")] = None,
    protocol: Annotated[Path | None, typer.Option(
        help="--live: the probing run's protocol (default protocols/probe.toml).")] = None,
    at: Annotated[str | None, typer.Option("--at", help="--live: the probing run's contact location X,Y, gel mm.")] = None,
    depth_mm: Annotated[float | None, typer.Option(help="--live: the probing run's depth below contact, mm.")] = None,
    save_recording: Annotated[Path | None, typer.Option(
        help="--live: keep the probing run's recording here (.h5; default: compared with, then deleted).")] = None,
    max_lag_ms: Annotated[float | None, typer.Option(
        help="--live: skip depth and forces of windows older than this, ms (default 100; tracking goes on).")] = None,
    window_ms: WindowMsOption = None,
    window_events: WindowEventsOption = None,
    depth_every_ms: Annotated[float | None, typer.Option(help=(
        "Run the depth source only every this many ms and keep its map in between; tracking and forces still "
        "run every window (--window-ms 1 --depth-every-ms 10: dense forces at 1 kHz)."))] = None,
    depth: Annotated[str | None, typer.Option(
        help="Depth source: truth (a virtual-rig recording's /truth/depth) or model (the network). Default: model "
             "with --model, live or a recording without /truth/depth; else truth.")] = None,
    model: Annotated[Path | None, typer.Option(
        help="Depth network: an .onnx with its card, or a bundled one (default, sae-only); "
             "default: newest in models/, else bundled.")] = None,
    out: Annotated[Path | None, typer.Option(help="Result file (.h5): per-window markers, displacements, forces.")] = None,
    out_depth: Annotated[bool, typer.Option("--out-depth", help=(
        "--out: keep each window's depth map too (40 kB a window; `labrig export --bag` writes it as an image)."))
    ] = False,
    view: Annotated[Path | None, typer.Option(
        help="Animation (.gif): SAE, tracks, depth, x/y/normal force maps.", callback=output_file)] = None,
    view_every: Annotated[int | None, typer.Option(help=(
        "Every n-th window in the animation (default: the probing phases' windows thinned to at most 200 frames; "
        "live: every 3rd)."))] = None,
    calibration: Annotated[Path | None, typer.Option(
        help="Folder with gel.toml, intrinsics.toml, extrinsics.toml (default: the folder of labrig's default rig; "
             "live: the rig file's folder).")] = None,
    rig_path: Annotated[Path | None, typer.Option("--rig", help=(
        "Rig TOML (default: the one stored in the recording; live: calibration/rig.toml)."))] = None,
    youngs_modulus_mpa: Annotated[float | None, typer.Option(
        help="Gel modulus, MPa (default: gel.toml, else the rig's).")] = None,
    serial: Annotated[bool, typer.Option(help="Run the stages in turn instead of in two threads.")] = False,
    view_server: Annotated[bool, typer.Option("--view-server", help=(
        "--live: serve the force field, depth map, tracks, net force and F/T to Foxglove (a WebSocket server; "
        "docs/ros2.md)."))] = False,
    view_port: Annotated[int, typer.Option(help="--view-server: its port (0: any free one, printed).")] = 8765,
    view_hz: Annotated[float, typer.Option(help=(
        "--view-server: the most windows a second it sends (a display's rate; 0: every window)."))] = 100.0,
    as_json: JsonOption = False,
) -> None:
    """Stream RECORDING (or the live camera) through SAE, tracker, depth, iFEM; per-window forces into
    --out, an animation into --view."""
    from labrig.config import load_rig
    from labrig.pipeline import depth_sources, results, run_setup, runtime
    from labrig.pipeline.run_summary import WindowLog, window_summary
    from labrig.pipeline.view import ViewFrames, probing_span_us
    from labrig.pipeline.windows import WindowSpec
    from labrig.recording import Recording

    check_out(out)
    if out_depth and out is None:
        raise LabrigError("--out-depth keeps the depth maps in the result file: give --out too")
    if live:
        if recording is not None:
            raise LabrigError(f"give a recording ({recording}) or --live, not both")
        if out_depth:
            raise LabrigError("--out-depth applies to a recording's run; the live result file keeps no depth maps")
        if serial:
            raise LabrigError("--serial applies to a recording; the live pipeline always runs its two stages in two threads")
        from labrig.cli.run_live import LiveOptions, run_live  # the live pipeline's modules load only for --live

        run_live(LiveOptions(window_ms, window_events, depth, model, out, view, view_every or 3, calibration, rig_path,
                             youngs_modulus_mpa, seconds, indenter, protocol, at, depth_mm, save_recording, max_lag_ms,
                             as_json, depth_every_ms, view_port if view_server else None, view_hz))
        return
    if recording is None:
        raise LabrigError("give a recording (labrig run REC) or --live (the rig's camera)")
    if view_server:
        raise LabrigError("--view-server streams a live run (labrig run --live); to look at a recording's run, "
                          "`labrig export RESULT.h5 --bag OUT.mcap` and open the bag in Foxglove")
    live_only = {"--seconds": seconds, "--indenter": indenter, "--protocol": protocol, "--at": at, "--depth-mm": depth_mm,
                 "--save-recording": save_recording, "--max-lag-ms": max_lag_ms}
    if given := [flag for flag, value in live_only.items() if value is not None]:
        raise LabrigError(f"{', '.join(given)} only apply to --live; drop them to run a recording")
    if depth == "truth" and model is not None:
        raise LabrigError("--model names a depth network and --depth truth reads the recording's true depth: "
                          "drop one of them")
    windows = WindowSpec.from_options(window_ms, window_events)
    depth_every_us = depth_every_option(depth_every_ms)
    check_view(view)
    if not recording.exists():
        raise LabrigError(f"{recording}: no such recording")
    window_us = windows.window_us
    with Recording(recording) as rec:
        shown = ViewFrames(probing_span_us(rec), view_every)
        setup = run_setup.setup_for_recording(
            rec, rig=load_rig(rig_path) if rig_path else None,
            calibration_dir=calibration_folder(calibration),
            youngs_modulus_mpa=youngs_modulus_mpa)
        if depth is None:
            has_truth = "truth/depth" in rec.streams and rec.rows("truth/depth") > 0
            depth = "truth" if model is None and has_truth else "model"
        source = depth_sources.depth_source(depth, setup, rec, model)
        pipe = runtime.Pipeline(setup, source, keep_sae=view is not None, depth_every_us=depth_every_us)
        attrs = {"recording": str(recording), "t0_host_ns": int(rec.attrs.get("t0_host_ns", 0)),
                 "depth_source": source.name, "window_us": window_us or 0,
                 "depth_every_us": depth_every_us or 0,
                 "window_events": window_events or 0, "youngs_modulus_mpa": setup.youngs_modulus_mpa,
                 "poisson_ratio": setup.poisson_ratio, "sources": json.dumps(setup.sources)}
        writer = (results.ResultWriter(out, len(setup.rest_px), attrs, depth=out_depth, rest_mm=setup.rest_mm())
                  if out is not None else None)
        start = time.perf_counter()
        log = WindowLog()
        try:
            for r in pipe.run(rec, window_us=window_us, window_events=window_events, concurrent=not serial):
                if writer is not None:
                    writer.write(r)
                if view is None or not shown.offer(r):
                    r.sae = None
                log.add(r)
        finally:
            if writer is not None:
                writer.close()
        wall = time.perf_counter() - start
    if not len(log):
        raise LabrigError(f"{recording}: no windows (no events?)")
    summary = window_summary(str(recording), log, wall, source.name, setup, window_us, window_events, out, view)
    if view is not None:
        _write_view(shown.frames, setup, view, as_json)
    if as_json:
        print_json(summary)
    else:
        print_run(summary)


def _write_view(frames: list[Any], setup: Any, view: Path, as_json: bool) -> None:
    """The animation, with a progress bar (none with --json)."""
    from rich.progress import MofNCompleteColumn, TimeElapsedColumn

    from labrig.pipeline.view import write_view

    with progress_bar(MofNCompleteColumn(), TimeElapsedColumn(), disable=as_json) as bar:
        task = bar.add_task(f"animation {view.name}", total=len(frames))
        write_view(frames, setup, view, progress=lambda done, _total: bar.update(task, completed=done))


def add_run_commands(app: typer.Typer) -> None:
    """Mount ``run`` on the main app."""
    app.command("run")(run)
