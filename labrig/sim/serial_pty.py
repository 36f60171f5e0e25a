"""Serving device twins on pseudo-terminals, so real drivers open them as serial ports.

A twin is a byte-level state machine with two methods (see :class:`SerialTwin`):
``receive(data, now_us)`` takes what the host wrote, ``transmit(now_us)``
returns what the device has sent by ``now_us`` (paced by its baud rate and its
own timing). :class:`TwinServer` runs any number of twins in one thread, each
on its own pty, on the host clock. Drivers see ordinary serial ports
(``/dev/pts/N``); nothing bypasses the bytes.

A twin whose timing must not depend on the server's load (the GRBL twin: its trigger
output switches when a line arrives) can have its port in a relay process
(:mod:`labrig.sim.pty_relay`, a :class:`RelayedPort`) that stamps the host's bytes as they
arrive; the twin gets those stamps instead of the time the server got round to reading.

Pseudo-terminals have no modem lines: setting DTR or RTS on one fails with
ENOTTY, which drivers must tolerate (a real port resets some boards on DTR).
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
import subprocess
import sys
import threading
import tty
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Protocol

from labrig.clock import HostClock, MonotonicClock
from labrig.sim import pty_relay
from labrig.sim.faults import RigFault


class SerialTwin(Protocol):
    """A device twin speaking bytes."""

    def receive(self, data: bytes, now_us: int) -> None:
        """Bytes the host wrote, arriving at ``now_us`` (host clock, us)."""

    def transmit(self, now_us: int) -> bytes:
        """Bytes the device has sent by ``now_us`` and not yet returned."""


#: What a host's serial driver holds for a reader that is late, bytes: Linux keeps up to 64 KiB of a
#: tty port's input in its flip buffers (``TTYB_DEFAULT_MEM_LIMIT``) beside the line discipline's
#: 4 KiB, and loses what comes after. A pty takes only about 17 KB, so the port holds the rest.
HOST_BUFFER_BYTES = 65536


class PtyPort:
    """One pseudo-terminal: the twin holds the master end; ``path`` is the serial port.

    A device's bytes wait for a late reader as they would on a real port: what the pty cannot
    take now is held (up to :data:`HOST_BUFFER_BYTES`, in order) and written as it drains, on the
    server's next ticks (:meth:`flush`); beyond that, new bytes are lost and counted.
    """

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        os.set_blocking(self.master, False)
        self.dropped_bytes = 0
        self.closed = False
        self._pending = bytearray()

    def fileno(self) -> int:
        return self.master

    def receive(self, now_us: int) -> list[tuple[int, bytes]]:
        """What the host wrote, stamped ``now_us`` (when the server read it)."""
        data = self.read()
        return [(now_us, data)] if data else []

    def read(self) -> bytes:
        try:
            return os.read(self.master, 65536)
        except BlockingIOError:
            return b""
        except OSError as exc:  # EIO: no client has the port open
            if exc.errno == errno.EIO:
                return b""
            raise

    @property
    def pending_bytes(self) -> int:
        """Bytes held for a late reader, not yet in the pty."""
        return len(self._pending)

    def write(self, data: bytes) -> None:
        """Queue ``data`` behind what is held and write what the pty takes now (never blocks the server).

        Bytes beyond :data:`HOST_BUFFER_BYTES` held are dropped and counted, as a real port's input is
        lost when nobody reads it for long."""
        self._pending += data
        self.flush()
        if len(self._pending) > HOST_BUFFER_BYTES:  # the newest bytes are the ones lost
            self.dropped_bytes += len(self._pending) - HOST_BUFFER_BYTES
            del self._pending[HOST_BUFFER_BYTES:]

    def flush(self) -> None:
        """Write what the pty takes of the held bytes. With no client on the port (EIO) they are lost."""
        if not self._pending:
            return
        try:
            n = os.write(self.master, self._pending)
        except BlockingIOError:
            return
        except OSError as exc:
            if exc.errno != errno.EIO:
                raise
            self.dropped_bytes += len(self._pending)
            self._pending.clear()
            return
        del self._pending[:n]

    def close(self) -> None:
        if self.closed:  # never close a descriptor number twice: it may belong to someone else by now
            return
        self.closed = True
        for fd in (self.master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


class RelayedPort:
    """A pty held by a :mod:`~labrig.sim.pty_relay` process, which stamps the host's bytes on arrival
    (``time.monotonic_ns``: the server's clock must be the monotonic host clock)."""

    #: Seconds to wait for the relay to start and name its port.
    START_TIMEOUT_S = 10.0

    def __init__(self) -> None:
        self._sock, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            self._process = subprocess.Popen([sys.executable, "-I", "-S", str(Path(pty_relay.__file__)), str(theirs.fileno())],
                                             pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL)
        finally:
            theirs.close()
        self._sock.settimeout(self.START_TIMEOUT_S)
        try:
            self.path = self._sock.recv(4096).decode()
        except (TimeoutError, OSError) as exc:
            self.close()
            raise RuntimeError(f"the serial relay did not start within {self.START_TIMEOUT_S} s: {exc}") from exc
        if not self.path:
            self.close()
            raise RuntimeError(f"the serial relay exited at start (code {self._process.wait()})")
        self._sock.setblocking(False)
        self.dropped_bytes = 0
        self.closed = False

    def fileno(self) -> int:
        return self._sock.fileno()

    def receive(self, now_us: int) -> list[tuple[int, bytes]]:
        """What the host wrote, each read stamped (us) when the relay saw it arrive."""
        out: list[tuple[int, bytes]] = []
        while True:
            try:
                message = self._sock.recv(pty_relay.STAMP.size + pty_relay.READ_BYTES)
            except (BlockingIOError, InterruptedError):
                return out
            if not message:  # the relay is gone: the port with it
                return out
            (stamp_ns,) = pty_relay.STAMP.unpack_from(message)
            out.append((stamp_ns // 1000, message[pty_relay.STAMP.size:]))

    def write(self, data: bytes) -> None:
        try:
            self._sock.send(data)
        except (BlockingIOError, OSError):
            self.dropped_bytes += len(data)

    def flush(self) -> None:
        """Nothing held here: the relay writes to its pty (what it cannot take is lost there)."""

    def close(self) -> None:
        if getattr(self, "closed", False):
            return
        self.closed = True
        self._sock.close()  # the relay sees EOF and exits; its pty goes with it
        try:
            self._process.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()


SerialPort = PtyPort | RelayedPort


class TwinServer:
    """Serve twins on ptys from one thread until stopped. Use as a context manager.

    ``relayed``: names of twins whose port sits in a relay process stamping arrivals
    (:class:`RelayedPort`; needs the monotonic host clock, the default).
    """

    def __init__(self, twins: dict[str, SerialTwin], clock: HostClock | None = None, tick_s: float = 0.0005,
                 relayed: frozenset[str] | set[str] = frozenset()) -> None:
        self.twins = twins
        self.clock = clock or MonotonicClock()
        if relayed and not isinstance(self.clock, MonotonicClock):
            raise ValueError("relayed ports stamp with the monotonic host clock: serve them on a MonotonicClock")
        self.tick_s = tick_s
        self.ports: dict[str, SerialPort] = {}
        try:
            for name in twins:
                self.ports[name] = RelayedPort() if name in relayed else PtyPort()
        except BaseException:
            for port in self.ports.values():
                port.close()
            raise
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
        #: Host time (us) up to which every twin has run on everything the host wrote before it:
        #: what a twin does (an output edge) before this time is known to its callbacks.
        self.served_until_us = -(1 << 62)

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
        masters = {port.fileno(): name for name, port in self.ports.items()}
        relayed = [name for name, port in self.ports.items() if isinstance(port, RelayedPort)]
        try:
            while not self._stop.is_set():
                if self._unplug_requests:
                    with self._unplug_lock:
                        requests, self._unplug_requests = self._unplug_requests, []
                    for name, done in requests:
                        self._pull(name)
                        done.set()
                    masters = {port.fileno(): name for name, port in self.ports.items() if name not in self.unplugged}
                    relayed = [name for name in relayed if name not in self.unplugged]
                readable, _, _ = select.select(list(masters), [], [], self.tick_s)
                now = self.now_us()
                # Relayed bytes stamped before ``now`` are in their sockets by now: take them all
                # before the twins run on to ``now``, so that each acts on its bytes at their stamps.
                for name in {*(masters[fd] for fd in readable), *relayed}:
                    for stamp_us, data in self.ports[name].receive(now):
                        self._serve(f"{name} receive", partial(self.twins[name].receive, data, stamp_us))
                for name, twin in self.twins.items():
                    if name in self.unplugged:
                        continue
                    out = self._serve(f"{name} transmit", partial(twin.transmit, now))
                    if out:
                        self.ports[name].write(out)
                    else:
                        self.ports[name].flush()
                self.served_until_us = now
        except BaseException as exc:  # surfaced to the owner; the thread must not die silently
            self.error = exc
            raise
