"""GRBL 1.1 CNC driver: the command API over a serial link, streaming, status samples, the pose.

The driver stands on three parts: :class:`~labrig.devices.grbl_channel.GrblChannel` (the serial
link, the lines in flight and their answers, polling, callbacks, waits with timeouts),
:class:`~labrig.devices.grbl_pose.PoseModel` (the tool pose rebuilt from the conversation) and
:class:`~labrig.devices.grbl_protocol.GrblProtocol` (the wire format). All host times are integer
microseconds of the injectable host clock (:mod:`labrig.clock`) relative to ``time_base_ns``
(set it to a recording's ``t0_host_ns`` to stamp in the recording's time base).

Callbacks (run on the I/O thread, or the caller's thread for lines it sends; keep them short):

* ``on_sample(StatusSample)``: every status report;
* ``on_gcode(t_host_us, direction, line)``: every line sent (0) and received (1), and the
  real-time bytes sent except ``?``;
* ``on_output(OutputEdge)``: each output toggle (camera trigger), with the host times the
  command was sent and acknowledged.

(:mod:`labrig.protocol.routing` puts them into a recording.) Every wait has a timeout; see
:mod:`labrig.devices.grbl_channel` for when a response counts as late. :meth:`Grbl.pose_at`
evaluates the reconstructed motion at any host time (:mod:`labrig.devices.grbl_pose`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from labrig.clock import HostClock, MonotonicClock
from labrig.devices.grbl_channel import QUERY_TIMEOUT_S, GrblChannel, Reply, StatusSample, Ticket
from labrig.devices.grbl_protocol import (
    GrblAlarm,
    GrblCommandError,
    GrblConnectionError,
    GrblError,
    GrblProtocol,
    GrblResetError,
    GrblTimeout,
    GrblUsageError,
    Realtime,
    Setting,
    format_number,
    jog_line,
    motion_line,
)
from labrig.devices.motion_profile import MachineLimits, Segment
from labrig.devices.serial_link import SerialPort

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
    "StreamResult",
]


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
    tickets: list[Ticket] = field(default_factory=list)
    answered: int = 0
    failed: Ticket | None = None
    max_in_flight_bytes: int = 0


class Grbl:
    """A GRBL 1.1 controller on a serial port.

    ``port``: an open serial-like object, or a port name/URL for ``serial.serial_for_url``
    (opened by :meth:`connect`, closed by :meth:`close`). ``poll_hz``: status polling rate (0: no
    automatic polling, responses then time out from sending). ``response_timeout_s``: see
    :mod:`labrig.devices.grbl_channel`. ``output_on``/``output_off``: the lines :meth:`set_output` sends.
    """

    def __init__(
        self,
        port: str | SerialPort,
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
        self.baudrate = baudrate
        self.clock = clock or MonotonicClock()
        self.response_timeout_s = float(response_timeout_s)
        self.on_output = on_output
        self.output_on = GrblProtocol.check_line(output_on)
        self.output_off = GrblProtocol.check_line(output_off)
        self.settings: dict[int, float] = {}
        self._io = GrblChannel(
            port, baudrate=baudrate, clock=self.clock, time_base_ns=time_base_ns, poll_hz=poll_hz,
            rx_limit_bytes=rx_limit_bytes, on_sample=on_sample, on_gcode=on_gcode,
        )  # fmt: skip
        self._pose = self._io.pose

    # -- lifecycle -------------------------------------------------------------------------

    def now_us(self) -> int:
        """Now on the host clock, in the driver's time base (us)."""
        return self._io.now_us()

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
        io = self._io
        io.open()
        t_begin = self.now_us()
        method = reset
        if reset in ("auto", "dtr"):
            count = io.welcomes
            if io.pulse_dtr():
                if not io.wait_welcome(count, timeout_s if reset == "dtr" else min(timeout_s, 2.5), required=reset == "dtr"):
                    method = "soft"
            else:
                method = "soft"
        if method == "soft":
            count = io.welcomes
            io.write_realtime(Realtime.SOFT_RESET)
            io.wait_welcome(count, timeout_s, required=True)
        io.wait_quiet(0.05, 0.5)
        sample = self.status(timeout_s=timeout_s)
        if read_settings:
            self.read_settings(timeout_s=timeout_s)
        alarm = io.core.alarm if sample.report.state == "Alarm" else None
        return ConnectInfo(io.version, sample.state, method, alarm, io.messages_since(t_begin))

    def close(self) -> None:
        """Stop the I/O thread and close the port if the driver opened it; later calls raise."""
        self._io.close()

    def __enter__(self) -> Grbl:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- state -------------------------------------------------------------------------

    @property
    def on_sample(self) -> Callable[[StatusSample], None] | None:
        return self._io.on_sample

    @on_sample.setter
    def on_sample(self, callback: Callable[[StatusSample], None] | None) -> None:
        self._io.on_sample = callback

    @property
    def on_gcode(self) -> Callable[[int, int, bytes], None] | None:
        return self._io.on_gcode

    @on_gcode.setter
    def on_gcode(self, callback: Callable[[int, int, bytes], None] | None) -> None:
        self._io.on_gcode = callback

    @property
    def time_base_ns(self) -> int:
        return self._io.time_base_ns

    @property
    def poll_hz(self) -> float:
        return self._io.poll_hz

    @property
    def byte_us(self) -> float:
        """One byte's time on the wire (us) at the baud rate."""
        return self._io.byte_us

    @property
    def callback_errors(self) -> list[BaseException]:
        """Exceptions the callbacks raised (the link went on)."""
        return self._io.callback_errors

    @property
    def last_sample(self) -> StatusSample | None:
        return self._io.last_sample

    @property
    def state(self) -> str:
        """The state of the last status report (``Unknown`` before the first)."""
        sample = self._io.last_sample
        return sample.state if sample is not None else "Unknown"

    @property
    def position_mm(self) -> tuple[float, float, float] | None:
        """Machine position of the last status report."""
        sample = self._io.last_sample
        return sample.position_mm if sample is not None else None

    @property
    def protocol(self) -> GrblProtocol:
        """The protocol core (its statistics: ``max_in_flight_bytes``, ``noise_bytes``, ...)."""
        return self._io.core

    @property
    def limits(self) -> MachineLimits:
        return self._pose.limits

    @property
    def link_latency_us(self) -> float:
        """One-way latency of the link (us), from the status queries' round trips."""
        return self._pose.link_latency_us

    # -- commands ------------------------------------------------------------------------

    def send(self, line: str | bytes, timeout_s: float | None = None) -> Reply:
        """Send one line after every earlier one is answered and wait for its ``ok`` (send-response).

        Raises :class:`GrblCommandError` on ``error:N``, :class:`GrblAlarm` when a critical alarm
        locks the controller meanwhile, :class:`GrblTimeout`, :class:`GrblConnectionError`.
        """
        io = self._io
        data = io.core.check_line(line)
        timeout = self.response_timeout_s if timeout_s is None else float(timeout_s)
        with io.cond:
            while io.core.in_flight:
                io.wait_oldest()
            ticket = io.send_locked(data, timeout)
        io.run_callbacks()
        io.wait_ticket(ticket)
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
        io = self._io
        program = [io.core.check_line(line) for line in lines]
        for data in program:
            if re.match(rb"\s*\$\s*(\d|N\d|I=|RST)", data, re.IGNORECASE):
                raise GrblUsageError(f"{data!r} writes EEPROM and must be sent alone: use write_setting() or send()")
        timeout = self.response_timeout_s if timeout_s is None else float(timeout_s)
        run = _StreamRun(len(program), progress)
        t_start = self.now_us()
        with io.cond:
            for i, data in enumerate(program):
                while run.failed is None:
                    self._scan(run)
                    fits = io.core.can_send(data) if mode == "count" else not io.core.in_flight
                    if run.failed is not None or fits:
                        break
                    io.wait_oldest()
                if run.failed is not None:
                    break
                run.tickets.append(io.send_locked(data, timeout, index=i))
                run.max_in_flight_bytes = max(run.max_in_flight_bytes, io.core.in_flight_bytes)
                if io.callbacks_pending or progress is not None:
                    self._scan(run)
            while run.answered < len(run.tickets):
                self._scan(run)
                if run.answered < len(run.tickets):
                    io.wait_step(run.tickets[run.answered])
        io.run_callbacks()
        if run.failed is not None:
            assert run.failed.code is not None
            raise GrblCommandError(run.failed.code, run.failed.line, run.failed.index)
        return StreamResult(mode, len(run.tickets), t_start, self.now_us(), run.max_in_flight_bytes)

    def check_program(self, lines: Iterable[str | bytes], timeout_s: float | None = None) -> list[tuple[int, GrblCommandError]]:
        """Run a program through GRBL's check mode (``$C``): the errors it would give, by line index.

        Leaving check mode soft-resets the controller (GRBL's behaviour); the position is kept.
        """
        self.send("$C", timeout_s)
        self._pose.checking = True  # the lines only parse: the pose model must not move
        errors: list[tuple[int, GrblCommandError]] = []
        try:
            for i, line in enumerate(lines):
                try:
                    self.send(line, timeout_s)
                except GrblCommandError as exc:
                    errors.append((i, GrblCommandError(exc.code, exc.line, i)))
        finally:
            count = self._io.welcomes
            self.send("$C", timeout_s)
            self._io.wait_welcome(count, 5.0, required=True)
            self._pose.checking = False
            self.status()
        return errors

    def read_settings(self, timeout_s: float | None = None) -> dict[int, float]:
        """``$$``: all settings; the pose model takes its limits from them."""
        reply = self.send("$$", timeout_s)
        settings = {e.number: e.value for e in reply.pushed if isinstance(e, Setting)}
        with self._io.cond:
            self.settings = settings
            self._pose.limits = MachineLimits.from_settings(settings)
        return dict(settings)

    def write_setting(self, number: int, value: float, timeout_s: float | None = None) -> None:
        """``$N=value`` (send-response only: GRBL's receiver is deaf while it writes EEPROM)."""
        if not isinstance(number, int) or number < 0:
            raise GrblUsageError(f"setting number must be a non-negative integer, got {number!r}")
        if not math.isfinite(value):
            raise GrblUsageError(f"setting value must be finite, got {value!r}")
        self.send(f"${number}={format_number(value)}", timeout_s)
        with self._io.cond:
            self.settings[number] = float(value)
            self._pose.limits = MachineLimits.from_settings(self.settings)

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
        line = "G90" + ("G53" if machine else "") + motion_line(x, y, z, feed_mm_min)
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
        return self._move("G91" + motion_line(dx, dy, dz, feed_mm_min), wait, timeout_s)

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
        return self.send(jog_line(x, y, z, feed_mm_min=feed_mm_min, relative=relative, machine=machine), timeout_s)

    def jog_cancel(self) -> None:
        """0x85: decelerate and drop the queued jogs (only acts while jogging)."""
        t = self._io.write_realtime(Realtime.JOG_CANCEL)
        with self._io.cond:
            self._pose.jog_cancel_written(t)

    def feed_hold(self) -> None:
        """``!``: decelerate to a stop and hold (Hold:1, then Hold:0); queued moves are kept."""
        t = self._io.write_realtime(Realtime.FEED_HOLD)
        with self._io.cond:
            self._pose.feed_hold_written(t)

    def resume(self) -> None:
        """``~``: resume from a hold (GRBL ignores it while the hold is still decelerating)."""
        t = self._io.write_realtime(Realtime.CYCLE_START)
        with self._io.cond:
            self._pose.resume_written(t)

    def soft_reset(self, timeout_s: float = 5.0) -> ConnectInfo:
        """0x18: halt at once and restart GRBL; unanswered lines are dropped (their waiters get
        :class:`GrblResetError`). A reset in motion leaves GRBL in Alarm (ALARM:3): unlock or home.
        """
        io = self._io
        count = io.welcomes
        t0 = self.now_us()
        t = io.write_realtime(Realtime.SOFT_RESET)
        with io.cond:
            self._pose.soft_reset_written(t)
        io.wait_welcome(count, timeout_s, required=True)
        io.wait_quiet(0.02, 0.3)
        sample = self.status(timeout_s=timeout_s)
        alarms = io.alarms_since(t0)
        return ConnectInfo(io.version, sample.state, "soft", alarms[-1] if alarms else None, io.messages_since(t0))

    def set_output(self, on: bool, timeout_s: float | None = None) -> OutputEdge:
        """Switch the output (``output_on``/``output_off``, M8/M9 by default) for the camera trigger.

        GRBL switches it once queued motion has finished, then answers; the edge lies between
        :attr:`OutputEdge.t_sent_us` and :attr:`OutputEdge.t_ack_us`.
        """
        line = self.output_on if on else self.output_off
        reply = self.send(line, timeout_s)
        edge = OutputEdge(int(bool(on)), line, reply.t_sent_us, reply.t_answer_us)
        if self.on_output is not None:
            self._io.call(self.on_output, edge)
        return edge

    def status(self, timeout_s: float = 1.0) -> StatusSample:
        """A fresh status report (its ``?`` sent after this call began).

        Raises :class:`GrblAlarm` at once while a critical alarm locks the controller (it ignores
        ``?`` until :meth:`soft_reset`), :class:`GrblTimeout` when no report comes in ``timeout_s``.
        """
        io = self._io
        t0 = self.now_us()
        deadline = t0 + timeout_s * 1e6
        with io.cond:
            io.request_poll_locked(t0)
            while True:
                io.raise_if_failed()
                sample = io.last_sample
                if sample is not None and sample.t_query_us is not None and sample.t_query_us >= t0:
                    return sample
                if io.core.locked:  # no report will come: say why at once
                    raise GrblAlarm(io.core.alarm or 0, "GRBL answers nothing, not even '?', until soft_reset()")
                now = self.now_us()
                if now >= deadline:
                    raise GrblTimeout(
                        f"no status report within {timeout_s:.1f} s (last state {self.state}); GRBL does not answer '?' "
                        "while homing: wait for it, else check the port and cable"
                    )
                if io.query_sent_us is None or now - io.query_sent_us > QUERY_TIMEOUT_S * 1e6:
                    io.request_poll_locked(now)
                io.cond.wait(min(0.02, (deadline - now) / 1e6))

    def wait_idle(self, timeout_s: float = 60.0) -> StatusSample:
        """Wait until every line is answered and GRBL reports Idle (polling status).

        Raises :class:`GrblAlarm` if it ends in Alarm, :class:`GrblTimeout` after ``timeout_s``
        (a hold counts as not idle).
        """
        io = self._io
        t0 = self.now_us()
        deadline = t0 + timeout_s * 1e6
        interval_s = 1.0 / io.poll_hz if io.poll_hz > 0 else 0.1
        with io.cond:
            while io.core.in_flight:
                if self.now_us() > deadline:
                    raise GrblTimeout(f"lines still unanswered after {timeout_s:.1f} s")
                io.wait_oldest()
        while True:
            sample = self.status(timeout_s=max(min(2.0, (deadline - self.now_us()) / 1e6), 0.05))
            if sample.report.state == "Idle":
                return sample
            if sample.report.state == "Alarm":
                self._raise_alarm_since(t0, "while waiting for Idle")
                raise GrblAlarm(io.core.alarm or 0, "controller in Alarm while waiting for Idle")
            if self.now_us() > deadline:
                raise GrblTimeout(f"controller still {sample.state} after {timeout_s:.1f} s")
            next_us = min(sample.t_host_us + interval_s * 1e6, deadline)
            with io.cond:  # poll no faster than poll_hz
                while (now := self.now_us()) < next_us:
                    io.raise_if_failed()
                    io.cond.wait((next_us - now) / 1e6)

    # -- pose reconstruction ----------------------------------------------------------------

    def pose_at(self, t_host_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Machine position (mm) at host times (us, driver time base): shape (3,) for a scalar, (N, 3) otherwise."""
        with self._io.cond:
            out = self._pose.positions_at(t_host_us)
        return out[0] if np.ndim(t_host_us) == 0 else out

    def planned_segments(self) -> list[Segment]:
        """The reconstructed motion: executed segments, then the current plan (host time base)."""
        with self._io.cond:
            return self._pose.segments()

    # -- internals -------------------------------------------------------------------------

    def _move(self, line: str, wait: bool, timeout_s: float | None) -> Reply:
        reply = self.send(line, timeout_s)
        if wait:
            self.wait_idle(timeout_s if timeout_s is not None else 3600.0)
        return reply

    def _raise_alarm_since(self, t0: int, context: str) -> None:
        alarms = self._io.alarms_since(t0)
        if alarms:
            raise GrblAlarm(alarms[-1], context)

    def _scan(self, run: _StreamRun) -> None:
        """Advance over a stream's answered lines (answers come in order): note the first error,
        raise if the controller reset under the stream, report progress, run pending callbacks.
        """
        io = self._io
        tickets = run.tickets
        k = run.answered
        while k < len(tickets) and tickets[k].done:
            if tickets[k].code is not None and run.failed is None:
                run.failed = tickets[k]
            k += 1
        if k < len(tickets) and tickets[k].discarded:
            io.raise_discarded(tickets[k])
        progressed = k != run.answered
        run.answered = k
        if (progressed and run.progress is not None) or io.callbacks_pending:
            io.cond.release()  # callbacks run without the lock
            try:
                io.run_callbacks()
                if progressed and run.progress is not None:
                    run.progress(k, run.total)
            finally:
                io.cond.acquire()
