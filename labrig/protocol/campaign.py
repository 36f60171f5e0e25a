"""Running a campaign: every recording of a campaign file, a manifest, resumable, in parallel on virtual rigs.

The output directory is a :class:`labrig.dataset.Dataset`. Its manifest (rewritten
atomically after each recording) has one row per recording: id, indenter, location,
parameters, split, status (``pending``, ``complete``, ``aborted``), file and
its SHA-256. A rerun skips recordings whose file is there with its checksum,
and redoes the rest (a crash leaves ``NAME.h5.partial``: it is moved aside
as ``NAME.h5.partial.N`` and the recording redone).

Recordings of one indenter share one rig session (hardware: the operator is
asked to mount each indenter). ``workers`` > 1 runs several virtual rigs in
parallel, each in its own processes; hardware campaigns are sequential.
"""

from __future__ import annotations

import functools
import multiprocessing as mp
import os
import queue
import signal
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing.managers import SyncManager
from pathlib import Path
from typing import Any

from labrig.cache import sha256_of
from labrig.config import load_rig
from labrig.dataset import COMPLETE, Dataset, read_manifest, write_manifest
from labrig.devices.bota import BotaTimeout
from labrig.devices.grbl import GrblTimeout
from labrig.errors import LabrigError
from labrig.indenters import load_indenters
from labrig.protocol.realtime import Shortfall, record_in_real_time
from labrig.protocol.rig_ready import ready_or_restarted
from labrig.protocol.runner import ProbeRunner, RunResult
from labrig.protocol.safety import StopRequest
from labrig.protocol.session import RigSession
from labrig.protocol.spec import Campaign, RecordingPlan
from labrig.recording import Recording
from labrig.recording.layout import partial_path
from labrig.recording.quality import assess, stored_quality
from labrig.sim.parent_watch import exit_with_parent


@dataclass(frozen=True)
class Outcome:
    """One recording done (or failed) by a worker."""

    plan_id: str
    status: str
    reason: str
    file: str
    sha256: str
    duration_s: float
    #: What fell behind real time, by how much ("" when the run kept up; see protocol.realtime).
    fell_behind: str = ""
    #: The virtual rig's twin that missed a driver's deadline and so ended the run ("" when none).
    late_twin: str = ""
    #: What damaged the recording's data ("" when clean; labrig.recording.quality).
    degraded: str = ""


class Manifest:
    """The campaign's manifest rows by recording id; saved atomically."""

    def __init__(self, out_dir: Path, campaign: Campaign) -> None:
        self.path = Dataset(out_dir).manifest_path
        self.rows: dict[str, dict[str, str]] = {}
        old = {row["id"]: row for row in read_manifest(self.path)} if self.path.exists() else {}
        for plan in campaign.plans:
            row = _plan_row(plan)
            before = old.get(plan.id)
            if before is not None and all(before.get(k) == row[k] for k in ("indenter", "x_mm", "y_mm", "split")):
                row.update({k: before.get(k) or "" for k in ("status", "reason", "file", "sha256", "duration_s", "made_by",
                                                              "fell_behind")})
            self.rows[plan.id] = row

    def done(self, plan: RecordingPlan, out_dir: Path) -> bool:
        """Complete, with its file present and unchanged."""
        row = self.rows[plan.id]
        if row["status"] != COMPLETE or not row["file"]:
            return False
        path = out_dir / row["file"]
        return path.exists() and sha256_of(path) == row["sha256"]

    def record(self, outcome: Outcome, made_by: str = "drivers") -> None:
        """Store an outcome; ``made_by``: the path that made the recording (``drivers`` or ``virtual-time``)."""
        self.rows[outcome.plan_id].update(status=outcome.status, reason=outcome.reason, file=outcome.file,
                                          sha256=outcome.sha256, duration_s=f"{outcome.duration_s:.3f}", made_by=made_by,
                                          fell_behind=outcome.fell_behind)
        self.save()

    def save(self) -> None:
        write_manifest(self.path, self.rows.values())


def _plan_row(plan: RecordingPlan) -> dict[str, str]:
    s = plan.spec
    return {
        "id": plan.id, "index": str(plan.index), "indenter": s.indenter, "x_mm": f"{s.location_mm[0]:g}",
        "y_mm": f"{s.location_mm[1]:g}", "depth_mm": "" if s.depth_mm is None else f"{s.depth_mm:g}",
        "force_n": "" if s.force_n is None else f"{s.force_n:g}", "normal_speed_mm_s": f"{s.normal_speed_mm_s:g}",
        "shear_direction_deg": f"{s.shear_direction_deg:g}", "shear_mm": f"{s.shear_mm:g}",
        "shear_speed_mm_s": f"{s.shear_speed_mm_s:g}", "wait_s": f"{s.wait_s:g}", "repetition": str(plan.repetition),
        "split": plan.split, "status": "pending", "reason": "", "file": "", "sha256": "", "duration_s": "", "made_by": "",
        "fell_behind": "",
    }


@dataclass(frozen=True)
class CampaignJob:
    """What a worker needs to record some plans of one indenter (picklable)."""

    rig_path: str
    indenters_path: str
    out_dir: str
    protocol_toml: str
    seed: int
    indenter: str
    plans: tuple[RecordingPlan, ...]


def pending_jobs(campaign: Campaign, manifest: Manifest, out_dir: Path, *, rig_path: Path, indenters_path: Path,
                 protocol_toml: str, workers: int) -> list[CampaignJob]:
    """The recordings still to make, grouped by indenter and cut into about ``workers`` jobs per indenter."""
    todo: dict[str, list[RecordingPlan]] = {}
    for plan in campaign.plans:
        if not manifest.done(plan, out_dir):
            todo.setdefault(plan.spec.indenter, []).append(plan)
    jobs = []
    for indenter, plans in todo.items():
        parts = max(1, min(workers, len(plans)))
        for k in range(parts):
            chunk = tuple(plans[k::parts])
            jobs.append(CampaignJob(str(rig_path), str(indenters_path), str(out_dir), protocol_toml,
                                    campaign.seed * 100_003 + chunk[0].index, indenter, chunk))
    return jobs


def run_job(job: CampaignJob, report: Callable[[Outcome], None], stop: StopRequest | None = None,
            before_session: Callable[[str], None] | None = None) -> None:
    """Record a job's plans on one rig session; ``report`` each outcome as it comes."""
    rig = load_rig(job.rig_path)
    indenters = load_indenters(job.indenters_path)
    indenter = indenters[job.indenter]
    if before_session is not None:
        before_session(job.indenter)
    session = RigSession.for_rig(rig, indenter, seed=job.seed, indenters_path=Path(job.indenters_path),
                                 shear_directions_deg=[plan.spec.shear_direction_deg for plan in job.plans])
    out_dir = Path(job.out_dir)
    with session:
        runner = ProbeRunner.for_session(session, stop=stop)
        for plan in job.plans:
            if stop is not None and stop.level >= 1:
                return
            record = functools.partial(_record_one, runner, plan, out_dir, job.protocol_toml)
            report(record_in_real_time(record, functools.partial(ready_or_restarted, session), stop))


def _record_one(runner: ProbeRunner, plan: RecordingPlan, out_dir: Path, protocol_toml: str) -> Outcome:
    path = Dataset(out_dir).recording_path(plan.id)
    partial = partial_path(path)
    if partial.exists():  # a crash mid-recording: keep it aside, redo the recording
        n = 1
        while partial.with_name(f"{partial.name}.{n}").exists():
            n += 1
        partial.rename(partial.with_name(f"{partial.name}.{n}"))
    extra = {"campaign_id": plan.id, "split": plan.split, "repetition": plan.repetition}
    try:
        result: RunResult = runner.run(plan.spec, path, protocol_toml=protocol_toml, extra=extra, overwrite=True)
    except (GrblTimeout, BotaTimeout) as exc:  # before the recording opened: travelling, taring
        late = Shortfall(late_twin=str(exc)) if runner.session.virtual else Shortfall()
        return Outcome(plan.id, "failed", str(exc), "", "", 0.0, late.describe(), late.late_twin)
    except LabrigError as exc:
        return Outcome(plan.id, "failed", str(exc), "", "", 0.0)
    return Outcome(plan.id, result.exit_status, result.reason, result.path.name, sha256_of(result.path), result.wall_s,
                   result.shortfall.describe(), result.shortfall.late_twin, degraded_reasons(result.path))


def degraded_reasons(path: Path) -> str:
    """What damaged a recording's data, in one line ("" when clean): its stored verdict, else assessed now."""
    with Recording(path) as rec:
        quality = stored_quality(rec) or assess(rec)
    return "; ".join(quality.reasons)


def _worker(job: CampaignJob, outcomes: Any, stop_level: Any) -> None:
    done = threading.Event()
    try:
        run_job(job, outcomes.put, _follow(stop_level, done))
    finally:
        done.set()


def _init_worker(parent_pid: int) -> None:
    """A campaign worker dies with the campaign, and leaves Ctrl-C to it (the campaign stops it)."""
    exit_with_parent(parent_pid, False)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _follow(shared_level: Any, done: threading.Event) -> StopRequest:
    """A worker's stop request, raised to the campaign's level (a shared int) as it rises until
    ``done``, and to 2 by a SIGTERM sent to the worker itself."""
    stop = StopRequest()

    def raise_to(level: int) -> None:
        while stop.level < level:
            stop.request()

    def follow() -> None:
        while stop.level < 2 and not done.wait(0.1):
            raise_to(int(shared_level.value))

    signal.signal(signal.SIGTERM, lambda signum, frame: raise_to(2))
    threading.Thread(target=follow, name="labrig-campaign-stop", daemon=True).start()
    return stop


def run_parallel(jobs: list[CampaignJob], workers: int, stop: StopRequest | None = None) -> Iterator[Outcome]:
    """Run jobs on ``workers`` processes (virtual rigs only); yields outcomes as they come. ``stop``
    (the campaign's Ctrl-C / SIGTERM) reaches every worker: jobs not started are cancelled, running
    ones end their recording as a stop would (finalized, aborted) and return."""
    ctx = mp.get_context("spawn")
    manager = SyncManager(ctx=ctx)
    manager.start(exit_with_parent, (os.getpid(), False))  # none of our processes outlives a killed campaign
    outcomes = manager.Queue()
    shared_level = manager.Value("i", 0)
    try:
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker,
                                 initargs=(os.getpid(),)) as pool:
            futures: list[Future[None]] = [pool.submit(_worker, job, outcomes, shared_level) for job in jobs]
            while True:
                if stop is not None and stop.level > shared_level.value:
                    shared_level.value = stop.level
                    for future in futures:
                        future.cancel()  # not started yet: stays pending in the manifest
                try:
                    yield outcomes.get(timeout=0.2)
                    continue
                except queue.Empty:
                    pass
                if all(f.done() for f in futures):
                    break
            while True:
                try:
                    yield outcomes.get_nowait()
                except queue.Empty:
                    break
            for f in futures:
                error = None if f.cancelled() else f.exception()
                if error is not None:
                    raise LabrigError(f"a campaign worker failed: {error}") from error
    finally:
        manager.shutdown()
