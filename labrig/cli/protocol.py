"""``labrig record`` (one probing run) and ``labrig campaign`` (a whole dataset), safely.

Mount on the main app with :func:`add_protocol_commands`. The work is in
:mod:`labrig.protocol`; this module parses, shows progress and prints.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.progress import TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from labrig.cli.console import (
    IndentersOption,
    JsonOption,
    RigOption,
    console,
    err_console,
    load_rig_and_indenters,
    on_ctrl_c,
    on_terminate,
    output_file,
    output_folder,
    print_json,
    progress_bar,
    stop_probing_run,
)
from labrig.dataset import SPLITS
from labrig.errors import LabrigError


def record(
    indenter: Annotated[str | None, typer.Option(help="Mounted indenter (default: the protocol's).")] = None,
    protocol: Annotated[Path | None, typer.Option(help="Protocol TOML (default: protocols/probe.toml).")] = None,
    at: Annotated[str | None, typer.Option("--at", help="Contact location X,Y in gel mm (from the gel centre).")] = None,
    depth: Annotated[float | None, typer.Option("--depth", help="Normal depth below contact, mm.")] = None,
    force: Annotated[float | None, typer.Option("--force", help="Normal force target, N (instead of a depth).")] = None,
    out: Annotated[Path, typer.Option("--out", help="Directory for the recording.")] = Path("recordings"),
    name: Annotated[str | None, typer.Option(help="File name (default: INDENTER-YYYYmmdd-HHMMSS.h5).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the virtual rig's noise (virtual rig only).")] = 0,
    plot: Annotated[Path | None, typer.Option(
        "--plot", help="Also draw events, forces and Z to this PNG.", callback=output_file)] = None,
    rig_path: RigOption = None,
    indenters_path: IndentersOption = None,
    as_json: JsonOption = False,
) -> None:
    """Record one probing run: approach, Normal Down, Wait, Shear, Wait, Shear Opposite, Wait, Normal Up."""
    from labrig.protocol import apply_overrides, load_protocol
    from labrig.protocol.files import DEFAULT_PROTOCOL
    from labrig.protocol.rigfile import device_config
    from labrig.protocol.runner import EVENTS_NEED_THE_PIPELINE, ProbeRunner, RunProgress
    from labrig.protocol.safety import StopRequest
    from labrig.protocol.session import RigSession

    rig, indenters, ind_path = load_rig_and_indenters(rig_path, indenters_path)
    protocol_path = protocol or DEFAULT_PROTOCOL
    spec = load_protocol(protocol_path, rig, indenters)
    spec = apply_overrides(spec, at=at, depth=depth, force=force, indenter=indenter, rig=rig, indenters=indenters)
    if spec.reads_events:
        raise LabrigError(EVENTS_NEED_THE_PIPELINE)
    if device_config(rig).virtual:
        err_console.print("no hardware configured: recording on the virtual rig (embedded)")
    session = RigSession.for_rig(rig, indenters[spec.indenter], seed=seed, indenters_path=ind_path,
                                 shear_directions_deg=[spec.shear_direction_deg])
    output_folder(out, "--out")
    path = out / (name or f"{spec.indenter}-{time.strftime('%Y%m%d-%H%M%S')}.h5")
    if path.suffix != ".h5":
        path = path.with_suffix(".h5")
    if path.exists():
        raise LabrigError(f"{path} exists; give another --name or --out")
    stop = StopRequest()
    total = spec.nominal_duration_s() + spec.approach.max_travel_mm / spec.approach.speed_mm_s / 2
    with progress_bar(TimeElapsedColumn(), disable=as_json) as bar:
        task = bar.add_task("opening the devices", total=total)
        started = time.monotonic()

        def show(p: RunProgress) -> None:
            bar.update(task, completed=time.monotonic() - started,
                       description=f"{p.phase:<15} depth {p.depth_mm:4.2f} mm  Fz {p.force_n[2]:6.2f} N  "
                                   f"Fxy {abs(complex(*p.force_n[:2])):5.2f} N  {p.event_rate_hz / 1e6:5.2f} Mev/s")

        with session, on_ctrl_c(stop_probing_run(stop)):
            runner = ProbeRunner.for_session(session, stop=stop, progress=show)
            started = time.monotonic()
            result = runner.run(spec, path, protocol_toml=protocol_path.read_text())
    if plot is not None:
        from labrig.recording import Recording
        from labrig.recording.plot import plot_overview

        with Recording(result.path) as rec:
            plot_overview(rec, plot)
    from labrig.protocol.campaign import degraded_reasons

    damage = degraded_reasons(result.path) if result.path.exists() else ""
    summary = {
        "path": str(result.path), "exit_status": result.exit_status, "reason": result.reason,
        "quality": "degraded" if damage else "clean", "quality_reasons": damage.split("; ") if damage else [],
        "indenter": spec.indenter, "virtual_rig": session.virtual, "phases": result.phases,
        "contact_machine_mm": result.contact_mm, "peak_force_n": result.peak_force_n, "wall_s": round(result.wall_s, 3),
        "plot": None if plot is None else str(plot),
    }
    if as_json:
        print_json(summary)
    else:
        style = "green" if result.exit_status == "complete" else "yellow"
        console.print(f"[{style}]{result.exit_status}[/] {result.path}" + (f": {result.reason}" if result.reason else ""))
        peak = result.peak_force_n
        console.print(f"peak |F| (N): x {peak[0]:.2f}  y {peak[1]:.2f}  z {peak[2]:.2f};  {result.wall_s:.1f} s")
        if damage:
            err_console.print(f"[yellow]degraded data[/]: {damage}; record it again")
    if result.exit_status != "complete" or damage:
        raise typer.Exit(1)


def campaign(
    file: Annotated[Path, typer.Argument(help="Campaign TOML (e.g. protocols/paper.toml).")],
    out: Annotated[Path, typer.Option("--out", help="Output directory (recordings and manifest.csv).")] = Path("data"),
    workers: Annotated[int, typer.Option(help="Virtual rigs in parallel (hardware campaigns run one at a time).")] = 1,
    virtual_time: Annotated[bool, typer.Option("--virtual-time", help=(
        "Simulate each recording in its own time on the virtual rig instead of serving it live to the drivers: "
        "deterministic, as fast as the CPU allows (training data; see docs/running.md)."))] = False,
    scheduler: Annotated[str | None, typer.Option(help="With --virtual-time: a Dask scheduler (tcp://host:8786) "
                                                       "instead of --workers local processes.")] = None,
    limit: Annotated[int | None, typer.Option(help="Record at most this many of the pending recordings.")] = None,
    yes: Annotated[bool, typer.Option("--yes", help="Hardware: do not ask before each indenter change.")] = False,
    rig_path: RigOption = None,
    indenters_path: Annotated[Path | None, typer.Option("--indenters", help=(
        "Indenter TOML (default: the campaign's [campaign] indenters, else protocols/indenters.toml)."))] = None,
    as_json: JsonOption = False,
) -> None:
    """Record a whole campaign with a manifest; rerun to resume after an interruption or a crash."""
    from labrig.protocol import load_campaign
    from labrig.protocol.campaign import Manifest, Outcome, pending_jobs, run_job, run_parallel
    from labrig.protocol.rigfile import device_config
    from labrig.protocol.runner import EVENTS_NEED_THE_PIPELINE
    from labrig.protocol.safety import StopRequest

    if workers < 1:
        raise LabrigError("--workers must be at least 1")
    from labrig.protocol.files import campaign_indenters_file

    rig, indenters, ind_path = load_rig_and_indenters(rig_path, indenters_path or campaign_indenters_file(file))
    plan = load_campaign(file, rig, indenters)
    devices = device_config(rig)
    if scheduler is not None and not virtual_time:
        raise LabrigError("--scheduler needs --virtual-time: through-driver runs are served live by local virtual rigs")
    if plan.variation is not None and not virtual_time:
        raise LabrigError(f"{file}: [vary] gives each recording a sensor of its own, which only a virtual-time "
                          "campaign makes: add --virtual-time")
    if not virtual_time and any(p.spec.reads_events for p in plan.plans):
        raise LabrigError(EVENTS_NEED_THE_PIPELINE)
    if workers > 1 and not devices.virtual and not virtual_time:
        raise LabrigError("--workers > 1 needs the virtual rig: a hardware campaign runs one recording at a time")
    output_folder(out, "--out")
    manifest = Manifest(out, plan)
    if virtual_time:
        _virtual_campaign(plan, manifest, out, rig.path, ind_path, workers=workers, scheduler=scheduler, limit=limit,
                          as_json=as_json)
        return
    protocol_text = plan.protocol.read_text() if plan.protocol is not None else ""
    jobs = pending_jobs(plan, manifest, out, rig_path=rig.path, indenters_path=ind_path, protocol_toml=protocol_text,
                        workers=workers)
    if limit is not None:
        jobs = _limit(jobs, limit)
    todo = sum(len(j.plans) for j in jobs)
    skipped = len(plan.plans) - sum(1 for row in manifest.rows.values() if row["status"] != "complete")
    manifest.save()
    if devices.virtual and not as_json:
        err_console.print(f"no hardware configured: {todo} recordings on the virtual rig ({workers} in parallel)")
    nominal = {p.id: p.spec.nominal_duration_s() + 3.0 for j in jobs for p in j.plans}
    t0 = time.monotonic()
    counts = {"complete": 0, "aborted": 0, "failed": 0, "short": 0, "degraded": 0}
    stop = StopRequest()
    count = TextColumn("{task.completed:.0f}/{task.fields[n]}")
    with progress_bar(count, TimeElapsedColumn(), TimeRemainingColumn(), disable=as_json) as bar:
        task = bar.add_task(f"campaign {plan.name}", total=sum(nominal.values()) or 1.0, n=todo)
        done = 0

        def take(outcome: Outcome) -> None:
            nonlocal done
            manifest.record(outcome)
            counts[outcome.status if outcome.status in counts else "failed"] += 1
            done += 1
            bar.update(task, advance=nominal.get(outcome.plan_id, 0.0), description=f"campaign {plan.name}: {outcome.plan_id}")
            count.text_format = f"{done}/{todo}"
            if outcome.status != "complete":
                err_console.print(f"[yellow]{outcome.plan_id} {outcome.status}[/]: {outcome.reason}")

        def ask(indenter: str) -> None:
            if not devices.virtual and not yes:
                bar.stop()
                typer.confirm(f"mount the {indenter} indenter, then continue?", abort=True)
                bar.start()

        with on_ctrl_c(stop_probing_run(stop)), on_terminate(stop):
            if workers == 1:
                for job in jobs:
                    if stop.level >= 1:
                        break
                    run_job(job, take, stop, before_session=ask)
            else:
                for outcome in run_parallel(jobs, workers, stop):
                    take(outcome)
    wall = time.monotonic() - t0
    recorded_s = sum(float(r["duration_s"] or 0) for r in manifest.rows.values())
    summary = {
        "campaign": plan.name, "out": str(out), "manifest": str(manifest.path), "recordings": len(plan.plans),
        "skipped_complete": skipped, "recorded": counts["complete"], "aborted": counts["aborted"], "failed": counts["failed"],
        "short": counts["short"], "degraded": counts["degraded"],
        "pending": sum(1 for r in manifest.rows.values() if r["status"] not in ("complete",)),
        "workers": workers, "wall_s": round(wall, 2),
        "recordings_per_min": round(60 * done / wall, 3) if done and wall > 0 else 0.0,
        "splits": {s: sum(1 for r in manifest.rows.values() if r["split"] == s) for s in SPLITS},
        "recorded_wall_s_total": round(recorded_s, 2),
    }
    summary["stopped"] = stop.level >= 1
    if as_json:
        print_json(summary)
        _exit_if_stopped(summary)
        return
    table = Table(title=f"campaign {plan.name}", title_justify="left")
    for column in ("recordings", "skipped", "recorded", "aborted", "failed", "pending", "per min"):
        table.add_column(column, justify="right")
    table.add_row(*(str(summary[k]) for k in ("recordings", "skipped_complete", "recorded", "aborted", "failed", "pending")),
                  f"{summary['recordings_per_min']:.2f}")
    console.print(table)
    console.print(f"manifest: {manifest.path}")
    if summary["pending"]:
        console.print("[yellow]some recordings are not complete: run the same command again to resume[/]")
    _exit_if_stopped(summary)


def _exit_if_stopped(summary: dict[str, Any]) -> None:
    """A campaign stopped by Ctrl-C or SIGTERM exits 1 (its recordings finalized, the manifest resumable)."""
    if summary["stopped"]:
        err_console.print(f"[yellow]stopped[/]: {summary['pending']} recordings not complete; "
                          "run the same command again to resume")
        raise typer.Exit(1)


def _virtual_campaign(plan: Any, manifest: Any, out: Path, rig_path: Path, indenters_path: Path, *, workers: int,
                      scheduler: str | None, limit: int | None, as_json: bool) -> None:
    from labrig.protocol.virtual_campaign import pending_tasks, run_virtual_campaign

    tasks = pending_tasks(plan, manifest, out, rig_path=rig_path, indenters_path=indenters_path, limit=limit)
    skipped = sum(1 for p in plan.plans if manifest.done(p, out))
    manifest.save()
    if not as_json:
        where = f"on the Dask cluster at {scheduler}" if scheduler else f"{workers} in parallel"
        err_console.print(f"{len(tasks)} recordings in virtual time ({where})")
    counts = {"complete": 0, "aborted": 0, "failed": 0, "degraded": 0}
    simulated_s = 0.0
    t0 = time.monotonic()
    with progress_bar(TimeElapsedColumn(), TimeRemainingColumn(), disable=as_json) as bar:
        task = bar.add_task(f"campaign {plan.name} (virtual time)", total=len(tasks) or 1)

        def take(outcome: Any) -> None:
            nonlocal simulated_s
            counts[outcome.status if outcome.status in counts else "failed"] += 1
            bar.update(task, advance=1, description=f"campaign {plan.name}: {outcome.plan_id}")
            if outcome.status != "complete":
                err_console.print(f"[yellow]{outcome.plan_id} {outcome.status}[/]: {outcome.reason}")

        outcomes = run_virtual_campaign(plan, manifest, tasks, workers=workers, scheduler=scheduler, take=take)
    wall = time.monotonic() - t0
    cpu_s = sum(o.duration_s for o in outcomes)
    for o in outcomes:
        row = manifest.rows[o.plan_id]
        if o.status == "complete" and row["file"]:
            simulated_s += _recording_seconds(out / row["file"])
    summary = {
        "campaign": plan.name, "out": str(out), "manifest": str(manifest.path), "made_by": "virtual-time",
        "recordings": len(plan.plans), "skipped_complete": skipped, "recorded": counts["complete"],
        "aborted": counts["aborted"], "failed": counts["failed"], "degraded": counts["degraded"],
        "pending": sum(1 for r in manifest.rows.values() if r["status"] != "complete"),
        "workers": None if scheduler else workers, "scheduler": scheduler, "wall_s": round(wall, 2),
        "recordings_per_min": round(60 * len(outcomes) / wall, 3) if outcomes and wall > 0 else 0.0,
        "simulated_s": round(simulated_s, 2), "task_s_total": round(cpu_s, 2),
        "simulated_s_per_task_s": round(simulated_s / cpu_s, 3) if cpu_s > 0 else 0.0,
        "splits": {s: sum(1 for r in manifest.rows.values() if r["split"] == s) for s in SPLITS},
    }
    if as_json:
        print_json(summary)
    else:
        table = Table(title=f"campaign {plan.name} (virtual time)", title_justify="left")
        for column in ("recordings", "skipped", "recorded", "aborted", "failed", "pending", "per min", "sim s / task s"):
            table.add_column(column, justify="right")
        table.add_row(*(str(summary[k]) for k in ("recordings", "skipped_complete", "recorded", "aborted", "failed", "pending")),
                      f"{summary['recordings_per_min']:.2f}", f"{summary['simulated_s_per_task_s']:.2f}")
        console.print(table)
        console.print(f"manifest: {manifest.path}")
        if summary["pending"]:
            console.print("[yellow]some recordings are not complete: run the same command again to resume[/]")
    if counts["failed"]:
        raise typer.Exit(1)


def _recording_seconds(path: Path) -> float:
    from labrig.recording import Recording

    with Recording(path) as rec:
        return rec.end_us() / 1e6


def _limit(jobs: list[Any], limit: int) -> list[Any]:
    from dataclasses import replace

    kept, left = [], max(0, limit)
    for job in jobs:
        if left == 0:
            break
        kept.append(replace(job, plans=job.plans[:left]))
        left -= len(kept[-1].plans)
    return kept


def add_protocol_commands(app: typer.Typer) -> None:
    """Mount ``record`` and ``campaign`` on the main app."""
    app.command("record")(record)
    app.command("campaign")(campaign)
