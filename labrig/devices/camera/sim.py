"""The ``sim`` camera backend: the EVT3 byte stream of the virtual rig's EVK4 twin, over a Unix socket."""

from __future__ import annotations

import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

from labrig.clock import HostClock
from labrig.devices.camera.base import DEFAULT_QUEUE_CHUNKS, Camera, CameraError, DeviceInfo
from labrig.devices.raw import Evt3Decoder, parse_header

#: The twin's trigger inputs (``I_TriggerIn.Channel``'s numbering); the rig wires GRBL's output to ``main``.
TWIN_TRIGGER_INPUTS = {"main": 0, "aux": 1, "loopback": 2}


class SimCamera(Camera):
    """Reads the EVT3 stream of an :class:`~labrig.sim.evk4_twin.Evk4Twin` from its Unix socket.

    ``connect_timeout_s``: how long ``open`` waits for the socket to accept. Data that
    arrives before ``start`` (or after ``stop``) is decoded and discarded, as a camera that is
    not streaming sends nothing. When the twin closes the connection the stream ends.
    """

    backend = "sim"

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        connect_timeout_s: float = 5.0,
        recv_bytes: int = 1 << 16,
        clock: HostClock | None = None,
        queue_chunks: int = DEFAULT_QUEUE_CHUNKS,
        trigger_in: tuple[str | int, ...] = ("main",),
    ) -> None:
        super().__init__(clock=clock, queue_chunks=queue_chunks, trigger_in=trigger_in)
        self.path = Path(path)
        self.connect_timeout_s = connect_timeout_s
        self.recv_bytes = int(recv_bytes)
        self.bytes_received = 0
        self._sock: socket.socket | None = None
        self._decoder: Evt3Decoder | None = None
        self._thread: threading.Thread | None = None
        self._halt = threading.Event()
        self._pending = b""

    def _open(self) -> None:
        deadline = time.monotonic() + self.connect_timeout_s
        last: OSError | None = None
        while True:
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                sock.connect(os.fspath(self.path))
                break
            except OSError as exc:
                sock.close()
                last = exc
                if time.monotonic() >= deadline:
                    raise CameraError(
                        f"cannot connect to the simulated camera at {self.path}: {last}; is `labrig sim serve` running?"
                    ) from None
                time.sleep(0.02)
        sock.settimeout(0.1)
        header_bytes = self._read_header(sock, deadline)
        header = parse_header(header_bytes)
        fmt = (header.format_name() or "").upper()
        if fmt != "EVT3":
            sock.close()
            raise CameraError(f"{self.path}: the stream is {fmt or 'of unknown format'}, expected EVT3")
        width, height = header.geometry() or (1280, 720)
        f = header.fields
        self._info = DeviceInfo(
            "sim", f.get("serial_number", ""), width, height, "IMX636 (simulated)", fmt, str(self.path), dict(f)
        )
        self._decoder = Evt3Decoder(width, height)
        self._sock = sock
        self._halt.clear()
        self._thread = threading.Thread(target=self._run, name=f"camera-sim:{self.path.name}", daemon=True)
        self._thread.start()

    def _read_header(self, sock: socket.socket, deadline: float) -> bytes:
        buf = b""
        while b"% end\n" not in buf:
            if time.monotonic() > deadline + 5.0 or len(buf) > 65536:
                sock.close()
                raise CameraError(f"{self.path}: no RAW header (ending with '% end') from the simulated camera")
            try:
                data = sock.recv(4096)
            except TimeoutError:
                continue
            if not data:
                sock.close()
                raise CameraError(f"{self.path}: the simulated camera closed the connection before its header")
            buf += data
        end = buf.index(b"% end\n") + len(b"% end\n")
        self._pending = buf[end:]
        return buf[:end]

    def _close(self) -> None:
        self._halt.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _run(self) -> None:
        assert self._sock is not None and self._decoder is not None
        sock, decoder = self._sock, self._decoder
        try:
            if self._pending:
                self._take(decoder.feed(self._pending), self.clock.now_ns())
                self._pending = b""
            while not self._halt.is_set():
                try:
                    data = sock.recv(self.recv_bytes)
                except TimeoutError:
                    continue
                t_host = self.clock.now_ns()
                if not data:
                    break
                self.bytes_received += len(data)
                self._take(decoder.feed(data), t_host)
        except Exception as exc:
            self._fail("reading the twin's socket failed", exc)
        else:
            self._end()

    def _take(self, out: Any, t_host_ns: int) -> None:
        if self._streaming.is_set():
            self._deliver(out.events, self._filter_triggers(out.triggers), t_host_ns)

    def trigger_inputs(self) -> dict[str, int]:
        return dict(TWIN_TRIGGER_INPUTS)
