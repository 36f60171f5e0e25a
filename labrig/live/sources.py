"""What the live runner reads: anything with ``read(timeout_s)`` and ``ended``.

A :class:`~labrig.devices.camera.Camera` is one; a :class:`ChunkTap` is another, fed by
:meth:`labrig.protocol.session.RigSession.add_chunk_listener` while a probing run records the
same camera. Nothing here blocks the camera reader: a camera drops and counts whole chunks when
its own queue is full, so does a :class:`ChunkTap`.
"""

from __future__ import annotations

import queue
import threading
from typing import Protocol

from labrig.devices.camera import DEFAULT_QUEUE_CHUNKS, CameraStats, EventChunk


class ChunkSource(Protocol):
    """What the live runner reads: a camera, or a :class:`ChunkTap`."""

    def read(self, timeout_s: float | None = None) -> EventChunk | None: ...

    @property
    def ended(self) -> bool: ...


class ChunkTap:
    """A chunk listener that never blocks: queues chunks for the live pipeline, drops (and counts) when full.

    Register it with :meth:`RigSession.add_chunk_listener`; :meth:`close` it when the
    producer is done, then :meth:`read` returns what is left and ``ended`` turns true.
    """

    def __init__(self, max_chunks: int = DEFAULT_QUEUE_CHUNKS) -> None:
        self._queue: queue.Queue[EventChunk] = queue.Queue(maxsize=max_chunks)
        self._closed = threading.Event()
        self.stats = CameraStats()

    def __call__(self, chunk: EventChunk) -> None:
        if self._closed.is_set():
            return
        try:
            self._queue.put_nowait(chunk)
        except queue.Full:
            self.stats.dropped_chunks += 1
            self.stats.dropped_events += int(chunk.events.size)
            return
        self.stats.chunks += 1
        self.stats.events += int(chunk.events.size)

    def close(self) -> None:
        self._closed.set()

    @property
    def ended(self) -> bool:
        return self._closed.is_set() and self._queue.empty()

    def read(self, timeout_s: float | None = None) -> EventChunk | None:
        if self.ended:
            return None
        try:
            return self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None
