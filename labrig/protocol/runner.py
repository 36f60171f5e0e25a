"""Run one probing sequence through the real drivers into one recording, safely.

Approach (search for contact), Normal Down (to a depth or a force), Wait,
Shear, Wait, Shear Opposite, Wait, Normal Up, Retract. At each phase start the
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
from labrig.protocol.plan import ProbePlan
from labrig.protocol.realtime import CAMERA_BEHIND_LIMIT_S, Shortfall
from labrig.protocol.safety import (
    SafetyError,
    SpeedLimits,
    StopRequest,
    check_location,
    check_targets,
    deepest_press_mm,
    depth_problem,
)
from labrig.protocol.session import NS_PER_US, TWIN_PATIENCE_S, RigSession
from labrig.protocol.spec import ProbeSpec
from labrig.recording import RecordingMetadata, RecordingWriter
from labrig.recording.schema import EXIT_ABORTED, EXIT_COMPLETE
from labrig.sim.faults import RigFault

F64 = npt.NDArray[np.float64]

#: Extra time allowed on top of a move's nominal duration, s.
MOVE_MARGIN_S = 5.0
CAMERA_SHORTFALL_US = round(CAMERA_BEHIND_LIMIT_S * 1e6)  # a camera stream ending this much before the run's end is reported
#: A force target is approached at the normal speed up to this fraction, then at FINE_SPEED_MM_S.
APPROACH_FRACTION = 0.7
FINE_SPEED_MM_S = 0.3
#: A controller's time from receiving an output line to switching the output, us (GRBL's parse).
OUTPUT_EXECUTE_US = 250.0
#: While the machine dwells, the camera trigger output toggles this often, s (in pairs, so each
#: phase keeps its level): edges for the camera clock fit beside the phase starts. On a loaded
#: host some lines reach the controller late and their edges lie below the fit; the more edges,
#: the more prompt ones for the fit to rest on (a 4 s wait adds 14).
SYNC_EDGE_INTERVAL_S = 0.25
#: F/T samples averaged for contact and force-target detection (noise 0.02 N -> 0.005 N).
DETECT_SAMPLES = 16


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
    ) -> None:
        self.session = session
        self.rig = rig
        self.indenter = indenter
        self.gel_in_machine = gel_in_machine
        self.stop = stop or StopRequest()
        self.progress = progress
        self.limits = session.limits.for_indenter(indenter.max_normal_force_n, indenter.max_shear_force_n)
        self._writer: RecordingWriter | None = None
        self._phases: list[str] = []
        self._output_level = 0
        self._plan: ProbePlan | None = None
        self._contact: F64 | None = None
        self._last_report = (0.0, 0)
        # A twin on a loaded host may stall for seconds; a real machine's moves keep their margin.
        self._move_margin_s = MOVE_MARGIN_S + (TWIN_PATIENCE_S if session.virtual else 0.0)
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
        if spec.indenter != self.indenter.name:
            raise SafetyError(f"the run needs the {spec.indenter} indenter but {self.indenter.name} is mounted")
        check_location(spec.location_mm, (self.rig.gel.size_x_mm, self.rig.gel.size_y_mm),
                       self.indenter.footprint_radius_mm, self.limits.gel_margin_mm)
        for value in (spec.depth_mm, spec.max_depth_mm):
            problem = None if value is None else depth_problem(value, self.indenter.name, self.indenter.max_depth_mm)
            if problem is not None:
                raise SafetyError(f"depth {problem}")
        if spec.force_n is not None and spec.force_n > self.limits.max_normal_force_n:
            raise SafetyError(f"force target {spec.force_n} N is over the normal force limit {self.limits.max_normal_force_n} N")
        plan = ProbePlan.build(spec, self.gel_in_machine, self.indenter, self.limits.clearance_mm)
        check_targets(plan.nominal_targets(self.indenter.max_depth_mm), self.limits)
        return plan

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
        try:
            result.contact_mm = self._sequence(plan, result)
        except _Abort as abort:
            result.exit_status, result.reason = EXIT_ABORTED, abort.reason
            if abort.late and self.session.virtual:
                late_twin = abort.reason
            try:
                self._recover(plan, hold=abort.hold)
            except (GrblError, _Abort) as exc:
                result.reason += f"; the retract failed too ({exc}): check the machine before the next run"
        finally:
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

    # -- the sequence -----------------------------------------------------------------------------

    def _sequence(self, plan: ProbePlan, result: RunResult) -> tuple[float, float, float]:
        spec = plan.spec
        self._plan, self._contact = plan, None
        self._phase("approach")
        contact = self._approach(plan)
        self._contact = contact
        result.contact_mm = (float(contact[0]), float(contact[1]), float(contact[2]))
        if self.stop.level >= 1:
            raise _Abort("stopped by the user (Ctrl-C)", hold=False)
        self._phase("normal_down")
        bottom = self._normal_down(plan, contact)
        steps: list[tuple[str, F64 | None, float]] = [("wait", None, spec.wait_s)]
        if spec.shear_mm > 0:
            steps += [("shear", plan.sheared_mm(bottom), spec.shear_speed_mm_s), ("wait", None, spec.wait_s),
                      ("shear_opposite", bottom, spec.shear_speed_mm_s), ("wait", None, spec.wait_s)]
        for name, target, value in steps:
            if self.stop.level >= 1:
                raise _Abort("stopped by the user (Ctrl-C)", hold=False)
            self._phase(name)
            if target is None:
                self._dwell(value)
            else:
                self._move(target, value)
        self._phase("normal_up")
        self._move(contact, spec.normal_speed_mm_s)
        self._phase("retract")
        self._move(contact - spec.retract_height_mm * plan.down, spec.retract_speed_mm_s)
        return result.contact_mm

    def _approach(self, plan: ProbePlan) -> F64:
        approach = plan.spec.approach
        reached = self.session.monitor.arm("contact", approach.contact_force_n, self.grbl.jog_cancel,
                                           average_samples=DETECT_SAMPLES)
        limit = plan.approach_limit_mm
        self.grbl.jog(*limit.tolist(), feed_mm_min=approach.speed_mm_s * 60, relative=False, machine=True)
        self._wait_motion(approach.max_travel_mm / approach.speed_mm_s)
        self.session.monitor.disarm()
        if not reached.is_set():
            raise _Abort(f"no contact within {approach.max_travel_mm} mm of the approach start "
                         f"(|Fz| stayed under {approach.contact_force_n} N): check the gel height in the rig's gel pose",
                         hold=False)
        return np.asarray(self.grbl.status().position_mm, dtype=np.float64)

    def _normal_down(self, plan: ProbePlan, contact: F64) -> F64:
        spec = plan.spec
        if spec.depth_mm is not None:
            self._move(plan.bottom_mm(contact), spec.normal_speed_mm_s)
            return plan.bottom_mm(contact)
        assert spec.force_n is not None
        cap = deepest_press_mm(self.indenter.max_depth_mm)
        max_depth = min(spec.max_depth_mm or cap, cap)
        deepest = plan.max_bottom_mm(contact, max_depth)
        # Fast to most of the force, then slowly: the jog's deceleration overshoots by
        # stiffness * v^2 / (2 a), about 1 N at 1.5 mm/s on this gel, 0.03 N at FINE_SPEED_MM_S.
        stages = [(APPROACH_FRACTION * spec.force_n, spec.normal_speed_mm_s),
                  (spec.force_n, min(spec.normal_speed_mm_s, FINE_SPEED_MM_S))]
        for threshold, speed in stages:
            here = np.asarray(self.grbl.status().position_mm, dtype=np.float64)
            reached = self.session.monitor.arm("force", threshold, self.grbl.jog_cancel, average_samples=DETECT_SAMPLES)
            self.grbl.jog(*deepest.tolist(), feed_mm_min=speed * 60, relative=False, machine=True)
            self._wait_motion(float(np.linalg.norm(deepest - here)) / speed)
            self.session.monitor.disarm()
            if not reached.is_set():
                raise _Abort(f"the force target {spec.force_n} N was not reached at the depth cap {max_depth} mm", hold=False)
        return np.asarray(self.grbl.status().position_mm, dtype=np.float64)

    # -- motion with checks -----------------------------------------------------------------------

    def _move(self, target: F64, speed_mm_s: float) -> None:
        here = np.asarray(self.grbl.status().position_mm, dtype=np.float64)
        distance = float(np.linalg.norm(np.asarray(target) - here))
        self._checked(lambda: self.grbl.move_to(*np.asarray(target).tolist(), feed_mm_min=speed_mm_s * 60, machine=True))
        self._wait_motion(distance / speed_mm_s)

    def _wait_motion(self, nominal_s: float) -> None:
        allowed_s = 1.5 * nominal_s + self._move_margin_s
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
                self.grbl.wait_idle(timeout_s=float(np.linalg.norm(target - here)) / speed * 1.5 + self._move_margin_s)
                here = target
        except GrblError as exc:
            raise SafetyError(f"travelling to the approach start failed: {exc}") from exc

    def _recover(self, plan: ProbePlan, hold: bool) -> None:
        """After an abort: stop, flush the plan, then go up along the gel normal and to the retract point."""
        grbl = self.grbl
        if hold:
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
        self._phase("retract", recovering=True)
        here = np.asarray(grbl.status().position_mm, dtype=np.float64)
        rise = float((here - plan.retract_mm) @ plan.down)  # distance below the retract plane along the normal
        speed = plan.spec.retract_speed_mm_s
        if rise > 0:
            above = here - rise * plan.down
            grbl.move_to(*above.tolist(), feed_mm_min=min(speed, plan.spec.normal_speed_mm_s * 2) * 60, machine=True)
            grbl.wait_idle(timeout_s=rise / speed * 3 + self._move_margin_s)
        grbl.move_to(*plan.retract_mm.tolist(), feed_mm_min=speed * 60, machine=True)
        grbl.wait_idle(timeout_s=30)

    def _open_writer(self, out: Path, spec: ProbeSpec, protocol_toml: str, extra: dict[str, Any] | None) -> RecordingWriter:
        from labrig.sim.truth import truth_streams

        info = {"virtual_rig": self.session.virtual, "made_by": "drivers", "seed": self.session.seed,
                "location_mm": list(spec.location_mm),
                "tare_n_nm": list(self.session.tare_n), "calibration": _calibration_files(self.rig), **(extra or {})}
        metadata = RecordingMetadata(indenter=self.indenter.name, protocol_toml=protocol_toml, rig_toml=self.rig.text,
                                     indenter_toml=indenter_toml(self.indenter), extra=info)
        streams = truth_streams(len(self.rig.markers.rest_positions_mm())) if self.session.virtual else ()
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
