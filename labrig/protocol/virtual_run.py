"""One probing run simulated in virtual time, into a recording shaped like a through-driver one.

:func:`record_virtual` plays the probing procedure (:mod:`labrig.protocol.procedure`: the runner's
phases, trigger edges, contact search, force targets and recovery, after the same checks
(:mod:`labrig.protocol.preflight`) and under the same force limits) on the virtual rig's devices
stepped on a manual clock (:class:`~labrig.sim.offline.OfflineRig`), and
routes their data into the recording as the rig session routes the drivers'
(:mod:`labrig.protocol.routing`). Nothing waits on the wall clock, so the recording is the same
for the same inputs and seed, whatever the load, and takes as long as the CPU needs.

The recording says how it was made: root attribute ``extra_made_by`` = ``virtual-time`` (a
through-driver campaign writes ``drivers``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.calibration.registration_file import gel_pose
from labrig.config import RigConfig
from labrig.devices.bota_stream import FtSample
from labrig.indenters import Indenter, indenter_toml
from labrig.physics.grid import network_grid_gel_mm
from labrig.pipeline.runtime import Pipeline
from labrig.protocol.event_estimate import EventEstimator, estimate_pipeline
from labrig.protocol.feedback import EstimateFeedback, ForceReading
from labrig.protocol.force_loop import CONTROL_STREAM, ForceLoop, HeldMove
from labrig.protocol.plan import ProbePlan
from labrig.protocol.preflight import checked_plan
from labrig.protocol.procedure import (
    Contact,
    Dwell,
    Halt,
    Move,
    MoveHolding,
    MoveUntil,
    Phase,
    Point,
    Position,
    Procedure,
    ProcedureAbort,
    Retreat,
    Step,
    move_limit_s,
    play,
    probe,
    recovery,
)
from labrig.protocol.rigfile import safety_limits
from labrig.protocol.routing import put_chunk, put_control, put_ft_rows, put_gcode
from labrig.protocol.runner import RunResult
from labrig.protocol.safety import ForceMonitor, SafetyLimits, SpeedLimits
from labrig.protocol.session import NS_PER_US
from labrig.protocol.spec import ProbeSpec
from labrig.recording import RecordingMetadata, RecordingWriter
from labrig.recording.schema import EXIT_ABORTED, EXIT_COMPLETE
from labrig.sim.live import put_truth_rows, truth_rows
from labrig.sim.offline import CAMERA_LOOP_RENDER_LAG_US, RENDER_LAG_US, OfflineRig, OfflineSinks
from labrig.sim.truth import truth_streams

F64 = npt.NDArray[np.float64]
MADE_BY_VIRTUAL_TIME = "virtual-time"
MADE_BY_DRIVERS = "drivers"
#: The writer's flush interval, wall s: each flush re-compresses the open chunks (most of the writer's CPU), and a
#: virtual-time recording whose process dies is made again from its seed, not resumed.
WRITER_FLUSH_S = 2.0
#: F/T samples gathered per writer put (~80 ms at 800 Hz; the rows are the same as one put each).
FT_BATCH = 64
US = 1_000_000


class _Abort(Exception):
    pass


def record_virtual(spec: ProbeSpec, out: str | Path, rig: RigConfig, indenter: Indenter, *, seed: int = 0,
                   protocol_toml: str = "", extra: dict[str, Any] | None = None,
                   on_step: Callable[[Step], None] | None = None, calibration_dir: str | Path | None = None,
                   model: str | Path | None = None) -> RunResult:
    """Simulate the probing run ``spec`` in virtual time into ``out``; raises SafetyError before any
    move if the plan is unsafe (the runner's checks), else returns the finalized recording.

    ``on_step`` sees every step of the procedure before it is played (a log, a test). A run whose force loop reads
    the event sensor (``feedback = "events"``) runs the pipeline beside it on the camera's chunks, with the rig's
    calibration (``calibration_dir``, default the rig file's folder) and the depth network ``model`` (default: as
    ``labrig run``)."""
    wall0 = time.perf_counter()
    limits = safety_limits(rig).for_indenter(indenter.max_normal_force_n, indenter.max_shear_force_n)
    plan = checked_plan(spec, rig, indenter, gel_pose(rig), limits)
    SpeedLimits.of_rig(rig).check(spec)
    pipeline = estimate_pipeline(rig, calibration_dir, model) if spec.reads_events else None
    out = Path(out)
    if out.exists():
        out.unlink()
    try:
        result = _VirtualRun(plan, rig, indenter, limits, seed, on_step, pipeline).record(out, protocol_toml, extra or {})
    finally:
        if pipeline is not None:
            pipeline.close()
    result.wall_s = time.perf_counter() - wall0
    return result


class _VirtualRun:
    """The executor in virtual time: plays the procedure's steps on an :class:`OfflineRig`."""

    def __init__(self, plan: ProbePlan, rig: RigConfig, indenter: Indenter, limits: SafetyLimits, seed: int,
                 on_step: Callable[[Step], None] | None = None, pipeline: Pipeline | None = None) -> None:
        self.plan, self.rig, self.indenter, self.limits, self.seed = plan, rig, indenter, limits, seed
        self.on_step = on_step
        self.contact: F64 | None = None
        self._last_held: HeldMove | None = None  # the held move before, on this contact
        self.writer: RecordingWriter | None = None
        self.grid_gel: F64 | None = None
        self.devices = OfflineRig(rig, indenter, seed=seed, start_tool_mm=plan.approach_start_mm, sinks=OfflineSinks(
            ft=self._on_ft, cnc=self._on_cnc, gcode=self._on_gcode, camera=self._on_chunk, rig_chunk=self._on_rig_chunk),
            render_lag_us=RENDER_LAG_US if pipeline is None else CAMERA_LOOP_RENDER_LAG_US)
        self.monitor = ForceMonitor(limits, on_trip=self.devices.feed_hold)
        self.estimator = None if pipeline is None else EventEstimator(pipeline, EstimateFeedback(),
                                                                      self.devices.host_ns_of_camera)
        self.feedback: ForceReading = self.monitor if self.estimator is None else self.estimator.feedback
        self.level = 0
        self.phases: list[str] = []
        self._ft_rows: list[FtSample] = []

    # -- routing (as RigSession routes the drivers' callbacks) -----------------------------------------

    def _on_ft(self, sample: FtSample) -> None:
        self.monitor.on_sample(sample.t_host_ns, sample.force_n)
        if self.writer is not None:
            self._ft_rows.append(sample)
            if len(self._ft_rows) >= FT_BATCH:
                self._flush_ft()

    def _flush_ft(self) -> None:
        """The F/T rows gathered so far into the writer, in one put (the same rows as one put each)."""
        if self.writer is not None and self._ft_rows:
            put_ft_rows(self.writer, self._ft_rows)
        self._ft_rows = []

    def _on_cnc(self, status: Any) -> None:
        if self.writer is not None:
            row = status.columns()
            row["t_host_us"] -= self.writer.t0_host_ns // NS_PER_US
            self.writer.put("cnc", **row)

    def _on_gcode(self, t_host_us: int, direction: int, line: bytes) -> None:
        if self.writer is not None:
            put_gcode(self.writer, t_host_us, direction, line)

    def _on_chunk(self, chunk: Any) -> None:
        if self.writer is not None:
            put_chunk(self.writer, chunk)
        if self.estimator is not None:
            self.estimator.on_chunk(chunk)

    def _on_rig_chunk(self, out: Any) -> None:
        if self.writer is not None:
            if self.grid_gel is None:
                self.grid_gel = network_grid_gel_mm(self.rig, self.devices.rig.camera)
            put_truth_rows(self.writer, truth_rows(out, self.grid_gel))

    # -- the run ----------------------------------------------------------------------------------------

    def record(self, out: Path, protocol_toml: str, extra: dict[str, Any]) -> RunResult:
        d = self.devices
        tare = d.power_on()
        self.monitor.peak_n = np.zeros(3)
        info = {"virtual_rig": True, "made_by": MADE_BY_VIRTUAL_TIME, "seed": self.seed,
                "location_mm": list(self.plan.spec.location_mm), "tare_n_nm": list(tare), **extra}
        info.update(self.plan.spec.control_record())
        metadata = RecordingMetadata(indenter=self.indenter.name, protocol_toml=protocol_toml, rig_toml=self.rig.text,
                                     indenter_toml=indenter_toml(self.indenter), extra=info)
        writer = RecordingWriter(out, metadata, clock=d.clock, flush_interval_s=WRITER_FLUSH_S, wake_on_put=False,
                                 extra_streams=truth_streams(len(self.rig.markers.rest_positions_mm()))
                                 + ((CONTROL_STREAM,) if self.plan.spec.holds_force else ())).open()
        self.writer = writer
        result = RunResult(out, EXIT_COMPLETE)
        try:
            self._play(probe(self.plan, self.indenter.max_depth_mm))
        except _Abort as abort:
            result.exit_status, result.reason = EXIT_ABORTED, str(abort)
            self._play(recovery(self.plan))
        finally:
            if self.contact is not None:
                result.contact_mm = (float(self.contact[0]), float(self.contact[1]), float(self.contact[2]))
            writer.phase_end(d.now_us - writer.t0_host_ns // NS_PER_US)
            d.finish()
            self._flush_ft()
            self.writer = None
            recording = writer.close(result.exit_status, result.reason)
            result.path = recording.path
            result.phases = list(self.phases)
            result.peak_force_n = tuple(float(v) for v in self.monitor.peak_n)  # type: ignore[assignment]
        return result

    def _play(self, procedure: Procedure) -> None:
        try:
            play(procedure, self._execute, self.on_step)
        except ProcedureAbort as abort:
            raise _Abort(abort.reason) from None

    def _execute(self, step: Step) -> Any:
        """One step of a procedure in virtual time; its reply."""
        d = self.devices
        match step:
            case Phase():
                self._phase(step.name)
            case Move():
                self._last_held = None  # the tool leaves the held moves' contact state
                self._move(step.target_mm, step.speed_mm_s)
            case MoveUntil():
                reached = self.monitor.arm(step.until.kind, step.until.threshold_n, d.jog_cancel,
                                           average_samples=step.until.average_samples)
                self._move(step.target_mm, step.speed_mm_s, jog=True)
                self.monitor.disarm()
                return reached.is_set()
            case MoveHolding():
                return self._move_holding(step)
            case Dwell():
                d.dwell(round(step.seconds * US), stop=self._tripped)
                self._check_trip()
            case Position():
                return np.asarray(d.timeline.position_mm, dtype=np.float64)
            case Contact():
                self.contact = np.asarray(step.position_mm, dtype=np.float64)
                self._last_held = None  # a new contact
            case Halt():
                d.feed_hold()
                d.dwell(500_000)
                d.flush()
            case Retreat():
                d.move(step.target_mm, step.speed_mm_s * 60)
                d.wait_idle(round(step.limit_s * US))
        return None

    def _move_holding(self, step: MoveHolding) -> str | None:
        """The held move in jog segments, one commanded per segment's span with the next already queued (GRBL's
        planner runs them without stopping); the loop reads its feedback's newest normal force (the F/T's tared |Fz|,
        or the event pipeline's estimate)."""
        d = self.devices
        timeline = d.timeline
        held = HeldMove(timeline.tail_mm, step.target_mm, step.normal, step.speed_mm_s,
                        ForceLoop(step.hold.target_n, step.hold.params), step.deepest_mm,
                        accel_mm_s2=timeline.limits.accel_along_mm_s2(step.normal), duration_s=step.duration_s,
                        until_tangential_n=step.until_tangential_n, slip=step.slip,
                        follows=self._last_held)
        segment_us = round(step.hold.params.segment_s * US)
        queued = 0
        while True:
            force_n, t_ns = self.feedback.normal_reading()
            now_us = d.now_us
            reading_us = -math.inf if t_ns is None else t_ns / 1000
            out = held.next_segment(now_us / US, force_n, timeline.position_at(now_us), reading_us / US,
                                    timeline.position_at(min(max(reading_us, 0), now_us)), self.feedback.contact_reading())
            if isinstance(out, str):
                d.jog_cancel()
                d.dwell(segment_us)
                return out
            if out is None:
                if held.ended_by is not None:  # a tangential target or a slip: stop here, and say so
                    d.jog_cancel()
                    if self.writer is not None:
                        put_control(self.writer, now_us * 1000, held, force_n, round((now_us - reading_us) * 1000),
                                    timeline.position_at(now_us))
                break
            end, feed_mm_min = out
            d.move(end, feed_mm_min, jog=True)
            if self.writer is not None:
                put_control(self.writer, now_us * 1000, held, force_n, round((now_us - reading_us) * 1000), end)
            queued += 1
            if queued >= 2:  # one segment ahead
                d.dwell(segment_us, stop=self._tripped)
                self._check_trip()
        self._last_held = held
        self._wait(move_limit_s(0.0, step.speed_mm_s))
        return None

    def _phase(self, name: str) -> None:
        writer = self.writer
        assert writer is not None
        self.level ^= 1
        t_edge = self.devices.set_output(bool(self.level)) - writer.t0_host_ns // NS_PER_US
        writer.put("trigger_out", t_host_us=t_edge, polarity=self.level, t_latest_host_us=t_edge)
        writer.phase_begin(name, t_edge)
        self.phases.append(name)

    def _tripped(self) -> bool:
        return self.monitor.trip is not None

    def _check_trip(self) -> None:
        trip = self.monitor.trip
        if trip is not None:
            raise _Abort(f"force limit: {trip.reason}")

    def _move(self, target: Point, speed_mm_s: float, *, jog: bool = False) -> None:
        d = self.devices
        distance = float(np.linalg.norm(np.asarray(target) - np.asarray(d.timeline.tail_mm)))
        d.move(target, speed_mm_s * 60, jog=jog)
        self._wait(move_limit_s(distance, speed_mm_s))

    def _wait(self, limit_s: float) -> None:
        status = self.devices.wait_idle(round(limit_s * US), stop=self._tripped)
        self._check_trip()
        if status is None:
            raise _Abort(f"the move did not finish within {limit_s:.1f} s")
