"""Windows over an event stream: fixed in time or in event count, from a recording or from live chunks.

* :class:`WindowSpec`: the one validated choice of windows: ``window_us`` (a time span, us) or
  ``window_events`` (an event count), exactly one, positive. Commands build it from their
  ``--window-ms`` / ``--window-events`` with :meth:`WindowSpec.from_options`.
* :func:`recording_windows`: (t0, t1, events) per window of a recording, in its host time base (us
  since the recording's start), events read as they are needed.
* :func:`window_ends_us`: only the (t0, t1) of a recording's windows, from the event time column
  (the evaluation's windows: the depth network sees its own trained span ending at each t1).
* :class:`EventWindower` / :func:`windows_from_chunks`: windows of a live stream of event chunks,
  in the camera's **device time** (us), as the events carry it.

Count windows end at the next window's first event (t1 = its time stamp); the last, partial count
window is dropped. The paper evaluates on windows of :data:`PAPER_WINDOW_EVENTS` events.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol, TypedDict

import numpy as np
import numpy.typing as npt

from labrig.errors import LabrigError
from labrig.eventtypes import EVENT_DTYPE
from labrig.recording import Recording

Events = npt.NDArray[Any]  # EVENT_DTYPE: x, y, p and ``t`` (us)

#: The runtime's default window, us.
DEFAULT_WINDOW_US = 10_000
#: Events per window in the paper's evaluation.
PAPER_WINDOW_EVENTS = 20_000
#: A device-time step larger than this between consecutive events restarts a live window grid, us.
MAX_JUMP_US = 10_000_000


class WindowError(LabrigError, ValueError):
    """Windows that are not one positive time span or event count."""


class WindowArgs(TypedDict):
    """The keyword arguments that choose an evaluation task's windows: ``window_events`` events each,
    or ``window_us`` (us) long."""

    window_events: int | None
    window_us: int | None


@dataclass(frozen=True)
class WindowSpec:
    """How a stream is cut: fixed time (``window_us``, us) or fixed event count (``window_events``).

    Exactly one is given and it is positive, else :class:`WindowError` (a :class:`LabrigError`
    and a ``ValueError``) says what to give.
    """

    window_us: int | None = DEFAULT_WINDOW_US
    window_events: int | None = None

    def __post_init__(self) -> None:
        us, events = self.window_us, self.window_events
        if us is not None and events is not None:
            got = f"{us / 1000:g} ms and {events} events"
        elif us is None and events is None:
            got = "neither"
        elif us is not None and us <= 0:
            got = f"{us / 1000:g} ms"
        elif events is not None and events <= 0:
            got = f"{events} events"
        else:
            return
        raise WindowError("give the windows as a positive --window-ms (a time span) or --window-events (an event count), "
                          f"not both; got {got}")

    @classmethod
    def from_options(cls, window_ms: float | None, window_events: int | None, *,
                     default_ms: float | None = DEFAULT_WINDOW_US / 1000) -> WindowSpec:
        """The windows of a command's ``--window-ms`` (ms) / ``--window-events``; ``default_ms`` when
        neither is given (None: one must be)."""
        if window_ms is None and window_events is None and default_ms is not None:
            window_ms = default_ms
        return cls(None if window_ms is None else round(window_ms * 1000), window_events)

    @classmethod
    def events_first(cls, window_us: int | None, window_events: int | None) -> WindowSpec:
        """``window_events`` windows when it is given (it replaces a default ``window_us``), else ``window_us``."""
        return cls(None, window_events) if window_events is not None else cls(window_us, None)


def _cut_count_windows(held: Events, n: int, *, exact_tail: bool) -> tuple[list[tuple[int, int, Events]], Events]:
    """Whole windows of ``n`` events off the front of ``held`` as (t0, t1, events), and the rest.

    t1 is the next window's first event; with ``exact_tail``, a window that no event follows
    (``held`` ends with it) is whole too and ends at its last event + 1.
    """
    out = []
    start = 0
    while held.size - start > n or (exact_tail and held.size - start == n):
        window = held[start:start + n]
        t1 = int(held["t"][start + n]) if held.size > start + n else int(window["t"][-1]) + 1
        out.append((int(window["t"][0]), t1, window))
        start += n
    return out, held[start:]


# -- a recording ---------------------------------------------------------------------------------


def recording_windows(recording: Recording, *, window_us: int | None = DEFAULT_WINDOW_US, window_events: int | None = None,
                      start_us: int = 0, end_us: int | None = None, read_us: int = 50_000) -> Iterator[tuple[int, int, Events]]:
    """(t0_us, t1_us, events) per window of ``recording`` (host time base, us): fixed time, or fixed event count.

    Time windows tile ``[start_us, end_us)`` (the recording's end by default; the last one is cut
    there). Count windows read ahead in ``read_us`` slices; t1 = the next window's first event.
    """
    spec = WindowSpec(window_us, window_events)
    end = recording.end_us() if end_us is None else int(end_us)
    if spec.window_us is not None:
        for t0 in range(int(start_us), end, spec.window_us):
            t1 = min(t0 + spec.window_us, end)
            yield t0, t1, recording.events_between(t0, t1)
        return
    n = int(spec.window_events or 0)
    buffer: list[Events] = []
    held = 0
    t = int(start_us)
    while t < end:
        chunk = recording.events_between(t, min(t + read_us, end))
        t += read_us
        if len(chunk):
            buffer.append(chunk)
            held += len(chunk)
        if held >= n:
            windows, rest = _cut_count_windows(np.concatenate(buffer) if len(buffer) > 1 else buffer[0], n, exact_tail=True)
            yield from windows
            buffer, held = ([rest] if len(rest) else []), len(rest)


def window_ends_us(recording: Recording, *, window_events: int | None = PAPER_WINDOW_EVENTS,
                   window_us: int | None = None) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(t0_us, t1_us) host times of sequential windows: ``window_events`` events each, or ``window_us`` long.

    Count windows are found from the event time column in one pass (no event payload is read).
    Only whole windows: the final partial one is dropped, and a count window needs an event after it.
    """
    spec = WindowSpec(window_us, window_events)
    end = recording.end_us()
    if spec.window_us is not None:
        t0 = np.arange(0, end - spec.window_us + 1, spec.window_us, dtype=np.int64)
        return t0, t0 + spec.window_us
    n = int(spec.window_events or 0)
    t = _event_times_us(recording)
    starts = np.arange(0, t.size - n, n)
    return t[starts].astype(np.int64), t[starts + n].astype(np.int64)


def _event_times_us(recording: Recording, chunk: int = 4_000_000) -> npt.NDArray[np.int64]:
    """Every event's host time (us), in order, read in chunks of the time column only."""
    model = recording.clock_model("camera")
    n = recording.n_events
    parts = []
    for start in range(0, n, chunk):
        t_dev = recording.column("events", "t_device_us", start, min(start + chunk, n))
        parts.append(model.to_host_us_int(t_dev))
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


# -- a live stream of chunks -----------------------------------------------------------------------


class EventBatch(Protocol):
    """Events that arrived together (a :class:`labrig.devices.camera.EventChunk`)."""

    @property
    def events(self) -> Events: ...  # ``t`` in device us

    @property
    def t_host_ns(self) -> int: ...  # host time they arrived


@dataclass(frozen=True)
class LiveWindow:
    """One window of a live stream: device times, its events, and when it became complete."""

    t0_us: int  # device time, window start
    t1_us: int  # device time, window end (exclusive)
    events: Events  # ``t`` in device us
    t_host_ns: int  # host time the chunk that closed the window arrived


class EventWindower:
    """Cuts a stream of event arrays (in arrival order) into windows in device time; pure, no threads.

    ``push(events, t_host_ns)`` returns the windows that chunk completed; ``flush()`` the last one
    at the end of the stream. Time windows are a grid of ``window_us`` anchored at a multiple of
    it. An event belongs to the window that is open when it arrives: a time window closes at the
    first event at or past its end, so a late (out of order) event joins the open window instead
    of reopening a closed one; an empty stretch of the stream gives empty windows; a jump of the
    device clock by more than :data:`MAX_JUMP_US` (a camera restart) starts a new grid. At the end
    the partial time window is kept (t1 = its last event + 1), a partial count window is dropped.
    """

    def __init__(self, window_us: int | None = DEFAULT_WINDOW_US, window_events: int | None = None) -> None:
        spec = WindowSpec(window_us, window_events)
        self.window_us = spec.window_us
        self.window_events = spec.window_events
        self._parts: list[Events] = []
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

    def push(self, events: Events, t_host_ns: int = 0) -> list[LiveWindow]:
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

    def _push_time(self, events: Events, t: npt.NDArray[np.int64], t_host_ns: int) -> list[LiveWindow]:
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

    def _push_count(self, events: Events, t_host_ns: int) -> list[LiveWindow]:
        self._parts.append(events)
        self._held += events.size
        if self._held <= int(self.window_events or 0):  # t1 is the next window's first event: wait for it
            return []
        windows, rest = _cut_count_windows(np.concatenate(self._parts), int(self.window_events or 0), exact_tail=False)
        self._parts, self._held = [rest], rest.size
        return [LiveWindow(t0, t1, window, t_host_ns) for t0, t1, window in windows]

    def _close(self, t0_us: int, t1_us: int, t_host_ns: int) -> LiveWindow:
        events = np.concatenate(self._parts) if len(self._parts) > 1 else (self._parts[0] if self._parts else
                                                                           np.zeros(0, EVENT_DTYPE))
        self._parts, self._held = [], 0
        return LiveWindow(t0_us, t1_us, events, t_host_ns)

    def flush(self) -> list[LiveWindow]:
        """The window still open at the end of the stream (a partial count window is dropped); resets."""
        out: list[LiveWindow] = []
        if self._held and self.window_us and self._index is not None and self._last_t is not None:
            t0 = self._index * self.window_us
            out.append(self._close(t0, min(t0 + self.window_us, max(self._last_t + 1, t0 + 1)), self._last_host_ns))
        elif self._held and self.window_events:
            windows, _ = _cut_count_windows(np.concatenate(self._parts), self.window_events, exact_tail=True)
            out += [LiveWindow(t0, t1, window, self._last_host_ns) for t0, t1, window in windows]
        self._parts, self._held, self._index = [], 0, None
        return out


def windows_from_chunks(chunks: Iterable[EventBatch], *, window_us: int | None = DEFAULT_WINDOW_US,
                        window_events: int | None = None) -> Iterator[LiveWindow]:
    """Every window of a finite stream of chunks, the last partial time window included."""
    windower = EventWindower(window_us, window_events)
    for chunk in chunks:
        yield from windower.push(chunk.events, chunk.t_host_ns)
    yield from windower.flush()
