"""``labrig groundtruth DATA``: ground-truth depth maps and contact masks as ``NAME.gt.h5`` sidecars.

Mount on the main app with :func:`add_groundtruth_commands`.
User errors (not a recording, no manifest, bad options) are :class:`LabrigError`
s, printed as one line by ``labrig``'s main.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.progress import MofNCompleteColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from labrig.cli.console import (
    CalibrationOption,
    JsonOption,
    calibration_folder,
    console,
    err_console,
    output_file,
    print_json,
    progress_bar,
)
from labrig.errors import LabrigError


def groundtruth(
    data: Annotated[Path, typer.Argument(help="A campaign output folder (with manifest.csv) or one recording (.h5).")],
    model: Annotated[str, typer.Option(
        help="Elastic model of the gel: layer (bonded thin layer) or halfspace (the paper's).")] = "layer",
    method: Annotated[str, typer.Option(help="Contact solution: auto (per indenter), hertz, sneddon or numerical.")] = "auto",
    rate_hz: Annotated[float, typer.Option(help="Maps per second (F/T sample times thinned to this rate).")] = 100.0,
    scale_mm: Annotated[float, typer.Option(help="Global normalisation: mm of depth per unit of the [0, 1] maps.")] = 2.5,
    calibration: CalibrationOption = None,
    rig_path: Annotated[Path | None, typer.Option("--rig", help="Rig TOML (default: the one stored in each recording).")] = None,
    overwrite: Annotated[bool, typer.Option(help="Redo sidecars that are already current.")] = False,
    plot: Annotated[Path | None, typer.Option(
        help="PNG of a few maps of the first recording beside its events.", callback=output_file)] = None,
    indenters_path: Annotated[Path | None, typer.Option("--indenters", help=(
        "Indenter TOML for recordings that do not carry their indenter's definition (default: "
        "protocols/indenters.toml); recordings that carry one use it."))] = None,
    workers: Annotated[int, typer.Option(help="Recordings in parallel, local processes (1: in this process).")] = 1,
    scheduler: Annotated[str | None, typer.Option(help="A Dask scheduler (tcp://host:8786) instead of --workers.")] = None,
    as_json: JsonOption = False,
) -> None:
    """Ground-truth normal-deformation maps and contact masks for recordings, as NAME.gt.h5 beside each."""
    from labrig.dataset import DatasetRecording, open_data
    from labrig.executor import run_tasks
    from labrig.groundtruth import ELASTIC_MODELS
    from labrig.groundtruth.batch import SidecarTask, is_current, plot_groundtruth, write_sidecar_task

    if model not in ELASTIC_MODELS:
        raise LabrigError(f"--model must be one of {', '.join(ELASTIC_MODELS)}, not {model!r}")
    if method not in ("auto", "hertz", "sneddon", "numerical"):
        raise LabrigError(f"--method must be auto, hertz, sneddon or numerical, not {method!r}")
    if rate_hz <= 0 or scale_mm <= 0:
        raise LabrigError("--rate-hz and --scale-mm must be positive")
    if workers < 1:
        raise LabrigError("--workers must be at least 1")
    calibration = calibration_folder(calibration)
    source = open_data(data)
    jobs, not_complete = (([source], 0) if isinstance(source, DatasetRecording)
                          else (source.complete(), source.count_not_complete()))
    settings: dict[str, Any] = {"elastic_model": model, "rate_hz": float(rate_hz), "scale_mm": float(scale_mm)}
    if method != "auto":
        settings["contact_model"] = method
    results: list[dict[str, Any]] = []
    start = time.perf_counter()
    tasks = []
    for job in jobs:
        if not overwrite and is_current(job, settings):
            results.append({"recording": str(job.path), "split": job.split, "status": "current", "sidecar": str(job.sidecar)})
        else:
            tasks.append(SidecarTask(str(job.path), str(job.sidecar), job.split, model, method, float(rate_hz),
                                     float(scale_mm), str(calibration),
                                     None if rig_path is None else str(rig_path),
                                     None if indenters_path is None else str(indenters_path)))
    with progress_bar(MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(), disable=as_json) as bar:
        overall = bar.add_task("recordings", total=len(jobs), completed=len(results))
        done = run_tasks(write_sidecar_task, tasks, workers=workers, scheduler=scheduler, use_cache=False,
                         raise_on_error=False, progress=lambda n, total: bar.update(overall, completed=len(results) + n))
    for task, entry, in zip(tasks, done):
        results.append(entry if entry is not None else {"recording": task.recording, "split": task.split,
                                                        "status": "failed", "reason": "the task raised"})
    for failure in done.failures:
        results[len(results) - len(tasks) + failure.index]["reason"] = f"{failure.error}: {failure.message}"
    if len(jobs) == 1 and results[0]["status"] == "failed":
        raise LabrigError(results[0]["reason"])
    written = [r for r in results if r["status"] == "written"]
    total_maps = sum(r["maps"] for r in written)
    busy_s = sum(r["seconds"] for r in written)
    summary = {
        "data": str(data),
        "recordings": len(jobs),
        "written": len(written),
        "current": sum(r["status"] == "current" for r in results),
        "failed": sum(r["status"] == "failed" for r in results),
        "not_complete_in_manifest": not_complete,
        "elastic_model": model,
        "method": method,
        "rate_hz": rate_hz,
        "scale_mm": scale_mm,
        "maps": total_maps,
        "maps_per_s": round(total_maps / busy_s, 1) if busy_s > 0 else None,
        "wall_s": round(time.perf_counter() - start, 3),
        "results": results,
    }
    if plot is not None:
        first = next((r for r in results if r.get("sidecar")), None)
        if first is None:
            raise LabrigError("--plot: no sidecar was written or found to plot")
        summary["plot"] = str(plot_groundtruth(first["recording"], first["sidecar"], plot))
    if as_json:
        print_json(summary)
    else:
        _print_summary(summary)
    if summary["failed"]:
        err_console.print(f"[red]{summary['failed']} of {len(jobs)} recordings failed[/]: their reasons are above; "
                          "fix the cause and rerun (sidecars already written are kept)")
        raise typer.Exit(1)


def _print_summary(s: dict[str, Any]) -> None:
    table = Table(title=f"ground truth ({s['elastic_model']}, {s['method']})", show_lines=False)
    for col in ("recording", "status", "model", "maps", "max depth mm", "maps/s"):
        table.add_column(col)
    for r in s["results"]:
        status = r["status"] if r["status"] != "failed" else f"[red]failed[/]: {escape(r['reason'])}"
        table.add_row(Path(r["recording"]).name, status,
                      f"{r.get('elastic_model', '')}/{r.get('contact_model', '')}" if r.get("elastic_model") else "",
                      str(r.get("maps", "")), f"{r['max_depth_mm']:.3f}" if "max_depth_mm" in r else "",
                      f"{r['maps_per_s']:.0f}" if r.get("maps_per_s") else "")
    console.print(table)
    console.print(f"{s['written']} written, {s['current']} already current, {s['failed']} failed "
                  f"({s['maps']:,} maps, {s['maps_per_s'] or 0:.0f} maps/s, {s['wall_s']:.1f} s)")
    sources = {(r["camera_source"], r["gel_pose_source"], r["gel_source"]) for r in s["results"] if "camera_source" in r}
    for camera, pose, gel in sources:
        style = "yellow" if camera.startswith("nominal camera") else "dim"
        console.print(f"[{style}]camera: {escape(camera)}; gel pose: {escape(pose)}; gel: {escape(gel)}[/]")
    if s.get("plot"):
        console.print(f"plot: {s['plot']}")


def add_groundtruth_commands(app: typer.Typer) -> None:
    """Mount ``groundtruth`` on the main app."""
    app.command("groundtruth")(groundtruth)
