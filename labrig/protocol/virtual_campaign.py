"""A campaign in virtual time: each recording one task for :func:`labrig.executor.run_tasks`.

The same campaign file, plan, split, manifest and resumability as a through-driver campaign
(:mod:`labrig.protocol.campaign`), but each recording is simulated by
:func:`~labrig.protocol.virtual_run.record_virtual` in its own time. A task names the campaign
file and one recording's id (plain values, so it travels to local processes or a Dask
cluster's workers, which must see the same paths); it writes its own file and returns an
:class:`~labrig.protocol.campaign.Outcome`, and the caller writes the manifest as outcomes come
back (:func:`run_virtual_campaign`). A recording's seed is the campaign's seed and its index,
so the same campaign gives the same recordings wherever and in whatever order they run.

A campaign whose ``[vary]`` changes the camera's thresholds (``sim.events.threshold*``) or the light
(``sim.lighting.*``)
gives each recording a sensor of its own, which a lab would calibrate: the task then records the
event-response scene on that camera (:func:`labrig.sim.calibration_scenes.record_led_ramps`,
:data:`CAMPAIGN_RAMPS`) and fits it (:func:`labrig.calibration.event_thresholds.fit_event_thresholds`),
records the calibration press and fits the light's slope response
(:mod:`labrig.protocol.light_calibration`), and writes both to ``ID.events.toml`` beside the
recording, which every later step reads for it (:func:`labrig.dataset.events_sidecar_path`).
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from labrig.cache import sha256_of
from labrig.calibration.event_thresholds import fit_event_thresholds
from labrig.calibration.event_thresholds_file import ContrastThresholds, load_event_thresholds, write_event_thresholds
from labrig.calibration.slope_response import SlopeResponse
from labrig.config import RigConfig, load_rig
from labrig.dataset import COMPLETE, Dataset, events_sidecar_path
from labrig.errors import LabrigError
from labrig.executor import run_tasks
from labrig.indenters import load_indenters
from labrig.protocol.campaign import Manifest, Outcome, degraded_reasons
from labrig.protocol.files import load_campaign
from labrig.protocol.light_calibration import measure_slope_response, record_slope_press, write_slope_response
from labrig.protocol.realtime import DEGRADED
from labrig.protocol.spec import Campaign, RecordingPlan
from labrig.protocol.virtual_run import MADE_BY_VIRTUAL_TIME, record_virtual
from labrig.recording.layout import partial_path
from labrig.sim.calibration_scenes import LedRamps, record_led_ramps
from labrig.sim.world_process import prepare_contact_tables

#: The event-response scene of a campaign recording's own camera: fewer cycles than the command's (5, 8 ramps used).
CAMPAIGN_RAMPS = LedRamps(cycles=5)


@dataclass(frozen=True)
class VirtualTask:
    """One recording of a campaign to simulate (paths as the worker sees them)."""

    campaign_path: str
    rig_path: str
    indenters_path: str
    out_dir: str
    plan_id: str


def recording_seed(campaign: Campaign, plan: RecordingPlan) -> int:
    """The virtual rig's seed of one recording: fixed by the campaign's seed and the recording's index."""
    return campaign.seed * 100_003 + plan.index


def record_task(task: VirtualTask) -> Outcome:
    """Simulate one recording of the campaign into ``out_dir`` (a crash's ``.partial`` is set aside first)."""
    rig = load_rig(task.rig_path)
    indenters = load_indenters(task.indenters_path)
    campaign = load_campaign(task.campaign_path, rig, indenters)
    plan = next((p for p in campaign.plans if p.id == task.plan_id), None)
    if plan is None:
        raise LabrigError(f"{task.campaign_path} has no recording {task.plan_id!r} (was the file changed?)")
    indenter = indenters[plan.spec.indenter]
    seed = recording_seed(campaign, plan)
    if campaign.variation is not None:
        rig = campaign.variation.rig_for(rig, seed)
    prepare_contact_tables(rig, indenter, [plan.spec.shear_direction_deg])
    path = Dataset(Path(task.out_dir)).recording_path(plan.id)
    _set_aside_partial(path)
    protocol_toml = campaign.protocol.read_text() if campaign.protocol is not None else ""
    extra = {"campaign_id": plan.id, "split": plan.split, "repetition": plan.repetition}
    try:
        result = record_virtual(plan.spec, path, rig, indenter, seed=seed,
                                protocol_toml=protocol_toml, extra=extra)
    except LabrigError as exc:
        return Outcome(plan.id, "failed", str(exc), "", "", 0.0)
    if campaign.variation is not None and (campaign.variation.varies("sim.events.threshold")
                                           or campaign.variation.varies("sim.lighting.")):
        calibrate_own_camera(rig, path, seed, Path(task.rig_path).parent)
    damage = degraded_reasons(result.path)
    if result.exit_status == COMPLETE and damage:  # virtual time is deterministic: trying again gives the same
        return Outcome(plan.id, DEGRADED, f"its data is damaged: {damage}", result.path.name, sha256_of(result.path),
                       result.wall_s, degraded=damage)
    return Outcome(plan.id, result.exit_status, result.reason, result.path.name, sha256_of(result.path), result.wall_s)


def calibrate_own_camera(rig: RigConfig, recording: Path, seed: int, calibration_dir: str | Path | None) -> Path:
    """Calibrate the contrast thresholds and the light's slope response of the sensor that made ``recording``
    (``rig``'s) into its ``ID.events.toml`` sidecar, as ``labrig calibrate events`` would (``calibration_dir``:
    the rig's calibration, for the press's ground truth); the file is written once, with both."""
    with tempfile.TemporaryDirectory(prefix="labrig-events-") as folder:
        scene = Path(folder) / "led-ramps.h5"
        record_led_ramps(scene, rig, seed=seed, ramps=CAMPAIGN_RAMPS)
        fit = fit_event_thresholds(scene, rig.roi)
    response = _own_light(rig, fit.thresholds, seed, calibration_dir)
    summary = {**fit.summary(), "shading": {**response.summary(), "press": OWN_PRESS}}
    return write_event_thresholds(events_sidecar_path(recording), fit.thresholds, summary,
                                  {"recording": "the event-response scene of this recording's camera", "seed": seed})


def calibrate_own_light(rig: RigConfig, recording: Path, seed: int, calibration_dir: str | Path | None) -> Path:
    """Add the slope response of the light that made ``recording`` (``rig``'s) to its ``ID.events.toml``, which
    must hold its thresholds (campaigns recorded before the press was part of the calibration)."""
    sidecar = events_sidecar_path(recording)
    response = _own_light(rig, load_event_thresholds(sidecar), seed, calibration_dir)
    return write_slope_response(sidecar, response, OWN_PRESS)


#: The ``press`` a campaign recording's ``[shading]`` names.
OWN_PRESS = "the calibration press of this recording's sensor"


def _own_light(rig: RigConfig, thresholds: ContrastThresholds, seed: int, calibration_dir: str | Path | None
               ) -> SlopeResponse:
    """The calibration press on the virtual rig ``rig`` (the standard sphere), fitted with ``thresholds``."""
    with tempfile.TemporaryDirectory(prefix="labrig-light-") as folder:
        press = Path(folder) / "slope-press.h5"
        record_slope_press(press, rig, load_indenters()["sphere"], seed=seed)
        return measure_slope_response(press, rig.roi, thresholds, calibration_dir)


def _set_aside_partial(path: Path) -> None:
    partial = partial_path(path)
    if partial.exists():
        n = 1
        while partial.with_name(f"{partial.name}.{n}").exists():
            n += 1
        partial.rename(partial.with_name(f"{partial.name}.{n}"))


def pending_tasks(campaign: Campaign, manifest: Manifest, out_dir: Path, *, rig_path: Path,
                  indenters_path: Path, limit: int | None = None) -> list[VirtualTask]:
    """One task per recording not yet complete (at most ``limit``), in run order."""
    if campaign.source is None:
        raise LabrigError("a virtual-time campaign needs its campaign file (workers load it)")
    todo = [p for p in campaign.plans if not manifest.done(p, out_dir)]
    if limit is not None:
        todo = todo[: max(0, limit)]
    return [VirtualTask(str(Path(campaign.source).resolve()), str(Path(rig_path).resolve()),
                        str(Path(indenters_path).resolve()), str(out_dir.resolve()), p.id) for p in todo]


def run_virtual_campaign(campaign: Campaign, manifest: Manifest, tasks: list[VirtualTask], *, workers: int | None,
                         scheduler: str | None, take: Callable[[Outcome], None] | None = None) -> list[Outcome]:
    """Run ``tasks`` (local processes, or a Dask cluster at ``scheduler``); the manifest records each
    outcome as it returns, then ``take`` sees it. A task that raised counts as ``failed``."""
    rig = load_rig(tasks[0].rig_path) if tasks else None
    indenters = load_indenters(tasks[0].indenters_path) if tasks else {}
    by_id = {p.id: p for p in campaign.plans}
    if rig is not None:  # build each table once here, not in every worker at the same time
        directions: dict[str, set[float]] = {}
        for task in tasks:
            spec = by_id[task.plan_id].spec
            directions.setdefault(spec.indenter, set()).add(spec.shear_direction_deg)
        for name, degs in directions.items():
            prepare_contact_tables(rig, indenters[name], sorted(degs))
    outcomes: list[Outcome] = []

    def returned(index: int, outcome: Outcome) -> None:
        manifest.record(outcome, made_by=MADE_BY_VIRTUAL_TIME)
        outcomes.append(outcome)
        if take is not None:
            take(outcome)

    results = run_tasks(record_task, tasks, workers=workers, scheduler=scheduler, use_cache=False,
                        raise_on_error=False, on_result=returned)
    for failure in results.failures:
        outcome = Outcome(tasks[failure.index].plan_id, "failed", f"{failure.error}: {failure.message}", "", "", 0.0)
        returned(failure.index, outcome)
    return outcomes
