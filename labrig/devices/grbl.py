"""GRBL 1.1 CNC driver: the command API over a serial link, streaming, status samples, the pose.

The driver stands on four parts: :class:`~labrig.devices.grbl_channel.GrblChannel` (the serial
link, the lines in flight and their answers, polling, callbacks),
:class:`~labrig.devices.grbl_waits.GrblWaits` (send-response, streaming, every wait with its timeout),
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
:mod:`labrig.devices.grbl_waits` for when a response counts as late. :meth:`Grbl.pose_at`
evaluates the reconstructed motion at any host time (:mod:`labrig.devices.grbl_pose`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.clock import HostClock, MonotonicClock
from labrig.devices.grbl_channel import GrblChannel, Reply, StatusSample
from labrig.devices.grbl_gcode import Coordinates, ModalState, coordinates_from_parameters, modal_state_from_report
from labrig.devices.grbl_protocol import (
    GrblAlarm,
    GrblCommandError,
    GrblConnectionError,
    GrblError,
    GrblProtocol,
    GrblResetError,
    GrblTimeout,
    GrblUsageError,
    Parameter,
    ParserState,
    Realtime,
    Setting,
    format_number,
    jog_line,
    motion_line,
)
from labrig.devices.grbl_waits import GrblWaits, StreamResult
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
]


#: GRBL's acknowledgement as it goes over the wire.
ACK_LINE = b"ok\r\n"


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

    def bounds_us(self, byte_us: float, execute_us: float) -> tuple[int, int]:
        """(earliest, latest) host times (us) of the switch, for an output line sent with nothing queued.

        Earliest: the send stamp (taken before the write) plus the line on the wire (its bytes and
        the newline at ``byte_us`` each) plus the controller's ``execute_us`` to parse it; never
        after the acknowledgement. Latest: the acknowledgement's receipt less ``ok\r\n`` on the
        wire, which the controller sends once the output has switched.
        """
        latest = round(self.t_ack_us - len(ACK_LINE) * byte_us)
        earliest = round(self.t_sent_us + (len(self.line) + 1) * byte_us + execute_us)
        latest = max(latest, round(self.t_sent_us))
        return min(earliest, latest), latest


@dataclass(frozen=True)
class ConnectInfo:
    """The controller after :meth:`Grbl.connect` or :meth:`Grbl.soft_reset`."""

    version: str | None
    state: str
    reset: str
    alarm: int | None
    messages: tuple[str, ...]


class Grbl:
    """A GRBL 1.1 controller on a serial port.

    ``port``: an open serial-like object, or a port name/URL for ``serial.serial_for_url``
    (opened by :meth:`connect`, closed by :meth:`close`). ``poll_hz``: status polling rate (0: no
    automatic polling, responses then time out from sending). ``response_timeout_s``: see
    :mod:`labrig.devices.grbl_waits`; ``status_timeout_s``: how long :meth:`status` waits by default
    (its ``?`` is resent every 0.5 s meanwhile); a twin on a loaded host needs more of both.
    ``output_on``/``output_off``: the lines :meth:`set_output` sends.
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
        status_timeout_s: float = 1.0,
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
        self.on_output = on_output
        self.output_on = GrblProtocol.check_line(output_on)
        self.output_off = GrblProtocol.check_line(output_off)
        self.settings: dict[int, float] = {}
        self._io = GrblChannel(
            port, baudrate=baudrate, clock=self.clock, time_base_ns=time_base_ns, poll_hz=poll_hz,
            rx_limit_bytes=rx_limit_bytes, on_sample=on_sample, on_gcode=on_gcode,
        )  # fmt: skip
        self._pose = self._io.pose
        self._waits = GrblWaits(self._io, response_timeout_s)
        self.status_timeout_s = float(status_timeout_s)

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
        io, waits = self._io, self._waits
        io.open()
        t_begin = self.now_us()
        method = reset
        if reset in ("auto", "dtr"):
            count = io.welcomes
            if io.pulse_dtr():
                if not waits.wait_welcome(count, timeout_s if reset == "dtr" else min(timeout_s, 2.5), required=reset == "dtr"):
                    method = "soft"
            else:
                method = "soft"
        if method == "soft":
            count = io.welcomes
            io.write_realtime(Realtime.SOFT_RESET)
            waits.wait_welcome(count, timeout_s, required=True)
        waits.wait_quiet(0.05, 0.5)
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
    def response_timeout_s(self) -> float:
        return self._waits.response_timeout_s

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

    # -- lines and waits -------------------------------------------------------------------

    def send(self, line: str | bytes, timeout_s: float | None = None) -> Reply:
        """Send one line after every earlier one is answered and wait for its ``ok`` (send-response).

        Raises :class:`GrblCommandError` on ``error:N``, :class:`GrblAlarm` when a critical alarm
        locks the controller meanwhile, :class:`GrblTimeout`, :class:`GrblConnectionError`.
        """
        return self._waits.send(line, timeout_s)

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
        return self._waits.stream(lines, mode=mode, progress=progress, timeout_s=timeout_s)

    def status(self, timeout_s: float | None = None) -> StatusSample:
        """A fresh status report (its ``?`` sent after this call began).

        Raises :class:`GrblAlarm` at once while a critical alarm locks the controller (it ignores
        ``?`` until :meth:`soft_reset`), :class:`GrblTimeout` when no report comes in ``timeout_s``.
        """
        return self._waits.status(self.status_timeout_s if timeout_s is None else timeout_s)

    def wait_idle(self, timeout_s: float = 60.0) -> StatusSample:
        """Wait until every line is answered and GRBL reports Idle (polling status).

        Raises :class:`GrblAlarm` if it ends in Alarm, :class:`GrblTimeout` after ``timeout_s``
        (a hold counts as not idle).
        """
        return self._waits.wait_idle(timeout_s)

    # -- commands ------------------------------------------------------------------------

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
            self._waits.wait_welcome(count, 5.0, required=True)
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

    def gcode_state(self, timeout_s: float | None = None) -> tuple[ModalState, Coordinates]:
        """``$G`` and ``$#``: the G-code parser's modal state and its offsets (machine mm), with the
        parser at the machine position of a fresh status report (the parser's own position while
        Idle or in Alarm; GRBL refuses ``$#`` with error:8 otherwise).

        Raises :class:`GrblError` when an answer lacks its report or holds one GRBL 1.1 does not send.
        """
        modal_reply = self.send("$G", timeout_s)
        parameter_reply = self.send("$#", timeout_s)
        sample = self.status(timeout_s)
        reports = [e.words for e in modal_reply.pushed if isinstance(e, ParserState)]
        parameters = {e.name: e.values for e in parameter_reply.pushed if isinstance(e, Parameter)}
        try:
            if not reports:
                raise ValueError("$G answered without a [GC:...] report")
            return modal_state_from_report(reports[-1]), coordinates_from_parameters(parameters, sample.position_mm)
        except ValueError as exc:
            raise GrblError(f"cannot read the controller's G-code state: {exc}") from None

    def unlock(self, timeout_s: float | None = None) -> None:
        """``$X``: leave Alarm without homing (position as GRBL has it)."""
        self.send("$X", timeout_s)
        self.status()

    def home(self, timeout_s: float = 120.0) -> StatusSample:
        """``$H``: run the homing cycle (GRBL is silent while homing, so the timeout covers all of it)."""
        t0 = self.now_us()
        self.send("$H", timeout_s)
        self._waits.raise_alarm_since(t0, "during homing")
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
        self._waits.wait_welcome(count, timeout_s, required=True)
        self._waits.wait_quiet(0.02, 0.3)
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
