"""GRBL 1.1 CNC driver on a pyserial port: commands, streaming, status samples, pose reconstruction.

Threads and time
----------------
One I/O thread owns reading: it feeds :class:`~labrig.devices.grbl_protocol.GrblProtocol`, pairs
responses with the lines waiting for them, polls ``?`` at ``poll_hz`` (10 Hz by default) and calls
the callbacks. Callers write lines and real-time bytes from their own thread. All host times are
integer microseconds of the injectable host clock (:mod:`labrig.clock`) relative to
``time_base_ns`` (set it to the recording's ``t0_host_ns`` to stamp in the recording's time base).

Callbacks (run on the I/O thread, or the caller's thread for lines it sends; keep them short):

* ``on_sample(StatusSample)``: every status report; :meth:`StatusSample.columns` is a ready row
  for ``RecordingWriter.put("cnc", ...)``;
* ``on_gcode(t_host_us, direction, line)``: every line sent (0) and received (1), and the
  real-time bytes sent except ``?``, e.g. ``writer.put("gcode", t_host_us=t, direction=d, line=l)``;
* ``on_output(OutputEdge)``: each output toggle (camera trigger), with the host times the
  command was sent and acknowledged.

Waiting
-------
Every wait has a timeout. A response is late when ``response_timeout_s`` passed since the line was
sent *and* since the last status report that showed the machine busy (Run, Jog, Hold, Home):
GRBL legitimately holds back ``ok`` while its planner is full, while a ``G4``/``M8`` waits for
motion to finish, and during a feed hold. So a lost ``ok`` is reported once the machine is idle
(or silent) for that long; with ``poll_hz=0`` the timeout counts from sending only.

Pose reconstruction
-------------------
The driver follows the modal G-code state of what it sends (G0/G1, G90/G91, G20/G21, G53, F,
``$J=``) and, when each ``ok`` arrives, plans the move on a
:class:`~labrig.devices.motion_profile.MotionTimeline` with the controller's own limits
(``$110-$112`` rates, ``$120-$122`` accelerations, ``$11`` junction deviation, ``$100-$102``
steps), at the ``ok``'s receive time less its transmission time. Holds, resumes, jog cancels and
resets are applied at the time their byte was written. Status reports during motion shift the
plan in time to where they put the machine (the ``ok`` arrives late by the link's latency: under
a millisecond on a pty, up to 16 ms through an FTDI chip); reports at rest re-anchor the position.
:meth:`Grbl.pose_at` evaluates the model at any host time; :meth:`Grbl.planned_segments` exports
it. Lines the model does not follow (arcs, G10/G92/G28, probing, homing, check mode) mark it for
re-anchoring at the next report at rest; until then it holds the last known position.
"""

from __future__ import annotations

import contextlib
import errno
import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import serial

from labrig.clock import NS_PER_US, HostClock, MonotonicClock
from labrig.devices.grbl_protocol import (
    Alarm,
    ErrorReply,
    Event,
    GrblAlarm,
    GrblCommandError,
    GrblConnectionError,
    GrblError,
    GrblProtocol,
    GrblResetError,
    GrblTimeout,
    GrblUsageError,
    Message,
    Ok,
    Realtime,
    Setting,
    Status,
    Welcome,
)
from labrig.devices.motion_profile import MachineLimits, MotionTimeline, Segment, make_block, quantize_mm

__all__ = [
    "ConnectInfo",
    "Grbl",
    "GrblAlarm",
    "GrblCommandError",
    "GrblConnectionError",
    "GrblError",
    "GrblResetError",
    "GrblTimeout",
    "GrblUsageError",
    "OutputEdge",
    "Reply",
    "StatusSample",
    "StreamResult",
]

#: States in which GRBL may hold back responses for as long as the motion takes.
BUSY_STATES = frozenset({"Run", "Jog", "Hold", "Home", "Door"})
#: A ``?`` unanswered this long is given up (GRBL ignores ``?`` while homing or alarm-locked).
QUERY_TIMEOUT_S = 0.5
#: Synchronising the pose model on status reports: search window and step (us), closest match
#: accepted (mm, a few steps), slowest motion used (mm/s).
SYNC_WINDOW_US = 40_000.0
SYNC_STEP_US = 20.0
SYNC_MATCH_MM = 0.02
SYNC_MIN_SPEED_MM_S = 2.0
#: After a cycle starts, the next status poll comes this soon (us) to time the motion early.
EARLY_POLL_US = 30_000


class SerialLike(Protocol):
    """What the driver needs of a port (pyserial's ``Serial`` and test fakes)."""

    timeout: float | None

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes) -> int | None: ...

    @property
    def in_waiting(self) -> int: ...

    def close(self) -> None: ...


# -- results -------------------------------------------------------------------------------


@dataclass(frozen=True)
class StatusSample:
    """One status report: host receive time (us), machine position (mm), feed (mm/min), state text."""

    t_host_us: int
    t_query_us: int | None
    position_mm: tuple[float, float, float]
    feed_mm_min: float
    state: str
    report: Status = field(repr=False)

    def columns(self) -> dict[str, Any]:
        """The row for ``RecordingWriter.put("cnc", **sample.columns())``."""
        return {
            "t_host_us": self.t_host_us,
            "position_mm": self.position_mm,
            "feed_mm_min": self.feed_mm_min,
            "state": self.state,
        }


@dataclass(frozen=True)
class Reply:
    """A line's answer: host times sent and answered (us) and the push lines that came with it."""

    line: bytes
    t_sent_us: int
    t_answer_us: int
    pushed: tuple[Event, ...] = ()


@dataclass(frozen=True)
class OutputEdge:
    """An output toggle: ``level`` 1/0, host times (us) the line was sent and acknowledged.

    The controller switches the output between the two (after any queued motion has finished:
    ``M8``/``M9`` wait for the planner to empty).
    """

    level: int
    line: bytes
    t_sent_us: int
    t_ack_us: int


@dataclass(frozen=True)
class StreamResult:
    """What :meth:`Grbl.stream` did."""

    mode: str
    lines: int
    t_start_us: int
    t_end_us: int
    max_in_flight_bytes: int

    @property
    def lines_per_s(self) -> float:
        return self.lines / max((self.t_end_us - self.t_start_us) / 1e6, 1e-9)


@dataclass(frozen=True)
class ConnectInfo:
    """The controller after :meth:`Grbl.connect` or :meth:`Grbl.soft_reset`."""

    version: str | None
    state: str
    reset: str
    alarm: int | None
    messages: tuple[str, ...]


@dataclass
class _StreamRun:
    """Book-keeping of one :meth:`Grbl.stream` call."""

    total: int
    progress: Callable[[int, int], None] | None
    tickets: list[_Ticket] = field(default_factory=list)
    answered: int = 0
    failed: _Ticket | None = None
    max_in_flight_bytes: int = 0


@dataclass
class _Ticket:
    """A line in flight and what came back for it (guarded by the driver's lock)."""

    line: bytes
    t_sent_us: int
    timeout_s: float
    index: int | None = None
    moves: tuple[tuple[tuple[float, float, float], float | None, str | None], ...] = ()
    resync: bool = False
    done: bool = False
    discarded: bool = False
    code: int | None = None
    t_answer_us: int = 0
    pushed: list[Event] = field(default_factory=list)


# -- following the G-code we send ------------------------------------------------------------

_WORD = re.compile(r"([A-Z])([+-]?(?:\d+\.?\d*|\.\d+))")


def _preparse(line: bytes) -> str:
    """The line as GRBL's pre-parser keeps it (no spaces or comments, upper case)."""
    out = []
    depth = False
    for ch in line.decode("ascii", "replace"):
        if depth:
            depth = ch != ")"
        elif ch == "(":
            depth = True
        elif ch == ";":
            break
        elif " " < ch < "\x7f":
            out.append(ch.upper())
    return "".join(out)


class _GcodeTracker:
    """The modal state of the lines sent, to know which straight moves each line queues.

    Positions are machine mm (the parser's unquantised target). ``wco_mm`` comes from status
    reports; lines with effects it does not model set ``resync`` on their ticket.
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

    def follow(self, line: bytes) -> tuple[list[tuple[tuple[float, float, float], float | None, str | None]], bool, float]:
        """(moves as (target, feed or None for rapid, tag), whether to re-anchor, dwell s) of ``line``."""
        text = _preparse(line)
        if text.startswith("$J="):
            return self._jog(text[3:])
        if text.startswith("$"):
            return [], text in ("$H", "$X") or text.startswith("$RST"), 0.0
        words = _WORD.findall(text)
        g = [float(v) for k, v in words if k == "G"]
        vals = {k: float(v) for k, v in words if k not in "GM"}
        m = [float(v) for k, v in words if k == "M"]
        resync = any(c in (10, 28, 30, 38.2, 38.3, 38.4, 38.5, 92, 92.1, 43.1, 49, 2, 3) or 54 <= c <= 59 for c in g)
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
            return [], resync, dwell
        if self.motion is None:
            return [], True, dwell
        target = self._target(axes, incremental=self.incremental and 53 not in g, machine=53 in g)
        self.position_mm = list(target)
        feed = None if self.motion == 0 else self.feed_mm_min
        return [(target, feed, None)], resync, dwell

    def _jog(self, body: str) -> tuple[list[tuple[tuple[float, float, float], float | None, str | None]], bool, float]:
        words = _WORD.findall(body)
        g = [float(v) for k, v in words if k == "G"]
        vals = {k: float(v) for k, v in words if k != "G"}
        unit = 25.4 if (20 in g or (self.inches and 21 not in g)) else 1.0
        incremental = 91 in g or (self.incremental and 90 not in g)
        axes = {i: vals[a] * unit for i, a in enumerate("XYZ") if a in vals}
        if not axes or "F" not in vals:
            return [], False, 0.0
        target = self._target(axes, incremental=incremental and 53 not in g, machine=53 in g)
        self.position_mm = list(target)
        return [(target, vals["F"] * unit, "jog")], False, 0.0

    def _target(self, axes: dict[int, float], *, incremental: bool, machine: bool) -> tuple[float, float, float]:
        target = list(self.position_mm)
        for axis, v in axes.items():
            if machine:
                target[axis] = v
            elif incremental:
                target[axis] += v
            else:
                target[axis] = v + self.wco_mm[axis]
        return (target[0], target[1], target[2])


def _fmt(value: float) -> str:
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


# -- the driver ------------------------------------------------------------------------------


class Grbl:
    """A GRBL 1.1 controller on a serial port.

    ``port``: an open serial-like object, or a port name/URL for ``serial.serial_for_url``
    (opened by :meth:`connect`, closed by :meth:`close`). ``poll_hz``: status polling rate (0: no
    automatic polling, responses then time out from sending). ``response_timeout_s``: see the
    module docstring. ``output_on``/``output_off``: the lines :meth:`set_output` sends.
    """

    def __init__(
        self,
        port: str | SerialLike,
        *,
        baudrate: int = 115200,
        clock: HostClock | None = None,
        time_base_ns: int = 0,
        poll_hz: float = 10.0,
        response_timeout_s: float = 2.0,
        on_sample: Callable[[StatusSample], None] | None = None,
        on_gcode: Callable[[int, int, bytes], None] | None = None,
        on_output: Callable[[OutputEdge], None] | None = None,
        output_on: str = "M8",
        output_off: str = "M9",
        rx_limit_bytes: int = 127,
    ) -> None:
        if poll_hz < 0 or poll_hz > 50:
            raise GrblUsageError(f"poll_hz must be 0..50 (GRBL recommends at most 10), got {poll_hz}")
        self._url = port if isinstance(port, str) else None
        self._port: Any = None if isinstance(port, str) else port
        self._owns_port = isinstance(port, str)
        self.baudrate = baudrate
        self.clock = clock or MonotonicClock()
        self.time_base_ns = int(time_base_ns)
        self.poll_hz = float(poll_hz)
        self.response_timeout_s = float(response_timeout_s)
        self.on_sample = on_sample
        self.on_gcode = on_gcode
        self.on_output = on_output
        self.output_on = GrblProtocol.check_line(output_on)
        self.output_off = GrblProtocol.check_line(output_off)
        self.byte_us = 10 * 1e6 / baudrate
        self.settings: dict[int, float] = {}
        self.callback_errors: list[BaseException] = []

        self._core = GrblProtocol(rx_limit_bytes=rx_limit_bytes)
        self._cond = threading.Condition(threading.RLock())
        self._tracker = _GcodeTracker()
        self._model = MotionTimeline(MachineLimits())
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._failure: GrblError | None = None
        self._pending_callbacks: list[Callable[[], None]] = []
        self._callback_lock = threading.Lock()
        self._tickets: deque[_Ticket] = deque()
        self._last_sample: StatusSample | None = None
        self._last_busy_us = -(1 << 62)
        self._last_rx_us = 0
        self._query_sent_us: int | None = None
        self._poll_requested = False
        self._next_poll_us = 0
        self._welcomes = 0
        self._version: str | None = None
        self._alarms: deque[tuple[int, int]] = deque(maxlen=64)
        self._messages: deque[tuple[int, str]] = deque(maxlen=64)
        self._resync = True
        self._checking = False
        self._round_trips_us: deque[float] = deque(maxlen=32)

    # -- lifecycle -------------------------------------------------------------------------

    def now_us(self) -> int:
        """Now on the host clock, in the driver's time base (us)."""
        return (self.clock.now_ns() - self.time_base_ns) // NS_PER_US

    def connect(self, *, reset: str = "auto", timeout_s: float = 5.0, read_settings: bool = True) -> ConnectInfo:
        """Open the port, reset the controller, wait for its banner, read its state and settings.

        ``reset``: ``"auto"`` pulses DTR (a hardware reset on Arduino boards) and falls back to a
        soft reset (0x18) if the port has no DTR (pseudo-terminals: ENOTTY) or no banner came;
        ``"dtr"``, ``"soft"``, or ``"none"`` (keep the controller as it is, e.g. homed).
        An Alarm on connect (homing enabled) is not an error: :attr:`ConnectInfo.state` says so;
        call :meth:`unlock` or :meth:`home`.
        """
        if reset not in ("auto", "dtr", "soft", "none"):
            raise GrblUsageError(f"reset must be auto, dtr, soft or none, got {reset!r}")
        self._open()
        with contextlib.suppress(AttributeError, OSError, serial.SerialException):
            self._port.reset_input_buffer()
        with self._cond:
            self._core.forget_in_flight()
            self._tickets.clear()
            self._failure = None
        self._start_io()
        t_begin = self.now_us()
        method = reset
        if reset in ("auto", "dtr"):
            count = self._welcomes
            if self._pulse_dtr():
                if not self._wait_welcome(count, timeout_s if reset == "dtr" else min(timeout_s, 2.5), required=reset == "dtr"):
                    method = "soft"
            else:
                method = "soft"
        if method == "soft":
            count = self._welcomes
            self._write_realtime(Realtime.SOFT_RESET)
            self._wait_welcome(count, timeout_s, required=True)
        self._wait_quiet(0.05, 0.5)
        sample = self.status(timeout_s=timeout_s)
        if read_settings:
            self.read_settings(timeout_s=timeout_s)
        with self._cond:
            messages = tuple(text for t, text in self._messages if t >= t_begin)
            alarm = self._core.alarm if sample.report.state == "Alarm" else None
            return ConnectInfo(self._version, sample.state, method, alarm, messages)

    def close(self) -> None:
        """Stop the I/O thread and close the port if the driver opened it."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._thread = None
        with self._cond:
            if self._failure is None:
                self._failure = GrblConnectionError("the GRBL driver was closed; connect() again")
            self._cond.notify_all()
        if self._owns_port and self._port is not None:
            with contextlib.suppress(Exception):
                self._port.close()
            self._port = None

    def __enter__(self) -> Grbl:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- state -------------------------------------------------------------------------

    @property
    def last_sample(self) -> StatusSample | None:
        return self._last_sample

    @property
    def state(self) -> str:
        """The state of the last status report (``Unknown`` before the first)."""
        sample = self._last_sample
        return sample.state if sample is not None else "Unknown"

    @property
    def position_mm(self) -> tuple[float, float, float] | None:
        """Machine position of the last status report."""
        sample = self._last_sample
        return sample.position_mm if sample is not None else None

    @property
    def protocol(self) -> GrblProtocol:
        """The protocol core (its statistics: ``max_in_flight_bytes``, ``noise_bytes``, ...)."""
        return self._core

    @property
    def limits(self) -> MachineLimits:
        return self._model.limits

    # -- commands ------------------------------------------------------------------------

    def send(self, line: str | bytes, timeout_s: float | None = None) -> Reply:
        """Send one line after every earlier one is answered and wait for its ``ok`` (send-response).

        Raises :class:`GrblCommandError` on ``error:N``, :class:`GrblAlarm` when a critical alarm
        locks the controller meanwhile, :class:`GrblTimeout`, :class:`GrblConnectionError`.
        """
        data = self._core.check_line(line)
        timeout = self.response_timeout_s if timeout_s is None else float(timeout_s)
        with self._cond:
            while self._core.in_flight:
                self._wait_step(self._tickets[0] if self._tickets else None)
            ticket = self._send_locked(data, timeout)
        self._run_callbacks()
        self._wait_ticket(ticket)
        if ticket.code is not None:
            raise GrblCommandError(ticket.code, ticket.line)
        return Reply(ticket.line, ticket.t_sent_us, ticket.t_answer_us, tuple(ticket.pushed))

    def stream(
        self,
        lines: Iterable[str | bytes],
        *,
        mode: str = "count",
        progress: Callable[[int, int], None] | None = None,
        timeout_s: float | None = None,
    ) -> StreamResult:
        """Send a program and wait until every line is answered.

        ``mode="count"``: character counting, as many lines in flight as fit in GRBL's RX buffer
        (never more than ``rx_limit_bytes`` unanswered bytes). ``mode="send-response"``: one line
        at a time. ``progress(answered, total)`` is called as responses arrive.
        On the first ``error:N`` no further line is sent; the lines already in GRBL's buffer still
        run (GRBL's own behaviour), their responses are awaited, then :class:`GrblCommandError`
        is raised with the line's index. Validate programs with :meth:`check_program` first.
        Settings writes must not be streamed (use :meth:`write_setting`).
        """
        if mode not in ("count", "send-response"):
            raise GrblUsageError(f"mode must be 'count' or 'send-response', got {mode!r}")
        program = [self._core.check_line(line) for line in lines]
        for data in program:
            if re.match(rb"\s*\$\s*(\d|N\d|I=|RST)", data, re.IGNORECASE):
                raise GrblUsageError(f"{data!r} writes EEPROM and must be sent alone: use write_setting() or send()")
        timeout = self.response_timeout_s if timeout_s is None else float(timeout_s)
        run = _StreamRun(len(program), progress)
        t_start = self.now_us()
        with self._cond:
            for i, data in enumerate(program):
                while run.failed is None:
                    self._scan(run)
                    fits = self._core.can_send(data) if mode == "count" else not self._core.in_flight
                    if run.failed is not None or fits:
                        break
                    self._wait_step(self._tickets[0] if self._tickets else None)
                if run.failed is not None:
                    break
                run.tickets.append(self._send_locked(data, timeout, index=i))
                run.max_in_flight_bytes = max(run.max_in_flight_bytes, self._core.in_flight_bytes)
                if self._pending_callbacks or progress is not None:
                    self._scan(run)
            while run.answered < len(run.tickets):
                self._scan(run)
                if run.answered < len(run.tickets):
                    self._wait_step(run.tickets[run.answered])
        self._run_callbacks()
        if run.failed is not None:
            assert run.failed.code is not None
            raise GrblCommandError(run.failed.code, run.failed.line, run.failed.index)
        return StreamResult(mode, len(run.tickets), t_start, self.now_us(), run.max_in_flight_bytes)

    def check_program(self, lines: Iterable[str | bytes], timeout_s: float | None = None) -> list[tuple[int, GrblCommandError]]:
        """Run a program through GRBL's check mode (``$C``): the errors it would give, by line index.

        Leaving check mode soft-resets the controller (GRBL's behaviour); the position is kept.
        """
        self.send("$C", timeout_s)
        self._checking = True  # the lines only parse: the pose model must not move
        errors: list[tuple[int, GrblCommandError]] = []
        try:
            for i, line in enumerate(lines):
                try:
                    self.send(line, timeout_s)
                except GrblCommandError as exc:
                    errors.append((i, GrblCommandError(exc.code, exc.line, i)))
        finally:
            count = self._welcomes
            self.send("$C", timeout_s)
            self._wait_welcome(count, 5.0, required=True)
            self._checking = False
            self.status()
        return errors

    def read_settings(self, timeout_s: float | None = None) -> dict[int, float]:
        """``$$``: all settings; the motion model takes its limits from them."""
        reply = self.send("$$", timeout_s)
        settings = {e.number: e.value for e in reply.pushed if isinstance(e, Setting)}
        with self._cond:
            self.settings = settings
            self._model.limits = MachineLimits.from_settings(settings)
        return dict(settings)

    def write_setting(self, number: int, value: float, timeout_s: float | None = None) -> None:
        """``$N=value`` (send-response only: GRBL's receiver is deaf while it writes EEPROM)."""
        if not isinstance(number, int) or number < 0:
            raise GrblUsageError(f"setting number must be a non-negative integer, got {number!r}")
        if not math.isfinite(value):
            raise GrblUsageError(f"setting value must be finite, got {value!r}")
        self.send(f"${number}={_fmt(value)}", timeout_s)
        with self._cond:
            self.settings[number] = float(value)
            self._model.limits = MachineLimits.from_settings(self.settings)

    def unlock(self, timeout_s: float | None = None) -> None:
        """``$X``: leave Alarm without homing (position as GRBL has it)."""
        self.send("$X", timeout_s)
        self.status()

    def home(self, timeout_s: float = 120.0) -> StatusSample:
        """``$H``: run the homing cycle (GRBL is silent while homing, so the timeout covers all of it)."""
        t0 = self.now_us()
        self.send("$H", timeout_s)
        self._raise_alarm_since(t0, "during homing")
        return self.status()

    def move_to(
        self,
        x: float | None = None,
        y: float | None = None,
        z: float | None = None,
        *,
        feed_mm_min: float | None,
        machine: bool = False,
        wait: bool = False,
        timeout_s: float | None = None,
    ) -> Reply:
        """Absolute move (``G90 G1 ... F``; ``feed_mm_min=None``: rapid G0) in work or ``machine`` coordinates.

        Returns when GRBL has queued the move; ``wait=True`` waits until the machine is Idle again.
        """
        line = "G90" + ("G53" if machine else "") + self._motion_words(x, y, z, feed_mm_min)
        return self._move(line, wait, timeout_s)

    def move_by(
        self,
        dx: float | None = None,
        dy: float | None = None,
        dz: float | None = None,
        *,
        feed_mm_min: float | None,
        wait: bool = False,
        timeout_s: float | None = None,
    ) -> Reply:
        """Relative move (``G91 G1 ... F``); leaves GRBL in G91 (move_to sets G90 again)."""
        return self._move("G91" + self._motion_words(dx, dy, dz, feed_mm_min), wait, timeout_s)

    def jog(
        self,
        x: float | None = None,
        y: float | None = None,
        z: float | None = None,
        *,
        feed_mm_min: float,
        relative: bool = True,
        machine: bool = False,
        timeout_s: float | None = None,
    ) -> Reply:
        """``$J=``: a jog (relative by default); GRBL answers error:15 if it would leave the travel."""
        if feed_mm_min is None or not feed_mm_min > 0:
            raise GrblUsageError("a jog needs a positive feed_mm_min (F is not modal for jogs)")
        head = "$J=" + ("G91" if relative else "G90") + ("G53" if machine else "")
        return self.send(head + self._axis_words(x, y, z) + f"F{_fmt(feed_mm_min)}", timeout_s)

    def jog_cancel(self) -> None:
        """0x85: decelerate and drop the queued jogs (only acts while jogging)."""
        t = self._write_realtime(Realtime.JOG_CANCEL)
        with self._cond:
            if self._model.state in ("run", "hold"):
                self._model.cancel(t + self.byte_us)
            self._resync = True

    def feed_hold(self) -> None:
        """``!``: decelerate to a stop and hold (Hold:1, then Hold:0); queued moves are kept."""
        t = self._write_realtime(Realtime.FEED_HOLD)
        with self._cond:
            if any(block.tag == "jog" for block in self._model.queue):  # GRBL cancels jogs on '!'
                self._model.cancel(t + self.byte_us)
                self._resync = True
            else:
                self._model.hold(t + self.byte_us)

    def resume(self) -> None:
        """``~``: resume from a hold (GRBL ignores it while the hold is still decelerating)."""
        t = self._write_realtime(Realtime.CYCLE_START)
        with self._cond:
            self._model.resume(t + self.byte_us)

    def soft_reset(self, timeout_s: float = 5.0) -> ConnectInfo:
        """0x18: halt at once and restart GRBL; unanswered lines are dropped (their waiters get
        :class:`GrblResetError`). A reset in motion leaves GRBL in Alarm (ALARM:3): unlock or home.
        """
        count = self._welcomes
        t0 = self.now_us()
        t = self._write_realtime(Realtime.SOFT_RESET)
        with self._cond:
            self._model.stop(t + self.byte_us)
        self._wait_welcome(count, timeout_s, required=True)
        self._wait_quiet(0.02, 0.3)
        sample = self.status(timeout_s=timeout_s)
        with self._cond:
            alarms = [code for t_alarm, code in self._alarms if t_alarm >= t0]
            messages = tuple(text for t_msg, text in self._messages if t_msg >= t0)
        return ConnectInfo(self._version, sample.state, "soft", alarms[-1] if alarms else None, messages)

    def set_output(self, on: bool, timeout_s: float | None = None) -> OutputEdge:
        """Switch the output (``output_on``/``output_off``, M8/M9 by default) for the camera trigger.

        GRBL switches it once queued motion has finished, then answers; the edge lies between
        :attr:`OutputEdge.t_sent_us` and :attr:`OutputEdge.t_ack_us`.
        """
        line = self.output_on if on else self.output_off
        reply = self.send(line, timeout_s)
        edge = OutputEdge(int(bool(on)), line, reply.t_sent_us, reply.t_answer_us)
        if self.on_output is not None:
            self._call(self.on_output, edge)
        return edge

    def status(self, timeout_s: float = 1.0) -> StatusSample:
        """A fresh status report (its ``?`` sent after this call began).

        Raises :class:`GrblAlarm` at once while a critical alarm locks the controller (it ignores
        ``?`` until :meth:`soft_reset`), :class:`GrblTimeout` when no report comes in ``timeout_s``.
        """
        t0 = self.now_us()
        deadline = t0 + timeout_s * 1e6
        with self._cond:
            self._request_poll_locked(t0)
            while True:
                self._raise_if_failed()
                sample = self._last_sample
                if sample is not None and sample.t_query_us is not None and sample.t_query_us >= t0:
                    return sample
                if self._core.locked:  # no report will come: say why at once
                    raise GrblAlarm(self._core.alarm or 0, "GRBL answers nothing, not even '?', until soft_reset()")
                now = self.now_us()
                if now >= deadline:
                    raise GrblTimeout(
                        f"no status report within {timeout_s:.1f} s (last state {self.state}); GRBL does not answer '?' "
                        "while homing: wait for it, else check the port and cable"
                    )
                if self._query_sent_us is None or now - self._query_sent_us > QUERY_TIMEOUT_S * 1e6:
                    self._request_poll_locked(now)
                self._cond.wait(min(0.02, (deadline - now) / 1e6))

    def wait_idle(self, timeout_s: float = 60.0) -> StatusSample:
        """Wait until every line is answered and GRBL reports Idle (polling status).

        Raises :class:`GrblAlarm` if it ends in Alarm, :class:`GrblTimeout` after ``timeout_s``
        (a hold counts as not idle).
        """
        t0 = self.now_us()
        deadline = t0 + timeout_s * 1e6
        interval_s = 1.0 / self.poll_hz if self.poll_hz > 0 else 0.1
        with self._cond:
            while self._core.in_flight:
                if self.now_us() > deadline:
                    raise GrblTimeout(f"lines still unanswered after {timeout_s:.1f} s")
                self._wait_step(self._tickets[0] if self._tickets else None)
        while True:
            sample = self.status(timeout_s=max(min(2.0, (deadline - self.now_us()) / 1e6), 0.05))
            if sample.report.state == "Idle":
                return sample
            if sample.report.state == "Alarm":
                self._raise_alarm_since(t0, "while waiting for Idle")
                raise GrblAlarm(self._core.alarm or 0, "controller in Alarm while waiting for Idle")
            if self.now_us() > deadline:
                raise GrblTimeout(f"controller still {sample.state} after {timeout_s:.1f} s")
            next_us = min(sample.t_host_us + interval_s * 1e6, deadline)
            with self._cond:  # poll no faster than poll_hz
                while (now := self.now_us()) < next_us:
                    self._raise_if_failed()
                    self._cond.wait((next_us - now) / 1e6)

    # -- pose reconstruction ----------------------------------------------------------------

    def pose_at(self, t_host_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Machine position (mm) at host times (us, driver time base): shape (3,) for a scalar, (N, 3) otherwise."""
        with self._cond:
            out = self._model.positions_at(t_host_us)
        return out[0] if np.ndim(t_host_us) == 0 else out

    def planned_segments(self) -> list[Segment]:
        """The reconstructed motion: executed segments, then the current plan (host time base)."""
        with self._cond:
            return self._model.segments()

    # -- internals: sending ----------------------------------------------------------------

    def _open(self) -> None:
        if self._port is None:
            if self._url is None:
                raise GrblUsageError("no port: pass a port name/URL or an open serial object")
            try:
                self._port = serial.serial_for_url(self._url, baudrate=self.baudrate, timeout=0.005)
            except (OSError, serial.SerialException) as exc:
                raise GrblConnectionError(f"cannot open {self._url}: {exc}; check the port name and permissions") from exc
            self._owns_port = True
        else:
            with contextlib.suppress(AttributeError, ValueError):
                self._port.timeout = 0.005

    def _port_name(self) -> str:
        return self._url or str(getattr(self._port, "port", None) or getattr(self._port, "name", "the port"))

    def _pulse_dtr(self) -> bool:
        """Pulse DTR (resets Arduino boards); False if the port has no modem lines (ptys: ENOTTY)."""
        try:
            self._port.dtr = False
            time.sleep(0.05)
            self._port.dtr = True
        except OSError as exc:
            if exc.errno in (errno.ENOTTY, errno.EINVAL, None):
                return False
            raise GrblConnectionError(f"setting DTR on {self._port_name()} failed: {exc}") from exc
        except (AttributeError, NotImplementedError, serial.SerialException):
            return False
        return True

    def _send_locked(self, data: bytes, timeout_s: float, index: int | None = None) -> _Ticket:
        self._raise_if_failed()
        if self._core.locked:
            code = self._core.alarm or 0
            raise GrblAlarm(code, f"GRBL ignores all lines until reset; call soft_reset() before sending {data.decode()!r}")
        ticket = _Ticket(data, 0, timeout_s, index=index)
        out = self._core.send_line(data, tag=ticket)
        moves, ticket.resync, dwell_s = self._tracker.follow(data)
        ticket.moves = tuple(moves)
        ticket.timeout_s += dwell_s
        ticket.t_sent_us = self._write_locked(out)
        self._tickets.append(ticket)
        self._log(ticket.t_sent_us, 0, data)
        return ticket

    def _write_locked(self, data: bytes) -> int:
        try:
            self._port.write(data)
        except (OSError, serial.SerialException) as exc:
            self._fail(exc)
            self._raise_if_failed()
        return self.now_us()

    def _write_realtime(self, command: bytes) -> int:
        with self._cond:
            self._raise_if_failed()
            data = self._core.realtime(command)
            t = self._write_locked(data)
            if command != Realtime.STATUS:
                self._log(t, 0, data)
        self._run_callbacks()
        return t

    def _request_poll_locked(self, now: int, explicit: bool = True) -> None:
        """Write ``?`` unless one is still unanswered (then, if ``explicit``, once it is answered)."""
        if self._query_sent_us is not None and now - self._query_sent_us <= QUERY_TIMEOUT_S * 1e6:
            self._poll_requested = self._poll_requested or explicit
            return
        if self._port is None or self._failure is not None:
            return
        self._query_sent_us = self._write_locked(self._core.realtime(Realtime.STATUS))
        self._poll_requested = False
        if self.poll_hz > 0:
            self._next_poll_us = self._query_sent_us + int(1e6 / self.poll_hz)

    @staticmethod
    def _axis_words(x: float | None, y: float | None, z: float | None) -> str:
        words = "".join(f"{a}{_fmt(v)}" for a, v in zip("XYZ", (x, y, z)) if v is not None)
        if not words:
            raise GrblUsageError("give at least one of x, y, z")
        for v in (x, y, z):
            if v is not None and not math.isfinite(v):
                raise GrblUsageError(f"axis values must be finite, got {v!r}")
        return words

    def _motion_words(self, x: float | None, y: float | None, z: float | None, feed_mm_min: float | None) -> str:
        words = self._axis_words(x, y, z)
        if feed_mm_min is None:
            return "G0" + words
        if not feed_mm_min > 0 or not math.isfinite(feed_mm_min):
            raise GrblUsageError(f"feed_mm_min must be positive (or None for a rapid), got {feed_mm_min!r}")
        return "G1" + words + f"F{_fmt(feed_mm_min)}"

    def _move(self, line: str, wait: bool, timeout_s: float | None) -> Reply:
        reply = self.send(line, timeout_s)
        if wait:
            self.wait_idle(timeout_s if timeout_s is not None else 3600.0)
        return reply

    # -- internals: waiting --------------------------------------------------------------

    def _raise_if_failed(self) -> None:
        if self._failure is not None:
            raise self._failure

    def _deadline_us(self, ticket: _Ticket) -> float:
        base = ticket.t_sent_us + ticket.timeout_s * 1e6
        if self.poll_hz > 0:
            base = max(base, self._last_busy_us + ticket.timeout_s * 1e6)
        return base

    def _wait_step(self, ticket: _Ticket | None) -> None:
        """One bounded wait for progress on ``ticket`` (the oldest unanswered line); raises on trouble."""
        self._raise_if_failed()
        if ticket is None:
            self._cond.wait(0.01)
            return
        if ticket.discarded:
            self._raise_discarded(ticket)
        if self._core.locked and self._alarms and self._alarms[-1][0] >= ticket.t_sent_us:
            raise GrblAlarm(
                self._alarms[-1][1], f"{ticket.line.decode()!r} unanswered; GRBL ignores all lines until soft_reset()"
            )
        if ticket.done:
            return
        now = self.now_us()
        deadline = self._deadline_us(ticket)
        if now >= deadline and not self._awaiting_fresh_status(deadline, now):
            raise self._timeout(ticket, now)
        self._cond.wait(min(0.05, max(deadline - now, 10_000) / 1e6))

    def _awaiting_fresh_status(self, deadline_us: float, now_us: int) -> bool:
        """Past a line's deadline, a lost 'ok' is only concluded from a status report newer than
        the deadline: a report from before it (the poller starved on a loaded host) may say Idle
        from before the cycle started. Without any report for 1 s the controller is unresponsive."""
        sample = self._last_sample
        return (self.poll_hz > 0 and sample is not None and sample.t_host_us < deadline_us
                and now_us - sample.t_host_us <= 1e6)

    def _wait_ticket(self, ticket: _Ticket) -> None:
        with self._cond:
            while not ticket.done:
                self._wait_step(ticket)
        self._run_callbacks()

    def _raise_discarded(self, ticket: _Ticket) -> None:
        alarms = [code for t, code in self._alarms if t >= ticket.t_sent_us]
        if alarms:
            raise GrblAlarm(alarms[-1], f"the controller reset and dropped {ticket.line.decode()!r} unanswered")
        raise GrblResetError(
            f"the controller reset and dropped {ticket.line.decode()!r} unanswered; send it again if still wanted"
        )

    def _raise_alarm_since(self, t0: int, context: str) -> None:
        with self._cond:
            alarms = [code for t, code in self._alarms if t >= t0]
        if alarms:
            raise GrblAlarm(alarms[-1], context)

    def _timeout(self, ticket: _Ticket, now: int) -> GrblTimeout:
        sample = self._last_sample
        line = ticket.line.decode()
        waited = (now - ticket.t_sent_us) / 1e6
        if self.poll_hz > 0 and (sample is None or now - sample.t_host_us > 1e6):
            why = "no status reports either: the controller is unresponsive (unplugged, wrong baud rate, or hung)"
        elif sample is not None:
            why = f"GRBL reports {sample.state}, so the 'ok' was lost (noise or an RX overflow)"
        else:
            why = "the 'ok' was lost or the controller is unresponsive"
        return GrblTimeout(
            f"no response to {line!r} after {waited:.1f} s ({ticket.timeout_s:.1f} s allowed); {why}; "
            "soft_reset() clears the line accounting"
        )

    def _wait_welcome(self, count: int, timeout_s: float, *, required: bool) -> bool:
        deadline = self.now_us() + timeout_s * 1e6
        with self._cond:
            while self._welcomes <= count:
                self._raise_if_failed()
                now = self.now_us()
                if now >= deadline:
                    if required:
                        raise GrblTimeout(
                            f"no GRBL welcome banner within {timeout_s:.1f} s on {self._port_name()}; "
                            f"is a GRBL controller connected at {self.baudrate} baud?"
                        )
                    return False
                self._cond.wait(min(0.05, (deadline - now) / 1e6))
        return True

    def _wait_quiet(self, quiet_s: float, max_s: float) -> None:
        """Wait until nothing arrived for ``quiet_s`` (push messages after a banner), at most ``max_s``."""
        end = self.now_us() + max_s * 1e6
        with self._cond:
            while True:
                now = self.now_us()
                if now >= end or now - self._last_rx_us >= quiet_s * 1e6:
                    return
                self._cond.wait(quiet_s / 2)

    def _scan(self, run: _StreamRun) -> None:
        """Advance over a stream's answered lines (answers come in order): note the first error,
        raise if the controller reset under the stream, report progress, run pending callbacks.
        """
        tickets = run.tickets
        k = run.answered
        while k < len(tickets) and tickets[k].done:
            if tickets[k].code is not None and run.failed is None:
                run.failed = tickets[k]
            k += 1
        if k < len(tickets) and tickets[k].discarded:
            self._raise_discarded(tickets[k])
        progressed = k != run.answered
        run.answered = k
        if (progressed and run.progress is not None) or self._pending_callbacks:
            self._cond.release()  # callbacks run without the lock
            try:
                self._run_callbacks()
                if progressed and run.progress is not None:
                    run.progress(k, run.total)
            finally:
                self._cond.acquire()

    # -- internals: the I/O thread -----------------------------------------------------------

    def _start_io(self) -> None:
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._io_loop, name="labrig-grbl-io", daemon=True)
        self._thread.start()

    def _io_loop(self) -> None:
        try:
            self._io_steps()
        finally:  # lines read just before a port failure still reach the callbacks (and recordings)
            self._run_callbacks()

    def _io_steps(self) -> None:
        port = self._port
        while not self._stop.is_set():
            try:
                waiting = port.in_waiting
                data = port.read(waiting if waiting > 0 else 1)
            except (OSError, serial.SerialException, TypeError, AttributeError) as exc:
                if not self._stop.is_set():
                    with self._cond:
                        self._fail(exc)
                return
            now = self.now_us()
            with self._cond:
                if data:
                    self._last_rx_us = now
                    self._on_data(data, now)
                if (self.poll_hz > 0 and now >= self._next_poll_us) or self._poll_requested:
                    try:
                        self._request_poll_locked(now, explicit=self._poll_requested)
                    except GrblError:
                        return
                self._cond.notify_all()
            self._run_callbacks()

    def _fail(self, exc: BaseException) -> None:
        if self._failure is None:
            self._failure = GrblConnectionError(
                f"serial port {self._port_name()} failed: {exc}; the controller was unplugged or the port closed: reconnect"
            )
        self._cond.notify_all()

    def _on_data(self, data: bytes, t: int) -> None:
        for raw, event in self._core.receive_lines(data):
            self._log(t, 1, raw)
            if isinstance(event, (Ok, ErrorReply)):
                self._on_response(event, t)
            elif isinstance(event, Status):
                self._on_status(event, raw, t)
            elif isinstance(event, Alarm):
                self._alarms.append((t, event.code))
                if event.critical:
                    self._model.stop(t)
                    self._resync = True
            elif isinstance(event, Welcome):
                self._welcomes += 1
                self._version = event.version
                for sent in event.dropped:
                    ticket = sent.tag
                    if isinstance(ticket, _Ticket):
                        ticket.discarded = True
                self._tickets.clear()
                self._model.stop(t)
                self._tracker.reset(self._model.position_mm)
                self._resync = True
                self._query_sent_us = None
            elif isinstance(event, Message):
                self._messages.append((t, event.text))
                self._attach(event)
            else:
                self._attach(event)

    def _attach(self, event: Event) -> None:
        """Push lines (settings, [GC:], [MSG:], ...) belong to the oldest unanswered line's reply."""
        if self._tickets:
            self._tickets[0].pushed.append(event)

    def _on_response(self, event: Ok | ErrorReply, t: int) -> None:
        sent = event.sent
        ticket = sent.tag if sent is not None else None
        if not isinstance(ticket, _Ticket):
            return
        if self._tickets and self._tickets[0] is ticket:
            self._tickets.popleft()
        else:
            with contextlib.suppress(ValueError):
                self._tickets.remove(ticket)
        ticket.done = True
        ticket.t_answer_us = t
        if isinstance(event, ErrorReply):
            ticket.code = event.code
            if ticket.moves:
                self._resync = True
            return
        if ticket.resync or self._checking:
            self._resync = True
        if self._checking:
            return
        # 'ok\r\n' took 4 byte times on the wire, plus the link's one-way latency.
        t_planned = t - 4 * self.byte_us - self.link_latency_us
        for target, feed, tag in ticket.moves:
            block = make_block(
                self._model.tail_mm, quantize_mm(target, self._model.limits.steps_per_mm), feed, self._model.limits, tag=tag
            )
            if block is not None:
                self._model.append(block, max(t_planned, self._model.t_us))
        if self._model.state == "queued":
            self._model.start(max(t_planned, self._model.t_us))
            if self.poll_hz > 0:  # an early report times the new motion (see _synchronize_model)
                self._next_poll_us = min(self._next_poll_us, t + EARLY_POLL_US)

    @property
    def link_latency_us(self) -> float:
        """One-way latency of the link (us): half the shortest round trip of recent status queries
        beyond the bytes' own time on the wire (0 until three queries were answered).
        """
        if len(self._round_trips_us) < 3:
            return 0.0
        return max(0.5 * min(self._round_trips_us), 0.0)

    def _on_status(self, event: Status, raw: bytes, t: int) -> None:
        t_query = self._query_sent_us
        self._query_sent_us = None
        if t_query is not None:  # the round trip beyond the bytes' own time on the wire
            self._round_trips_us.append(t - t_query - (len(raw) + 3) * self.byte_us)
        if event.state in BUSY_STATES:
            self._last_busy_us = t
        if event.wco_mm is not None and len(event.wco_mm) >= 3:
            self._tracker.wco_mm = [float(v) for v in event.wco_mm[:3]]
        if event.position_mm is None or len(event.position_mm) < 3:
            return
        position = (float(event.position_mm[0]), float(event.position_mm[1]), float(event.position_mm[2]))
        sample = StatusSample(t, t_query, position, float(event.feed_mm_min or 0.0), event.state_text, event)
        self._last_sample = sample
        t_sampled = t - (len(raw) + 2) * self.byte_us
        if t_query is not None:
            t_sampled = max(t_sampled, t_query + self.byte_us)
        if t_query is not None and event.state in ("Run", "Jog"):
            # GRBL samples the position when the '?' arrives (its reply may wait behind other output).
            self._synchronize_model(position, t_query + self.byte_us + self.link_latency_us)
        self._anchor(event, position, max(t_sampled, self._model.t_us))
        if self.on_sample is not None:
            self._pending_callbacks.append(lambda: self.on_sample(sample))  # type: ignore[misc]

    def _synchronize_model(self, position: tuple[float, float, float], t_sampled: float) -> None:
        """Shift the running plan in time so it passes the reported position when the machine did.

        The model starts each move at the host time its ``ok`` arrived, which lags the controller
        by the transport latency; a report during motion tells the lag. Only fast enough motion
        (the position resolves the time to a fraction of a millisecond) and close matches count;
        half the measured lag is applied per report to average out jitter.
        """
        if self._model.state != "run" or self._resync:
            return
        t = t_sampled + np.arange(-SYNC_WINDOW_US, SYNC_WINDOW_US, SYNC_STEP_US)
        path = self._model.positions_at(t)
        distance = np.linalg.norm(path - np.asarray(position), axis=1)
        k = int(np.argmin(distance))
        if distance[k] > SYNC_MATCH_MM or k in (0, len(t) - 1):
            return
        speed = np.linalg.norm(path[min(k + 1, len(t) - 1)] - path[max(k - 1, 0)]) / (2 * SYNC_STEP_US) * 1e6
        if speed < SYNC_MIN_SPEED_MM_S:
            return
        self._model.shift_plan(0.5 * (t_sampled - t[k]))

    def _anchor(self, event: Status, position: tuple[float, float, float], t: float) -> None:
        """Re-anchor the motion model (and the G-code tracker) on a report of the machine at rest.

        Only when no line is unanswered (one could still be about to move the machine). A model
        still moving is stopped there (it lagged the machine); a model elsewhere jumps.
        """
        if event.state not in ("Idle", "Alarm", "Check", "Sleep") or self._core.in_flight:
            return
        if self._model.state in ("run", "hold"):
            self._model.stop(t)
        if self._model.queue:
            return
        if self._resync or max(abs(a - b) for a, b in zip(self._model.position_mm, position)) > 1e-3:
            self._model.set_position(position, t)
        if self._resync:
            self._tracker.position_mm = list(position)
            self._resync = False

    def _log(self, t: int, direction: int, line: bytes) -> None:
        if self.on_gcode is not None:
            cb = self.on_gcode
            self._pending_callbacks.append(lambda: cb(t, direction, line))

    def _call(self, fn: Callable[..., None], *args: object) -> None:
        try:
            fn(*args)
        except Exception as exc:  # a broken callback must not kill the link
            self.callback_errors.append(exc)

    def _run_callbacks(self) -> None:
        with self._callback_lock:  # one runner at a time keeps the callbacks in order
            with self._cond:
                pending, self._pending_callbacks = self._pending_callbacks, []
            for fn in pending:
                self._call(fn)
