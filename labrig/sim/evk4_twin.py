"""A byte-level EVK4 twin: a Unix-socket server that streams EVT 3.0 like the camera's USB link.

The world process feeds it event chunks in camera time (``feed(events, triggers)``, from the
rig thread); a client (``labrig.devices.camera`` ``sim`` backend) connects to the socket and
reads a RAW header (``% ...`` lines ending with ``% end``) followed by one continuous EVT3
word stream: chunks are encoded with labrig's EVT3 encoder and joined so that a decoder sees
one stream (every TIME_HIGH step between chunks, 24-bit wraps as 4095 -> 0, trigger words).

``feed`` never blocks: chunks wait in a bounded FIFO (``max_buffered_events``); when the
client does not read fast enough the FIFO fills and new chunks are dropped and counted in
``dropped_events`` (as the camera's FIFO overflows). Without a client, fed chunks are
discarded and counted in ``unclaimed_events``. One client at a time; when it disconnects the
twin waits for the next one, which gets a fresh header and stream (device times keep going).

USB bursts (``release_at``): a chunk fed at host time t leaves the twin no earlier than
``release_at(t)`` (host us, on ``clock``), so the client receives the data in bursts.
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import threading
from collections import deque
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.clock import HostClock, MonotonicClock
from labrig.devices.raw import TRIGGER_DTYPE, Evt3StreamEncoder, make_header

#: Bytes handed to one send() call at most.
_SEND_BYTES = 1 << 18
#: Encoded bytes waiting for the socket before the next chunk is encoded.
_OUT_LOW_WATER = 1 << 20


def as_triggers(triggers: npt.NDArray[Any] | Iterable[tuple[int, int]] | None) -> npt.NDArray[Any]:
    """TRIGGER_DTYPE edges from an array with fields p, t (and id), or (t_camera_us, polarity) pairs (channel 0)."""
    if triggers is None:
        return np.zeros(0, TRIGGER_DTYPE)
    if isinstance(triggers, np.ndarray) and triggers.dtype.names:
        out = np.zeros(triggers.size, TRIGGER_DTYPE)
        out["t"], out["p"] = triggers["t"], triggers["p"]
        if "id" in triggers.dtype.names:
            out["id"] = triggers["id"]
        return out
    pairs = list(triggers)
    out = np.zeros(len(pairs), TRIGGER_DTYPE)
    for i, (t, p) in enumerate(pairs):
        out[i] = (int(p), int(t), 0)
    return out


class Evk4Twin:
    """Unix-socket EVK4 twin (see the module docstring). Counters are read without locking."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        width: int = 1280,
        height: int = 720,
        max_buffered_events: int = 4_000_000,
        serial: str = "00000000",
        header: dict[str, str] | None = None,
        release_at: Callable[[int], int] | None = None,
        clock: HostClock | None = None,
    ) -> None:
        """``release_at(t_host_us)``: the host time (us, ``clock``'s) a chunk fed at ``t_host_us`` may leave (None: at once)."""
        self.path = Path(path)
        self.release_at = release_at
        self.clock = clock or MonotonicClock()
        self.width = int(width)
        self.height = int(height)
        self.max_buffered_events = int(max_buffered_events)
        self.header_fields = {"serial_number": serial, "plugin_name": "hal_plugin_imx636_evk4", **(header or {})}
        #: Payload bytes written to clients (headers included).
        self.bytes_sent = 0
        #: Events dropped because the FIFO was full (client not reading fast enough).
        self.dropped_events = 0
        self.dropped_triggers = 0
        #: Events fed while no client was connected (discarded).
        self.unclaimed_events = 0
        #: Events encoded into a client's stream.
        self.events_sent = 0
        self.triggers_sent = 0
        #: Clients accepted so far.
        self.connections = 0
        self._fifo: deque[tuple[npt.NDArray[Any], npt.NDArray[Any], int]] = deque()  # events, triggers, release us
        self._fifo_events = 0
        self._lock = threading.Lock()
        self._client_on = threading.Event()
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._server: socket.socket | None = None
        self._thread: threading.Thread | None = None

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> Evk4Twin:
        """Listen on ``path`` (a stale socket file is replaced) and serve clients in a thread."""
        if self._thread is not None:
            raise RuntimeError("Evk4Twin already started")
        if self.path.is_socket():
            self.path.unlink()
        srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        srv.bind(os.fspath(self.path))
        srv.listen(4)
        srv.setblocking(False)
        self._server = srv
        self._thread = threading.Thread(target=self._serve, name=f"evk4-twin:{self.path.name}", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving, disconnect the client and remove the socket file."""
        self._stop.set()
        self._poke()
        if self._thread is not None:
            self._thread.join(timeout=5)
        if self._server is not None:
            self._server.close()
            self._server = None
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1
        try:
            if self.path.is_socket():
                self.path.unlink()
        except OSError:
            pass

    def __enter__(self) -> Evk4Twin:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def connected(self) -> bool:
        """A client is connected now."""
        return self._client_on.is_set()

    def wait_connected(self, timeout_s: float | None = None) -> bool:
        return self._client_on.wait(timeout_s)

    @property
    def buffered_events(self) -> int:
        """Events waiting in the FIFO."""
        return self._fifo_events

    # -- feeding (any thread; never blocks on the client) ---------------------------------------
    def feed(self, events: npt.NDArray[Any], triggers: npt.NDArray[Any] | Iterable[tuple[int, int]] | None = None) -> bool:
        """Queue a chunk (events x, y, p, t in camera us; triggers (t_camera_us, polarity) or p/t/id).

        Returns False when it was dropped (FIFO full) or discarded (no client). Raises ValueError
        for events the EVT3 stream cannot carry (outside the sensor, p not 0/1, negative t).
        """
        tr = as_triggers(triggers)
        n = int(events.size)
        if n == 0 and tr.size == 0:
            return True
        _check_events(events, self.width, self.height)
        if not self._client_on.is_set():
            self.unclaimed_events += n
            return False
        with self._lock:
            if self._fifo_events + n > self.max_buffered_events:
                self.dropped_events += n
                self.dropped_triggers += int(tr.size)
                return False
            release = 0 if self.release_at is None else self.release_at(self.clock.now_ns() // 1000)
            self._fifo.append((np.array(events, copy=True), tr, release))
            self._fifo_events += n
        self._poke()
        return True

    def _poke(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self._wake_w, b"x")

    # -- server thread ----------------------------------------------------------------------------
    def _serve(self) -> None:
        assert self._server is not None
        while not self._stop.is_set():
            watch_r: list[socket.socket | int] = [self._server, self._wake_r]
            readable, _, _ = select.select(watch_r, [], [], 0.2)
            if self._wake_r in readable:
                self._drain_wake()
            if self._server in readable:
                try:
                    client, _ = self._server.accept()
                except OSError:
                    continue
                self.connections += 1
                try:
                    self._stream_to(client)
                finally:
                    self._client_on.clear()
                    with self._lock:
                        self._fifo.clear()
                        self._fifo_events = 0
                    client.close()

    def _drain_wake(self) -> None:
        with contextlib.suppress(OSError):
            os.read(self._wake_r, 4096)

    def _stream_to(self, client: socket.socket) -> None:
        client.setblocking(False)
        encoder = Evt3StreamEncoder(self.width, self.height)
        out = bytearray(make_header("EVT3", self.width, self.height, self.header_fields))
        self._client_on.set()
        while not self._stop.is_set():
            wait_s = 0.2
            while len(out) < _OUT_LOW_WATER:
                with self._lock:
                    if not self._fifo:
                        break
                    if self._fifo[0][2]:
                        early_us = self._fifo[0][2] - self.clock.now_ns() // 1000
                        if early_us > 0:  # its burst is not released yet
                            wait_s = min(wait_s, early_us / 1e6)
                            break
                    events, triggers, _ = self._fifo.popleft()
                    self._fifo_events -= events.size
                out += encoder.encode(events, triggers)
                self.events_sent += int(events.size)
                self.triggers_sent += int(triggers.size)
            watch_w = [client] if out else []
            watch_r: list[socket.socket | int] = [client, self._wake_r]
            readable, writable, _ = select.select(watch_r, watch_w, [], wait_s)
            if self._wake_r in readable:
                self._drain_wake()
            if client in readable:
                try:
                    if not client.recv(4096):
                        return  # the client closed its end
                except (BlockingIOError, InterruptedError):
                    pass
                except OSError:
                    return
            if client in writable and out:
                try:
                    sent = client.send(memoryview(out)[:_SEND_BYTES])
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:
                    return  # broken pipe / reset: the client is gone
                del out[:sent]
                self.bytes_sent += sent
        # stopping: hand over what is encoded if the client takes it at once
        try:
            client.setblocking(True)
            client.settimeout(0.5)
            client.sendall(out)
            self.bytes_sent += len(out)
        except OSError:
            pass


def _check_events(events: npt.NDArray[Any], width: int, height: int) -> None:
    names = events.dtype.names or ()
    if not {"x", "y", "p", "t"} <= set(names):
        raise ValueError(f"events need fields x, y, p, t; got {names}")
    if events.size == 0:
        return
    if int(events["x"].max()) >= width or int(events["y"].max()) >= height:
        raise ValueError(f"events outside the {width}x{height} sensor")
    if int(events["p"].max()) > 1 or int(events["p"].min()) < 0 or int(events["t"].min()) < 0:
        raise ValueError("event p must be 0/1 and t non-negative")
