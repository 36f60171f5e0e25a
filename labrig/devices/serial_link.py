"""One serial link under the device drivers: a port opened with its quirks, a reader thread that
stamps each chunk on the host clock, writes, close, and a failure latch.

The GRBL and Bota drivers both stand on :class:`SerialLink`; it knows nothing of their protocols.

Threads and time
----------------
:meth:`SerialLink.start` starts one reader thread that owns the input side. Each read takes what
is waiting (at least one byte, at most the port's read timeout), then what came with the first
byte, and stamps the chunk with the host clock's time (integer ns) the moment the read returned;
``on_chunk(data, t_host_ns)`` gets it on that thread. A read that times out with nothing calls
``on_idle(t_host_ns)`` instead (owners run their timers there). ``on_stop()`` runs on the reader
thread as it ends, whatever the reason. Writes happen on the caller's thread.

Failures
--------
The first failure is latched: the port failing a read or a write, the owner's ``on_chunk`` or
``on_idle`` raising (a broken callback stops the reader and is kept, never lost), or one the owner
reports with :meth:`SerialLink.fail`. The owner turns each :class:`LinkFailure` into its own error
(``error_for``); :attr:`SerialLink.error` keeps it, ``on_failure(error)`` is called once, the reader
stops, and :meth:`SerialLink.write` and :meth:`SerialLink.raise_if_failed` raise it from then on.
:meth:`SerialLink.open` clears the latch for a new connection.

Port quirks
-----------
A port is an open pyserial-like object (kept open at close: the caller owns it) or a name / URL for
``serial.serial_for_url`` (opened here, closed at close). DTR resets Arduino-style boards: a
pulse (:meth:`SerialLink.pulse_dtr`) says whether the port has modem lines; pseudo-terminals (the
virtual rig) refuse the ioctl with ENOTTY. ``low_latency`` asks an FTDI chip for 1 ms latency
instead of its 16 ms default, where the port supports it.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol

import serial

from labrig.clock import HostClock

log = logging.getLogger(__name__)

#: What a failing port raises on reads: pyserial reports a vanished device as SerialException
#: or OSError; a port closed under a blocked read gives TypeError or AttributeError.
READ_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, TypeError, AttributeError)
#: What a failing port raises on writes.
WRITE_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError)
#: What opening a port by name raises (no such device, no permission, a malformed URL).
OPEN_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, ValueError)


class SerialPort(Protocol):
    """What a link needs of a port (pyserial's ``Serial`` and test fakes)."""

    timeout: float | None

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes) -> int | None: ...

    @property
    def in_waiting(self) -> int: ...

    def close(self) -> None: ...


def port_name(port: str | SerialPort | None) -> str:
    """A port's name for messages: the name or URL itself, or an open port's own name."""
    if isinstance(port, str):
        return port
    return str(getattr(port, "port", None) or getattr(port, "name", None) or "the port")


@dataclass(frozen=True)
class LinkFailure:
    """Why a link failed: the port could not be opened, read or written, or the owner's callback raised."""

    kind: Literal["open", "read", "write", "callback"]
    cause: BaseException


class SerialLink:
    """A serial port, its reader thread and its failure latch (see the module docstring).

    ``error_for``: the owner's error for a failure (raised, latched, handed to ``on_failure``).
    ``read_timeout_s``: how long one read waits (the reader's tick for ``on_idle``).
    ``write_timeout_s``: the port's write timeout (None: leave the port's own).
    """

    def __init__(
        self,
        port: str | SerialPort,
        *,
        baudrate: int,
        clock: HostClock,
        error_for: Callable[[LinkFailure], Exception],
        on_chunk: Callable[[bytes, int], None],
        on_idle: Callable[[int], None] | None = None,
        on_stop: Callable[[], None] | None = None,
        on_failure: Callable[[Exception], None] | None = None,
        read_timeout_s: float = 0.05,
        write_timeout_s: float | None = None,
        low_latency: bool = False,
        thread_name: str = "labrig-serial",
    ) -> None:
        self._url = port if isinstance(port, str) else None
        self._given: SerialPort | None = None if isinstance(port, str) else port
        self.baudrate = baudrate
        self.clock = clock
        self.read_timeout_s = read_timeout_s
        self.write_timeout_s = write_timeout_s
        self.low_latency = low_latency
        self.thread_name = thread_name
        self._error_for = error_for
        self._on_chunk = on_chunk
        self._on_idle = on_idle
        self._on_stop = on_stop
        self._on_failure = on_failure
        self._port: SerialPort | None = None
        self._owns_port = False
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._latch = threading.Lock()
        self._error: Exception | None = None
        #: Why the reader ended ("" while it runs or before it starts).
        self.exit_reason = ""

    # -- state -------------------------------------------------------------------------------

    @property
    def name(self) -> str:
        """The port's name for messages: the URL, or the open port's own name."""
        return port_name(self._url or (self._port if self._port is not None else self._given))

    @property
    def port(self) -> SerialPort:
        """The open port (its baud rate, flush, ...); raises if the link is not open."""
        if self._port is None:
            raise RuntimeError(f"the serial link to {self.name} is not open")
        return self._port

    @property
    def is_open(self) -> bool:
        return self._port is not None

    @property
    def error(self) -> Exception | None:
        """The latched failure (the owner's error), or None."""
        return self._error

    def in_reader_thread(self) -> bool:
        """Whether the caller runs on the reader thread (a callback: it must not wait for the reader)."""
        return self._thread is threading.current_thread()

    # -- life cycle -------------------------------------------------------------------------

    def open(self) -> None:
        """Open the port by name (or adopt the given one), set its timeouts, clear the latch."""
        if self._port is None:
            if self._url is None:
                assert self._given is not None
                self._port, self._owns_port = self._given, False
                with contextlib.suppress(AttributeError, ValueError):
                    self._port.timeout = self.read_timeout_s
                if self.write_timeout_s is not None:
                    with contextlib.suppress(AttributeError, ValueError):
                        self._port.write_timeout = self.write_timeout_s  # type: ignore[attr-defined]
            else:
                options: dict[str, float] = {"timeout": self.read_timeout_s}
                if self.write_timeout_s is not None:
                    options["write_timeout"] = self.write_timeout_s
                try:
                    self._port = serial.serial_for_url(self._url, baudrate=self.baudrate, **options)
                except OPEN_ERRORS as exc:
                    raise self._error_for(LinkFailure("open", exc)) from exc
                self._owns_port = True
            if self.low_latency:
                with contextlib.suppress(Exception):  # 1 ms FTDI latency where the port supports it
                    self._port.set_low_latency_mode(True)  # type: ignore[union-attr]
        with self._latch:
            self._error = None
        self.exit_reason = ""

    def start(self) -> None:
        """Start the reader thread (no-op while it runs)."""
        if self._thread is not None and self._thread.is_alive():
            return
        port = self.port
        self._stop.clear()
        self._thread = threading.Thread(target=self._read_loop, args=(port,), name=self.thread_name, daemon=True)
        self._thread.start()

    def close(self, timeout_s: float = 2.0) -> bool:
        """Stop the reader (waiting up to ``timeout_s`` unless called from it) and close the port if
        the link opened it. Returns whether the reader has ended."""
        self._stop.set()
        port = self._port
        if port is not None and hasattr(port, "cancel_read"):
            with contextlib.suppress(Exception):
                port.cancel_read()
        thread = self._thread
        ended = True
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)
            ended = not thread.is_alive()
            if not ended:
                log.warning("serial reader on %s did not end within %g s", self.name, timeout_s)
        self._thread = None
        if self._owns_port and port is not None:
            with contextlib.suppress(Exception):
                port.close()
        self._port = None
        return ended

    # -- input side helpers ------------------------------------------------------------------

    def reset_input_buffer(self) -> None:
        """Drop what the port has buffered (stale bytes from before a connect); no-op where unsupported."""
        with contextlib.suppress(AttributeError, OSError, serial.SerialException):
            self.port.reset_input_buffer()  # type: ignore[attr-defined]

    def pulse_dtr(self, low_s: float = 0.05) -> bool:
        """Pulse DTR low for ``low_s`` (resets Arduino-style boards).

        False when the port has no modem lines (a pty: ENOTTY) or no DTR at all; other OS errors raise.
        """
        port = self.port
        try:
            port.dtr = False  # type: ignore[attr-defined]
            time.sleep(low_s)
            port.dtr = True  # type: ignore[attr-defined]
        except OSError as exc:  # SerialException is an OSError without errno
            if exc.errno in (errno.ENOTTY, errno.EINVAL, None):
                return False
            raise
        except (AttributeError, NotImplementedError):
            return False
        return True

    # -- output side ------------------------------------------------------------------------

    def write(self, data: bytes, *, char_gap_s: float = 0.0) -> int:
        """Write ``data`` (a byte at a time with ``char_gap_s`` pauses when positive and longer
        than one byte); returns the host time (ns) just before the first byte went out: the earliest
        the device can act on them, a true lower bound however long this thread is descheduled
        afterwards (a stamp taken when the write returned was late by milliseconds on a loaded host).
        A failing port latches and raises the owner's error; a link not open raises it without latching."""
        if self._port is None:
            raise self._error_for(LinkFailure("write", RuntimeError("the port is not open: connect first")))
        t_start_ns = self.clock.now_ns()
        try:
            if char_gap_s > 0 and len(data) > 1:
                for i in range(len(data)):
                    self.port.write(data[i : i + 1])
                    time.sleep(char_gap_s)
            else:
                self.port.write(data)
        except WRITE_ERRORS as exc:
            raise self.fail(self._error_for(LinkFailure("write", exc))) from None
        return t_start_ns

    # -- the failure latch -------------------------------------------------------------------

    def fail(self, error: Exception) -> Exception:
        """Latch ``error`` unless a failure is latched already; returns the latched one (to raise).

        The first call stops the reader and calls ``on_failure`` (a raising hook is logged).
        """
        with self._latch:
            if self._error is not None:
                return self._error
            self._error = error
        self._stop.set()
        if self._on_failure is not None:
            try:
                self._on_failure(error)
            except Exception:
                log.exception("the failure hook of the serial link to %s raised", self.name)
        return error

    def raise_if_failed(self) -> None:
        if self._error is not None:
            raise self._error

    # -- the reader thread ----------------------------------------------------------------------

    def _read_loop(self, port: SerialPort) -> None:
        try:
            self._read_until_stopped(port)
        finally:
            if self._on_stop is not None:
                try:
                    self._on_stop()
                except Exception:
                    log.exception("the stop hook of the serial link to %s raised", self.name)

    def _read_until_stopped(self, port: SerialPort) -> None:
        while not self._stop.is_set():
            try:
                waiting = port.in_waiting
                data = port.read(waiting or 1)
                if data and not waiting:  # woke on the first byte: take what came with it
                    more = port.in_waiting
                    if more:
                        data += port.read(more)
            except READ_ERRORS as exc:
                if self._stop.is_set():
                    break
                self.exit_reason = f"port failed: {exc}"
                self.fail(self._error_for(LinkFailure("read", exc)))
                return
            t_ns = self.clock.now_ns()
            try:
                if data:
                    self._on_chunk(data, t_ns)
                elif self._on_idle is not None:
                    self._on_idle(t_ns)
            except Exception as exc:
                self.exit_reason = f"callback raised {type(exc).__name__}: {exc}"
                self.fail(self._error_for(LinkFailure("callback", exc)))
                return
        if not self.exit_reason:
            self.exit_reason = "closed"
