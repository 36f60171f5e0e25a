"""The pipeline on a live event stream in real time: device-time windows over camera chunks.

Sources (:mod:`labrig.live.sources`) deliver chunks of events in the camera's **device time**
(us); :class:`~labrig.pipeline.windows.EventWindower` cuts them into windows (fixed time or fixed
event count) as they arrive.

Real time (:class:`LiveRunner`): the front stage (windowing, SAE, tracker) runs in its own
thread (:class:`~labrig.pipeline.front_thread.FrontThread`) and sees every window, so markers
stay tracked; the back stage (depth, displacements, forces, and whatever the caller does with
each result) runs in the caller's thread. A window's age is the host time since the chunk that
closed it arrived. When the back stage reaches a window older than ``max_lag_ms`` (default
100 ms), it **skips** it and every window queued behind it but the newest, and goes on with that
one: skipped windows are tracked and their events counted into the depth source's state (the
brightness change), but get no depth, forces or result. So the forces shown are never
much older than ``max_lag_ms`` and a slow stretch is caught up at once; a pipeline slower than
real time gives runs of consecutive windows with jumps between them. (Also skipped: windows that
find the queue between the stages full, 256 windows.) A processed window whose result was ready
more than one window span after it closed is counted **late**. Sources deliver chunks in bursts
(a camera's USB transfers; the virtual rig's camera about every 50 ms), so a burst of windows is
processed one after the other and its last ones can be late without the pipeline falling behind
on average: the latency percentiles say how far behind the results were.
"""

from __future__ import annotations

import threading
import time
from array import array
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.clock import HostClock, MonotonicClock
from labrig.live.sources import ChunkSource
from labrig.pipeline.front_stage import TrackedWindow
from labrig.pipeline.front_thread import FrontThread, Handoff
from labrig.pipeline.runtime import Pipeline, WindowResult
from labrig.pipeline.windows import DEFAULT_WINDOW_US, EventWindower, LiveWindow, WindowSpec

#: The back stage skips windows older than this (host time since the chunk that closed them arrived), ms.
MAX_LAG_MS = 100.0
#: Windows that may wait between the stages; when full, new ones are tracked only.
QUEUE_WINDOWS = 256


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
    #: Per processed window: its end (device us) and when its result was ready (host us), for the event-to-force
    #: latency; the camera's clock offset (host us - device us) is the lower envelope of the chunks' arrivals.
    window_end_us: array[int] = field(default_factory=lambda: array("q"))
    ready_host_us: array[float] = field(default_factory=lambda: array("d"))
    camera_offset_us: float | None = None
    first_t_us: int | None = None  # device time of the first window's start
    last_t_us: int | None = None  # device time of the last window's end
    time_jumps: int = 0
    wall_s: float = 0.0
    end_reason: str = ""

    def arrived(self, t_device_us: int, t_host_ns: int) -> None:
        """A chunk whose newest event (device us) arrived at ``t_host_ns``: the envelope of the camera's clock."""
        offset = t_host_ns / 1000 - t_device_us
        if self.camera_offset_us is None or offset < self.camera_offset_us:
            self.camera_offset_us = offset

    def event_to_force_ms(self) -> npt.NDArray[np.float64]:
        """Per processed window, ms: from its newest event's camera time (on the host clock, through the lower
        envelope of the chunks' arrivals: the least-delayed chunk arrived the moment it was stamped) to its result
        (its oldest event waited one window longer)."""
        if self.camera_offset_us is None:
            return np.zeros(0)
        end_host_us = np.asarray(self.window_end_us, np.float64) + self.camera_offset_us
        return (np.asarray(self.ready_host_us, np.float64) - end_host_us) / 1000

    def summary(self) -> dict[str, Any]:
        """Stable keys, units in names."""
        lat = np.asarray(self.latency_ms, np.float64)
        e2f = self.event_to_force_ms()
        span = 0.0 if self.first_t_us is None or self.last_t_us is None else (self.last_t_us - self.first_t_us) / 1e6
        return {
            "chunks": self.chunks, "events": self.events, "windows_tracked": self.windows,
            "windows_processed": self.processed, "windows_skipped": self.skipped, "windows_late": self.late,
            "latency_median_ms": float(np.median(lat)) if lat.size else None,
            "latency_p95_ms": float(np.percentile(lat, 95)) if lat.size else None,
            "latency_max_ms": float(lat.max()) if lat.size else None,
            "event_to_force_median_ms": float(np.median(e2f)) if e2f.size else None,
            "event_to_force_p99_ms": float(np.percentile(e2f, 99)) if e2f.size else None,
            "stream_s": span, "stream_wall_s": self.wall_s, "time_jumps": self.time_jumps, "end_reason": self.end_reason,
        }


@dataclass(frozen=True)
class PendingWindow:
    """A tracked window waiting for the back stage, and when it became complete."""

    tracked: TrackedWindow
    t_host_ns: int  # host time the chunk that closed the window arrived


class LiveRunner:
    """Streams a :class:`~labrig.live.sources.ChunkSource` through a :class:`~labrig.pipeline.runtime.Pipeline` in real time.

    ``run()`` yields each processed window's result in the caller's thread (the back stage);
    see the module docstring for the skip and late policy. ``stats`` is updated as it goes.
    """

    def __init__(self, pipeline: Pipeline, source: ChunkSource, *, window_us: int | None = DEFAULT_WINDOW_US,
                 window_events: int | None = None, max_lag_ms: float | None = MAX_LAG_MS,
                 clock: HostClock | None = None, poll_s: float = 0.05) -> None:
        """``window_events`` (if given) replaces the default time windows. ``max_lag_ms``: skip the back
        stage of windows older than this (None: never, however late)."""
        spec = WindowSpec.events_first(window_us, window_events)
        if max_lag_ms is not None and max_lag_ms <= 0:
            raise ValueError("max_lag_ms must be positive (or None)")
        self.pipeline = pipeline
        self.source = source
        self.windower = EventWindower(spec.window_us, spec.window_events)
        self.max_lag_ms = max_lag_ms
        self.clock = clock or MonotonicClock()
        self.poll_s = poll_s
        self.stats = LiveStats(window_us=spec.window_us, window_events=spec.window_events)

    def run(self, *, seconds: float | None = None, stop: threading.Event | None = None) -> Iterator[WindowResult]:
        """Windows until ``seconds`` (host time from now) pass, ``stop`` is set or the source ends."""
        stop = stop or threading.Event()
        start_ns = self.clock.now_ns()
        deadline_ns = None if seconds is None else start_ns + round(seconds * 1e9)

        def front(handoff: Handoff[PendingWindow]) -> None:
            self._front(handoff, stop, deadline_ns)

        try:
            with FrontThread(front, max_queued=QUEUE_WINDOWS, name="labrig-live-front") as pending_windows:
                for pending in pending_windows:
                    if self._stale(pending):
                        newest = self._newest(pending_windows, pending)
                        if newest is None:
                            continue
                        pending = newest
                    result = self.pipeline.back(pending.tracked)
                    self._account(pending, result)
                    yield result
        finally:
            self.stats.wall_s = (self.clock.now_ns() - start_ns) / 1e9

    def _stale(self, pending: PendingWindow) -> bool:
        age_ms = (self.clock.now_ns() - pending.t_host_ns) / 1e6
        return self.max_lag_ms is not None and age_ms > self.max_lag_ms

    def _newest(self, pending_windows: FrontThread[PendingWindow], stale: PendingWindow) -> PendingWindow | None:
        """Catch up after ``stale``: skip it and every window queued behind it but the newest, which
        is returned unless it is stale too. A skipped window is still observed (:meth:`Pipeline.observe`)."""
        newest = stale
        for pending in pending_windows.queued():
            self.pipeline.observe(newest.tracked)
            self.stats.skipped += 1
            newest = pending
        if self._stale(newest):
            self.pipeline.observe(newest.tracked)
            self.stats.skipped += 1
            return None
        return newest

    def _account(self, pending: PendingWindow, result: WindowResult) -> None:
        now_ns = self.clock.now_ns()
        latency_ms = (now_ns - pending.t_host_ns) / 1e6
        self.stats.processed += 1
        self.stats.latency_ms.append(latency_ms)
        self.stats.window_end_us.append(result.t1_us)
        self.stats.ready_host_us.append(now_ns / 1000)
        if latency_ms * 1000 > result.t1_us - result.t0_us:
            self.stats.late += 1

    def _front(self, handoff: Handoff[PendingWindow], stop: threading.Event, deadline_ns: int | None) -> None:
        """The front thread: read chunks, cut windows, track each, queue it for the back stage."""
        reason = ""
        try:
            while not handoff.halted:
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
                if chunk.events.size:
                    self.stats.arrived(int(chunk.events["t"][-1]), chunk.t_host_ns)
                start = time.perf_counter()
                windows = self.windower.push(chunk.events, chunk.t_host_ns)
                read_s = time.perf_counter() - start
                for window in windows:
                    self._dispatch(window, handoff, read_s)
                    read_s = 0.0
            if not handoff.halted:
                for window in self.windower.flush():
                    self._dispatch(window, handoff, 0.0)
        finally:
            self.stats.end_reason = reason or self.stats.end_reason
            self.stats.time_jumps = self.windower.time_jumps

    def _dispatch(self, window: LiveWindow, handoff: Handoff[PendingWindow], read_s: float) -> None:
        """Every window through the front stage; queued for the back stage if there is room, else its forces
        are skipped (its events still count: :meth:`Pipeline.skip`)."""
        stats = self.stats
        stats.windows += 1
        if stats.first_t_us is None:
            stats.first_t_us = window.t0_us
        stats.last_t_us = window.t1_us
        if handoff.full():  # this thread is the only producer: room now stays until the put
            self.pipeline.skip(window.t0_us, window.t1_us, window.events)
            stats.skipped += 1
            return
        tracked = self.pipeline.front(window.t0_us, window.t1_us, window.events, read_s)
        handoff.put(PendingWindow(tracked, window.t_host_ns))
