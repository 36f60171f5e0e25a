"""What every camera backend shares: lifecycle, the chunk queue, biases, ROI, trigger inputs, failures.

A backend's reader thread decodes what the device sends and hands :class:`EventChunk` s to
:meth:`Camera._deliver`; they wait in a bounded queue for the consumer (whole chunks are dropped
and counted when it falls behind). The thread ends the stream with :meth:`Camera._end` when the
source is exhausted, or with :meth:`Camera._fail` when it breaks: then :meth:`Camera.read` raises
the failure once the chunks before it are consumed, so a broken stream is never taken for a
finished one.

Trigger inputs are named as the Metavision SDK names them (``main``, ``aux``, ``loopback``); each
device reports which it has and the event id each one's edges carry (an EVK4 has ``main`` with
id 0 only; an EVK2's ``main`` edges carry id 1). A plain integer is taken as an event id.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from labrig.clock import HostClock, MonotonicClock
from labrig.errors import LabrigError

#: IMX636 bias names and OpenEB's *recommended* ranges of their offsets from the factory default
#: (``imx636_bias_settings.h``; the SDK refuses values outside them unless its range check is
#: bypassed). The sensor's allowed ranges are wider (``IMX636_ALLOWED_BIASES``).
IMX636_BIASES: dict[str, tuple[int, int]] = {
    "bias_diff_on": (-85, 140),
    "bias_diff_off": (-35, 190),
    "bias_diff": (-25, 23),
    "bias_fo": (-35, 55),
    "bias_hpf": (0, 120),
    "bias_refr": (-20, 235),
}
#: The IMX636's allowed bias offset ranges (``imx636_bias_settings_iterator.h``), for reference.
IMX636_ALLOWED_BIASES: dict[str, tuple[int, int]] = {
    "bias_diff_on": (-150, 200),
    "bias_diff_off": (-150, 200),
    "bias_diff": (-150, 200),
    "bias_fo": (-150, 200),
    "bias_hpf": (0, 255),
    "bias_refr": (-50, 255),
}

#: Trigger input names, as ``metavision_hal.I_TriggerIn.Channel`` has them (lower case).
TRIGGER_INPUTS = ("main", "aux", "loopback")

#: Chunks waiting for the consumer before new ones are dropped.
DEFAULT_QUEUE_CHUNKS = 1024


class CameraError(LabrigError):
    """The camera cannot be opened or used, or its stream broke."""


@dataclass(frozen=True)
class EventChunk:
    """Events and trigger edges that arrived together, with the host time they arrived."""

    events: npt.NDArray[Any]
    triggers: npt.NDArray[Any]
    t_host_ns: int

    @property
    def t_device_us(self) -> int:
        """Device time of the chunk's last event (or last trigger; -1 if empty)."""
        if self.events.size:
            return int(self.events["t"][-1])
        return int(self.triggers["t"][-1]) if self.triggers.size else -1


@dataclass(frozen=True)
class DeviceInfo:
    """What the camera says about itself.

    ``source``: where the data comes from as the backend knows it (the SDK's connection type,
    e.g. ``USB`` or ``File``; a file path; a socket path). ``fields``: everything else the device
    reports, under the device's own keys (the SDK's system info, a RAW header's fields).
    """

    backend: str
    serial: str
    width: int
    height: int
    sensor: str = "IMX636"
    format: str = "EVT3"
    source: str = ""
    fields: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Roi:
    """A rectangular region of interest in sensor pixels."""

    x: int
    y: int
    width: int
    height: int


@dataclass
class CameraStats:
    chunks: int = 0
    events: int = 0
    triggers: int = 0
    dropped_chunks: int = 0
    dropped_events: int = 0
    roi_filtered_events: int = 0


_END = object()


class Camera:
    """Base of the backends: lifecycle, chunk queue, biases, ROI, trigger inputs.

    ``open`` / ``close`` (or ``with``), ``start`` / ``stop`` the stream; read with
    :meth:`read` or :meth:`chunks`. ``clock``: labrig's host clock (MonotonicClock by default)
    used for ``t_host_ns``; give a recording's writer the same clock. ``trigger_in``: trigger
    inputs enabled on open, by name (``main``) or event id.
    """

    backend: ClassVar[str] = ""

    def __init__(
        self, *, clock: HostClock | None = None, queue_chunks: int = DEFAULT_QUEUE_CHUNKS,
        trigger_in: tuple[str | int, ...] = ("main",)
    ) -> None:
        self.trigger_in = tuple(trigger_in)
        self.clock: HostClock = clock or MonotonicClock()
        self.stats = CameraStats()
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=queue_chunks)
        self._is_open = False
        self._streaming = threading.Event()
        self._ended = False
        self._biases: dict[str, int] = dict.fromkeys(IMX636_BIASES, 0)
        self._roi: Roi | None = None
        self._trigger_ids: set[int] = set()
        self._info: DeviceInfo | None = None
        #: Why the stream broke (set by the reader thread); :meth:`read` raises it.
        self.error: CameraError | None = None

    # -- lifecycle ------------------------------------------------------------------------------
    def open(self) -> Camera:
        if self._is_open:
            return self
        self._open()
        self._is_open = True
        try:
            for channel in self.trigger_in:
                self.enable_trigger_in(channel)
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        if not self._is_open:
            return
        self.stop()
        self._close()
        self._is_open = False

    def start(self) -> None:
        """Start streaming (opens the camera first if needed)."""
        self.open()
        if not self._streaming.is_set():
            self._streaming.set()
            self._start()

    def stop(self) -> None:
        if self._streaming.is_set():
            self._streaming.clear()
            self._stop()

    def __enter__(self) -> Camera:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._is_open

    @property
    def streaming(self) -> bool:
        return self._streaming.is_set()

    @property
    def ended(self) -> bool:
        """The stream has ended (file replayed, socket closed by the twin, or broken: see :attr:`error`)."""
        return self._ended

    # -- data -------------------------------------------------------------------------------------
    def read(self, timeout_s: float | None = None) -> EventChunk | None:
        """The next chunk; None on timeout or once the stream has ended and the queue is empty.

        Raises :attr:`error` (a :class:`CameraError`) once the chunks before a failure are read.
        """
        if self._ended and self._queue.empty():
            self._ended_read()
            return None
        try:
            item = self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None
        if item is _END:
            self._ended = True
            self._ended_read()
            return None
        return item  # type: ignore[no-any-return]

    def _ended_read(self) -> None:
        if self.error is not None:
            raise self.error

    def chunks(self, timeout_s: float | None = None) -> Iterator[EventChunk]:
        """Chunks until the stream ends, or until none arrives within ``timeout_s``."""
        while True:
            chunk = self.read(timeout_s)
            if chunk is None:
                return
            yield chunk

    def _deliver(self, events: npt.NDArray[Any], triggers: npt.NDArray[Any], t_host_ns: int) -> None:
        """Queue one chunk (reader threads); drop and count it when the queue is full."""
        if self._roi is not None and events.size:
            r = self._roi
            keep = (events["x"] >= r.x) & (events["x"] < r.x + r.width) & (events["y"] >= r.y) & (events["y"] < r.y + r.height)
            if not keep.all():
                self.stats.roi_filtered_events += int(events.size - np.count_nonzero(keep))
                events = events[keep]
        if events.size == 0 and triggers.size == 0:
            return
        try:
            self._queue.put_nowait(EventChunk(events, triggers, t_host_ns))
        except queue.Full:
            self.stats.dropped_chunks += 1
            self.stats.dropped_events += int(events.size)
            return
        self.stats.chunks += 1
        self.stats.events += int(events.size)
        self.stats.triggers += int(triggers.size)

    def _end(self) -> None:
        """Mark the end of the stream (reader threads); waits for room in the queue while streaming."""
        while True:
            try:
                self._queue.put(_END, timeout=0.1)
                return
            except queue.Full:
                if not self._streaming.is_set():
                    self._ended = True
                    return

    def _fail(self, why: str, exc: BaseException | None = None) -> None:
        """End the stream as broken (reader threads): :meth:`read` raises after the chunks before it."""
        detail = f": {type(exc).__name__}: {exc}" if exc is not None else ""
        error = CameraError(f"{self.backend} camera: {why}{detail}")
        error.__cause__ = exc
        self.error = error
        self._end()

    # -- settings ---------------------------------------------------------------------------------
    @property
    def info(self) -> DeviceInfo:
        if self._info is None:
            raise CameraError("the camera is not open; call open() first")
        return self._info

    def get_biases(self) -> dict[str, int]:
        return dict(self._biases)

    def get_bias(self, name: str) -> int:
        return self.get_biases()[_check_bias_name(name)]

    def set_bias(self, name: str, value: int) -> None:
        """Set one IMX636 bias (offset from the factory default); CameraError outside its recommended range."""
        name = _check_bias_name(name)
        lo, hi = IMX636_BIASES[name]
        if not lo <= int(value) <= hi:
            raise CameraError(f"{name} = {value} is outside its range [{lo}, {hi}] (OpenEB's recommended range for the IMX636)")
        self._set_bias(name, int(value))
        self._biases[name] = int(value)

    def set_biases(self, biases: dict[str, int]) -> None:
        for name, value in biases.items():
            self.set_bias(name, value)

    @property
    def roi(self) -> Roi | None:
        return self._roi

    def set_roi(self, x: int, y: int, width: int, height: int) -> None:
        """Keep only events inside the rectangle (x, y, width, height) in pixels."""
        info = self.info
        if width <= 0 or height <= 0 or x < 0 or y < 0 or x + width > info.width or y + height > info.height:
            raise CameraError(f"ROI {x},{y} {width}x{height} does not fit the {info.width}x{info.height} sensor")
        roi = Roi(int(x), int(y), int(width), int(height))
        self._set_roi(roi)
        self._roi = roi

    def clear_roi(self) -> None:
        self._set_roi(None)
        self._roi = None

    # -- trigger inputs ---------------------------------------------------------------------------
    def trigger_inputs(self) -> dict[str, int]:
        """The trigger inputs this device has: name -> the event id its edges carry."""
        return {"main": 0}

    def trigger_id(self, channel: str | int) -> int:
        """The event id of trigger input ``channel`` (a name, or an event id this device has)."""
        inputs = self.trigger_inputs()
        if isinstance(channel, str):
            name = channel.lower()
            if name not in inputs:
                raise CameraError(f"trigger input {channel!r}: this {self.backend} camera has "
                                  f"{', '.join(f'{n} (id {i})' for n, i in inputs.items())}")
            return inputs[name]
        if int(channel) not in inputs.values():
            raise CameraError(f"trigger channel {channel}: this {self.backend} camera's trigger inputs carry ids "
                              f"{sorted(set(inputs.values()))} ({', '.join(f'{n} = {i}' for n, i in inputs.items())})")
        return int(channel)

    @property
    def trigger_channels(self) -> set[int]:
        """Event ids of the enabled trigger inputs."""
        return set(self._trigger_ids)

    def enable_trigger_in(self, channel: str | int = "main") -> None:
        """Report edges on trigger input ``channel`` (a name such as ``main``, or its event id)."""
        event_id = self.trigger_id(channel)
        self._enable_trigger(event_id, True)
        self._trigger_ids.add(event_id)

    def disable_trigger_in(self, channel: str | int = "main") -> None:
        event_id = self.trigger_id(channel)
        self._enable_trigger(event_id, False)
        self._trigger_ids.discard(event_id)

    def _filter_triggers(self, triggers: npt.NDArray[Any]) -> npt.NDArray[Any]:
        if triggers.size == 0:
            return triggers
        return triggers[np.isin(triggers["id"], list(self._trigger_ids))]

    # -- backend hooks ----------------------------------------------------------------------------
    def _open(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        pass

    def _start(self) -> None:
        pass

    def _stop(self) -> None:
        pass

    def _set_bias(self, name: str, value: int) -> None:
        pass

    def _set_roi(self, roi: Roi | None) -> None:
        pass

    def _enable_trigger(self, event_id: int, on: bool) -> None:
        pass


def _check_bias_name(name: str) -> str:
    if name not in IMX636_BIASES:
        raise CameraError(f"unknown bias {name!r}; the IMX636 has {', '.join(IMX636_BIASES)}")
    return name
