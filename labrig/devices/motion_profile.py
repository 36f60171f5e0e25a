"""Trapezoidal motion planning of a GRBL-style controller, shared by the twin and the driver.

Frames and units
----------------
Positions are machine coordinates (MPos) of the tool reference point in mm, axes X, Y, Z.
Speeds are mm/s along the path, accelerations mm/s**2, times host microseconds (float ``t_us``).
Settings keep GRBL's own units (rates in mm/min) and are converted once, in :class:`MachineLimits`.

Model
-----
* A move is a straight :class:`Block` between two step-quantised positions. Its nominal speed
  is the programmed feed (or the rapid rate) capped so that no axis exceeds its ``$110-$112``
  rate; its acceleration is the largest one that keeps every axis within ``$120-$122``.
* A corner between two blocks may be taken at the junction-deviation speed
  ``v**2 = a * d * s / (1 - s)`` with ``s = sin(theta / 2)``, ``theta`` the angle between the
  reversed incoming and the outgoing direction and ``d`` the ``$11`` deviation (mm). Straight
  continuations are limited only by the blocks' nominal speeds; reversals stop.
* The queue is planned as the firmware does: a backward pass from a full stop at the end of the
  last queued block, then a forward pass from the current speed. Each block then runs a
  trapezoid: accelerate, cruise, decelerate (or a triangle when it is too short to cruise).
* A feed hold decelerates at full acceleration along the queued path; the remaining blocks stay
  queued and resume from rest.

Pure functions (:func:`make_block`, :func:`junction_speed_mm_s`, :func:`plan_speeds`,
:func:`trapezoid`, :func:`positions_at`) do the maths; :class:`MotionTimeline` applies them on a
time axis (append, cycle start, hold, resume, stop) and keeps the executed history, so a caller
can ask for the position at any time. The GRBL twin runs the machine with it; the driver runs the
same timeline on the host times of the controller's answers to reconstruct the pose between polls.

The twin's planner differs from the firmware in small ways (documented in :mod:`labrig.sim.grbl_twin`):
no step-segment buffer, exact real-valued profiles, and the whole queue is replanned on each change.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

Vec3 = tuple[float, float, float]

#: GRBL's floor on a programmed feed (mm/min).
MINIMUM_FEED_MM_MIN = 1.0
#: Corners sharper than this (cosine of the turn) are taken at a full stop; straighter ones without a limit.
_COS_STRAIGHT = 0.999999
US_PER_S = 1_000_000.0


@dataclass(frozen=True)
class MachineLimits:
    """Per-axis limits from GRBL settings, in GRBL's units."""

    max_rate_mm_min: Vec3 = (500.0, 500.0, 500.0)  # $110-$112
    accel_mm_s2: Vec3 = (10.0, 10.0, 10.0)  # $120-$122
    steps_per_mm: Vec3 = (250.0, 250.0, 250.0)  # $100-$102
    junction_deviation_mm: float = 0.010  # $11

    @classmethod
    def from_settings(cls, settings: Mapping[int, float]) -> MachineLimits:
        """Limits from a ``{number: value}`` settings map (``$$``); missing ones keep the defaults."""
        d = cls()

        def axes(first: int, default: Vec3) -> Vec3:
            return tuple(float(settings.get(first + i, default[i])) for i in range(3))  # type: ignore[return-value]

        return cls(
            max_rate_mm_min=axes(110, d.max_rate_mm_min),
            accel_mm_s2=axes(120, d.accel_mm_s2),
            steps_per_mm=axes(100, d.steps_per_mm),
            junction_deviation_mm=float(settings.get(11, d.junction_deviation_mm)),
        )

    def accel_along_mm_s2(self, direction: Sequence[float]) -> float:
        """The acceleration of a straight move along ``direction`` (mm/s**2): the largest that keeps every axis
        within its own, as the planner gives a block."""
        norm = math.sqrt(sum(float(u) * float(u) for u in direction))
        return min(acc * norm / abs(float(u)) for u, acc in zip(direction, self.accel_mm_s2) if abs(float(u)) > 1e-12)


@dataclass(frozen=True)
class Block:
    """One straight move as the planner holds it.

    ``nominal_mm_s``: the cruise speed before overrides; ``max_entry_mm_s``: the fastest the
    block may be entered (junction and both nominal speeds), set when it joins a queue.
    ``tag`` is the caller's (a line number, a jog marker, ...).
    """

    start_mm: Vec3
    end_mm: Vec3
    length_mm: float
    unit: Vec3
    nominal_mm_s: float
    accel_mm_s2: float
    rapid: bool = False
    max_entry_mm_s: float = 0.0
    tag: object = None

    def point_mm(self, s_mm: float) -> Vec3:
        """The point ``s_mm`` along the block."""
        return (
            self.start_mm[0] + self.unit[0] * s_mm,
            self.start_mm[1] + self.unit[1] * s_mm,
            self.start_mm[2] + self.unit[2] * s_mm,
        )


@dataclass(frozen=True)
class Segment:
    """A piece of constant acceleration along a straight line: the unit of the exported plan.

    Position at ``t_start_us <= t <= t_start_us + duration_us``:
    ``start_mm + unit * (v_start_mm_s * tau + accel_mm_s2 * tau**2 / 2)``, ``tau = (t - t_start_us) / 1e6`` s.
    After its end the position stays at the end point until the next segment starts. A segment
    of zero duration with zero speed is a jump (the position counter was set, e.g. by homing).
    """

    t_start_us: float
    duration_us: float
    start_mm: Vec3
    unit: Vec3
    v_start_mm_s: float
    accel_mm_s2: float
    tag: object = None

    @property
    def t_end_us(self) -> float:
        return self.t_start_us + self.duration_us

    @property
    def distance_mm(self) -> float:
        tau = self.duration_us / US_PER_S
        return self.v_start_mm_s * tau + 0.5 * self.accel_mm_s2 * tau * tau

    @property
    def end_mm(self) -> Vec3:
        d = self.distance_mm
        return (self.start_mm[0] + self.unit[0] * d, self.start_mm[1] + self.unit[1] * d, self.start_mm[2] + self.unit[2] * d)

    @property
    def v_end_mm_s(self) -> float:
        return self.v_start_mm_s + self.accel_mm_s2 * self.duration_us / US_PER_S


# -- pure functions ----------------------------------------------------------------------


def quantize_mm(position_mm: Sequence[float], steps_per_mm: Sequence[float]) -> Vec3:
    """The position the steppers can reach: rounded to whole steps per axis."""
    return tuple(round(p * s) / s for p, s in zip(position_mm, steps_per_mm))  # type: ignore[return-value]


def make_block(
    start_mm: Sequence[float],
    end_mm: Sequence[float],
    feed_mm_min: float | None,
    limits: MachineLimits,
    *,
    tag: object = None,
) -> Block | None:
    """A block from ``start_mm`` to ``end_mm`` (both step-quantised by the caller).

    ``feed_mm_min=None`` is a rapid (G0): each axis limited by its max rate only. Returns None for
    a move of no whole step, which the firmware drops.
    """
    delta = [float(e) - float(s) for s, e in zip(start_mm, end_mm)]
    steps = [abs(round(d * spm)) for d, spm in zip(delta, limits.steps_per_mm)]
    if max(steps) == 0:
        return None
    length = math.sqrt(sum(d * d for d in delta))
    unit = tuple(d / length for d in delta)
    speed = math.inf if feed_mm_min is None else max(float(feed_mm_min), MINIMUM_FEED_MM_MIN) / 60.0
    accel = math.inf
    for u, rate, acc in zip(unit, limits.max_rate_mm_min, limits.accel_mm_s2):
        if abs(u) > 1e-12:
            speed = min(speed, rate / 60.0 / abs(u))
            accel = min(accel, acc / abs(u))
    return Block(
        start_mm=tuple(float(x) for x in start_mm),  # type: ignore[arg-type]
        end_mm=tuple(float(x) for x in end_mm),  # type: ignore[arg-type]
        length_mm=length,
        unit=unit,  # type: ignore[arg-type]
        nominal_mm_s=speed,
        accel_mm_s2=accel,
        rapid=feed_mm_min is None,
        tag=tag,
    )


def junction_speed_mm_s(previous: Block, block: Block, deviation_mm: float) -> float:
    """The fastest speed to pass the corner from ``previous`` into ``block`` (junction deviation)."""
    cos_turn = -sum(a * b for a, b in zip(previous.unit, block.unit))  # -1: straight on, +1: reversal
    if cos_turn > _COS_STRAIGHT:
        return 0.0
    if cos_turn < -_COS_STRAIGHT:
        return math.inf
    sin_half = math.sqrt(0.5 * (1.0 - cos_turn))
    accel = min(previous.accel_mm_s2, block.accel_mm_s2)
    return math.sqrt(accel * deviation_mm * sin_half / (1.0 - sin_half))


def plan_speeds(
    lengths_mm: Sequence[float],
    nominal_mm_s: Sequence[float],
    accel_mm_s2: Sequence[float],
    max_entry_mm_s: Sequence[float],
    v_start_mm_s: float,
) -> list[tuple[float, float]]:
    """Entry and exit speed of each queued block: a stop after the last, ``v_start_mm_s`` now.

    ``max_entry_mm_s[i]`` caps the speed at the start of block ``i`` (ignored for block 0, which is
    entered at the current speed). Backward pass from the final stop, then forward pass from now.
    """
    n = len(lengths_mm)
    exits = [0.0] * n
    for i in range(n - 1, 0, -1):
        entry = min(
            max_entry_mm_s[i], nominal_mm_s[i], nominal_mm_s[i - 1], math.sqrt(exits[i] ** 2 + 2 * accel_mm_s2[i] * lengths_mm[i])
        )
        exits[i - 1] = entry
    speeds = []
    entry = v_start_mm_s
    for i in range(n):
        exit_ = min(exits[i], math.sqrt(entry * entry + 2 * accel_mm_s2[i] * lengths_mm[i]))
        speeds.append((entry, exit_))
        entry = exit_
    return speeds


def trapezoid(
    length_mm: float, v_entry_mm_s: float, v_nominal_mm_s: float, v_exit_mm_s: float, accel_mm_s2: float
) -> list[tuple[float, float, float]]:
    """Pieces ``(v_start_mm_s, accel_mm_s2, duration_s)`` covering ``length_mm`` from entry to exit speed.

    Accelerate (or decelerate, if entered above nominal) to the peak speed, cruise, decelerate to
    the exit speed. If the speeds cannot be reached within the length at ``accel_mm_s2`` (only by
    rounding), the single ramp that can is used instead.
    """
    if length_mm <= 0.0:
        return []
    v0, v1, a = max(v_entry_mm_s, 0.0), max(v_exit_mm_s, 0.0), accel_mm_s2
    vn = max(v_nominal_mm_s, v1)
    if abs(v0 * v0 - v1 * v1) >= 2 * a * length_mm:  # one ramp only (exact or a rounding rescue)
        if v0 == v1:
            return [(v0, 0.0, length_mm / v0)] if v0 > 0 else []
        a_eff = (v1 * v1 - v0 * v0) / (2 * length_mm)
        return [(v0, a_eff, (v1 - v0) / a_eff)]
    # Entered above nominal: slow down to it; otherwise the highest peak that still fits.
    peak = vn if v0 > vn else min(vn, math.sqrt((2 * a * length_mm + v0 * v0 + v1 * v1) / 2))
    d_first = abs(v0 * v0 - peak * peak) / (2 * a)
    d_last = (peak * peak - v1 * v1) / (2 * a)
    d_cruise = max(length_mm - d_first - d_last, 0.0)
    pieces = []
    if peak != v0:
        pieces.append((v0, a if peak > v0 else -a, abs(peak - v0) / a))
    if d_cruise > 0.0 and peak > 0.0:
        pieces.append((peak, 0.0, d_cruise / peak))
    if peak > v1:
        pieces.append((peak, -a, (peak - v1) / a))
    return pieces


def positions_at(
    segments: Sequence[Segment], t_us: npt.ArrayLike, initial_mm: Sequence[float] = (0.0, 0.0, 0.0)
) -> npt.NDArray[np.float64]:
    """Positions (N, 3) mm at host times ``t_us`` of a time-ordered segment list; ``initial_mm`` before the first."""
    return SegmentTable.from_segments(segments, initial_mm).positions_at(t_us)


def _row_of(seg: Segment) -> tuple[float, ...]:
    return (seg.t_start_us, seg.duration_us, *seg.start_mm, *seg.unit, seg.v_start_mm_s, seg.accel_mm_s2)


def _position_in(starts: list[float], listed: list[list[float]], t_us: float,
                 before: tuple[float, ...]) -> tuple[float, float, float]:
    """The position (mm) at ``t_us`` on rows given as Python floats (``starts`` their start times), ``before``
    ahead of the first."""
    i = bisect.bisect_right(starts, t_us) - 1
    if i < 0:
        return before[0], before[1], before[2]
    t0, duration, x, y, z, ux, uy, uz, v0, accel = listed[i]
    tau = min(max(t_us - t0, 0.0), duration) / US_PER_S
    dist = v0 * tau + 0.5 * accel * tau * tau
    return x + ux * dist, y + uy * dist, z + uz * dist


class SegmentTable:
    """Segments as columns for vectorised evaluation, and as Python floats for one-time lookups (append-only:
    amortised growth, so a table that gains a row every few milliseconds for minutes never copies itself whole)."""

    def __init__(self, initial_mm: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        self.initial_mm = tuple(float(x) for x in initial_mm)
        self._buf = np.zeros((16, 10))
        self._n = 0
        self._starts: list[float] = []  # each row's start (us), for bisect
        self._listed: list[list[float]] = []  # each row as Python floats

    @classmethod
    def from_segments(cls, segments: Sequence[Segment], initial_mm: Sequence[float] = (0.0, 0.0, 0.0)) -> SegmentTable:
        table = cls(initial_mm)
        for seg in segments:
            table.append(seg)
        return table

    def __len__(self) -> int:
        return self._n

    def append(self, seg: Segment) -> None:
        if self._n == len(self._buf):
            grown = np.zeros((2 * len(self._buf), 10))
            grown[: self._n] = self._buf[: self._n]
            self._buf = grown
        self._set(self._n, seg)
        self._n += 1

    def replace(self, index: int, seg: Segment) -> None:
        if not 0 <= index < self._n:
            raise IndexError(f"segment row {index} of {self._n}")
        self._set(index, seg)

    def _set(self, index: int, seg: Segment) -> None:
        self._buf[index] = _row_of(seg)
        row = self._buf[index].tolist()
        if index == len(self._listed):
            self._starts.append(row[0])
            self._listed.append(row)
        else:
            self._starts[index] = row[0]
            self._listed[index] = row

    def _array(self) -> npt.NDArray[np.float64]:
        """The rows (K, 10), a view: valid until the next :meth:`append` or :meth:`replace`."""
        return self._buf[: self._n]

    def position_of(self, t_us: float) -> tuple[float, float, float]:
        """The position (mm) at one host time, as Python floats (the same arithmetic as :meth:`positions_of_rows`)."""
        return _position_in(self._starts, self._listed, t_us, self.initial_mm)

    def positions_at(self, t_us: npt.ArrayLike, extra: Sequence[Segment] = ()) -> npt.NDArray[np.float64]:
        """Positions (N, 3) mm at ``t_us``, with ``extra`` segments (a live plan) after the table's."""
        rows = self._array()
        if extra:
            more = np.asarray([_row_of(s) for s in extra])
            rows = np.concatenate([rows, more]) if len(rows) else more
        return self.positions_of_rows(rows, t_us)

    def with_extra(self, extra: Sequence[Segment]) -> npt.NDArray[np.float64]:
        """The table's rows (K, 10) followed by ``extra`` segments' rows (for :meth:`positions_of_rows`)."""
        rows = self._array()
        if not extra:
            return rows
        more = np.asarray([_row_of(s) for s in extra])
        return np.concatenate([rows, more]) if len(rows) else more

    def positions_of_rows(self, rows: npt.NDArray[np.float64], t_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Positions (N, 3) mm at ``t_us`` on segment rows from :meth:`with_extra` (``initial_mm`` before them)."""
        t = np.atleast_1d(np.asarray(t_us, dtype=np.float64))
        if t.size == 1 and len(rows):  # one time (kHz samplers): the same arithmetic on Python floats
            i = int(np.searchsorted(rows[:, 0], t[0], side="right")) - 1
            if i < 0:
                return np.array([self.initial_mm])
            t0, duration, x, y, z, ux, uy, uz, v0, accel = rows[i].tolist()
            tau = min(max(float(t[0]) - t0, 0.0), duration) / US_PER_S
            dist = v0 * tau + 0.5 * accel * tau * tau
            return np.array([[x + ux * dist, y + uy * dist, z + uz * dist]])
        out = np.empty((t.size, 3), dtype=np.float64)
        out[:] = self.initial_mm
        if len(rows) == 0:
            return out
        idx = np.searchsorted(rows[:, 0], t, side="right") - 1
        have = idx >= 0
        r = rows[idx[have]]
        tau = np.clip(t[have] - r[:, 0], 0.0, r[:, 1]) / US_PER_S
        dist = r[:, 8] * tau + 0.5 * r[:, 9] * tau * tau
        out[have] = r[:, 2:5] + r[:, 5:8] * dist[:, None]
        return out


# -- the timeline ------------------------------------------------------------------------


@dataclass(frozen=True)
class _Piece:
    """A planned piece inside one queued block: ``s0_mm`` along it at ``t0_us``."""

    t0_us: float
    dt_us: float
    block: Block
    s0_mm: float
    v0_mm_s: float
    accel_mm_s2: float
    last_of_block: bool

    @property
    def t1_us(self) -> float:
        return self.t0_us + self.dt_us

    def at(self, t_us: float) -> tuple[float, float]:
        """(distance along the block mm, speed mm/s) at ``t_us`` within the piece."""
        tau = min(max(t_us - self.t0_us, 0.0), self.dt_us) / US_PER_S
        return self.s0_mm + self.v0_mm_s * tau + 0.5 * self.accel_mm_s2 * tau * tau, max(
            self.v0_mm_s + self.accel_mm_s2 * tau, 0.0
        )

    def segment(self, t1_us: float | None = None) -> Segment:
        dt = self.dt_us if t1_us is None else min(max(t1_us - self.t0_us, 0.0), self.dt_us)
        return Segment(
            self.t0_us, dt, self.block.point_mm(self.s0_mm), self.block.unit, self.v0_mm_s, self.accel_mm_s2, self.block.tag
        )


class MotionTimeline:
    """Blocks executing on a time axis, with the executed history kept for position queries.

    States: ``idle`` (nothing queued), ``queued`` (blocks waiting for a cycle start), ``run``,
    ``hold`` (decelerating to a feed hold), ``held`` (stopped in a hold, blocks kept). Every
    operation takes a host time ``t_us`` that must not go backwards; the timeline first brings
    itself to that time (finishing blocks), then acts.

    ``feed_scale`` and ``rapid_scale`` (override fractions) multiply nominal speeds at each replan.
    """

    def __init__(self, limits: MachineLimits, position_mm: Sequence[float] = (0.0, 0.0, 0.0), t_us: float = 0.0) -> None:
        self.limits = limits
        self.feed_scale = 1.0
        self.rapid_scale = 1.0
        self._history = SegmentTable(position_mm)
        self._history_list: list[Segment] = []
        self._queue: deque[Block] = deque()
        self._plan: list[_Piece] = []
        self._t_us = float(t_us)
        self._progress_mm = 0.0  # along queue[0] at _t_us
        self._speed_mm_s = 0.0
        self._position_mm: Vec3 = tuple(float(x) for x in position_mm)  # type: ignore[assignment]
        self._state = "idle"
        self._flush_on_stop = False
        self._cycle_row = 0  # first history row of the motion since the last rest
        # the plan's rows (as an array and as Python floats) and the pieces they were made of
        self._plan_rows: tuple[npt.NDArray[np.float64], list[float], list[list[float]]] | None = None
        self._plan_key: list[_Piece] = []

    # -- queries -----------------------------------------------------------------

    @property
    def state(self) -> str:
        return self._state

    @property
    def t_us(self) -> float:
        return self._t_us

    @property
    def queue(self) -> tuple[Block, ...]:
        return tuple(self._queue)

    @property
    def position_mm(self) -> Vec3:
        """The position at :attr:`t_us`."""
        return self._position_mm

    @property
    def speed_mm_s(self) -> float:
        return self._speed_mm_s

    @property
    def tail_mm(self) -> Vec3:
        """Where the queue ends (the position when nothing is queued)."""
        return self._queue[-1].end_mm if self._queue else self._position_mm

    def next_event_us(self) -> float:
        """When the first queued block finishes or the hold comes to rest (inf if nothing moves)."""
        for piece in self._plan:
            if piece.last_of_block:
                return piece.t1_us
        return self._plan[-1].t1_us if self._plan else math.inf

    def segments(self, include_plan: bool = True) -> list[Segment]:
        """Executed segments up to :attr:`t_us`, then (optionally) the current plan beyond it."""
        out = list(self._history_list)
        if include_plan:
            out += [p.segment() for p in self._plan]
        return out

    def positions_at(self, t_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Positions (N, 3) mm at ``t_us``: history, then the current plan (which later events may change)."""
        t = np.atleast_1d(np.asarray(t_us, dtype=np.float64))
        out = self._history.positions_of_rows(self._history._array(), t)
        rows = self._planned()[0]
        if len(rows):  # the plan starts where the history ends: a time from its start on is the plan's
            late = t >= rows[0, 0]
            if late.any():
                out[late] = self._history.positions_of_rows(rows, t[late])
        return out

    def position_at(self, t_us: float) -> tuple[float, float, float]:
        """:meth:`positions_at` for one time, as Python floats (kHz samplers; the same arithmetic)."""
        _, starts, listed = self._planned()
        if starts and t_us >= starts[0]:
            return _position_in(starts, listed, t_us, self._history.initial_mm)
        return self._history.position_of(t_us)

    def _planned(self) -> tuple[npt.NDArray[np.float64], list[float], list[list[float]]]:
        """The plan's rows (kept while the plan does not change)."""
        if self._plan_rows is None or len(self._plan_key) != len(self._plan) or any(
                a is not b for a, b in zip(self._plan_key, self._plan)):
            rows = np.asarray([_row_of(p.segment()) for p in self._plan], dtype=np.float64).reshape(-1, 10)
            listed = rows.tolist()
            self._plan_rows = (rows, [r[0] for r in listed], listed)
            self._plan_key = list(self._plan)
        return self._plan_rows

    # -- operations ----------------------------------------------------------------

    def advance(self, t_us: float) -> list[tuple[float, Block]]:
        """Bring the timeline to ``t_us``; returns the blocks finished on the way, with their end times.

        Finished pieces move to the history whole; the piece in progress stays planned (it is cut
        only when the plan changes), so the history grows by pieces, not by calls.
        """
        t_us = max(float(t_us), self._t_us)
        done: list[tuple[float, Block]] = []
        while self._plan and self._plan[0].t1_us <= t_us:
            piece = self._plan.pop(0)
            self._commit(piece.segment())
            self._progress_mm, self._speed_mm_s = piece.at(piece.t1_us)
            self._position_mm = piece.block.point_mm(self._progress_mm)
            if piece.last_of_block:
                if self._queue and self._queue[0] is piece.block:
                    self._queue.popleft()
                self._position_mm = piece.block.end_mm
                self._progress_mm = 0.0
                done.append((piece.t1_us, piece.block))
        if self._plan:
            piece = self._plan[0]
            self._progress_mm, self._speed_mm_s = piece.at(t_us)
            self._position_mm = piece.block.point_mm(self._progress_mm)
        else:
            self._speed_mm_s = 0.0
            self._settle()
        self._t_us = t_us
        return done

    def append(self, block: Block, t_us: float) -> Block:
        """Queue ``block`` (its ``max_entry_mm_s`` is set from the queue's last block) and replan if running."""
        self.advance(t_us)
        if self._queue:
            prev = self._queue[-1]
            entry = min(
                junction_speed_mm_s(prev, block, self.limits.junction_deviation_mm), prev.nominal_mm_s, block.nominal_mm_s
            )
        else:
            entry = 0.0
        block = replace(block, max_entry_mm_s=entry)
        self._queue.append(block)
        if self._state == "idle":
            self._state = "queued"
        elif self._state == "run":
            self._replan()
        return block

    def start(self, t_us: float) -> bool:
        """Cycle start: run the queued blocks (from a stop). False if there was nothing to start."""
        self.advance(t_us)
        if self._state != "queued" or not self._queue:
            return False
        self._state = "run"
        self._cycle_row = len(self._history_list)
        self._replan()
        return True

    def hold(self, t_us: float) -> None:
        """Feed hold: decelerate at full acceleration along the queued path; blocks stay queued."""
        self.advance(t_us)
        if self._state == "run":
            self._state = "hold"
            plan = self._stop_plan()
            self._cut()
            self._plan = plan
            self._settle()
        elif self._state == "queued":
            self._state = "held"

    def resume(self, t_us: float) -> bool:
        """Cycle start after a hold has come to rest; False if not resting in a hold."""
        self.advance(t_us)
        if self._state != "held":
            return False
        self._state = "queued" if self._queue else "idle"
        return self.start(t_us) if self._queue else True

    def cancel(self, t_us: float) -> None:
        """Jog cancel: decelerate like a hold, then drop the rest of the queue (ends idle)."""
        self.hold(t_us)
        self._flush_on_stop = True
        self._settle()

    def stop(self, t_us: float) -> None:
        """Halt at once (soft reset): no deceleration, the queue is dropped."""
        self.advance(t_us)
        self._cut()
        self._queue.clear()
        self._progress_mm = 0.0
        self._speed_mm_s = 0.0
        self._state = "idle"
        self._flush_on_stop = False

    def set_position(self, position_mm: Sequence[float], t_us: float) -> None:
        """Set the position counter while at rest with nothing queued (homing, re-anchoring): a jump."""
        self.advance(t_us)
        if self._queue:
            raise RuntimeError("set_position needs an empty queue")
        new = (float(position_mm[0]), float(position_mm[1]), float(position_mm[2]))
        if new != self._position_mm:
            self._commit(Segment(self._t_us, 0.0, new, (0.0, 0.0, 0.0), 0.0, 0.0, "jump"))
            self._position_mm = new

    def shift_plan(self, dt_us: float, window_us: float = 250_000.0) -> float:
        """Move the current motion later by ``dt_us`` (earlier if negative): the plan, and the
        executed segments of this cycle that ended within ``window_us`` before now.

        For a model that follows a machine it cannot see, when an observation says the machine is
        ahead of or behind the plan. Older history stays as it was (corrections converge within a
        few observations); the shift never moves a segment before the start of the one it follows.
        Returns the shift applied.
        """
        if not self._plan:
            return 0.0
        rows = self._history_list
        i = len(rows)
        while i > self._cycle_row and rows[i - 1].t_end_us >= self._t_us - window_us:
            i -= 1
        first_start = rows[i].t_start_us if i < len(rows) else self._plan[0].t0_us
        if i > 0:
            dt_us = max(dt_us, rows[i - 1].t_start_us - first_start)
        for j in range(i, len(rows)):
            rows[j] = replace(rows[j], t_start_us=rows[j].t_start_us + dt_us)
            self._history.replace(j, rows[j])
        self._plan = [replace(p, t0_us=p.t0_us + dt_us) for p in self._plan]
        return dt_us

    def rescale(self, t_us: float) -> None:
        """Replan after :attr:`feed_scale` or :attr:`rapid_scale` changed."""
        self.advance(t_us)
        if self._state == "run":
            self._replan()

    # -- internals -----------------------------------------------------------------

    def _cut(self) -> None:
        """Drop the plan, keeping the part of the piece in progress already executed."""
        if self._plan and self._plan[0].t0_us < self._t_us:
            self._commit(self._plan[0].segment(self._t_us))
        self._plan = []

    def _commit(self, seg: Segment) -> None:
        if seg.duration_us > 0.0 or seg.tag == "jump":
            self._history.append(seg)
            self._history_list.append(seg)

    def _nominal(self, block: Block) -> float:
        return block.nominal_mm_s * (self.rapid_scale if block.rapid else self.feed_scale)

    def _replan(self) -> None:
        self._cut()
        blocks = list(self._queue)
        if not blocks:
            self._plan = []
            self._settle()
            return
        lengths = [b.length_mm for b in blocks]
        lengths[0] = max(lengths[0] - self._progress_mm, 0.0)
        nominal = [self._nominal(b) for b in blocks]
        speeds = plan_speeds(
            lengths, nominal, [b.accel_mm_s2 for b in blocks], [b.max_entry_mm_s for b in blocks], self._speed_mm_s
        )
        plan: list[_Piece] = []
        t = self._t_us
        for i, (block, (v_in, v_out)) in enumerate(zip(blocks, speeds)):
            s = self._progress_mm if i == 0 else 0.0
            pieces = trapezoid(lengths[i], v_in, nominal[i], v_out, block.accel_mm_s2)
            if not pieces:
                plan.append(_Piece(t, 0.0, block, block.length_mm, 0.0, 0.0, True))
                continue
            for j, (v0, a, dt_s) in enumerate(pieces):
                dt_us = dt_s * US_PER_S
                plan.append(_Piece(t, dt_us, block, s, v0, a, j == len(pieces) - 1))
                s += v0 * dt_s + 0.5 * a * dt_s * dt_s
                t += dt_us
        self._plan = plan

    def _stop_plan(self) -> list[_Piece]:
        """Pieces that bring the current motion to rest at full deceleration along the queue."""
        plan: list[_Piece] = []
        v, t, s = self._speed_mm_s, self._t_us, self._progress_mm
        for block in self._queue:
            if v <= 0.0:
                break
            remaining = max(block.length_mm - s, 0.0)
            a = block.accel_mm_s2
            if v * v <= 2 * a * remaining:
                dt_us = v / a * US_PER_S
                plan.append(_Piece(t, dt_us, block, s, v, -a, False))
                v = 0.0
                break
            v_out = math.sqrt(v * v - 2 * a * remaining)
            dt_us = (v - v_out) / a * US_PER_S
            plan.append(_Piece(t, dt_us, block, s, v, -a, True))
            t += dt_us
            v, s = v_out, 0.0
        return plan

    def _settle(self) -> None:
        """Update the state once nothing is planned ahead (a hold at rest, a finished cycle)."""
        if self._plan:
            return
        self._speed_mm_s = 0.0
        if self._state in ("hold", "held"):
            if self._flush_on_stop:
                self._queue.clear()
                self._progress_mm = 0.0
                self._flush_on_stop = False
                self._state = "idle"
            else:
                self._state = "held"
        elif self._state == "run":
            self._state = "queued" if self._queue else "idle"
