"""The GRBL conversation over a serial link: lines in flight and their answers, status polling,
push messages and callbacks.

Threads and time
----------------
The link's reader thread (:class:`~labrig.devices.serial_link.SerialLink`) feeds
:class:`~labrig.devices.grbl_protocol.GrblProtocol` with each stamped chunk, pairs responses
with the tickets of the lines waiting for them, feeds the
:class:`~labrig.devices.grbl_pose.PoseModel`, and polls ``?`` at ``poll_hz``. Callers write lines
and real-time bytes from their own thread and wait on :attr:`GrblChannel.cond`, which guards
everything here (:mod:`labrig.devices.grbl_waits`). All host times are integer microseconds of the
host clock relative to ``time_base_ns``.

Callbacks (``on_sample``, ``on_gcode``, and the driver's ``on_output``) are queued under the lock
and run without it, in order, on the reader thread or the caller's thread for lines it sends. One
that raises is kept in :attr:`GrblChannel.callback_errors`; the link goes on.
"""

from __future__ import annotations

import contextlib
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from labrig.clock import NS_PER_US, HostClock
from labrig.devices.grbl_pose import LineEffect, PoseModel
from labrig.devices.grbl_protocol import (
    Alarm,
    ErrorReply,
    Event,
    GrblAlarm,
    GrblConnectionError,
    GrblError,
    GrblProtocol,
    Message,
    Ok,
    Realtime,
    Status,
    Welcome,
)
from labrig.devices.serial_link import LinkFailure, SerialLink, SerialPort

#: States in which GRBL may hold back responses for as long as the motion takes.
BUSY_STATES = frozenset({"Run", "Jog", "Hold", "Home", "Door"})
#: A ``?`` unanswered this long is given up (GRBL ignores ``?`` while homing or alarm-locked).
QUERY_TIMEOUT_S = 0.5
#: After a cycle starts, the next status poll comes this soon (us) to time the motion early.
EARLY_POLL_US = 30_000
#: How long one read of the port waits (s): the reader's tick for polling.
READ_TIMEOUT_S = 0.005


@dataclass(frozen=True)
class StatusSample:
    """One status report: host receive time (us), machine position (mm), feed (mm/min), state text."""

    t_host_us: int
    t_query_us: int | None
    position_mm: tuple[float, float, float]
    feed_mm_min: float
    state: str
    report: Status = field(repr=False)

    def columns(self) -> dict[str, int | float | str | tuple[float, float, float]]:
        """The sample as columns: ``t_host_us``, ``position_mm``, ``feed_mm_min``, ``state``."""
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


@dataclass
class Ticket:
    """A line in flight and what came back for it (guarded by the channel's lock)."""

    line: bytes
    t_sent_us: int
    timeout_s: float
    index: int | None = None
    effect: LineEffect = field(default_factory=LineEffect)
    done: bool = False
    discarded: bool = False
    code: int | None = None
    t_answer_us: int = 0
    pushed: list[Event] = field(default_factory=list)


class GrblChannel:
    """Lines, answers, polls and waits of one GRBL controller (see the module docstring)."""

    def __init__(
        self,
        port: str | SerialPort,
        *,
        baudrate: int,
        clock: HostClock,
        time_base_ns: int,
        poll_hz: float,
        rx_limit_bytes: int,
        on_sample: Callable[[StatusSample], None] | None,
        on_gcode: Callable[[int, int, bytes], None] | None,
    ) -> None:
        self.clock = clock
        self.time_base_ns = int(time_base_ns)
        self.poll_hz = float(poll_hz)
        self.on_sample = on_sample
        self.on_gcode = on_gcode
        self.byte_us = 10 * 1e6 / baudrate
        self.callback_errors: list[BaseException] = []
        self.core = GrblProtocol(rx_limit_bytes=rx_limit_bytes)
        self.cond = threading.Condition(threading.RLock())
        self.pose = PoseModel(self.byte_us)
        self.link = SerialLink(
            port,
            baudrate=baudrate,
            clock=clock,
            error_for=self._error_for,
            on_chunk=self._on_chunk,
            on_idle=self._on_idle,
            on_stop=self.run_callbacks,
            on_failure=self._on_failure,
            read_timeout_s=READ_TIMEOUT_S,
            thread_name="labrig-grbl-io",
        )
        self.tickets: deque[Ticket] = deque()
        self.last_sample: StatusSample | None = None
        self.last_busy_us = -(1 << 62)
        self.last_rx_us = 0
        self.welcomes = 0
        self.version: str | None = None
        self.alarms: deque[tuple[int, int]] = deque(maxlen=64)
        self.messages: deque[tuple[int, str]] = deque(maxlen=64)
        self._pending_callbacks: list[Callable[[], None]] = []
        self._callback_lock = threading.Lock()
        self._query_sent_us: int | None = None
        self._poll_requested = False
        self._next_poll_us = 0

    def now_us(self) -> int:
        """Now on the host clock, in the channel's time base (us)."""
        return self._us(self.clock.now_ns())

    def _us(self, t_ns: int) -> int:
        return (t_ns - self.time_base_ns) // NS_PER_US

    # -- life cycle ---------------------------------------------------------------------------

    def open(self) -> None:
        """Open the port, drop stale input and the line accounting, start the reader."""
        self.link.open()
        self.link.reset_input_buffer()
        with self.cond:
            self.core.forget_in_flight()
            self.tickets.clear()
        self.link.start()

    def close(self) -> None:
        """Latch "closed" for every later call (unless a failure came first) and close the link."""
        self.link.fail(GrblConnectionError("the GRBL driver was closed; connect() again"))
        self.link.close()

    def pulse_dtr(self) -> bool:
        """Pulse DTR (resets Arduino boards); False if the port has no modem lines (ptys: ENOTTY)."""
        try:
            return self.link.pulse_dtr()
        except OSError as exc:
            raise GrblConnectionError(f"setting DTR on {self.link.name} failed: {exc}") from exc

    def _error_for(self, failure: LinkFailure) -> GrblError:
        exc = failure.cause
        if failure.kind == "open":
            return GrblConnectionError(f"cannot open {self.link.name}: {exc}; check the port name and permissions")
        if failure.kind == "callback":
            error = GrblConnectionError(f"the GRBL reader stopped on {type(exc).__name__}: {exc}; reconnect")
            error.__cause__ = exc
            return error
        return GrblConnectionError(
            f"serial port {self.link.name} failed: {exc}; the controller was unplugged or the port closed: reconnect"
        )

    def _on_failure(self, error: Exception) -> None:
        with self.cond:
            self.cond.notify_all()

    def raise_if_failed(self) -> None:
        self.link.raise_if_failed()

    # -- sending ----------------------------------------------------------------------------------

    def send_locked(self, data: bytes, timeout_s: float, index: int | None = None) -> Ticket:
        """Write a line (the lock held) and return its ticket; the pose model follows it."""
        self.raise_if_failed()
        if self.core.locked:
            code = self.core.alarm or 0
            raise GrblAlarm(code, f"GRBL ignores all lines until reset; call soft_reset() before sending {data.decode()!r}")
        ticket = Ticket(data, 0, timeout_s, index=index)
        out = self.core.send_line(data, tag=ticket)
        ticket.effect = self.pose.line_sent(data)
        ticket.timeout_s += ticket.effect.dwell_s
        ticket.t_sent_us = self._write_locked(out)
        self.tickets.append(ticket)
        self._log(ticket.t_sent_us, 0, data)
        return ticket

    def write_realtime(self, command: bytes) -> int:
        """Write a real-time byte; returns the host time (us) it was written."""
        with self.cond:
            self.raise_if_failed()
            data = self.core.realtime(command)
            t = self._write_locked(data)
            if command != Realtime.STATUS:
                self._log(t, 0, data)
        self.run_callbacks()
        return t

    def request_poll_locked(self, now: int, explicit: bool = True) -> None:
        """Write ``?`` unless one is still unanswered (then, if ``explicit``, once it is answered)."""
        if self._query_sent_us is not None and now - self._query_sent_us <= QUERY_TIMEOUT_S * 1e6:
            self._poll_requested = self._poll_requested or explicit
            return
        if not self.link.is_open or self.link.error is not None:
            return
        self._query_sent_us = self._write_locked(self.core.realtime(Realtime.STATUS))
        self._poll_requested = False
        if self.poll_hz > 0:
            self._next_poll_us = self._query_sent_us + int(1e6 / self.poll_hz)

    @property
    def query_sent_us(self) -> int | None:
        """When the unanswered ``?`` was written (None: none is unanswered)."""
        return self._query_sent_us

    def _write_locked(self, data: bytes) -> int:
        return self._us(self.link.write(data))

    # -- callbacks ----------------------------------------------------------------------------

    def call(self, fn: Callable[..., None], *args: object) -> None:
        """Run a callback now; one that raises is kept in :attr:`callback_errors` (never kills the link)."""
        try:
            fn(*args)
        except Exception as exc:
            self.callback_errors.append(exc)

    @property
    def callbacks_pending(self) -> bool:
        return bool(self._pending_callbacks)

    def run_callbacks(self) -> None:
        """Run the queued callbacks, in order, without the lock."""
        with self._callback_lock:  # one runner at a time keeps the callbacks in order
            with self.cond:
                pending, self._pending_callbacks = self._pending_callbacks, []
            for fn in pending:
                self.call(fn)

    def _log(self, t: int, direction: int, line: bytes) -> None:
        if self.on_gcode is not None:
            cb = self.on_gcode
            self._pending_callbacks.append(lambda: cb(t, direction, line))

    # -- the reader thread ------------------------------------------------------------------------

    def _on_chunk(self, data: bytes, t_ns: int) -> None:
        now = self._us(t_ns)
        with self.cond:
            self.last_rx_us = now
            self._on_data(data, now)
            self._poll_if_due(now)
            self.cond.notify_all()
        self.run_callbacks()

    def _on_idle(self, t_ns: int) -> None:
        now = self._us(t_ns)
        with self.cond:
            self._poll_if_due(now)
            self.cond.notify_all()
        self.run_callbacks()

    def _poll_if_due(self, now: int) -> None:
        if (self.poll_hz > 0 and now >= self._next_poll_us) or self._poll_requested:
            with contextlib.suppress(GrblError):  # a failed write is latched: the reader stops
                self.request_poll_locked(now, explicit=self._poll_requested)

    def _on_data(self, data: bytes, t: int) -> None:
        for raw, event in self.core.receive_lines(data):
            self._log(t, 1, raw)
            if isinstance(event, (Ok, ErrorReply)):
                self._on_response(event, t)
            elif isinstance(event, Status):
                self._on_status(event, raw, t)
            elif isinstance(event, Alarm):
                self.alarms.append((t, event.code))
                if event.critical:
                    self.pose.alarm(t)
            elif isinstance(event, Welcome):
                self.welcomes += 1
                self.version = event.version
                for sent in event.dropped:
                    if isinstance(sent.tag, Ticket):
                        sent.tag.discarded = True
                self.tickets.clear()
                self.pose.controller_reset(t)
                self._query_sent_us = None
            else:
                if isinstance(event, Message):
                    self.messages.append((t, event.text))
                if self.tickets:  # push lines (settings, [GC:], [MSG:], ...) belong to the oldest unanswered line
                    self.tickets[0].pushed.append(event)

    def _on_response(self, event: Ok | ErrorReply, t: int) -> None:
        ticket = event.sent.tag if event.sent is not None else None
        if not isinstance(ticket, Ticket):
            return
        if self.tickets and self.tickets[0] is ticket:
            self.tickets.popleft()
        else:
            with contextlib.suppress(ValueError):
                self.tickets.remove(ticket)
        ticket.done = True
        ticket.t_answer_us = t
        if isinstance(event, ErrorReply):
            ticket.code = event.code
        started = self.pose.line_answered(ticket.effect, t, error=isinstance(event, ErrorReply))
        if started and self.poll_hz > 0:  # an early report times the new motion
            self._next_poll_us = min(self._next_poll_us, t + EARLY_POLL_US)

    def _on_status(self, event: Status, raw: bytes, t: int) -> None:
        t_query = self._query_sent_us
        self._query_sent_us = None
        if event.state in BUSY_STATES:
            self.last_busy_us = t
        self.pose.status_report(event, line_bytes=len(raw), t_us=t, t_query_us=t_query, lines_in_flight=bool(self.core.in_flight))
        if event.position_mm is None or len(event.position_mm) < 3:
            return
        position = (float(event.position_mm[0]), float(event.position_mm[1]), float(event.position_mm[2]))
        sample = StatusSample(t, t_query, position, float(event.feed_mm_min or 0.0), event.state_text, event)
        self.last_sample = sample
        on_sample = self.on_sample
        if on_sample is not None:
            self._pending_callbacks.append(lambda: on_sample(sample))

    # -- what came in -------------------------------------------------------------------------

    def alarms_since(self, t0: int) -> list[int]:
        with self.cond:
            return [code for t, code in self.alarms if t >= t0]

    def messages_since(self, t0: int) -> tuple[str, ...]:
        with self.cond:
            return tuple(text for t, text in self.messages if t >= t0)
