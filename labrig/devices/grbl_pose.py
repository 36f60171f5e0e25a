"""The tool pose of a GRBL machine rebuilt from its conversation, sans I/O: events in, pose out.

Frames, units, times
--------------------
Positions are machine coordinates (MPos) of the tool reference in mm; times are host
microseconds in the driver's time base (floats where sub-microsecond byte times matter).

Model
-----
:class:`GcodeFollower` follows the modal G-code state of the lines sent (G0/G1, G90/G91,
G20/G21, G53, F, ``$J=``) to know which straight moves each line queues. :class:`PoseModel`
plans those moves on a :class:`~labrig.devices.motion_profile.MotionTimeline` with the
controller's own limits (``$110-$112`` rates, ``$120-$122`` accelerations, ``$11`` junction
deviation, ``$100-$102`` steps) when each line's ``ok`` arrives, at the ``ok``'s receive time
less its transmission time and the link's one-way latency. Holds, resumes, jog cancels and
resets apply at the time their byte was written. Status reports during motion shift the plan in
time to where they put the machine (the ``ok`` arrives late by the link's latency: under a
millisecond on a pty, up to 16 ms through an FTDI chip); reports at rest re-anchor the position.
Lines the model does not follow (arcs, G10/G92/G28, probing, homing, check mode) mark it for
re-anchoring at the next report at rest; until then it holds the last known position.

The driver (:class:`~labrig.devices.grbl.Grbl`) feeds it under its lock; tests feed it by hand.
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.devices.grbl_gcode import preparse as preparse_text
from labrig.devices.grbl_protocol import Status
from labrig.devices.motion_profile import MachineLimits, MotionTimeline, Segment, Vec3, make_block, quantize_mm

#: Synchronising the pose model on status reports: search window and step (us), closest match
#: accepted (mm, a few steps), slowest motion used (mm/s).
SYNC_WINDOW_US = 40_000.0
SYNC_STEP_US = 20.0
SYNC_MATCH_MM = 0.02
SYNC_MIN_SPEED_MM_S = 2.0
#: States in which the machine is at rest, so a report re-anchors the model.
REST_STATES = frozenset({"Idle", "Alarm", "Check", "Sleep"})

_WORD = re.compile(r"([A-Z])([+-]?(?:\d+\.?\d*|\.\d+))")
#: G codes whose effect the follower does not model (arcs, probing, offsets, homing positions).
_UNMODELLED_G = (10, 28, 30, 38.2, 38.3, 38.4, 38.5, 92, 92.1, 43.1, 49, 2, 3)


@dataclass(frozen=True)
class PlannedMove:
    """A straight move a line queues: machine target (mm), feed (mm/min; None: rapid), planner tag."""

    target_mm: Vec3
    feed_mm_min: float | None
    tag: str | None = None


@dataclass(frozen=True)
class LineEffect:
    """What a line sent does to the pose: its moves, whether the model must re-anchor, its dwell (s)."""

    moves: tuple[PlannedMove, ...] = ()
    resync: bool = False
    dwell_s: float = 0.0


def preparse(line: bytes) -> str:
    """The line as GRBL's pre-parser keeps it (no spaces or comments, upper case)."""
    return preparse_text(line.decode("ascii", "replace"))


class GcodeFollower:
    """The modal state of the lines sent, to know which straight moves each line queues.

    Positions are machine mm (the parser's unquantised target). ``wco_mm`` comes from status
    reports; lines with effects it does not model say ``resync``.
    """

    def __init__(self) -> None:
        self.position_mm = [0.0, 0.0, 0.0]
        self.wco_mm = [0.0, 0.0, 0.0]
        self.incremental = False
        self.inches = False
        self.motion: int | None = 0
        self.feed_mm_min = 0.0

    def reset(self, position_mm: Sequence[float]) -> None:
        """Parser defaults after a controller reset, at ``position_mm``."""
        self.position_mm = [float(p) for p in position_mm]
        self.incremental = False
        self.inches = False
        self.motion = 0
        self.feed_mm_min = 0.0

    def follow(self, line: bytes) -> LineEffect:
        """What ``line`` does, and the modal state after it."""
        text = preparse(line)
        if text.startswith("$J="):
            return self._jog(text[3:])
        if text.startswith("$"):
            return LineEffect(resync=text in ("$H", "$X") or text.startswith("$RST"))
        words = _WORD.findall(text)
        g = [float(v) for k, v in words if k == "G"]
        vals = {k: float(v) for k, v in words if k not in "GM"}
        m = [float(v) for k, v in words if k == "M"]
        resync = any(c in _UNMODELLED_G or 54 <= c <= 59 for c in g)
        if 20 in g or 21 in g:
            self.inches = 20 in g
        if 90 in g or 91 in g:
            self.incremental = 91 in g
        for c in g:
            if c in (0, 1):
                self.motion = int(c)
            elif c in (2, 3, 38.2, 38.3, 38.4, 38.5, 80):
                self.motion = None
        if 2 in m or 30 in m:
            self.incremental, self.motion = False, 1
        unit = 25.4 if self.inches else 1.0
        if "F" in vals:
            self.feed_mm_min = vals["F"] * unit
        dwell = vals.get("P", 0.0) if 4 in g else 0.0
        axes = {i: vals[a] * unit for i, a in enumerate("XYZ") if a in vals}
        if not axes or any(c in (10, 28, 30, 92, 43.1) for c in g):
            return LineEffect(resync=resync, dwell_s=dwell)
        if self.motion is None:
            return LineEffect(resync=True, dwell_s=dwell)
        target = self._target(axes, incremental=self.incremental and 53 not in g, machine=53 in g)
        self.position_mm = list(target)
        feed = None if self.motion == 0 else self.feed_mm_min
        return LineEffect((PlannedMove(target, feed),), resync, dwell)

    def _jog(self, body: str) -> LineEffect:
        words = _WORD.findall(body)
        g = [float(v) for k, v in words if k == "G"]
        vals = {k: float(v) for k, v in words if k != "G"}
        unit = 25.4 if (20 in g or (self.inches and 21 not in g)) else 1.0
        incremental = 91 in g or (self.incremental and 90 not in g)
        axes = {i: vals[a] * unit for i, a in enumerate("XYZ") if a in vals}
        if not axes or "F" not in vals:
            return LineEffect()
        target = self._target(axes, incremental=incremental and 53 not in g, machine=53 in g)
        self.position_mm = list(target)
        return LineEffect((PlannedMove(target, vals["F"] * unit, "jog"),))

    def _target(self, axes: dict[int, float], *, incremental: bool, machine: bool) -> Vec3:
        target = list(self.position_mm)
        for axis, v in axes.items():
            if machine:
                target[axis] = v
            elif incremental:
                target[axis] += v
            else:
                target[axis] = v + self.wco_mm[axis]
        return (target[0], target[1], target[2])


class PoseModel:
    """The machine's motion rebuilt from the driver's events (see the module docstring).

    ``byte_us``: one byte's time on the wire (us) at the link's baud rate. ``checking``: the
    controller is in check mode (lines only parse; the model must not move).
    """

    def __init__(self, byte_us: float) -> None:
        self.byte_us = byte_us
        self.checking = False
        self.follower = GcodeFollower()
        self._timeline = MotionTimeline(MachineLimits())
        self._resync = True
        self._round_trips_us: deque[float] = deque(maxlen=32)

    @property
    def limits(self) -> MachineLimits:
        return self._timeline.limits

    @limits.setter
    def limits(self, limits: MachineLimits) -> None:
        self._timeline.limits = limits

    @property
    def link_latency_us(self) -> float:
        """One-way latency of the link (us): half the shortest round trip of recent status queries
        beyond the bytes' own time on the wire (0 until three queries were answered).
        """
        if len(self._round_trips_us) < 3:
            return 0.0
        return max(0.5 * min(self._round_trips_us), 0.0)

    # -- events from the conversation -----------------------------------------------------------

    def line_sent(self, line: bytes) -> LineEffect:
        """A line was written: follow its modal effect (its moves are planned when answered)."""
        return self.follower.follow(line)

    def line_answered(self, effect: LineEffect, t_us: float, *, error: bool) -> bool:
        """A line's answer (``ok``, or ``error:N`` when ``error``) arrived at ``t_us``: plan its
        moves. Returns whether a motion cycle started (an early status report times it best)."""
        if error:
            if effect.moves:
                self._resync = True
            return False
        if effect.resync or self.checking:
            self._resync = True
        if self.checking:
            return False
        timeline = self._timeline
        # 'ok\r\n' took 4 byte times on the wire, plus the link's one-way latency.
        t_planned = t_us - 4 * self.byte_us - self.link_latency_us
        for move in effect.moves:
            target = quantize_mm(move.target_mm, timeline.limits.steps_per_mm)
            block = make_block(timeline.tail_mm, target, move.feed_mm_min, timeline.limits, tag=move.tag)
            if block is not None:
                timeline.append(block, max(t_planned, timeline.t_us))
        if timeline.state == "queued":
            timeline.start(max(t_planned, timeline.t_us))
            return True
        return False

    def status_report(
        self, report: Status, *, line_bytes: int, t_us: int, t_query_us: int | None, lines_in_flight: bool
    ) -> None:
        """A status report of ``line_bytes`` bytes arrived at ``t_us`` (answering a ``?`` written
        at ``t_query_us``, None if unsolicited). ``lines_in_flight``: some line is unanswered (it
        could still be about to move the machine, so a report at rest does not re-anchor)."""
        if t_query_us is not None:  # the round trip beyond the bytes' own time on the wire
            self._round_trips_us.append(t_us - t_query_us - (line_bytes + 3) * self.byte_us)
        if report.wco_mm is not None and len(report.wco_mm) >= 3:
            self.follower.wco_mm = [float(v) for v in report.wco_mm[:3]]
        if report.position_mm is None or len(report.position_mm) < 3:
            return
        position = (float(report.position_mm[0]), float(report.position_mm[1]), float(report.position_mm[2]))
        t_sampled = t_us - (line_bytes + 2) * self.byte_us
        if t_query_us is not None:
            t_sampled = max(t_sampled, t_query_us + self.byte_us)
        if t_query_us is not None and report.state in ("Run", "Jog"):
            # GRBL samples the position when the '?' arrives (its reply may wait behind other output).
            self._synchronize(position, t_query_us + self.byte_us + self.link_latency_us)
        if report.state in REST_STATES and not lines_in_flight:
            self._anchor(position, max(t_sampled, self._timeline.t_us))

    def alarm(self, t_us: float) -> None:
        """A critical alarm (limits) stopped the machine dead at ``t_us``."""
        self._timeline.stop(t_us)
        self._resync = True

    def controller_reset(self, t_us: float) -> None:
        """The welcome banner: the controller restarted; motion stopped, parser defaults."""
        self._timeline.stop(t_us)
        self.follower.reset(self._timeline.position_mm)
        self._resync = True

    def soft_reset_written(self, t_us: float) -> None:
        """0x18 was written at ``t_us``: the machine halts once it arrives."""
        self._timeline.stop(t_us + self.byte_us)

    def jog_cancel_written(self, t_us: float) -> None:
        """0x85 was written: a running jog decelerates and its queue is dropped."""
        if self._timeline.state in ("run", "hold"):
            self._timeline.cancel(t_us + self.byte_us)
        self._resync = True

    def feed_hold_written(self, t_us: float) -> None:
        """``!`` was written: decelerate to a hold (GRBL cancels jogs instead)."""
        if any(block.tag == "jog" for block in self._timeline.queue):
            self._timeline.cancel(t_us + self.byte_us)
            self._resync = True
        else:
            self._timeline.hold(t_us + self.byte_us)

    def resume_written(self, t_us: float) -> None:
        """``~`` was written: resume from a hold."""
        self._timeline.resume(t_us + self.byte_us)

    # -- the pose ------------------------------------------------------------------------------

    def positions_at(self, t_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Machine positions (N, 3) mm at host times ``t_us``."""
        return self._timeline.positions_at(t_us)

    def segments(self) -> list[Segment]:
        """The reconstructed motion: executed segments, then the current plan."""
        return self._timeline.segments()

    # -- internals -----------------------------------------------------------------------------

    def _synchronize(self, position: Vec3, t_sampled: float) -> None:
        """Shift the running plan in time so it passes the reported position when the machine did.

        The model starts each move at the host time its ``ok`` arrived, which lags the controller
        by the transport latency; a report during motion tells the lag. Only fast enough motion
        (the position resolves the time to a fraction of a millisecond) and close matches count;
        half the measured lag is applied per report to average out jitter.
        """
        if self._timeline.state != "run" or self._resync:
            return
        t = t_sampled + np.arange(-SYNC_WINDOW_US, SYNC_WINDOW_US, SYNC_STEP_US)
        path = self._timeline.positions_at(t)
        distance = np.linalg.norm(path - np.asarray(position), axis=1)
        k = int(np.argmin(distance))
        if distance[k] > SYNC_MATCH_MM or k in (0, len(t) - 1):
            return
        speed = np.linalg.norm(path[min(k + 1, len(t) - 1)] - path[max(k - 1, 0)]) / (2 * SYNC_STEP_US) * 1e6
        if speed < SYNC_MIN_SPEED_MM_S:
            return
        self._timeline.shift_plan(0.5 * (t_sampled - t[k]))

    def _anchor(self, position: Vec3, t_us: float) -> None:
        """Re-anchor the motion model (and the G-code follower) on a report of the machine at rest.

        A model still moving is stopped there (it lagged the machine); a model elsewhere jumps.
        """
        timeline = self._timeline
        if timeline.state in ("run", "hold"):
            timeline.stop(t_us)
        if timeline.queue:
            return
        if self._resync or max(abs(a - b) for a, b in zip(timeline.position_mm, position)) > 1e-3:
            timeline.set_position(position, t_us)
        if self._resync:
            self.follower.position_mm = list(position)
            self._resync = False
