"""The pipeline on a live event stream: device-time windows over camera chunks, kept in real time.

Sources are anything with ``read(timeout_s) -> EventChunk | None`` and ``ended`` (a
:class:`~labrig.devices.camera.Camera`, or a :class:`ChunkTap` fed by
:meth:`labrig.protocol.session.RigSession.add_chunk_listener`).

Windows (:class:`EventWindower`) are in the camera's **device time** (us), as the events carry
it: fixed time (a grid of ``window_us`` anchored at a multiple of it) or fixed event count
(t1 = the next window's first event). An event belongs to the window that is open when it
arrives: a time window closes at the first event at or past its end, so a late (out of order)
event joins the open window instead of reopening a closed one; an empty stretch of the
stream gives empty windows; a jump of the device clock by more than ``MAX_JUMP_US``
(a camera restart) starts a new grid. At the end the partial time window is kept (t1 = its
last event + 1), a partial count window is dropped, as in :func:`labrig.pipeline.runtime.windows`.

Real time (:class:`LiveRunner`): the front stage (windowing, SAE, tracker) runs in its own
thread and sees every window, so markers stay tracked; the back stage (depth, displacements,
forces, and whatever the caller does with each result) runs in the caller's thread. A
window's age is the host time since the chunk that closed it arrived. When the back stage
reaches a window older than ``max_lag_ms`` (default 100 ms), it **skips** it and every window
queued behind it but the newest, and goes on with that one: skipped windows are tracked only,
no depth, forces or result. So the forces shown are never much older than ``max_lag_ms`` and
a slow stretch is caught up at once; a pipeline slower than real time gives runs of
consecutive windows with jumps between them. (Also skipped: windows that find the queue
between the stages full, 256 windows.) A processed window whose result was ready more than one window span after it
closed is counted **late**. Sources deliver chunks in bursts (a camera's USB transfers; the
virtual rig's camera about every 50 ms), so a burst of windows is processed one after the
other and its last ones can be late without the pipeline falling behind on average: the
latency percentiles say how far behind the results were. Nothing here blocks the camera
reader: a camera drops and counts whole chunks when its own queue is full, so does a
:class:`ChunkTap`.
"""

from __future__ import annotations

import queue
import threading
import time
from array import array
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from labrig.clock import HostClock, MonotonicClock
from labrig.devices.camera import DEFAULT_QUEUE_CHUNKS, CameraStats, EventChunk
from labrig.eventtypes import EVENT_DTYPE
from labrig.pipeline.runtime import DEFAULT_WINDOW_US, Pipeline, WindowResult

#: A device-time step larger than this between consecutive events restarts the window grid, us.
MAX_JUMP_US = 10_000_000
#: The back stage skips windows older than this (host time since the chunk that closed them arrived), ms.
MAX_LAG_MS = 100.0
#: Windows that may wait between the stages; when full, new ones are tracked only.
QUEUE_WINDOWS = 256


# -- windows over chunks ----------------------------------------------------------------------------


@dataclass(frozen=True)
class LiveWindow:
    """One window of a live stream: device times, its events, and when it became complete."""

    t0_us: int  # device time, window start
    t1_us: int  # device time, window end (exclusive)
    events: npt.NDArray[Any]  # EVENT_DTYPE, ``t`` in device us
    t_host_ns: int  # host time the chunk that closed the window arrived


def _empty_events() -> npt.NDArray[Any]:
    return np.zeros(0, EVENT_DTYPE)


class EventWindower:
    """Cuts a stream of event arrays (in arrival order) into windows; pure, no threads.

    ``push(events, t_host_ns)`` returns the windows that chunk completed; ``flush()`` the
    last one at the end of the stream. Give exactly one of ``window_us`` and ``window_events``.
    """

    def __init__(self, window_us: int | None = DEFAULT_WINDOW_US, window_events: int | None = None) -> None:
        if (window_us is None) == (window_events is None):
            raise ValueError("give exactly one of window_us and window_events")
        if (window_us is not None and window_us <= 0) or (window_events is not None and window_events <= 0):
            raise ValueError("window_us and window_events must be positive")
        self.window_us = window_us
        self.window_events = window_events
        self._parts: list[npt.NDArray[Any]] = []
        self._held = 0
        self._index: int | None = None  # open time window: [index * window_us, (index + 1) * window_us)
        self._last_t: int | None = None
        self._last_host_ns = 0
        self.first_t_us: int | None = None
        self.time_jumps = 0

    @property
    def last_t_us(self) -> int | None:
        """Device time of the newest event seen."""
        return self._last_t

    def push(self, events: npt.NDArray[Any], t_host_ns: int = 0) -> list[LiveWindow]:
        """Add a chunk's events (device time ``t``, us); the windows it completed, in order."""
        self._last_host_ns = t_host_ns
        if events.size == 0:
            return []
        t = events["t"].astype(np.int64)
        if self.first_t_us is None:
            self.first_t_us = int(t[0])
        out: list[LiveWindow] = []
        previous = self._last_t if self._last_t is not None else int(t[0])
        jumps = np.flatnonzero(np.abs(np.diff(t, prepend=previous)) > MAX_JUMP_US).tolist()
        for a, b in zip([0, *jumps], [*jumps, t.size], strict=True):
            if a == b:
                continue
            if a in jumps:  # the device clock jumped (a camera restart): a new grid from here
                self.time_jumps += 1
                out += self.flush()
            if self.window_us:
                out += self._push_time(events[a:b], t[a:b], t_host_ns)
            else:
                out += self._push_count(events[a:b], t_host_ns)
            self._last_t = int(t[b - 1])
        return out

    def _push_time(self, events: npt.NDArray[Any], t: npt.NDArray[np.int64], t_host_ns: int) -> list[LiveWindow]:
        w = int(self.window_us or 0)
        if self._index is None:
            self._index = int(t[0]) // w
        # Arrival order: an event never reopens a window that a later-stamped event has closed.
        index = np.maximum.accumulate(np.maximum(t // w, self._index))
        starts = np.flatnonzero(np.diff(index, prepend=index[0] - 1))
        out = []
        for a, b in zip(starts.tolist(), [*starts[1:].tolist(), t.size], strict=True):
            k = int(index[a])
            while self._index < k:  # close the open window, then any empty ones up to k
                out.append(self._close(self._index * w, (self._index + 1) * w, t_host_ns))
                self._index += 1
            self._parts.append(events[a:b])
            self._held += b - a
        return out

    def _push_count(self, events: npt.NDArray[Any], t_host_ns: int) -> list[LiveWindow]:
        n = int(self.window_events or 0)
        self._parts.append(events)
        self._held += events.size
        if self._held <= n:  # t1 is the next window's first event: wait for it
            return []
        held = np.concatenate(self._parts)
        out, start = [], 0
        while held.size - start > n:
            window = held[start:start + n]
            out.append(LiveWindow(int(window["t"][0]), int(held["t"][start + n]), window, t_host_ns))
            start += n
        rest = held[start:]
        self._parts, self._held = [rest], rest.size
        return out

    def _close(self, t0_us: int, t1_us: int, t_host_ns: int) -> LiveWindow:
        events = np.concatenate(self._parts) if len(self._parts) > 1 else (self._parts[0] if self._parts else _empty_events())
        self._parts, self._held = [], 0
        return LiveWindow(t0_us, t1_us, events, t_host_ns)

    def flush(self) -> list[LiveWindow]:
        """The window still open at the end of the stream (a partial count window is dropped); resets."""
        out: list[LiveWindow] = []
        if self._held and self.window_us and self._index is not None and self._last_t is not None:
            t0 = self._index * self.window_us
            out.append(self._close(t0, min(t0 + self.window_us, max(self._last_t + 1, t0 + 1)), self._last_host_ns))
        elif self._held and self.window_events and self._held == self.window_events and self._last_t is not None:
            events = np.concatenate(self._parts)
            out.append(LiveWindow(int(events["t"][0]), self._last_t + 1, events, self._last_host_ns))
        self._parts, self._held, self._index = [], 0, None
        return out


def windows_from_chunks(chunks: Iterable[EventChunk], *, window_us: int | None = DEFAULT_WINDOW_US,
                        window_events: int | None = None) -> Iterator[LiveWindow]:
    """Every window of a finite stream of chunks, the last partial time window included."""
    windower = EventWindower(window_us, window_events)
    for chunk in chunks:
        yield from windower.push(chunk.events, chunk.t_host_ns)
    yield from windower.flush()


# -- sources ------------------------------------------------------------------------------------------


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


# -- the runner ---------------------------------------------------------------------------------------


@dataclass
class LiveStats:
    """How a live run kept up. Windows: ``windows`` closed and tracked = ``processed`` + ``skipped``."""

    window_us: int | None = None
    window_events: int | None = None
    chunks: int = 0
    events: int = 0
    windows: int = 0
    processed: int = 0
    skipped: int = 0  # tracked only: older than max_lag_ms when the back stage reached them (or the queue was full)
    late: int = 0  # processed, but ready more than one window span after the window closed
    latency_ms: array[float] = field(default_factory=lambda: array("d"))  # per processed window
    first_t_us: int | None = None  # device time of the first window's start
    last_t_us: int | None = None  # device time of the last window's end
    time_jumps: int = 0
    wall_s: float = 0.0
    end_reason: str = ""

    def summary(self) -> dict[str, Any]:
        """Stable keys, units in names."""
        lat = np.asarray(self.latency_ms, np.float64)
        span = 0.0 if self.first_t_us is None or self.last_t_us is None else (self.last_t_us - self.first_t_us) / 1e6
        return {
            "chunks": self.chunks, "events": self.events, "windows_tracked": self.windows,
            "windows_processed": self.processed, "windows_skipped": self.skipped, "windows_late": self.late,
            "latency_median_ms": float(np.median(lat)) if lat.size else None,
            "latency_p95_ms": float(np.percentile(lat, 95)) if lat.size else None,
            "latency_max_ms": float(lat.max()) if lat.size else None,
            "stream_s": span, "stream_wall_s": self.wall_s, "time_jumps": self.time_jumps, "end_reason": self.end_reason,
        }


_DONE = object()


class LiveRunner:
    """Streams a :class:`ChunkSource` through a :class:`~labrig.pipeline.runtime.Pipeline` in real time.

    ``run()`` yields each processed window's result in the caller's thread (the back stage);
    see the module docstring for the skip and late policy. ``stats`` is updated as it goes.
    """

    def __init__(self, pipeline: Pipeline, source: ChunkSource, *, window_us: int | None = DEFAULT_WINDOW_US,
                 window_events: int | None = None, max_lag_ms: float | None = MAX_LAG_MS,
                 clock: HostClock | None = None, poll_s: float = 0.05) -> None:
        """``max_lag_ms``: skip the back stage of windows older than this (None: never, however late)."""
        if window_events is not None:
            window_us = None
        if max_lag_ms is not None and max_lag_ms <= 0:
            raise ValueError("max_lag_ms must be positive (or None)")
        self.pipeline = pipeline
        self.source = source
        self.windower = EventWindower(window_us, window_events)
        self.max_lag_ms = max_lag_ms
        self.clock = clock or MonotonicClock()
        self.poll_s = poll_s
        self.stats = LiveStats(window_us=window_us, window_events=window_events)

    def run(self, *, seconds: float | None = None, stop: threading.Event | None = None) -> Iterator[WindowResult]:
        """Windows until ``seconds`` (host time from now) pass, ``stop`` is set or the source ends."""
        stop = stop or threading.Event()
        states: queue.Queue[Any] = queue.Queue(maxsize=QUEUE_WINDOWS)
        failure: list[BaseException] = []
        halt = threading.Event()  # the consumer has gone: the front stops at once
        start_ns = self.clock.now_ns()
        deadline_ns = None if seconds is None else start_ns + round(seconds * 1e9)
        thread = threading.Thread(target=self._front, args=(states, stop, halt, deadline_ns, failure),
                                  name="labrig-live-front", daemon=True)
        thread.start()
        done = False
        try:
            while not done:
                try:
                    state = states.get(timeout=0.1)
                except queue.Empty:
                    continue
                if state is _DONE:
                    break
                if self._stale(state):
                    state, done = self._newest(states, state)
                    if state is None:
                        continue
                result = self.pipeline.back(state)
                self._account(state, result)
                yield result
        finally:
            halt.set()
            while thread.is_alive():  # unblock the front if it waits on a full queue
                try:
                    states.get_nowait()
                except queue.Empty:
                    thread.join(0.01)
            self.stats.wall_s = (self.clock.now_ns() - start_ns) / 1e9
        if failure:
            raise failure[0]

    def _stale(self, state: dict[str, Any]) -> bool:
        age_ms = (self.clock.now_ns() - state["t_host_ns"]) / 1e6
        return self.max_lag_ms is not None and age_ms > self.max_lag_ms

    def _newest(self, states: queue.Queue[Any], stale: dict[str, Any]) -> tuple[dict[str, Any] | None, bool]:
        """Catch up after ``stale``: skip it and every window queued behind it but the newest, which
        is returned unless it is stale too; and whether the stream ended behind it."""
        newest, done = stale, False
        while not done:
            try:
                item = states.get_nowait()
            except queue.Empty:
                break
            if item is _DONE:
                done = True
            else:
                self.stats.skipped += 1
                newest = item
        if self._stale(newest):
            self.stats.skipped += 1
            return None, done
        return newest, done

    def _account(self, state: dict[str, Any], result: WindowResult) -> None:
        latency_ms = (self.clock.now_ns() - state["t_host_ns"]) / 1e6
        self.stats.processed += 1
        self.stats.latency_ms.append(latency_ms)
        if latency_ms * 1000 > result.t1_us - result.t0_us:
            self.stats.late += 1

    def _front(self, states: queue.Queue[Any], stop: threading.Event, halt: threading.Event, deadline_ns: int | None,
               failure: list[BaseException]) -> None:
        reason = ""
        try:
            while not halt.is_set():
                if stop.is_set():
                    reason = "stopped"
                    break
                if deadline_ns is not None and self.clock.now_ns() >= deadline_ns:
                    reason = "seconds reached"
                    break
                chunk = self.source.read(self.poll_s)
                if chunk is None:
                    if self.source.ended:
                        reason = "the stream ended"
                        break
                    continue
                self.stats.chunks += 1
                self.stats.events += int(chunk.events.size)
                start = time.perf_counter()
                windows = self.windower.push(chunk.events, chunk.t_host_ns)
                read_s = time.perf_counter() - start
                for window in windows:
                    self._dispatch(window, states, read_s, halt)
                    read_s = 0.0
            if not halt.is_set():
                for window in self.windower.flush():
                    self._dispatch(window, states, 0.0, halt)
        except BaseException as exc:  # handed to the consumer
            failure.append(exc)
        finally:
            self.stats.end_reason = reason or self.stats.end_reason
            self.stats.time_jumps = self.windower.time_jumps
            while not halt.is_set():
                try:
                    states.put(_DONE, timeout=0.1)
                    break
                except queue.Full:
                    continue

    def _dispatch(self, window: LiveWindow, states: queue.Queue[Any], read_s: float, halt: threading.Event) -> None:
        """Track every window; queue it for the back stage if there is room, else skip its forces."""
        stats = self.stats
        stats.windows += 1
        if stats.first_t_us is None:
            stats.first_t_us = window.t0_us
        stats.last_t_us = window.t1_us
        if states.full():
            self.pipeline.tracker.update(window.events)
            stats.skipped += 1
            return
        state = self.pipeline.front(window.t0_us, window.t1_us, window.events, read_s)
        state["t_host_ns"] = window.t_host_ns
        while not halt.is_set():  # room is there (this thread is the only producer), unless the consumer quit
            try:
                states.put(state, timeout=0.1)
                return
            except queue.Full:
                continue
