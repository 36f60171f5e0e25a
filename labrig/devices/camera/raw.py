"""The ``raw`` camera backend: a RAW file (EVT3 / EVT2) replayed as if live."""

from __future__ import annotations

import itertools
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.clock import NS_PER_US, HostClock
from labrig.devices.camera.base import DEFAULT_QUEUE_CHUNKS, Camera, CameraError, DeviceInfo
from labrig.devices.raw import RawFormatError, open_decoder

#: Every trigger input a RAW file can hold edges of (``I_TriggerIn.Channel``'s numbering).
FILE_TRIGGER_INPUTS = {"main": 0, "aux": 1, "loopback": 2}
#: Bytes of the file decoded when the camera opens (a throwaway decode), bytes.
WARM_UP_BYTES = 1 << 12


class RawReplayCamera(Camera):
    """Replays a RAW file (EVT3 / EVT2) as a live camera.

    ``speed``: 1.0 paces chunks by their event times (real time), 2.0 twice as fast, None as
    fast as possible. ``packet_us``: device time per delivered chunk when paced (a camera hands
    over USB packets of about 1 ms at high rates). Triggers in the file are replayed on every
    channel (trigger-in settings do not filter a recording).
    """

    backend = "raw"

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        speed: float | None = 1.0,
        packet_us: int = 1000,
        read_bytes: int = 1 << 18,
        clock: HostClock | None = None,
        queue_chunks: int = DEFAULT_QUEUE_CHUNKS,
        trigger_in: tuple[str | int, ...] = ("main",),
    ) -> None:
        super().__init__(clock=clock, queue_chunks=queue_chunks, trigger_in=trigger_in)
        self.path = Path(path)
        self.speed = speed
        self.packet_us = int(packet_us)
        self.read_bytes = int(read_bytes)
        self._thread: threading.Thread | None = None
        self._halt = threading.Event()

    def _open(self) -> None:
        if not self.path.is_file():
            raise CameraError(f"{self.path}: no such RAW file")
        try:
            header, fmt, geo, decoder = open_decoder(self.path)
            with open(self.path, "rb") as raw:  # the decoder's kernels load now, not in the stream's first chunk
                raw.seek(header.size)
                decoder.feed(raw.read(WARM_UP_BYTES))
        except RawFormatError as exc:
            raise CameraError(str(exc)) from None
        width, height = geo or (1280, 720)
        f = header.fields
        self._info = DeviceInfo(
            "raw",
            f.get("serial_number", ""),
            width,
            height,
            f.get("sensor_name", f.get("sensor_generation", "")),
            fmt,
            str(self.path),
            dict(f),
        )

    def _start(self) -> None:
        self._halt.clear()
        self._thread = threading.Thread(target=self._run, name=f"camera-raw:{self.path.name}", daemon=True)
        self._thread.start()

    def _stop(self) -> None:
        self._halt.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def _run(self) -> None:
        try:
            self._replay()
        except Exception as exc:
            self._fail("replay failed", exc)
        else:
            self._end()

    def trigger_inputs(self) -> dict[str, int]:
        return dict(FILE_TRIGGER_INPUTS)

    def _replay(self) -> None:
        header, _, _, decoder = open_decoder(self.path)
        header_size = header.size
        wall0: int | None = None
        dev0 = 0
        with open(self.path, "rb") as f:
            f.seek(header_size)
            while not self._halt.is_set():
                data = f.read(self.read_bytes)
                if not data:
                    break
                out = decoder.feed(data)
                for events, triggers in self._packets(out.events, out.triggers):
                    t_dev = int(events["t"][-1]) if events.size else int(triggers["t"][-1])
                    if self.speed:
                        if wall0 is None:
                            wall0, dev0 = self.clock.now_ns(), t_dev
                        due = wall0 + int((t_dev - dev0) * NS_PER_US / self.speed)
                        while not self._halt.is_set():
                            left = due - self.clock.now_ns()
                            if left <= 0:
                                break
                            time.sleep(min(left / 1e9, 0.05))
                        if self._halt.is_set():
                            return
                    self._deliver(events, triggers, self.clock.now_ns())
        decoder.finish()

    def _packets(
        self, events: npt.NDArray[Any], triggers: npt.NDArray[Any]
    ) -> Iterator[tuple[npt.NDArray[Any], npt.NDArray[Any]]]:
        if not self.speed or events.size == 0:
            if events.size or triggers.size:
                yield events, triggers
            return
        t = events["t"]
        edges = np.flatnonzero(np.diff(t // self.packet_us)) + 1
        bounds = [0, *edges.tolist(), t.size]
        t_tr = triggers["t"]
        tr_done = 0
        for a, b in itertools.pairwise(bounds):
            last = b == t.size
            k = t_tr.size if last else int(np.searchsorted(t_tr, t[b - 1], side="right"))
            yield events[a:b], triggers[tr_done:k]
            tr_done = max(tr_done, k)
