"""The probing procedure: its steps replayed without devices, then played by both executors on the
virtual rig (through the drivers over ptys, and in virtual time) with the same steps, phases, moves and trigger edges."""

from __future__ import annotations

import math
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labrig.calibration.registration_file import gel_pose
from labrig.config import RigConfig
from labrig.indenters import Indenter
from labrig.protocol.plan import ProbePlan
from labrig.protocol.preflight import checked_plan
from labrig.protocol.procedure import (
    APPROACH_FRACTION,
    FINE_SPEED_MM_S,
    Contact,
    Dwell,
    ForceAbove,
    Halt,
    Move,
    MoveUntil,
    Phase,
    Position,
    ProcedureAbort,
    Retreat,
    Step,
    play,
    probe,
    recovery,
)
from labrig.protocol.rigfile import safety_limits
from labrig.protocol.safety import SafetyError, SafetyLimits, deepest_press_mm
from labrig.protocol.spec import ApproachSpec, ProbeSpec

QUICK = ProbeSpec(
    "sphere", depth_mm=0.6, normal_speed_mm_s=2.0, wait_s=0.1, shear_mm=0.4, shear_speed_mm_s=2.0,
    approach=ApproachSpec(start_height_mm=0.4, speed_mm_s=1.0, contact_force_n=0.1, max_travel_mm=1.5),
    retract_height_mm=1.0, retract_speed_mm_s=5.0,
)


def _plan(spec: ProbeSpec, rig: RigConfig, sphere: Indenter) -> ProbePlan:
    limits = safety_limits(rig).for_indenter(sphere.max_normal_force_n, sphere.max_shear_force_n)
    return checked_plan(spec, rig, sphere, gel_pose(rig), limits)


def _replay(procedure: Any, *, position: np.ndarray, reached: bool = True) -> tuple[list[Step], Any]:
    """Play a procedure without devices: every condition holds (or none), the machine is at ``position``."""
    steps: list[Step] = []

    def execute(step: Step) -> Any:
        if isinstance(step, Position):
            return position
        return reached if isinstance(step, MoveUntil) else None

    return steps, play(procedure, execute, steps.append)


def test_the_depth_sequence_moves_from_the_contact_found(rig: RigConfig, sphere: Indenter) -> None:
    plan = _plan(QUICK, rig, sphere)
    contact = plan.approach_start_mm + 0.43 * plan.down
    steps, result = _replay(probe(plan, sphere.max_depth_mm), position=contact)
    assert result == tuple(contact)
    assert [s.name for s in steps if isinstance(s, Phase)] == list(QUICK.phases())
    assert [s.name for s in steps if isinstance(s, Phase) and s.stoppable] == list(QUICK.phases()[1:-2])
    search = steps[1]
    assert isinstance(search, MoveUntil) and search.until == ForceAbove("contact", 0.1)
    np.testing.assert_allclose(search.target_mm, plan.approach_limit_mm)
    assert steps[2:4] == [Position(), Contact(tuple(contact))]
    bottom = contact + 0.6 * plan.down
    moves = [(s.target_mm, s.speed_mm_s) for s in steps if isinstance(s, Move)]
    expected = [(bottom, 2.0), (bottom + 0.4 * plan.shear_dir, 2.0), (bottom, 2.0), (contact, 2.0),
                (contact - 1.0 * plan.down, 5.0)]
    assert len(moves) == len(expected)
    for (target, speed), (want, want_speed) in zip(moves, expected):
        np.testing.assert_allclose(target, want, atol=1e-12)
        assert speed == want_speed
    assert [s for s in steps if isinstance(s, Dwell)] == [Dwell(0.1)] * 3


def test_no_shear_skips_the_shear_phases(rig: RigConfig, sphere: Indenter) -> None:
    plan = _plan(replace(QUICK, shear_mm=0.0), rig, sphere)
    steps, _ = _replay(probe(plan, sphere.max_depth_mm), position=plan.approach_start_mm)
    assert [s.name for s in steps if isinstance(s, Phase)] == ["approach", "normal_down", "wait", "normal_up", "retract"]


def test_a_force_target_searches_in_two_stages_down_to_the_depth_cap(rig: RigConfig, sphere: Indenter) -> None:
    spec = replace(QUICK, depth_mm=None, force_n=2.0, max_depth_mm=None)
    plan = _plan(spec, rig, sphere)
    contact = plan.approach_start_mm + 0.4 * plan.down
    steps, _ = _replay(probe(plan, sphere.max_depth_mm), position=contact)
    stages = [s for s in steps if isinstance(s, MoveUntil)][1:]
    assert [s.until for s in stages] == [ForceAbove("force", APPROACH_FRACTION * 2.0), ForceAbove("force", 2.0)]
    assert [s.speed_mm_s for s in stages] == [2.0, FINE_SPEED_MM_S]
    for stage in stages:
        np.testing.assert_allclose(stage.target_mm, contact + deepest_press_mm(sphere.max_depth_mm) * plan.down)


def test_a_condition_that_never_holds_aborts_with_the_reason(rig: RigConfig, sphere: Indenter) -> None:
    plan = _plan(QUICK, rig, sphere)
    with pytest.raises(ProcedureAbort, match=r"no contact within 1\.5 mm"):
        _replay(probe(plan, sphere.max_depth_mm), position=plan.approach_start_mm, reached=False)
    forced = _plan(replace(QUICK, depth_mm=None, force_n=2.0, max_depth_mm=0.5), rig, sphere)
    with pytest.raises(ProcedureAbort, match=r"force target 2\.0 N was not reached at the depth cap 0\.5 mm"):
        procedure = probe(forced, sphere.max_depth_mm)
        answers = iter([None, True, forced.approach_start_mm, None, None, False])  # reached contact, not the force
        play(procedure, lambda step: next(answers))


def test_recovery_goes_up_the_normal_then_to_the_retract_point(rig: RigConfig, sphere: Indenter) -> None:
    plan = _plan(QUICK, rig, sphere)
    deep = plan.retract_mm + 3.0 * plan.down
    steps, _ = _replay(recovery(plan), position=deep)
    assert steps[:3] == [Halt(), Phase("retract", recovering=True), Position()]
    up, last = steps[3], steps[4]
    assert isinstance(up, Retreat) and isinstance(last, Retreat) and len(steps) == 5
    np.testing.assert_allclose(up.target_mm, plan.retract_mm, atol=1e-9)  # straight up onto the retract plane
    assert up.speed_mm_s == min(QUICK.retract_speed_mm_s, 2 * QUICK.normal_speed_mm_s)
    np.testing.assert_allclose(last.target_mm, plan.retract_mm)
    above = plan.retract_mm - 1.0 * plan.down
    steps, _ = _replay(recovery(plan), position=above)
    assert [type(s) for s in steps] == [Halt, Phase, Position, Retreat]  # already above: no rise


def test_preflight_refuses_the_wrong_indenter_and_unsafe_targets(rig: RigConfig, sphere: Indenter) -> None:
    limits = safety_limits(rig)
    with pytest.raises(SafetyError, match="needs the cube indenter"):
        checked_plan(replace(QUICK, indenter="cube"), rig, sphere, gel_pose(rig), limits)
    cramped = replace(limits, workspace_min_mm=(-200.0, -200.0, -45.0))
    with pytest.raises(SafetyError, match="outside the workspace"):
        checked_plan(QUICK, rig, sphere, gel_pose(rig), cramped)


# -- both executors, step by step -----------------------------------------------------------------


def _motion_lines(rec: Any) -> list[tuple[str, dict[str, float]]]:
    """The moves, jogs and output switches the host sent, as (head, {word: value})."""
    gcode = rec.stream("gcode")
    out = []
    for direction, line in zip(gcode["direction"], gcode["line"]):
        text = bytes(line).decode(errors="replace")
        match = re.fullmatch(r"(\$J=G90G53|G90G53G1|M8|M9)((?:[XYZF]-?[\d.]+)*)", text)
        if direction == 0 and match:
            out.append((match[1], {w[0]: float(w[1:]) for w in re.findall(r"[XYZF]-?[\d.]+", match[2])}))
    return out


def _from_contact(steps: list[Step]) -> tuple[np.ndarray, list[Step]]:
    """The contact a run found, and its steps with every target after it taken relative to it (mm)."""
    contact = next(np.asarray(s.position_mm) for s in steps if isinstance(s, Contact))
    at = next(i for i, s in enumerate(steps) if isinstance(s, Contact))
    relative = [replace(s, target_mm=tuple(np.asarray(s.target_mm) - contact))  # type: ignore[arg-type]
                if i > at and isinstance(s, Move | MoveUntil) else s for i, s in enumerate(steps)]
    return contact, [s for s in relative if not isinstance(s, Contact)]


def _same(a: Step, b: Step, atol_mm: float) -> bool:
    if isinstance(a, Move | MoveUntil | Retreat) and type(a) is type(b):
        near = np.allclose(a.target_mm, b.target_mm, atol=atol_mm)  # type: ignore[union-attr]
        return bool(near) and a == replace(b, target_mm=a.target_mm)  # type: ignore[arg-type]
    return a == b


def test_both_executors_play_the_same_steps_phases_moves_and_edges(rig: RigConfig, sphere: Indenter, tmp_path: Path) -> None:
    """One procedure through the drivers over ptys (real time) and in virtual time: the same steps
    in the same order (each target after the contact at the same place relative to the contact each
    run found), the same phases with a trigger edge at each start, and the same G-code moves, jogs
    and output switches."""
    from labrig.protocol.rigfile import DeviceConfig
    from labrig.protocol.runner import ProbeRunner
    from labrig.protocol.session import RigSession
    from labrig.protocol.virtual_run import record_virtual
    from labrig.recording import Recording

    plan = _plan(QUICK, rig, sphere)
    through_drivers: list[Step] = []
    with RigSession(rig, DeviceConfig(), SafetyLimits(), indenter=sphere) as session:
        runner = ProbeRunner(session, rig, sphere, gel_in_machine=gel_pose(rig), on_step=through_drivers.append)
        drivers = runner.run(QUICK, tmp_path / "drivers.h5")
    in_virtual_time: list[Step] = []
    virtual = record_virtual(QUICK, tmp_path / "virtual.h5", rig, sphere, seed=1, on_step=in_virtual_time.append)
    assert drivers.exit_status == virtual.exit_status == "complete", (drivers.reason, virtual.reason)

    contact_d, steps_d = _from_contact(through_drivers)
    contact_v, steps_v = _from_contact(in_virtual_time)
    for contact in (contact_d, contact_v):  # on the approach, between its start and its limit
        travel = float((contact - plan.approach_start_mm) @ plan.down)
        np.testing.assert_allclose(contact, plan.approach_start_mm + travel * plan.down, atol=0.005)
        assert 0 < travel < QUICK.approach.max_travel_mm
    assert [type(s).__name__ for s in steps_d] == [type(s).__name__ for s in steps_v]
    for a, b in zip(steps_d, steps_v):
        assert _same(a, b, atol_mm=0.005), (a, b)  # status positions to 3 decimals, virtual ones to a step

    with Recording(drivers.path) as d, Recording(virtual.path) as v:
        assert [p.name for p in d.phases()] == [p.name for p in v.phases()] == list(QUICK.phases())
        for rec in (d, v):
            edges = rec.column("trigger_out", "t_host_us")
            assert edges.tolist() == [p.t_start_us for p in rec.phases()]  # one edge at each phase start (short waits)
        assert d.column("trigger_out", "polarity").tolist() == v.column("trigger_out", "polarity").tolist()
        lines_d, lines_v = _motion_lines(d), _motion_lines(v)
        assert [head for head, _ in lines_d] == [head for head, _ in lines_v]
        assert sum(head == "$J=G90G53" for head, _ in lines_d) == 1 and sum(head == "G90G53G1" for head, _ in lines_d) == 5
        for k, ((head, words_d), (_, words_v)) in enumerate(zip(lines_d, lines_v)):
            assert words_d.keys() == words_v.keys() and words_d.get("F") == words_v.get("F")
            after_contact = head == "G90G53G1"  # the jog searches for it from the plan's approach start
            for i, axis in enumerate("XYZ"):
                if axis in words_d:
                    shift = (contact_d[i] - contact_v[i]) if after_contact else 0.0
                    assert abs(words_d[axis] - words_v[axis] - shift) < 0.005, (k, axis, words_d, words_v)


def test_a_held_force_shears_along_the_gel_plane_with_the_loop_on_the_normal(rig: RigConfig, sphere: Indenter) -> None:
    from labrig.protocol.procedure import MoveHolding

    spec = replace(QUICK, shear_hold_force_n=2.0)
    plan = _plan(spec, rig, sphere)
    contact = plan.approach_start_mm + 0.43 * plan.down
    steps, _ = _replay(probe(plan, sphere.max_depth_mm), position=contact)
    held = [s for s in steps if isinstance(s, MoveHolding)]
    bottom = contact + 0.6 * plan.down
    assert len(held) == 2 and all(h.hold.target_n == 2.0 and h.hold.feedback == "ft" for h in held)
    np.testing.assert_allclose(held[0].target_mm, bottom + 0.4 * plan.shear_dir, atol=1e-12)
    np.testing.assert_allclose(held[1].target_mm, bottom, atol=1e-12)
    np.testing.assert_allclose(held[0].normal, plan.down)
    assert [s.target_mm for s in steps if isinstance(s, Move)][1:] != []  # Normal Down, Up and Retract stay moves
    with pytest.raises(ProcedureAbort, match=r"the force loop holding 2 N stopped: saturated"):
        play(probe(plan, sphere.max_depth_mm),
             lambda step: contact if isinstance(step, Position) else
             (True if isinstance(step, MoveUntil) else ("saturated: ..." if isinstance(step, MoveHolding) else None)))


def test_a_held_shear_in_virtual_time_reaches_and_holds_its_force(rig: RigConfig, sphere: Indenter,
                                                                  tmp_path: Path) -> None:
    """Pressed 0.6 mm (about 3 N), sheared holding 1.5 N: the loop backs off to it during the shear and holds it
    through the shear back, within 0.1 N RMS on the F/T; its commands are in the recording's control stream."""
    from labrig.evaluation.control import control_run
    from labrig.protocol.virtual_run import record_virtual
    from labrig.recording import Recording

    spec = replace(QUICK, shear_hold_force_n=1.5, shear_mm=0.8, shear_speed_mm_s=1.0)
    result = record_virtual(spec, tmp_path / "held.h5", rig, sphere, seed=3)
    assert result.exit_status == "complete", result.reason
    with Recording(result.path) as rec:
        t = rec.column("ft", "t_host_us")
        fz = np.abs(rec.column("ft", "force_n")[:, 2] - rec.column("ft", "force_n")[:100, 2].mean())
        phases = {p.name: p for p in rec.phases()}
        back = phases["shear_opposite"]
        during = fz[(t >= back.t_start_us) & (t < back.t_end_us)]
        assert np.sqrt(np.mean((during - 1.5) ** 2)) < 0.1
        wait = next(p for p in rec.phases() if p.name == "wait")
        assert fz[(t >= wait.t_start_us) & (t < wait.t_end_us)].mean() > 2.0  # pressed harder than held
        control = rec.stream("control")
        assert len(control["t_host_us"]) >= 2 * 0.8 / (1.0 * spec.control.segment_s)
        assert np.all(control["target_n"] == 1.5) and np.median(np.diff(control["t_host_us"])) == 10_000
    run = control_run(result.path)
    assert run is not None and math.isnan(run.step_rise_s)  # no held press: no step
    assert 0.1 < run.hold_rms_n_ft < 1.0  # both shears, the first starting with the back-off from 3 N


def test_a_loop_that_stops_aborts_the_run_and_retracts(rig: RigConfig, sphere: Indenter, tmp_path: Path) -> None:
    """A held force the depth cap forbids (1.5 N held no deeper than 0.05 mm below contact, saturated after 50 ms):
    the run aborts with the loop's reason and retracts."""
    from labrig.protocol.force_loop import ForceLoopParams
    from labrig.protocol.virtual_run import record_virtual

    spec = replace(QUICK, depth_mm=None, force_n=1.5, press_hold_s=0.5, max_depth_mm=0.05,
                   control=ForceLoopParams(saturation_s=0.05))
    result = record_virtual(spec, tmp_path / "capped.h5", rig, sphere, seed=3)
    assert result.exit_status == "aborted"
    assert "the force loop holding 1.5 N stopped: saturated" in result.reason
    assert result.phases[-1] == "retract" and "wait" not in result.phases


def test_a_held_press_steps_to_its_force_and_holds_it_through_waits_and_shears(rig: RigConfig, sphere: Indenter,
                                                                               tmp_path: Path) -> None:
    """From contact the loop presses to 3 N without overshooting it by more than 10 %, holds it through the waits
    and the shears (0.1 N RMS on the F/T), and every held step is in the control stream."""
    from labrig.evaluation.charts import held_force
    from labrig.evaluation.control import control_run, step_response
    from labrig.protocol.procedure import MoveHolding
    from labrig.protocol.virtual_run import record_virtual
    from labrig.recording import Recording

    spec = replace(QUICK, depth_mm=None, force_n=3.0, press_hold_s=1.0, shear_mm=0.5, shear_speed_mm_s=1.0)
    plan = _plan(spec, rig, sphere)
    steps, _ = _replay(probe(plan, sphere.max_depth_mm), position=plan.approach_start_mm + 0.43 * plan.down)
    held = [s for s in steps if isinstance(s, MoveHolding)]
    assert [h.duration_s for h in held] == [1.0, spec.wait_s, 0.0, spec.wait_s, 0.0, spec.wait_s]
    assert all(h.hold.target_n == 3.0 for h in held)
    result = record_virtual(spec, tmp_path / "press.h5", rig, sphere, seed=3)
    assert result.exit_status == "complete", result.reason
    with Recording(result.path) as rec:
        t = rec.column("ft", "t_host_us")
        fz = np.abs(rec.column("ft", "force_n")[:, 2] - rec.column("ft", "force_n")[:100, 2].mean())
        phases = rec.phases()
        press = next(p for p in phases if p.name == "normal_down")
        inside = (t >= press.t_start_us) & (t < press.t_end_us)
        assert step_response((t[inside] - press.t_start_us) / 1e6, fz[inside], 3.0, start_n=0.0).overshoot_pct <= 10
        later = np.zeros(t.shape, bool)
        for p in phases:
            if p.name in ("wait", "shear", "shear_opposite"):
                later |= (t >= p.t_start_us) & (t < p.t_end_us)
        assert np.sqrt(np.mean((fz[later] - 3.0) ** 2)) < 0.1
        control = rec.stream("control")
        assert np.all(control["target_n"] == 3.0) and control["stiffness_n_per_mm"].min() >= 8.0
    run = control_run(result.path)  # what labrig evaluate's control section shows
    assert run is not None and run.feedback == "ft" and run.target_n == 3.0 and run.loop_hz == pytest.approx(100, 0.01)
    assert run.step_overshoot_pct <= 10 and run.hold_rms_n_ft < 0.1 and math.isnan(run.hold_rms_n_estimate)
    assert [name for name, _, _ in run.phases_s if name != "approach"][:2] == ["normal_down", "wait"]
    assert np.nanmax(run.target_series_n) == 3.0 and np.isnan(run.target_series_n[0])
    figure = held_force(run.t_s, run.ft_fz_n, run.target_series_n, phases=run.phases_s)
    assert len(figure.axes[0].lines) == 2
