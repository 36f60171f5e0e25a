"""Touch-offs: find the gel surface at a location and press it in quasi-static steps (calibration).

:func:`press` travels above a location (every target checked like a probing
run's, :func:`~labrig.protocol.preflight.checked_plan`), tares, approaches
until the mean |Fz| of ``DETECT_SAMPLES`` F/T samples exceeds the contact force
(the runner's detection), then steps to each depth below the detected contact
(move, settle, average F/T samples), optionally shears, and goes back up,
recording the camera's events from the approach to the deepest step. Machine
mm, tared F/T N in sensor axes. The result is a
:class:`~labrig.calibration.registration.Press`, which the rig registration
and the gel modulus fit analyse.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt

from labrig.calibration.registration import Press
from labrig.config import RigConfig
from labrig.devices.bota import BotaSensor
from labrig.devices.grbl import Grbl, GrblTimeout
from labrig.errors import CalibrationError, LabrigError
from labrig.frames import Pose
from labrig.indenters import Indenter, indenter_toml
from labrig.protocol.plan import ProbePlan
from labrig.protocol.preflight import checked_plan
from labrig.protocol.procedure import DETECT_SAMPLES, MOVE_MARGIN_S
from labrig.protocol.session import RigSession
from labrig.protocol.spec import ApproachSpec, ProbeSpec
from labrig.recording import RecordingMetadata, RecordingWriter

F64 = npt.NDArray[np.float64]

#: Travel speed above the gel (to the clearance and the approach start), mm/s.
TRAVEL_SPEED_MM_S = 5.0


def press(
    session: RigSession,
    rig: RigConfig,
    indenter: Indenter,
    gel_pose: Pose,
    location_mm: tuple[float, float],
    depths_mm: Sequence[float],
    *,
    shear_mm: float = 0.0,
    shear_direction_deg: float = 0.0,
    record_to: str | Path | None = None,
    approach_start_mm: float = 0.8,
    approach_speed_mm_s: float = 0.5,
    contact_force_n: float = 0.1,
    max_travel_mm: float = 2.0,
    speed_mm_s: float = 1.0,
    settle_s: float = 0.05,
    samples: int = 40,
) -> Press:
    """Touch off at ``location_mm`` (gel frame of ``gel_pose``), press in steps to each depth below the
    detected contact, optionally shear, and go back up. Events are recorded to ``record_to`` from the
    approach to the deepest step. Raises CalibrationError when no contact is found."""
    if not depths_mm:
        raise CalibrationError("no indentation depths given")
    spec = ProbeSpec(indenter.name, location_mm=(float(location_mm[0]), float(location_mm[1])),
                     depth_mm=float(max(depths_mm)), normal_speed_mm_s=speed_mm_s, shear_mm=shear_mm,
                     shear_direction_deg=shear_direction_deg, shear_speed_mm_s=speed_mm_s,
                     approach=ApproachSpec(start_height_mm=approach_start_mm, speed_mm_s=approach_speed_mm_s,
                                           contact_force_n=contact_force_n, max_travel_mm=max_travel_mm),
                     retract_height_mm=1.0)
    limits = session.limits.for_indenter(indenter.max_normal_force_n, indenter.max_shear_force_n)
    plan = checked_plan(spec, rig, indenter, gel_pose, limits)  # refuses unsafe targets
    grbl, _ = _devices(session)
    if grbl.status().state.startswith("Alarm"):
        raise CalibrationError("GRBL is in Alarm: home it (labrig cnc home) first")
    session.monitor.trip = None
    here = _position(grbl)
    up = here.copy()
    up[2] = max(here[2], plan.clearance_mm[2])
    for target in (up, plan.clearance_mm, plan.approach_start_mm):
        _move(session, target, TRAVEL_SPEED_MM_S)
    session.tare()
    writer = None
    if record_to is not None:
        record_to = Path(record_to)
        writer = _open_recording(session, rig, indenter, spec, depths_mm, record_to)
        writer.phase_begin("approach")
    contact: F64 | None = None
    depth_rows: list[float] = []
    forces: list[F64] = []
    shear_force = None
    shear_dir = None
    status = "complete"
    reason = ""
    try:
        reached = session.monitor.arm("contact", contact_force_n, grbl.jog_cancel, average_samples=DETECT_SAMPLES)
        grbl.jog(*plan.approach_limit_mm.tolist(), feed_mm_min=approach_speed_mm_s * 60, relative=False, machine=True)
        _wait(session, max_travel_mm / approach_speed_mm_s * 1.5 + MOVE_MARGIN_S)
        session.monitor.disarm()
        if not reached.is_set():
            raise CalibrationError(
                f"no contact found at {spec.location_mm} mm within {max_travel_mm} mm of the approach start "
                f"({approach_start_mm} mm above the gel surface of the pose used): |Fz| stayed under "
                f"{contact_force_n} N. Check the gel height (rig.toml [rig] gel_origin_machine_mm) or raise max_travel_mm")
        contact = _position(grbl)
        if writer is not None:
            writer.phase_begin("normal_down")
        for depth in sorted(float(d) for d in depths_mm):
            _move(session, contact + depth * plan.down, speed_mm_s)
            time.sleep(settle_s)
            forces.append(_mean_force(session, samples))
            depth_rows.append(float((_position(grbl) - contact) @ plan.down))
        if writer is not None:
            end_ns = session.clock.now_ns()
            writer.phase_end((end_ns - writer.t0_host_ns) // 1000)
            session.end(end_ns)
        bottom = contact + depth_rows[-1] * plan.down
        if shear_mm > 0:
            # The tip's whole in-plane motion since contact is the shear (pressing along the nominal
            # normal drifts it a little across a tilted gel): keep it from the contact point.
            shear_dir = bottom + shear_mm * plan.shear_dir - contact
            _move(session, bottom + shear_mm * plan.shear_dir, speed_mm_s)
            time.sleep(settle_s)
            shear_force = _mean_force(session, samples) - forces[-1]
            _move(session, bottom, speed_mm_s)
    except BaseException as exc:
        status, reason = "aborted", str(exc) or type(exc).__name__
        raise
    finally:
        session.monitor.disarm()
        if writer is not None:
            with contextlib.suppress(Exception):
                session.end(session.clock.now_ns(), limit_s=1.0)
            writer.close(status, reason, raise_on_fault=False)
        with contextlib.suppress(Exception):
            _recover_above(session, plan, contact, speed_mm_s)
    assert contact is not None  # the approach raised otherwise
    return Press(indenter.name, spec.location_mm, contact, np.asarray(indenter.tool_offset_mm, dtype=np.float64),
                 plan.down.copy(), np.asarray(depth_rows), np.asarray(forces), shear_dir, shear_force,
                 Path(record_to) if record_to is not None else None)


def lift(session: RigSession, gel_pose: Pose, indenter: Indenter, height_mm: float, speed_mm_s: float = 5.0) -> None:
    """The indenter tip up to ``height_mm`` above the gel origin (machine z), e.g. after the last press."""
    grbl, _ = _devices(session)
    here = _position(grbl)
    target = here.copy()
    target[2] = max(here[2], float(gel_pose.translation_mm[2]) + height_mm - float(indenter.tool_offset_mm[2]))
    _move(session, target, speed_mm_s)


def _open_recording(session: RigSession, rig: RigConfig, indenter: Indenter, spec: ProbeSpec,
                    depths_mm: Sequence[float], path: Path) -> RecordingWriter:
    """A fresh recording at ``path`` for one touch-off, routed from the session."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    meta = RecordingMetadata(indenter=indenter.name, rig_toml=rig.text, indenter_toml=indenter_toml(indenter), extra={
        "purpose": "calibration touch-off", "virtual_rig": bool(session.virtual), "seed": int(session.seed),
        "location_mm": json.dumps(list(spec.location_mm)), "depths_mm": json.dumps([float(d) for d in depths_mm])})
    writer = RecordingWriter(path, meta, clock=session.clock).open()
    session.begin(writer)
    return writer


def _recover_above(session: RigSession, plan: ProbePlan, contact: F64 | None, speed_mm_s: float) -> None:
    """After a press (or its failure): clear a hold or alarm, then rise along the pressing direction to
    1 mm above the contact point (or where the tool is, if no contact was found)."""
    grbl, _ = _devices(session)
    if session.monitor.trip is not None or grbl.status().state.startswith(("Hold", "Alarm")):
        grbl.soft_reset()
        if grbl.status().state.startswith("Alarm"):
            grbl.unlock()
    here = _position(grbl)
    anchor = contact if contact is not None else here
    above = anchor - 1.0 * plan.down
    rise = float((here - above) @ plan.down)
    if rise > 0:
        _move(session, here - rise * plan.down, speed_mm_s)


def _devices(session: RigSession) -> tuple[Grbl, BotaSensor]:
    if session.grbl is None or session.ft is None:
        raise LabrigError("the rig session is not open: open it (`with RigSession.for_rig(...) as session`) first")
    return session.grbl, session.ft


def _position(grbl: Grbl) -> F64:
    """The machine position now (mm)."""
    return np.asarray(grbl.status().position_mm, dtype=np.float64)


def _wait(session: RigSession, timeout_s: float) -> None:
    """Until GRBL is idle; raises CalibrationError on a tripped force limit or after ``timeout_s``."""
    grbl, _ = _devices(session)
    deadline = time.monotonic() + timeout_s
    while True:
        if session.monitor.trip is not None:
            raise CalibrationError(f"force limit during calibration: {session.monitor.trip.reason}")
        try:
            grbl.wait_idle(timeout_s=0.2)
            return
        except GrblTimeout:
            if time.monotonic() > deadline:
                raise CalibrationError(f"a move did not finish within {timeout_s:.1f} s (GRBL {grbl.state})") from None


def _move(session: RigSession, target: F64, speed_mm_s: float) -> None:
    """A straight move to ``target`` (machine mm) at ``speed_mm_s``, waited for."""
    grbl, _ = _devices(session)
    here = _position(grbl)
    grbl.move_to(*np.asarray(target, dtype=np.float64).tolist(), feed_mm_min=speed_mm_s * 60, machine=True)
    _wait(session, 1.5 * float(np.linalg.norm(target - here)) / speed_mm_s + MOVE_MARGIN_S)


def _mean_force(session: RigSession, samples: int) -> F64:
    """The mean of the next ``samples`` tared F/T forces (N, sensor axes)."""
    _, ft = _devices(session)
    got = ft.wait_samples(samples)
    return np.asarray(np.mean([s.force_n for s in got], axis=0), dtype=np.float64)
