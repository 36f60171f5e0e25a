"""The probing procedure, told once: a plan of steps that an executor plays on the drivers or in virtual time.

:func:`probe` is the paper's sequence as a generator (sans-I/O, in the manner of Bluesky's
plans): Approach (a contact search), Normal Down (to a depth, or searching for a force), Wait,
Shear, Wait, Shear Opposite, Wait, Normal Up, Retract. It yields frozen steps and receives, through
``generator.send``, what the devices report back; it never touches a device. :func:`recovery` is
what follows an abort: stop, then up along the gel normal to the retract point. :func:`play` runs
either to its end with an executor's ``execute(step) -> reply``: the drivers'
(:class:`~labrig.protocol.runner.ProbeRunner`) or the virtual-time one
(:func:`~labrig.protocol.virtual_run.record_virtual`).

Steps and their replies (positions: the CNC's tool reference point, machine mm):

* :class:`Phase`: toggle the camera trigger output and log the phase at the edge (None).
* :class:`Move`: a straight feed move, waited to its end (None).
* :class:`MoveUntil`: an absolute jog cut short when its :class:`ForceAbove` condition holds
  (whether it held).
* :class:`MoveHolding`: a move along the gel plane in short jog segments while the force loop
  (:mod:`labrig.protocol.force_loop`) holds the normal force, optionally until a tangential force or with a slip
  reflex (:mod:`labrig.protocol.slip`) (None, or the loop's stop: the procedure then aborts with it).
* :class:`Dwell`: hold still (None). Through the drivers the trigger output also toggles in pairs
  meanwhile (edges for the camera clock fit on a loaded host, each phase keeping its level); in
  virtual time every edge is exact and a dwell adds none.
* :class:`Position`: where the machine is now (three numbers, machine mm).
* :class:`Contact`: the contact point found; depths are measured below it (None).
* :class:`Halt`: stop the motion and drop the planned moves, the position kept (None).
* :class:`Retreat`: after an abort, a move with its own time limit (None).

Everything that can be refused before moving is checked on the plan beforehand
(:func:`~labrig.protocol.preflight.checked_plan`); the procedure itself raises
:class:`ProcedureAbort` when the rig does not answer as planned (no contact, a force not reached).
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from labrig.protocol.force_loop import ForceLoopParams
from labrig.protocol.plan import ProbePlan
from labrig.protocol.safety import deepest_press_mm
from labrig.protocol.slip import SlipReflex

F64 = npt.NDArray[np.float64]
#: A machine position, mm (x, y, z).
Point = tuple[float, float, float]

#: A force target is approached at the normal speed up to this fraction, then at FINE_SPEED_MM_S.
APPROACH_FRACTION = 0.7
FINE_SPEED_MM_S = 0.3
#: F/T samples averaged for contact and force-target detection (noise 0.02 N -> 0.005 N).
DETECT_SAMPLES = 16
#: Extra time allowed on top of a move's nominal duration, s.
MOVE_MARGIN_S = 5.0
#: How long the last move of a recovery (to the retract point) may take, s.
RETREAT_LIMIT_S = 30.0


@dataclass(frozen=True)
class Phase:
    """A phase starts: the trigger output toggles and the phase is logged at the edge's time.

    ``stoppable``: a first Ctrl-C (which lets the current phase finish) stops the run here.
    ``recovering``: after an abort; logged even if the output cannot be switched."""

    name: str
    stoppable: bool = False
    recovering: bool = False


@dataclass(frozen=True)
class Move:
    """A straight feed move to ``target_mm`` at ``speed_mm_s``, waited to its end."""

    target_mm: Point
    speed_mm_s: float


@dataclass(frozen=True)
class ForceAbove:
    """The mean tared |Fz| of the last ``average_samples`` F/T samples exceeds ``threshold_n`` (N).

    ``kind``: what is searched for, the first touch (``contact``) or a force target (``force``)."""

    kind: Literal["contact", "force"]
    threshold_n: float
    average_samples: int = DETECT_SAMPLES


@dataclass(frozen=True)
class MoveUntil:
    """An absolute jog toward ``target_mm`` at ``speed_mm_s``, cancelled once ``until`` holds;
    replies whether it held before the jog ended."""

    target_mm: Point
    speed_mm_s: float
    until: ForceAbove


@dataclass(frozen=True)
class HoldForce:
    """The normal force held at ``target_n`` (N on the gel, pressing positive), read from ``feedback`` ("ft": the
    F/T sensor's tared |Fz|), by a loop with ``params``."""

    target_n: float
    feedback: str
    params: ForceLoopParams


@dataclass(frozen=True)
class MoveHolding:
    """Along the gel plane toward ``target_mm``'s place at ``speed_mm_s`` (its component along ``normal`` ignored),
    and for at least ``duration_s``, while ``hold`` moves the tool along ``normal`` (the gel's inward unit normal,
    machine axes), never deeper than ``deepest_mm``; replies None at the end, or the loop's stop (its reason), the
    motion then stopped. A target at the tool's own place is a force held in place."""

    target_mm: Point
    speed_mm_s: float
    hold: HoldForce
    normal: Point
    deepest_mm: Point  # the loop never presses further along ``normal`` than this point (the depth cap)
    duration_s: float = 0.0
    until_tangential_n: float | None = None  # the move ends once the tangential force reaches this (N)
    slip: SlipReflex | None = None  # what the move does when its contact slips


@dataclass(frozen=True)
class Dwell:
    """Hold still for ``seconds``."""

    seconds: float


@dataclass(frozen=True)
class Position:
    """Ask where the machine is; replies its position (machine mm, three numbers)."""


@dataclass(frozen=True)
class Contact:
    """The contact point the approach found (machine mm)."""

    position_mm: Point


@dataclass(frozen=True)
class Halt:
    """Stop the motion and drop the planned moves, keeping the position (a recovery's first step)."""


@dataclass(frozen=True)
class Retreat:
    """After an abort: a move to ``target_mm`` at ``speed_mm_s``, waited for at most ``limit_s``."""

    target_mm: Point
    speed_mm_s: float
    limit_s: float


Step = Phase | Move | MoveUntil | MoveHolding | Dwell | Position | Contact | Halt | Retreat
#: A procedure: yields steps, is sent their replies, returns its result.
Procedure = Generator[Step, Any, Any]


class ProcedureAbort(Exception):
    """The procedure gives up: the rig did not answer as planned (the motion is not held)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def move_limit_s(distance_mm: float, speed_mm_s: float) -> float:
    """How long a move of ``distance_mm`` at ``speed_mm_s`` may take, s."""
    return 1.5 * (distance_mm / speed_mm_s) + MOVE_MARGIN_S


def probe(plan: ProbePlan, indenter_max_depth_mm: float) -> Generator[Step, Any, Point]:
    """The probing sequence of ``plan`` from the approach start; returns the contact point (machine mm).

    ``indenter_max_depth_mm``: the mounted indenter's, which caps a force target's search."""
    spec = plan.spec
    approach = spec.approach
    yield Phase("approach")
    contact_found = ForceAbove("contact", approach.contact_force_n)
    touched = yield MoveUntil(_point(plan.approach_limit_mm), approach.speed_mm_s, contact_found)
    if not touched:
        raise ProcedureAbort(f"no contact within {approach.max_travel_mm} mm of the approach start "
                             f"(|Fz| stayed under {approach.contact_force_n} N): check the gel height in the rig's gel pose")
    contact = np.asarray((yield Position()), dtype=np.float64)
    yield Contact(_point(contact))
    yield Phase("normal_down", stoppable=True)
    bottom = yield from _press(plan, contact, indenter_max_depth_mm)
    yield Phase("wait", stoppable=True)
    yield from _wait(plan, contact, indenter_max_depth_mm)
    if spec.has_shear:
        yield Phase("shear", stoppable=True)
        yield from _shear(plan, plan.sheared_mm(bottom), contact, indenter_max_depth_mm, forward=True)
        yield Phase("wait", stoppable=True)
        yield from _wait(plan, contact, indenter_max_depth_mm)
        yield Phase("shear_opposite", stoppable=True)
        yield from _shear(plan, bottom, contact, indenter_max_depth_mm)
        yield Phase("wait", stoppable=True)
        yield from _wait(plan, contact, indenter_max_depth_mm)
    yield Phase("normal_up")
    if spec.release_force_n is not None:
        here = np.asarray((yield Position()), dtype=np.float64)
        release = HoldForce(spec.release_force_n, spec.feedback, spec.control)
        yield from _held(plan, here, contact, release, spec.normal_speed_mm_s, indenter_max_depth_mm,
                         spec.release_hold_s)
    yield Move(_point(contact), spec.normal_speed_mm_s)
    yield Phase("retract")
    yield Move(_point(contact - spec.retract_height_mm * plan.down), spec.retract_speed_mm_s)
    return _point(contact)


def _press(plan: ProbePlan, contact: F64, indenter_max_depth_mm: float) -> Generator[Step, Any, F64]:
    """Normal Down: to the depth below ``contact``, or down until the force target (in two stages:
    fast to most of it, then slowly, since a jog's deceleration overshoots by stiffness * v^2 / (2 a),
    about 1 N at 1.5 mm/s on this gel, 0.03 N at FINE_SPEED_MM_S); returns where it ended."""
    spec = plan.spec
    if spec.depth_mm is not None:
        bottom = plan.bottom_mm(contact)
        yield Move(_point(bottom), spec.normal_speed_mm_s)
        return bottom
    assert spec.force_n is not None
    if spec.press_hold_s is not None:
        hold = HoldForce(spec.force_n, spec.feedback, spec.control)
        yield from _held(plan, contact, contact, hold, spec.normal_speed_mm_s, indenter_max_depth_mm, spec.press_hold_s)
        return np.asarray((yield Position()), dtype=np.float64)
    cap = deepest_press_mm(indenter_max_depth_mm)
    max_depth = min(spec.max_depth_mm or cap, cap)
    deepest = plan.max_bottom_mm(contact, max_depth)
    for threshold, speed in ((APPROACH_FRACTION * spec.force_n, spec.normal_speed_mm_s),
                             (spec.force_n, min(spec.normal_speed_mm_s, FINE_SPEED_MM_S))):
        reached = yield MoveUntil(_point(deepest), speed, ForceAbove("force", threshold))
        if not reached:
            raise ProcedureAbort(f"the force target {spec.force_n} N was not reached at the depth cap {max_depth} mm")
    return np.asarray((yield Position()), dtype=np.float64)


def _shear(plan: ProbePlan, target: F64, contact: F64, indenter_max_depth_mm: float, *,
           forward: bool = False) -> Generator[Step, Any, None]:
    """A shear to ``target``: a straight move, or, with a held force, a move along the gel plane with the loop on
    the normal; the ``forward`` one (Shear) ends at a tangential force target and has the slip reflex."""
    spec = plan.spec
    held_n = spec.shear_held_n
    if held_n is None:
        yield Move(_point(target), spec.shear_speed_mm_s)
        return
    hold = HoldForce(held_n, spec.feedback, spec.control)
    until_n, slip = None, None
    if forward:
        until_n = spec.shear_force_n
        if spec.slip_action is not None:
            friction = spec.slip.friction if spec.slip.friction is not None else plan.friction
            slip = SlipReflex(spec.slip_action, spec.slip, friction, plan.press_limit_n)
    yield from _held(plan, target, contact, hold, spec.shear_speed_mm_s, indenter_max_depth_mm,
                     until_tangential_n=until_n, slip=slip)


def _wait(plan: ProbePlan, contact: F64, indenter_max_depth_mm: float) -> Generator[Step, Any, None]:
    """A wait: still, or with a held press, the force held in place."""
    spec = plan.spec
    if spec.press_hold_s is None or spec.force_n is None:
        yield Dwell(spec.wait_s)
        return
    here = np.asarray((yield Position()), dtype=np.float64)
    hold = HoldForce(spec.force_n, spec.feedback, spec.control)
    yield from _held(plan, here, contact, hold, spec.normal_speed_mm_s, indenter_max_depth_mm, spec.wait_s)


def _held(plan: ProbePlan, target: F64, contact: F64, hold: HoldForce, speed_mm_s: float,
          indenter_max_depth_mm: float, duration_s: float = 0.0, *, until_tangential_n: float | None = None,
          slip: SlipReflex | None = None) -> Generator[Step, Any, None]:
    """A move toward ``target``'s place in the gel plane (for at least ``duration_s``) with the loop on the normal,
    no deeper below ``contact`` than a force target's search may go; aborts with the loop's reason if it stops."""
    spec = plan.spec
    cap = deepest_press_mm(indenter_max_depth_mm)
    deepest = plan.max_bottom_mm(contact, min(spec.max_depth_mm or cap, cap))
    stopped = yield MoveHolding(_point(target), speed_mm_s, hold, _point(plan.down), _point(deepest), duration_s,
                                until_tangential_n, slip)
    if stopped is not None:
        raise ProcedureAbort(f"the force loop holding {hold.target_n:g} N stopped: {stopped}")


def recovery(plan: ProbePlan) -> Generator[Step, Any, None]:
    """After an abort: stop and drop the planned moves, then go up along the gel normal to the
    retract plane (no faster than twice the normal speed) and on to the retract point."""
    yield Halt()
    yield Phase("retract", recovering=True)
    here = np.asarray((yield Position()), dtype=np.float64)
    rise = float((here - plan.retract_mm) @ plan.down)  # distance below the retract plane along the normal
    speed = plan.spec.retract_speed_mm_s
    if rise > 0:
        up_speed = min(speed, plan.spec.normal_speed_mm_s * 2)
        yield Retreat(_point(here - rise * plan.down), up_speed, rise / speed * 3 + MOVE_MARGIN_S)
    yield Retreat(_point(plan.retract_mm), speed, RETREAT_LIMIT_S)


def _point(v: F64) -> Point:
    return (float(v[0]), float(v[1]), float(v[2]))


def play(procedure: Procedure, execute: Callable[[Step], Any], on_step: Callable[[Step], None] | None = None) -> Any:
    """Run ``procedure`` to its end, answering each step with ``execute(step)``; returns its result.

    ``on_step`` sees every step before it is executed (as Bluesky's ``msg_hook``)."""
    reply = None
    while True:
        try:
            step = procedure.send(reply)
        except StopIteration as end:
            return end.value
        if on_step is not None:
            on_step(step)
        reply = execute(step)
