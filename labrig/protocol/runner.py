"""Run one probing sequence through the real drivers into one recording, safely.

:class:`ProbeRunner` plays the probing procedure (:mod:`labrig.protocol.procedure`: Approach,
Normal Down to a depth or a force, Wait, Shear, Wait, Shear Opposite, Wait, Normal Up, Retract)
on the drivers of an open :class:`RigSession`. At each phase start the
CNC output wired to the camera's trigger input toggles (M8/M9), so the
recording carries hardware sync edges, and the phase is logged on the host
clock. Before any move every target is checked against the workspace and every
speed against the controller's max rates (``$110-$112``); during
the run the :class:`~labrig.protocol.safety.ForceMonitor` holds the machine
within one F/T sample of a force over its limit, and every wait has a timeout.

Stopping: a tripped force limit, a GRBL alarm, a lost device or a second
Ctrl-C hold the machine at once, flush its plan and retract along the gel
normal; a first Ctrl-C lets the current phase finish, then goes up. The
recording is finalized either way (``aborted`` with the reason).
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.cache import sha256_of
from labrig.calibration.registration_file import gel_pose
from labrig.config import RigConfig
from labrig.devices.grbl import Grbl, GrblAlarm, GrblError, GrblTimeout
from labrig.errors import LabrigError
from labrig.frames import Pose
from labrig.indenters import Indenter, indenter_toml
from labrig.protocol.feedback import EstimateFeedback, ForceReading
from labrig.protocol.force_loop import CONTROL_STREAM, ForceLoop, HeldMove
from labrig.protocol.plan import ProbePlan
from labrig.protocol.preflight import checked_plan
from labrig.protocol.procedure import (
    MOVE_MARGIN_S,
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
from labrig.protocol.realtime import CAMERA_BEHIND_LIMIT_S, Shortfall
from labrig.protocol.routing import put_control
from labrig.protocol.safety import SafetyError, SpeedLimits, StopRequest
from labrig.protocol.session import NS_PER_US, TWIN_PATIENCE_S, RigSession
from labrig.protocol.spec import ProbeSpec
from labrig.recording import RecordingMetadata, RecordingWriter
from labrig.recording.schema import EXIT_ABORTED, EXIT_COMPLETE
from labrig.sim.faults import RigFault
from labrig.sim.truth import truth_streams

F64 = npt.NDArray[np.float64]

CAMERA_SHORTFALL_US = round(CAMERA_BEHIND_LIMIT_S * 1e6)  # a camera stream ending this much before the run's end is reported
#: A controller's time from receiving an output line to switching the output, us (GRBL's parse).
OUTPUT_EXECUTE_US = 250.0
#: While the machine dwells, the camera trigger output toggles this often, s (in pairs, so each
#: phase keeps its level): edges for the camera clock fit beside the phase starts. On a loaded
#: host some lines reach the controller late and their edges lie below the fit; the more edges,
#: the more prompt ones for the fit to rest on (a 4 s wait adds 14).
SYNC_EDGE_INTERVAL_S = 0.25


@dataclass(frozen=True)
class RunProgress:
    """What a run is doing now: phase, depth below the contact point (mm, 0 before contact),
    tared force (N, sensor axes), camera events so far and their rate over the last report."""

    phase: str
    force_n: tuple[float, float, float]
    camera_events: int
    depth_mm: float = 0.0
    event_rate_hz: float = 0.0


@dataclass
class RunResult:
    """What one probing run did (host times: recording us)."""

    path: Path
    exit_status: str
    reason: str = ""
    phases: list[str] = field(default_factory=list)
    contact_mm: tuple[float, float, float] | None = None
    peak_force_n: tuple[float, float, float] = (0.0, 0.0, 0.0)
    wall_s: float = 0.0
    #: What fell behind real time, by how much (stored in the recording too).
    shortfall: Shortfall = field(default_factory=Shortfall)


class _Abort(Exception):
    """Ends a run's sequence. ``late``: a device missed a deadline (on the virtual rig: its twin was starved)."""

    def __init__(self, reason: str, hold: bool, late: bool = False) -> None:
        super().__init__(reason)
        self.reason = reason
        self.hold = hold
        self.late = late


#: Why a run whose loop reads the event sensor cannot be recorded without the live pipeline.
EVENTS_NEED_THE_PIPELINE = ('[control] feedback = "events" holds the force on the event sensor\'s estimate, which needs '
                            "the live pipeline beside the run: run it with `labrig run --live --protocol FILE`, or in "
                            "virtual time (`labrig campaign --virtual-time`)")


class ProbeRunner:
    """Runs :class:`ProbeSpec` s on an open :class:`RigSession` for one mounted indenter."""

    def __init__(
        self,
        session: RigSession,
        rig: RigConfig,
        indenter: Indenter,
        *,
        gel_in_machine: Pose,
        stop: StopRequest | None = None,
        progress: Callable[[RunProgress], None] | None = None,
        on_step: Callable[[Step], None] | None = None,
    ) -> None:
        """``on_step`` sees every step of the procedure before it is played (a log, a test)."""
        self.session = session
        self.rig = rig
        self.indenter = indenter
        self.gel_in_machine = gel_in_machine
        self.stop = stop or StopRequest()
        self.progress = progress
        self.on_step = on_step
        self.limits = session.limits.for_indenter(indenter.max_normal_force_n, indenter.max_shear_force_n)
        #: The event sensor's estimate, filled by the live pipeline beside the run (``feedback = "events"``).
        self.estimate: EstimateFeedback | None = None
        self._writer: RecordingWriter | None = None
        self._phases: list[str] = []
        self._output_level = 0
        self._plan: ProbePlan | None = None
        self._contact: F64 | None = None
        self._last_held: HeldMove | None = None  # the held move before, on this contact
        self._hold_on_halt = False
        self._last_report = (0.0, 0)
        # A twin on a loaded host may stall for seconds; a real machine's moves keep their margin.
        self._patience_s = TWIN_PATIENCE_S if session.virtual else 0.0
        self._rig_faults_from_us = 0  # host us: the virtual rig's faults from then on abort the run

    @classmethod
    def for_session(cls, session: RigSession, *, stop: StopRequest | None = None,
                    progress: Callable[[RunProgress], None] | None = None) -> ProbeRunner:
        """A runner for the session's mounted indenter at the rig's gel pose: the registration
        (``rig-registration.toml`` next to the rig file) once calibrated, else the nominal pose."""
        if session.indenter is None:
            raise LabrigError("the rig session names no mounted indenter")
        return cls(session, session.rig, session.indenter, gel_in_machine=gel_pose(session.rig), stop=stop,
                   progress=progress)

    @property
    def grbl(self) -> Grbl:
        assert self.session.grbl is not None
        return self.session.grbl

    # -- one run ------------------------------------------------------------------------------

    def check(self, spec: ProbeSpec) -> ProbePlan:
        """Everything that can be refused before moving (raises SafetyError with all problems)."""
        return checked_plan(spec, self.rig, self.indenter, self.gel_in_machine, self.limits)

    def _check_speeds(self, spec: ProbeSpec) -> None:
        """The run's speeds against the controller's max rates (``$110-$112``, read at connect): a
        faster speed would silently run at the max rate, so it is refused before moving."""
        limits = SpeedLimits.of_grbl(self.grbl.settings)
        if limits is not None:
            limits.check(spec)

    def run(self, spec: ProbeSpec, out: str | Path, *, protocol_toml: str = "", extra: dict[str, Any] | None = None,
            overwrite: bool = False) -> RunResult:
        """Travel above the location, tare, record the sequence, retract. Raises before moving
        if the plan is unsafe; otherwise always returns a finalized recording."""
        if spec.reads_events and self.estimate is None:
            raise LabrigError(EVENTS_NEED_THE_PIPELINE)
        plan = self.check(spec)
        self._check_speeds(spec)
        out = Path(out)
        if out.exists() and not overwrite:
            raise SafetyError(f"{out} exists; choose another name or allow overwriting")
        t_start = time.perf_counter()
        self._rig_faults_from_us = self.session.clock.now_ns() // NS_PER_US
        self._travel_to_start(plan)
        self.session.tare()
        writer = self._open_writer(out, spec, protocol_toml, extra)
        result = RunResult(out, EXIT_COMPLETE)
        late_twin = ""
        self._plan, self._contact = plan, None
        try:
            self._play(probe(plan, self.indenter.max_depth_mm))
        except _Abort as abort:
            result.exit_status, result.reason = EXIT_ABORTED, abort.reason
            if abort.late and self.session.virtual:
                late_twin = abort.reason
            self._hold_on_halt = abort.hold
            try:
                self._play(recovery(plan))
            except (GrblError, _Abort) as exc:
                result.reason += f"; the retract failed too ({exc}): check the machine before the next run"
        finally:
            if self._contact is not None:
                result.contact_mm = (float(self._contact[0]), float(self._contact[1]), float(self._contact[2]))
            end_ns = self.session.clock.now_ns()
            writer.phase_end((end_ns - writer.t0_host_ns) // NS_PER_US)
            behind_us = self.session.end(end_ns)
            if behind_us > CAMERA_SHORTFALL_US:
                result.reason = "; ".join(filter(None, [result.reason, (
                    f"the camera stream stops {behind_us / 1e6:.2f} s before the run's end (the camera fell "
                    "behind and stalled): the events after that are missing")]))
            result.shortfall = Shortfall(behind_us / 1e6, self.session.ft_max_gap_us / 1e6, late_twin)
            self._writer = None
            recording = writer.close(result.exit_status, result.reason, attrs=result.shortfall.attrs())
            result.path = recording.path
            result.phases = list(self._phases)
            result.peak_force_n = tuple(float(v) for v in self.session.monitor.peak_n)  # type: ignore[assignment]
            result.wall_s = time.perf_counter() - t_start
        return result

    # -- playing the procedure on the drivers ------------------------------------------------------

    def _play(self, procedure: Procedure) -> Any:
        try:
            return play(procedure, self._execute, self.on_step)
        except ProcedureAbort as abort:
            raise _Abort(abort.reason, hold=False) from None

    def _execute(self, step: Step) -> Any:
        """One step of a procedure on the drivers; its reply."""
        match step:
            case Phase():
                if step.stoppable and self.stop.level >= 1:
                    raise _Abort("stopped by the user (Ctrl-C)", hold=False)
                self._phase(step.name, recovering=step.recovering)
            case Move():
                self._last_held = None  # the tool leaves the held moves' contact state
                self._move(step.target_mm, step.speed_mm_s)
            case MoveUntil():
                return self._move_until(step)
            case MoveHolding():
                return self._move_holding(step)
            case Dwell():
                self._dwell(step.seconds)
            case Position():
                return np.asarray(self.grbl.status().position_mm, dtype=np.float64)
            case Contact():
                self._contact = np.asarray(step.position_mm, dtype=np.float64)
                self._last_held = None  # a new contact
            case Halt():
                self._halt()
            case Retreat():
                self.grbl.move_to(*step.target_mm, feed_mm_min=step.speed_mm_s * 60, machine=True)
                self.grbl.wait_idle(timeout_s=step.limit_s + self._patience_s)
        return None

    def _move_until(self, step: MoveUntil) -> bool:
        """Jog toward the target with the monitor armed to cancel the jog once the condition holds."""
        here = np.asarray(self.grbl.status().position_mm, dtype=np.float64)
        until = step.until
        reached = self.session.monitor.arm(until.kind, until.threshold_n, self.grbl.jog_cancel,
                                           average_samples=until.average_samples)
        self.grbl.jog(*step.target_mm, feed_mm_min=step.speed_mm_s * 60, relative=False, machine=True)
        self._wait_motion(move_limit_s(float(np.linalg.norm(np.asarray(step.target_mm) - here)), step.speed_mm_s))
        self.session.monitor.disarm()
        return reached.is_set()

    # -- motion with checks -----------------------------------------------------------------------

    def _move(self, target: Point, speed_mm_s: float) -> None:
        here = np.asarray(self.grbl.status().position_mm, dtype=np.float64)
        distance = float(np.linalg.norm(np.asarray(target) - here))
        self._checked(lambda: self.grbl.move_to(*target, feed_mm_min=speed_mm_s * 60, machine=True))
        self._wait_motion(move_limit_s(distance, speed_mm_s))

    def _move_holding(self, step: MoveHolding) -> str | None:
        """The held move in absolute jog segments, one sent per segment's span on the host clock with the next
        already queued (GRBL's planner runs them without stopping, and a jog cancel drops them); the loop reads the
        feedback's newest normal force (the F/T's tared |Fz|, or the live pipeline's estimate). A host late by a
        segment lets the queue run dry: the machine stops and waits."""
        here = np.asarray(self.grbl.status().position_mm, dtype=np.float64)
        held = HeldMove(here, step.target_mm, step.normal, step.speed_mm_s, ForceLoop(step.hold.target_n, step.hold.params),
                        step.deepest_mm, accel_mm_s2=self.grbl.limits.accel_along_mm_s2(step.normal),
                        duration_s=step.duration_s, until_tangential_n=step.until_tangential_n, slip=step.slip,
                        follows=self._last_held)
        period_s = step.hold.params.segment_s
        clock = self.session.clock
        feedback: ForceReading = self.session.monitor
        if step.hold.feedback == "events":
            assert self.estimate is not None  # check() refused the run otherwise
            feedback = self.estimate
        queued = 0
        next_s = time.monotonic()
        while True:
            self._check_faults()
            force_n, t_ns = feedback.normal_reading()
            now_ns = clock.now_ns()
            reading_ns = now_ns if t_ns is None else t_ns
            now_us = self.grbl.now_us()
            here_mm, reading_mm = self.grbl.pose_at(np.array([now_us, now_us - (now_ns - reading_ns) / 1000]))
            reading_s = -math.inf if t_ns is None else reading_ns / 1e9  # no reading yet: the loop stops
            out = held.next_segment(now_ns / 1e9, force_n, here_mm, reading_s, reading_mm, feedback.contact_reading())
            if isinstance(out, str):
                self.grbl.jog_cancel()
                self._wait_motion(MOVE_MARGIN_S)
                return out
            if out is None:
                if held.ended_by is not None:  # a tangential target or a slip: stop here, and say so
                    self.grbl.jog_cancel()
                    if self._writer is not None:
                        put_control(self._writer, now_ns, held, force_n, now_ns - reading_ns, here_mm)
                break
            end, feed_mm_min = out
            self._checked(partial(self.grbl.jog, *end, feed_mm_min=feed_mm_min, relative=False, machine=True))
            if self._writer is not None:
                put_control(self._writer, now_ns, held, force_n, now_ns - reading_ns, end)
            queued += 1
            if queued >= 2:  # one segment ahead
                next_s += period_s
                time.sleep(max(0.0, next_s - time.monotonic()))
            else:
                next_s = time.monotonic()
        self._last_held = held
        self._wait_motion(move_limit_s(0.0, step.speed_mm_s))
        return None

    def _wait_motion(self, limit_s: float) -> None:
        """Wait for the machine to finish its moves, checking for faults; ``limit_s`` before the twin's patience."""
        allowed_s = limit_s + self._patience_s
        deadline = time.monotonic() + allowed_s
        while True:
            self._check_faults()
            try:
                self.grbl.wait_idle(timeout_s=0.2)
                self._check_faults()
                return
            except GrblTimeout:
                if time.monotonic() > deadline:
                    raise _Abort(f"the move did not finish within {allowed_s:.1f} s "
                                 f"(GRBL {self.grbl.state})", hold=True, late=True) from None
            except GrblError as exc:
                self._check_faults()
                raise _Abort(f"GRBL: {exc}", hold=False) from exc
            self._report()

    def _dwell(self, seconds: float) -> None:
        """Hold still for ``seconds``, toggling the trigger output in pairs (SYNC_EDGE_INTERVAL_S)."""
        start = time.monotonic()
        end = start + seconds
        pairs = max(0, math.floor((seconds - SYNC_EDGE_INTERVAL_S / 2) / (2 * SYNC_EDGE_INTERVAL_S)))
        edges = [start + (k + 1) * SYNC_EDGE_INTERVAL_S for k in range(2 * pairs)]
        while (left := end - time.monotonic()) > 0:
            self._check_faults()
            if edges and time.monotonic() >= edges[0]:
                edges.pop(0)
                self._toggle_output()
            pause = min(left, 0.02)
            if edges:
                pause = min(pause, max(0.0, edges[0] - time.monotonic()))
            time.sleep(pause)
            self._report()

    def _checked(self, action: Callable[[], Any]) -> Any:
        self._check_faults()
        try:
            return action()
        except GrblError as exc:
            self._check_faults()
            raise _Abort(f"GRBL: {exc}", hold=False, late=isinstance(exc, GrblTimeout)) from exc

    def _check_faults(self) -> None:
        session = self.session
        trip = session.monitor.trip
        if trip is not None:
            raise _Abort(f"force limit: {trip.reason}", hold=True)
        if self.stop.level >= 2:
            raise _Abort("stopped by the user (second Ctrl-C): held and retracted", hold=True)
        if session.ft is not None and session.ft.error is not None:
            raise _Abort(f"F/T sensor lost: {session.ft.error}", hold=True)
        if session.camera is not None and session.camera.error is not None:
            raise _Abort(f"camera lost: {session.camera.error}", hold=True)
        if session.world is not None and session.world.error is not None:
            raise _Abort(f"virtual rig failed: {session.world.error!r}", hold=True)
        fault = self._new_rig_fault()
        if fault is not None:
            self._rig_faults_from_us = fault.t_host_us + 1
            raise _Abort(f"the virtual rig refused a request: {fault.message}", hold=True)

    def _new_rig_fault(self) -> RigFault | None:
        """The first request the virtual rig refused during this run (it stays up; see LiveWorld.faults)."""
        faults: list[RigFault] = getattr(self.session.world, "faults", [])
        return next((f for f in faults if f.t_host_us >= self._rig_faults_from_us), None)

    def _report(self) -> None:
        if self.progress is None or not self._phases:
            return
        now, events = time.monotonic(), self.session.camera_events
        last_t, last_events = self._last_report
        if now - last_t < 0.1:
            return
        rate = (events - last_events) / (now - last_t) if last_t else 0.0
        self._last_report = (now, events)
        depth = 0.0
        sample = self.grbl.last_sample
        if self._contact is not None and self._plan is not None and sample is not None:
            depth = max(0.0, float((np.asarray(sample.position_mm) - self._contact) @ self._plan.down))
        f = self.session.monitor.last_n
        self.progress(RunProgress(self._phases[-1], (float(f[0]), float(f[1]), float(f[2])), events, depth, rate))

    # -- phases, travel, recovery -------------------------------------------------------------------

    def _phase(self, name: str, *, recovering: bool = False) -> None:
        """Toggle the camera trigger and log the phase start (after queued motion has finished).

        ``recovering``: after an abort, faults are known already; the phase is logged even if
        the trigger output cannot be switched."""
        writer = self._writer
        assert writer is not None
        t_us = writer.host_us()
        try:
            t_us = self._toggle_output(recovering=recovering)
        except GrblError:
            if not recovering:
                raise
        writer.phase_begin(name, t_us)
        self._phases.append(name)
        self._report()

    def _toggle_output(self, *, recovering: bool = False) -> int:
        """Toggle the camera trigger output; log the edge; its recording host time (us)."""
        writer = self._writer
        assert writer is not None
        self._output_level ^= 1
        level = self._output_level
        edge = self.grbl.set_output(bool(level)) if recovering else self._checked(lambda: self.grbl.set_output(bool(level)))
        # The output switches once the line has arrived (motion finished before it was sent) and
        # before the ack goes out: the clock fit rests on the earliest times, within the latest.
        earliest, latest = edge.bounds_us(self.grbl.byte_us, OUTPUT_EXECUTE_US)
        t0_us = writer.t0_host_ns // NS_PER_US
        writer.put("trigger_out", t_host_us=earliest - t0_us, polarity=level, t_latest_host_us=latest - t0_us)
        return earliest - t0_us

    def _travel_to_start(self, plan: ProbePlan) -> None:
        """Up to the travel height, across, down to the approach start (not recorded)."""
        state = self.grbl.status().state
        if state.startswith("Alarm"):
            raise SafetyError("GRBL is in Alarm: home it (labrig cnc home) or, if its position is known, unlock it")
        self.session.monitor.trip = None
        self.session.monitor.peak_n = np.zeros(3)
        speed = plan.spec.retract_speed_mm_s
        here = np.asarray(self.grbl.status().position_mm, dtype=np.float64)
        up = here.copy()
        up[2] = max(here[2], plan.clearance_mm[2])
        try:
            for target in (up, plan.clearance_mm, plan.approach_start_mm):
                self.grbl.move_to(*target.tolist(), feed_mm_min=speed * 60, machine=True)
                self.grbl.wait_idle(timeout_s=move_limit_s(float(np.linalg.norm(target - here)), speed) + self._patience_s)
                here = target
        except GrblError as exc:
            raise SafetyError(f"travelling to the approach start failed: {exc}") from exc

    def _halt(self) -> None:
        """After an abort: hold the machine to a stop and flush its plan (a hold abort), or let it
        finish its move; unlock it if it is in Alarm."""
        grbl = self.grbl
        if self._hold_on_halt:
            with contextlib.suppress(GrblError):
                grbl.feed_hold()
            deadline = time.monotonic() + 3.0
            while time.monotonic() < deadline:
                try:
                    if grbl.status().state in ("Hold:0", "Idle", "Alarm"):
                        break
                except GrblAlarm:
                    break
                except GrblError:
                    pass
                time.sleep(0.02)
            grbl.soft_reset()  # flush the plan; held to a stop first, the position is kept
        else:
            try:
                grbl.wait_idle(timeout_s=10)
            except GrblAlarm:
                grbl.soft_reset()
            except GrblError:
                pass
        if grbl.status().state == "Alarm":
            grbl.unlock()

    def _open_writer(self, out: Path, spec: ProbeSpec, protocol_toml: str, extra: dict[str, Any] | None) -> RecordingWriter:
        info = {"virtual_rig": self.session.virtual, "made_by": "drivers", "seed": self.session.seed,
                "location_mm": list(spec.location_mm),
                "tare_n_nm": list(self.session.tare_n), "calibration": _calibration_files(self.rig), **(extra or {})}
        info.update(spec.control_record())
        metadata = RecordingMetadata(indenter=self.indenter.name, protocol_toml=protocol_toml, rig_toml=self.rig.text,
                                     indenter_toml=indenter_toml(self.indenter), extra=info)
        streams = truth_streams(len(self.rig.markers.rest_positions_mm())) if self.session.virtual else ()
        if spec.holds_force:
            streams = (*streams, CONTROL_STREAM)
        if out.exists():
            out.unlink()
        writer = RecordingWriter(out, metadata, clock=self.session.clock, extra_streams=streams).open()
        self._writer = writer
        self._phases = []
        self.session.begin(writer)
        return writer


def _calibration_files(rig: RigConfig) -> str:
    """JSON {path: SHA-256} of the calibration files next to the rig file (the rig file itself excluded)."""
    files = {}
    for path in sorted(rig.path.parent.glob("*.toml")):
        if path.resolve() != rig.path.resolve():
            files[str(path)] = sha256_of(path)
    return json.dumps(files)
