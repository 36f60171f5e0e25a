"""Serving device twins on pseudo-terminals, so real drivers open them as serial ports.

A twin is a byte-level state machine with two methods (see :class:`SerialTwin`):
``receive(data, now_us)`` takes what the host wrote, ``transmit(now_us)``
returns what the device has sent by ``now_us`` (paced by its baud rate and its
own timing). :class:`TwinServer` runs any number of twins in one thread, each
on its own pty, on the host clock. Drivers see ordinary serial ports
(``/dev/pts/N``); nothing bypasses the bytes.

Pseudo-terminals have no modem lines: setting DTR or RTS on one fails with
ENOTTY, which drivers must tolerate (a real port resets some boards on DTR).
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import threading
import tty
from collections.abc import Callable
from functools import partial
from typing import Protocol

from labrig.clock import HostClock, MonotonicClock
from labrig.sim.faults import RigFault


class SerialTwin(Protocol):
    """A device twin speaking bytes."""

    def receive(self, data: bytes, now_us: int) -> None:
        """Bytes the host wrote, arriving at ``now_us`` (host clock, us)."""

    def transmit(self, now_us: int) -> bytes:
        """Bytes the device has sent by ``now_us`` and not yet returned."""


class PtyPort:
    """One pseudo-terminal: the twin holds the master end; ``path`` is the serial port."""

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        os.set_blocking(self.master, False)
        self.dropped_bytes = 0
        self.closed = False

    def read(self) -> bytes:
        try:
            return os.read(self.master, 65536)
        except BlockingIOError:
            return b""
        except OSError as exc:  # EIO: no client has the port open
            if exc.errno == errno.EIO:
                return b""
            raise

    def write(self, data: bytes) -> None:
        """Write what the pty takes now; the rest is dropped and counted, as a
        real port's output is lost when nobody reads it (never blocks the server)."""
        try:
            n = os.write(self.master, data)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            if exc.errno != errno.EIO:
                raise
            n = 0
        self.dropped_bytes += len(data) - n

    def close(self) -> None:
        if self.closed:  # never close a descriptor number twice: it may belong to someone else by now
            return
        self.closed = True
        for fd in (self.master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


class TwinServer:
    """Serve twins on ptys from one thread until stopped. Use as a context manager."""

    def __init__(self, twins: dict[str, SerialTwin], clock: HostClock | None = None, tick_s: float = 0.0005) -> None:
        self.twins = twins
        self.clock = clock or MonotonicClock()
        self.tick_s = tick_s
        self.ports = {name: PtyPort() for name in twins}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="labrig-twins", daemon=True)
        self.error: BaseException | None = None
        #: What a twin raised on a request (the thread goes on serving; the owner reports them).
        self.faults: list[RigFault] = []
        self._failing: dict[str, str] = {}
        #: Twins whose port was pulled by :meth:`unplug`.
        self.unplugged: set[str] = set()
        self._unplug_lock = threading.Lock()
        self._unplug_requests: list[tuple[str, threading.Event]] = []

    @property
    def paths(self) -> dict[str, str]:
        return {name: port.path for name, port in self.ports.items()}

    def now_us(self) -> int:
        return self.clock.now_ns() // 1000

    def start(self) -> TwinServer:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        for port in self.ports.values():
            port.close()
        with self._unplug_lock:
            requests, self._unplug_requests = self._unplug_requests, []
        for name, done in requests:
            self.unplugged.add(name)
            done.set()

    def unplug(self, name: str, timeout_s: float = 2.0) -> None:
        """Fault injection: the device ``name`` vanishes (cable pulled). Its pty closes, so the
        driver's reads and writes on the port fail; the other twins keep running."""
        if name not in self.ports:
            raise KeyError(f"no twin named {name!r}")
        done = threading.Event()
        with self._unplug_lock:
            if self._thread.is_alive():
                self._unplug_requests.append((name, done))
            else:
                self._pull(name)
                return
        if not done.wait(timeout_s):
            raise TimeoutError(f"the twin server did not unplug {name!r} within {timeout_s} s")

    def _pull(self, name: str) -> None:
        self.ports[name].close()
        self.unplugged.add(name)

    def __enter__(self) -> TwinServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _serve(self, label: str, request: Callable[[], bytes | None]) -> bytes | None:
        """One twin request; what it raises is kept in :attr:`faults` (once per kind of error in a
        row) and the thread goes on serving the twins: a bad request must not take the rig down."""
        try:
            reply = request()
        except Exception as exc:
            kind = f"{label}: {type(exc).__name__}"
            if self._failing.get(label) != kind:
                self.faults.append(RigFault(self.now_us(), f"{kind}: {exc}"))
            self._failing[label] = kind
            return None
        self._failing.pop(label, None)
        return reply

    def _run(self) -> None:
        masters = {port.master: name for name, port in self.ports.items()}
        try:
            while not self._stop.is_set():
                if self._unplug_requests:
                    with self._unplug_lock:
                        requests, self._unplug_requests = self._unplug_requests, []
                    for name, done in requests:
                        self._pull(name)
                        done.set()
                    masters = {port.master: name for name, port in self.ports.items() if name not in self.unplugged}
                readable, _, _ = select.select(list(masters), [], [], self.tick_s)
                now = self.now_us()
                for fd in readable:
                    name = masters[fd]
                    data = self.ports[name].read()
                    if data:
                        self._serve(f"{name} receive", partial(self.twins[name].receive, data, now))
                for name, twin in self.twins.items():
                    if name in self.unplugged:
                        continue
                    out = self._serve(f"{name} transmit", partial(twin.transmit, self.now_us()))
                    if out:
                        self.ports[name].write(out)
        except BaseException as exc:  # surfaced to the owner; the thread must not die silently
            self.error = exc
            raise
