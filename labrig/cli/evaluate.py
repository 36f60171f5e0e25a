"""``labrig evaluate DATA``: the paper's tables and figures for a campaign, in a static report.

Mount on the main app with :func:`add_evaluate_commands`. User errors (no
manifest, missing sidecars, bad options) are :class:`LabrigError` s, printed as one line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.progress import MofNCompleteColumn, TaskID, TimeElapsedColumn

from labrig.cli.console import (
    CalibrationOption,
    JsonOption,
    calibration_folder,
    console,
    err_console,
    print_json,
    progress_bar,
)


def evaluate_command(
    data: Annotated[Path, typer.Argument(help="Campaign folder (manifest.csv, recordings, NAME.gt.h5 sidecars).")],
    split: Annotated[str, typer.Option(help="Which recordings: test, val, train or all.")] = "test",
    model: Annotated[Path | None, typer.Option(
        help="Depth network: an .onnx with its card, or a bundled one "
             "(default: the SAE and the brightness change since rest; sae-only: the paper's network).")] = None,
    models: Annotated[Path | None, typer.Option(
        "--models", help="Folder of Table II networks (tools/depth_sweep.py --table2); missing rows are reported.")] = None,
    out: Annotated[Path, typer.Option(help="Report folder: index.html, figures/, tables/*.csv, results.json.")] = Path(
        "report"),
    window_events: Annotated[int | None, typer.Option(help="Events per evaluation window (default 20000, the paper's).")
                             ] = None,
    window_ms: Annotated[float | None, typer.Option(help="Fixed-time evaluation windows (ms) instead.")] = None,
    calibration: CalibrationOption = None,
    workers: Annotated[int | None, typer.Option(help="Local processes (default: one per core; 1: in this process).")
                       ] = None,
    scheduler: Annotated[str | None, typer.Option(help="A Dask scheduler address (tcp://host:8786) to run the tasks on.")
                         ] = None,
    cache: Annotated[Path | None, typer.Option(help="Result cache folder (default $LABRIG_CACHE/eval or ~/.cache/labrig/eval).")
                     ] = None,
    no_cache: Annotated[bool, typer.Option("--no-cache", help="Recompute every task (results are still stored).")] = False,
    table1: Annotated[bool, typer.Option(help="Track each recording at 5 patch sizes x 2 for Table I.")] = True,
    trackers: Annotated[str, typer.Option(
        help="Table I's trackers, comma-separated: paper-published, paper, circle-fit, evetac (Evetac's published "
             "tracker).")] = "paper-published,paper",
    sweep: Annotated[bool, typer.Option("--sweep", help="Also chart accuracy against latency over the pipeline's knobs.")
                     ] = False,
    sweep_recordings: Annotated[int, typer.Option(help="Recordings the sweep uses (spread over the split; 0: all).")] = 4,
    stress: Annotated[bool, typer.Option("--stress", help="Also push each method along stress axes on the virtual rig "
                                         "until it breaks (force range, speed, slip, noise, contrast, window, clock, "
                                         "dead pixels, marker placement, missing markers, USB bursts, contrast "
                                         "threshold, ON/OFF ratio, LED slope gain, membrane level, hold).")] = False,
    stress_grid: Annotated[str, typer.Option(help="The stress axes' values: full, or reduced (3 per axis).")] = "full",
    stress_axes: Annotated[str | None, typer.Option(
        help="Only these stress axes, comma-separated keys (e.g. contrast_threshold,hold; default: every axis).")] = None,
    stress_metrics: Annotated[str | None, typer.Option(
        help="Only these of the stress axes' measures, comma-separated: tracking, forces, depth (default: all).")] = None,
    label_poses: Annotated[str, typer.Option(
        help="The gel poses the label errors are measured with: lab (the registration), or lab,true (also the sim's "
             "own pose: what the registration costs the labels).")] = "lab",
    as_json: JsonOption = False,
) -> None:
    """Evaluate the pipeline on DATA: Tables I-III, errors per range, runtime, dense and label errors; a report."""
    from labrig.evaluation.evaluate import EvaluationSettings, evaluate_campaign
    from labrig.evaluation.report import check_report, print_summary
    from labrig.evaluation.report_sections import build_report

    settings = EvaluationSettings(
        data=data, split=split, model=model, models_dir=models,
        window_events=window_events if window_events is not None or window_ms is not None else 20_000,
        window_ms=window_ms, calibration_dir=calibration_folder(calibration), workers=workers, scheduler=scheduler,
        cache_dir=cache,
        use_cache=not no_cache, table1=table1, trackers=tuple(t.strip() for t in trackers.split(",") if t.strip()),
        sweep=sweep, sweep_recordings=sweep_recordings or None,
        label_poses=tuple(p.strip() for p in label_poses.split(",") if p.strip()),
        stress=stress or stress_axes is not None or stress_metrics is not None, stress_grid=stress_grid,
        stress_axes=tuple(a.strip() for a in stress_axes.split(",") if a.strip()) if stress_axes else None,
        stress_metrics=tuple(m.strip() for m in stress_metrics.split(",") if m.strip()) if stress_metrics is not None
        else None)
    if sweep_recordings < 0:
        from labrig.errors import LabrigError

        raise LabrigError("--sweep-recordings must be 0 (all) or positive")
    with progress_bar(MofNCompleteColumn(), TimeElapsedColumn(), disable=as_json) as bar:
        ids: dict[str, TaskID] = {}

        def progress(kind: str, done: int, total: int) -> None:
            if kind not in ids:
                ids[kind] = bar.add_task(kind, total=total)
            bar.update(ids[kind], completed=done, total=total)

        evaluation = evaluate_campaign(settings, progress)
        report = build_report(evaluation)
        index = report.write(out)
    problems = check_report(out)
    summary = {**evaluation.summary, "report": str(index), "report_problems": problems}
    if as_json:
        print_json(summary, default=float)
        return
    print_summary(report, console)
    for problem in problems:
        err_console.print(f"[yellow]report: {escape(problem)}[/]")
    console.print(f"report: [bold]{escape(str(index))}[/]")


def add_evaluate_commands(app: typer.Typer) -> None:
    """Mount ``evaluate`` on the main app."""
    app.command("evaluate")(evaluate_command)
