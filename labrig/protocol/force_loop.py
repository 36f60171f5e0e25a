"""Normal-force regulation as a state machine: a force reading in, a place along the gel normal out.

Sans-I/O, in the manner of :mod:`labrig.devices.grbl_protocol`: :meth:`ForceLoop.update` takes the time, the
newest normal force (N on the gel, pressing positive; from the F/T sensor or from the event sensor's estimate)
and where the tool was along the gel's inward normal when that force was read, and returns a
:class:`LoopCommand`: the place to go to (mm along the normal), or a stop with its reason. An executor turns the
command into motion (a short jog segment through the drivers, the tool's path in virtual time) and calls again
when the next reading arrives.

The law is a stiffness step: the gel is a spring along the normal, so the force is on target ``e / k`` further
in, with ``e`` the target minus the reading and ``k`` the contact's stiffness (N/mm). The goal is set from the
tool's place *at the reading's time*, so a late reading (the F/T's filter, the event pipeline's window) moves
the goal no further than a fresh one would; and ``k`` is taken no lower than the stiffest the contact has shown
(``stiffness_n_per_mm``, raised by the secant stiffness measured between readings, with a margin): a stiffer
guess stops short of the target and the next readings close the rest, so a step does not overshoot. The goal is
an end point the motion controller plans to stop at (GRBL decelerates to rest at the end of its queue), so the
machine's acceleration limit cannot carry the tool past it; the executor keeps the goal within what the machine
can reach in the next segments (:class:`HeldMove`).

A reading above the target backs the tool off by what that reading asks, ``e / k``, and no further until a reading
shows the unloading (falls by at least :data:`UNLOADING_SEEN` of what ``k`` says the back-off took off), the load
grows, or the tool presses back in; the held moves of one contact carry this on from one to the next. An event
camera cannot see a dent partly undone: its pixels fire once their brightness has changed by a contrast threshold,
and a small unloading changes the membrane's shading by less, so an estimate that reads a little high keeps reading
so while the tool backs off; a loop that believed it each time would walk the true force down without end. A
feedback that sees the unloading (the F/T sensor, a large release) moves on at once.

A scattered feedback (``reading_noise_n``, its sigma in N: the event estimate's) is trusted in proportion to how
far an error stands out of it: the loop acts on ``e**3 / (e**2 + s**2)`` instead of ``e``, the whole of a large
error (a step is as fast) and half of one as large as the scatter, so the tool does not chase every window's
error. On the step, until a reading has reached the target, the part left out may hold the tool still but never
turn it back: a late reading taken further out on the way in asks less than the tool has already gone, and a
shrunk goal behind the tool would stop it short of the target. And a fall counts as a back-off's unloading only
once it exceeds twice the scatter (a back-off begun on a reading high by chance would otherwise pass the next
ordinary reading for the unloading, and walk on).

Trips, each a stop with one line saying why (the executor then stops the motion and retracts):

* **stalled**: the newest reading is older than ``stale_after_s`` (a camera lost, a pipeline behind);
* **saturated**: the goal stayed beyond what the tool may reach (the depth cap, the speed limit) for
  ``saturation_s`` (a target the rig cannot reach);
* **oscillating**: the error changed sign ``oscillation_crossings`` times within ``oscillation_window_s``
  with an amplitude over ``oscillation_band_n`` (a contact stiffer than assumed, a feedback slower than its
  stamps say).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.protocol.slip import ContactReading, SlipCheck, SlipDetector, SlipReflex
from labrig.recording.schema import Column, StreamSpec

#: The secant stiffness is measured between readings at least this far apart along the normal (mm) ...
STIFFNESS_BASELINE_MM = 0.02
#: ... and the loop assumes this much more than it measured (a sphere stiffens as it goes in).
STIFFNESS_MARGIN = 1.25
#: A shear to a tangential force slows to TANGENTIAL_FINE_SPEED_MM_S (mm/s) from this fraction of its target on: the
#: CNC's deceleration from the shear speed (2 mm/s at 10 mm/s**2: 0.2 mm) would carry the force well past it.
TANGENTIAL_APPROACH_FRACTION = 0.5
TANGENTIAL_FINE_SPEED_MM_S = 0.3
#: A back-off is seen once the reading has fallen by this share of what the stiffness says it took off.
UNLOADING_SEEN = 0.5
#: ... and by this many times the feedback's scatter: one reading high by chance that began a back-off is no unloading.
UNLOADING_SCATTERS = 2.0


@dataclass(frozen=True)
class ForceLoopParams:
    """Gains and limits of the normal-force loop (units in the names)."""

    stiffness_n_per_mm: float = 8.0  # the least contact stiffness assumed: each reading moves the goal e / k
    max_speed_mm_s: float = 2.0  # either way along the normal
    segment_s: float = 0.01  # a command's span: the loop reads and commands this often
    stale_after_s: float = 0.02  # a reading older than this stops the loop
    saturation_s: float = 3.0  # the goal out of reach this long: the target is out of reach
    oscillation_band_n: float = 0.5  # error swings under this are not counted as oscillation
    oscillation_crossings: int = 4  # sign changes of the error (each over the band) ...
    oscillation_window_s: float = 1.0  # ... within this long trip the loop
    reading_noise_n: float = 0.0  # the feedback's scatter (1 sigma): an error this small earns half its move

    def __post_init__(self) -> None:
        for name in ("stiffness_n_per_mm", "segment_s", "max_speed_mm_s", "stale_after_s", "saturation_s",
                     "oscillation_window_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, not {value}")
        if not (math.isfinite(self.reading_noise_n) and self.reading_noise_n >= 0):
            raise ValueError(f"reading_noise_n must be zero or a positive number (N), not {self.reading_noise_n}")
        if self.oscillation_crossings < 2 or self.oscillation_band_n < 0:
            raise ValueError("oscillation_crossings must be at least 2 and oscillation_band_n not negative")


@dataclass(frozen=True)
class LoopCommand:
    """What to do until the next reading: go to ``goal_mm`` along the gel's inward normal (the reading's frame, mm),
    or stop (``stop`` the reason). ``error_n``: target minus reading; ``stiffness_n_per_mm``: the stiffness the goal
    assumed; ``clipped``: the goal was cut to what the tool may reach."""

    goal_mm: float
    error_n: float
    stiffness_n_per_mm: float
    clipped: bool = False
    stop: str | None = None


class ForceLoop:
    """The loop for one target (N on the gel, pressing positive); :meth:`update` once per reading."""

    def __init__(self, target_n: float, params: ForceLoopParams | None = None) -> None:
        if not (math.isfinite(target_n) and target_n >= 0):
            raise ValueError(f"the force target must be zero or positive (N), not {target_n}")
        self.params = params or ForceLoopParams()
        self.target_n = float(target_n)
        self.stopped: str | None = None
        self.stiffness_n_per_mm = self.params.stiffness_n_per_mm
        self._anchor: tuple[float, float] | None = None  # (place mm, force N) the secant is measured from
        self._backoff: tuple[float, float, float] | None = None  # a back-off's reading: place mm, force N, and the
        # place it asked for (mm): the tool goes no further out until a reading shows the unloading
        self._step: tuple[float, int] | None = None  # the target and the side its readings approach from (0: reached)
        self._clipped_since_s: float | None = None
        self._last_sign = 0
        self._crossings: deque[float] = deque()

    def update(self, t_s: float, force_n: float, place_mm: float, reading_t_s: float | None = None,
               reach_mm: tuple[float, float] = (-math.inf, math.inf), place_now_mm: float | None = None
               ) -> LoopCommand:
        """The command at time ``t_s`` (s, any fixed origin) from the newest reading ``force_n`` (N, pressing
        positive), taken at ``reading_t_s`` (default ``t_s``; -inf: no reading yet) with the tool at ``place_mm``
        along the inward normal (mm, any fixed origin) and now at ``place_now_mm`` (default: unknown); the goal is
        cut to ``reach_mm`` (lowest, highest place allowed). Once stopped, every later call stops too."""
        p = self.params
        error = self.target_n - float(force_n)
        if self.stopped is not None:
            return LoopCommand(place_mm, error, self.stiffness_n_per_mm, stop=self.stopped)
        age_s = t_s - (t_s if reading_t_s is None else reading_t_s)
        if not math.isfinite(age_s):
            return self._stop(place_mm, error, "the force feedback gave no reading")
        if age_s > p.stale_after_s or not (math.isfinite(force_n) and math.isfinite(place_mm)):
            return self._stop(place_mm, error, f"the force feedback stalled: the newest reading is "
                                               f"{age_s * 1e3:.0f} ms old (more than {p.stale_after_s * 1e3:.0f} ms)")
        k = self._stiffness(place_mm, float(force_n))
        correction = self._trusted_n(error)
        if not self._reached(error) and place_now_mm is not None:
            still = place_now_mm - place_mm  # on the step, the scatter may hold the tool still, never turn it back
            correction = min(max(k * still, min(correction, error)), max(correction, error))
        wanted = max(place_mm + correction / k, self._backoff_limit(place_mm, float(force_n), correction, k))
        goal = min(max(wanted, reach_mm[0]), reach_mm[1])
        clipped = goal != wanted
        if clipped:
            self._clipped_since_s = t_s if self._clipped_since_s is None else self._clipped_since_s
            if t_s - self._clipped_since_s >= p.saturation_s:
                return self._stop(goal, error, f"saturated: the force stayed {error:+.2f} N off its target with the "
                                               f"tool at the limit of its reach for {p.saturation_s:g} s")
        else:
            self._clipped_since_s = None
        if self._oscillating(t_s, error):
            return self._stop(goal, error, f"oscillating: the force crossed its target {p.oscillation_crossings} "
                                           f"times within {p.oscillation_window_s:g} s by more than "
                                           f"{p.oscillation_band_n:g} N; raise stiffness_n_per_mm")
        return LoopCommand(goal, error, k, clipped)

    def _reached(self, error: float) -> bool:
        """Whether a reading has reached the target since the loop began or the target changed (``error``: this
        reading's, N): the step to it is over."""
        side = 1 if error > 0 else -1
        if self._step is None or self._step[0] != self.target_n:
            self._step = (self.target_n, side)
        if self._step[1] != 0 and (error == 0 or side != self._step[1]):
            self._step = (self.target_n, 0)
        return self._step[1] == 0

    def _trusted_n(self, error: float) -> float:
        """The part of the error ``error`` (N) the loop acts on: ``e**3 / (e**2 + s**2)`` with ``s`` the feedback's
        scatter (``reading_noise_n``). An error well above the scatter is acted on whole (a step is as fast as a
        clean feedback's); one within it in proportion to how far it stands out, so the scatter reaches the force
        only in part while readings that agree still close the rest."""
        noise = self.params.reading_noise_n
        if noise == 0:
            return error
        return error * error * error / (error * error + noise * noise)

    def _stiffness(self, place_mm: float, force_n: float) -> float:
        """The stiffness to assume (N/mm): the setting, or more if the secant since the anchor reading says so."""
        anchor = self._anchor
        if anchor is None:
            self._anchor = (place_mm, force_n)
        elif abs(place_mm - anchor[0]) >= STIFFNESS_BASELINE_MM:
            secant = (force_n - anchor[1]) / (place_mm - anchor[0])
            self.stiffness_n_per_mm = max(self.params.stiffness_n_per_mm, STIFFNESS_MARGIN * secant)
            self._anchor = (place_mm, force_n)
        return self.stiffness_n_per_mm

    def continue_from(self, earlier: ForceLoop, offset_mm: float) -> None:
        """Carry on from ``earlier``, the loop of the move before on the same contact: the stiffness it measured
        and, for the same target, whether a reading has reached it and the back-off it is in. Places run from each
        move's start: ``earlier``'s place ``p`` is ``p + offset_mm`` in this loop's."""
        self.stiffness_n_per_mm = earlier.stiffness_n_per_mm
        if earlier._anchor is not None:
            self._anchor = (earlier._anchor[0] + offset_mm, earlier._anchor[1])
        if earlier.target_n != self.target_n:
            return
        self._step = earlier._step
        if earlier._backoff is not None:
            place, force, limit = earlier._backoff
            self._backoff = (place + offset_mm, force, limit + offset_mm)

    def _backoff_limit(self, place_mm: float, force_n: float, error: float, k: float) -> float:
        """How far out (mm along the normal) the tool may go on this reading (``error``: the error acted on, N):
        where the reading that began the back-off asked for (its place + e / k), until a reading shows the unloading
        (it fell by UNLOADING_SEEN of what ``k`` says the back-off took off since, and by UNLOADING_SCATTERS times
        ``reading_noise_n``), or it has risen by its excess over the target and by more than ``oscillation_band_n``
        (a load that grows), or the tool has pressed back in a baseline beyond where the back-off began; then from
        this reading. -inf: no limit (the reading is not above the target)."""
        if self._backoff is not None:
            from_place, from_force, _ = self._backoff
            backed_mm = from_place - place_mm
            fall_n = from_force - force_n
            seen = (backed_mm >= STIFFNESS_BASELINE_MM and fall_n >= UNLOADING_SEEN * k * backed_mm
                    and fall_n >= UNLOADING_SCATTERS * self.params.reading_noise_n)
            risen = force_n - from_force >= max(from_force - self.target_n, self.params.oscillation_band_n)
            if seen or risen or backed_mm <= -STIFFNESS_BASELINE_MM:
                self._backoff = None
        if error >= 0:
            return -math.inf
        if self._backoff is None:
            self._backoff = (place_mm, force_n, place_mm + error / k)
        return self._backoff[2]

    def _oscillating(self, t_s: float, error: float) -> bool:
        p = self.params
        if abs(error) <= p.oscillation_band_n:
            return False
        sign = 1 if error > 0 else -1
        if self._last_sign and sign != self._last_sign:
            self._crossings.append(t_s)
        self._last_sign = sign
        while self._crossings and t_s - self._crossings[0] > p.oscillation_window_s:
            self._crossings.popleft()
        return len(self._crossings) >= p.oscillation_crossings

    def _stop(self, place_mm: float, error: float, reason: str) -> LoopCommand:
        self.stopped = reason
        return LoopCommand(place_mm, error, self.stiffness_n_per_mm, stop=reason)


class HeldMove:
    """The jog segments of a move along the gel plane with the force loop on the normal.

    From ``start_mm`` (machine mm) toward ``target_mm``'s place in the gel plane (its component along ``normal``,
    the gel's inward unit normal in machine axes, is ignored) at ``speed_mm_s``, in segments of the loop's
    ``segment_s`` (or, with no lateral move, for ``duration_s``: a force held in place). Along ``normal`` the
    segments head for the loop's goal at a speed that a stop at half the machine's acceleration (``accel_mm_s2``
    along the normal) allows and that changes by at most that acceleration per segment, never further in than
    ``deepest_mm`` (a point the tool's component along ``normal`` stays at or short of: the deepest press
    allowed). An executor calls
    :meth:`next_segment` once per segment with the newest reading and where the tool is, and sends the segment it
    returns.

    With the reading's tangential part (a :class:`~labrig.protocol.slip.ContactReading`) the move may also end
    early: once the tangential force reaches ``until_tangential_n`` (N; :attr:`ended_by` "tangential force"), or
    when ``slip``'s detector tells the contact slips (:attr:`slipped_at_s`) and its action is "stop" (ended_by
    "slip"); the action "press" raises the loop's target instead (:meth:`SlipDetector.press_target_n`, at most the
    reflex's ``press_limit_n``), and "report" only records it.

    ``follows``: the held move just before on the same contact (the press before a wait, a wait before a shear),
    whose loop this one carries on from (:meth:`ForceLoop.continue_from`)."""

    def __init__(self, start_mm: npt.ArrayLike, target_mm: npt.ArrayLike, normal: npt.ArrayLike,
                 speed_mm_s: float, loop: ForceLoop, deepest_mm: npt.ArrayLike | None = None, *,
                 accel_mm_s2: float = 10.0, duration_s: float = 0.0, until_tangential_n: float | None = None,
                 slip: SlipReflex | None = None, follows: HeldMove | None = None) -> None:
        if not (math.isfinite(accel_mm_s2) and accel_mm_s2 > 0):
            raise ValueError(f"the acceleration must be a positive number (mm/s**2), not {accel_mm_s2}")
        self.start = np.asarray(start_mm, np.float64)
        self.normal = np.asarray(normal, np.float64) / np.linalg.norm(normal)
        delta = np.asarray(target_mm, np.float64) - self.start
        self.lateral = delta - (delta @ self.normal) * self.normal
        self.loop = loop
        if follows is not None and np.allclose(follows.normal, self.normal):
            loop.continue_from(follows.loop, float((follows.start - self.start) @ self.normal))
        self.accel_mm_s2 = float(accel_mm_s2)
        segment_s = loop.params.segment_s
        lateral_mm = float(np.linalg.norm(self.lateral))
        by_path = math.ceil(lateral_mm / (speed_mm_s * segment_s) - 1e-9) if lateral_mm > 0 else 0
        self.segments = max(1, by_path, math.ceil(duration_s / segment_s - 1e-9))
        self._lateral_mm = lateral_mm
        self._lateral_speed_mm_s = lateral_mm / (self.segments * segment_s)
        self._progress_mm = 0.0  # how far along the lateral path the segments handed out reach
        self.done = 0
        self.last = LoopCommand(0.0, 0.0, loop.params.stiffness_n_per_mm)
        self.speed_mm_s = 0.0  # the last segment's commanded speed along the normal
        self._end_place = 0.0
        self.max_place_mm = math.inf if deepest_mm is None else float(
            (np.asarray(deepest_mm, np.float64) - self.start) @ self.normal)
        self.until_tangential_n = until_tangential_n
        self.slip = slip
        self.slip_detector = None if slip is None else SlipDetector(slip.friction, slip.params)
        self.contact: ContactReading | None = None  # the newest reading with its tangential part
        self.slip_check: SlipCheck | None = None  # the detector's verdict on it
        self.slipped_at_s: float | None = None  # when the detector first told slip (the executor's clock, s)
        self.ended_by: str | None = None  # "tangential force" or "slip": the move ended before its path did

    def place_mm(self, position_mm: npt.ArrayLike) -> float:
        """A machine position's place along the inward normal from the start (mm)."""
        return float((np.asarray(position_mm, np.float64) - self.start) @ self.normal)

    def next_segment(self, t_s: float, force_n: float, here_mm: npt.ArrayLike, reading_t_s: float | None = None,
                     reading_mm: npt.ArrayLike | None = None, contact: ContactReading | None = None
                     ) -> tuple[npt.NDArray[np.float64], float] | str | None:
        """The next segment's end (machine mm) and feed (mm/min), from the reading ``force_n`` taken at
        ``reading_t_s`` with the tool at ``reading_mm`` (default: now, ``here_mm``) and, where given, the same
        reading's tangential part ``contact``; the loop's stop (its reason) instead; None once the move's last
        segment has been handed out, or once it ended early (:attr:`ended_by`)."""
        if (self.done >= self.segments and self._progress_mm >= self._lateral_mm) or self.ended_by is not None:
            return None
        if contact is not None and self._ends_on(t_s, contact, here_mm if reading_mm is None else reading_mm):
            return None
        p = self.loop.params
        at_reading = self.place_mm(here_mm if reading_mm is None else reading_mm)
        command = self.loop.update(t_s, force_n, at_reading, reading_t_s, (-math.inf, self.max_place_mm),
                                   self.place_mm(here_mm))
        self.last = command
        if command.stop is not None:
            return command.stop
        self.done += 1
        self.speed_mm_s = self._normal_speed(command.goal_mm - self._end_place)
        place = self._end_place + self.speed_mm_s * p.segment_s
        self._progress_mm = min(self._lateral_mm, self._progress_mm + self._lateral_pace_mm_s() * p.segment_s)
        along = self._progress_mm / self._lateral_mm if self._lateral_mm > 0 else 0.0
        end = self.start + self.lateral * along + self.normal * place
        # the path's pace comes from the segments' schedule: the feed only caps it
        feed_mm_min = max(math.hypot(self._lateral_speed_mm_s, p.max_speed_mm_s) * 60, 1.0)
        self._end_place = place
        return end, feed_mm_min

    def _lateral_pace_mm_s(self) -> float:
        """The lateral path's speed (mm/s): the move's, or, past TANGENTIAL_APPROACH_FRACTION of a tangential
        target, no more than TANGENTIAL_FINE_SPEED_MM_S (the stop at the target then overshoots it by little)."""
        until, contact = self.until_tangential_n, self.contact
        if until is not None and contact is not None and contact.tangential_n >= TANGENTIAL_APPROACH_FRACTION * until:
            return min(self._lateral_speed_mm_s, TANGENTIAL_FINE_SPEED_MM_S)
        return self._lateral_speed_mm_s

    def travel_mm(self, position_mm: npt.ArrayLike) -> float:
        """How far a machine position is along the move's lateral path from the start (mm)."""
        if self._lateral_mm <= 0:
            return 0.0
        return float((np.asarray(position_mm, np.float64) - self.start) @ self.lateral) / self._lateral_mm

    def _ends_on(self, t_s: float, contact: ContactReading, reading_mm: npt.ArrayLike) -> bool:
        """Whether ``contact`` (measured with the tool at ``reading_mm``) ends the move (a tangential target reached,
        a slip to stop at); a slip to press against raises the loop's target."""
        self.contact = contact
        if self.until_tangential_n is not None and contact.tangential_n >= self.until_tangential_n:
            self.ended_by = "tangential force"
            return True
        if self.slip is None or self.slip_detector is None:
            return False
        self.slip_check = self.slip_detector.update(contact, self.travel_mm(reading_mm))
        if not self.slip_check.slipping:
            return False
        if self.slipped_at_s is None:
            self.slipped_at_s = t_s
        if self.slip.action == "stop":
            self.ended_by = "slip"
            return True
        if self.slip.action == "press":
            wanted = self.slip_detector.press_target_n(contact)
            self.loop.target_n = min(max(self.loop.target_n, wanted), self.slip.press_limit_n)
        return False

    def _normal_speed(self, to_goal_mm: float) -> float:
        """The next segment's speed along the normal (mm/s): toward the goal ``to_goal_mm`` past the last end, no
        faster than a stop at half the machine's acceleration allows and than the goal is one segment away, and no
        more than the acceleration's change from the last segment's speed (a path the machine follows as
        commanded, its segments in line)."""
        p = self.loop.params
        dt = p.segment_s
        braking = math.sqrt(self.accel_mm_s2 * abs(to_goal_mm))  # v**2 = 2 (a / 2) d
        wanted = math.copysign(min(p.max_speed_mm_s, braking, abs(to_goal_mm) / dt), to_goal_mm)
        step = self.accel_mm_s2 * dt
        return min(max(wanted, self.speed_mm_s - step), self.speed_mm_s + step)


#: What the loop did, segment by segment (a recording of a run that holds a force has it).
CONTROL_STREAM = StreamSpec(
    "control",
    (
        Column("t_host_us", "<i8", "us", "host time the segment was commanded"),
        Column("target_n", "<f4", "N", "the normal force to hold, on the gel, pressing positive"),
        Column("feedback_n", "<f4", "N", "the reading the command came from"),
        Column("reading_age_us", "<i8", "us", "how old the reading was"),
        Column("speed_mm_s", "<f4", "mm/s", "commanded press-in speed along the gel normal"),
        Column("stiffness_n_per_mm", "<f4", "N/mm", "the contact stiffness the goal assumed"),
        Column("clipped", "u1", "", "1: the goal was cut to the tool's reach (depth cap, speed)"),
        Column("position_mm", "<f8", "mm", "the segment's end, machine X, Y, Z", (3,)),
        Column("tangential_n", "<f4", "N", "the reading's tangential force |Ft| on the gel (nan: not read)"),
        Column("slip_share", "<f4", "", "share of the contact's markers at friction (nan: no dense field, no reflex)"),
        Column("friction_ratio", "<f4", "", "|Ft| / (friction |Fn|) of the reading (nan: no slip reflex)"),
        Column("stiffness_ratio", "<f4", "", "d|Ft|/d(travel) over its steepest in the move: the stall (nan: not yet)"),
        Column("following_ratio", "<f4", "",
               "d|u_t|/d(travel) of the contact's markers over its steepest: the field's stall (nan: no field)"),
        Column("slipping", "u1", "", "1: the slip reflex tells the contact slips"),
        Column("slip_cue", "S16", "", "the cue that tells it: share, net ratio, force stall, field stall (empty: none)"),
    ),
    chunk_rows=1024,
    description="the force loop's commands (feedback, command, segment)",
)
