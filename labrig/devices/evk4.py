"""The event camera (Prophesee EVK4, IMX636): one interface, three backends.

>>> with open_camera("sim", path="/tmp/labrig-evk4.sock") as cam:   # doctest: +SKIP
...     cam.start()
...     for chunk in cam.chunks(timeout_s=1.0):
...         chunk.events["t"], chunk.triggers, chunk.t_host_ns

Backends:

* ``metavision``: a real camera through the Metavision SDK / OpenEB Python module
  ``metavision_hal`` (HAL device: ``DeviceDiscovery.open``, ``I_LL_Biases``, ``I_ROI``,
  ``I_TriggerIn``, ``I_EventsStream`` + ``I_EventsStreamDecoder`` with CD and external-trigger
  decoder callbacks). Times are what the SDK's decoder reports (it shifts the sensor clock to
  start near zero).
* ``raw``: replays a RAW file (EVT3 / EVT2) as if live, paced by the event times
  (``speed`` = 1 real time, 2 twice as fast, None as fast as possible).
* ``sim``: reads the EVT3 byte stream of :class:`labrig.sim.evk4_twin.Evk4Twin` from a Unix
  socket and decodes it with the streaming RAW decoder used for files.

Every backend delivers :class:`EventChunk` s: events (EVENT_DTYPE, ``t`` = device time in us),
trigger edges (TRIGGER_DTYPE) and ``t_host_ns``, the host time (labrig's host clock) the data
arrived. Chunks wait in a bounded queue between the backend's reader thread and the consumer;
when the consumer falls behind, whole chunks are dropped and counted (``stats``).
:func:`record_camera` moves chunks into a :class:`~labrig.recording.RecordingWriter`.

Biases use the IMX636 names (``bias_diff_on``, ``bias_diff_off``, ``bias_diff``, ``bias_fo``,
``bias_hpf``, ``bias_refr``; offsets from the factory default, 0 = default). On ``raw`` and
``sim`` they are checked and kept but change nothing; the region of interest is applied in
software there (events outside it are dropped), by the sensor on ``metavision``.
"""

from __future__ import annotations

import importlib
import itertools
import os
import queue
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from labrig.clock import NS_PER_US, HostClock, MonotonicClock
from labrig.devices.raw import TRIGGER_DTYPE, Evt3Decoder, RawFormatError, open_decoder, parse_header
from labrig.errors import LabrigError
from labrig.eventtypes import EVENT_DTYPE

#: IMX636 bias names and their allowed offsets from the factory default (events.md section 5).
IMX636_BIASES: dict[str, tuple[int, int]] = {
    "bias_diff_on": (-85, 140),
    "bias_diff_off": (-35, 190),
    "bias_diff": (-25, 23),
    "bias_fo": (-35, 55),
    "bias_hpf": (0, 120),
    "bias_refr": (-20, 235),
}
BACKENDS = ("metavision", "raw", "sim")
SDK_MISSING = "the metavision backend needs the Metavision SDK / OpenEB from Prophesee (Python module metavision_hal)"

#: Chunks waiting for the consumer before new ones are dropped.
DEFAULT_QUEUE_CHUNKS = 1024


class CameraError(LabrigError):
    """The camera cannot be opened or used."""


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
    """What the camera says about itself."""

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
    """Base of the backends: lifecycle, chunk queue, biases, ROI, trigger-in.

    ``open`` / ``close`` (or ``with``), ``start`` / ``stop`` the stream; read with
    :meth:`read` or :meth:`chunks`. ``clock``: labrig's host clock (MonotonicClock by default)
    used for ``t_host_ns``; give a recording's writer the same clock. ``trigger_in``: trigger
    input channels enabled on open (0 = main).
    """

    backend: ClassVar[str] = ""

    def __init__(
        self, *, clock: HostClock | None = None, queue_chunks: int = DEFAULT_QUEUE_CHUNKS, trigger_in: tuple[int, ...] = (0,)
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
        self._trigger_channels: set[int] = set()
        self._info: DeviceInfo | None = None
        self.error: BaseException | None = None

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
        """The stream has ended (file replayed, socket closed by the twin, device gone)."""
        return self._ended

    # -- data -------------------------------------------------------------------------------------
    def read(self, timeout_s: float | None = None) -> EventChunk | None:
        """The next chunk; None on timeout or once the stream has ended and the queue is empty."""
        if self._ended and self._queue.empty():
            return None
        try:
            item = self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None
        if item is _END:
            self._ended = True
            return None
        return item  # type: ignore[no-any-return]

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
        """Set one IMX636 bias (offset from the factory default); CameraError outside its range."""
        name = _check_bias_name(name)
        lo, hi = IMX636_BIASES[name]
        if not lo <= int(value) <= hi:
            raise CameraError(f"{name} = {value} is outside its range [{lo}, {hi}]")
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

    @property
    def trigger_channels(self) -> set[int]:
        return set(self._trigger_channels)

    def enable_trigger_in(self, channel: int = 0) -> None:
        """Report edges on trigger input ``channel`` (0 = main, 1 = aux)."""
        self._enable_trigger(int(channel), True)
        self._trigger_channels.add(int(channel))

    def disable_trigger_in(self, channel: int = 0) -> None:
        self._enable_trigger(int(channel), False)
        self._trigger_channels.discard(int(channel))

    def _filter_triggers(self, triggers: npt.NDArray[Any]) -> npt.NDArray[Any]:
        if triggers.size == 0:
            return triggers
        return triggers[np.isin(triggers["id"], list(self._trigger_channels))]

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

    def _enable_trigger(self, channel: int, on: bool) -> None:
        pass


def _check_bias_name(name: str) -> str:
    if name not in IMX636_BIASES:
        raise CameraError(f"unknown bias {name!r}; the IMX636 has {', '.join(IMX636_BIASES)}")
    return name


# -- raw: replay a file ---------------------------------------------------------------------------


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
        trigger_in: tuple[int, ...] = (0,),
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
            header, fmt, geo, _ = open_decoder(self.path)
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
        except BaseException as exc:  # surfaced to the consumer through .error and the end of stream
            self.error = exc
        finally:
            self._end()

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


# -- sim: the twin's socket -----------------------------------------------------------------------


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
        trigger_in: tuple[int, ...] = (0,),
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
                except OSError as exc:
                    self.error = exc
                    break
                t_host = self.clock.now_ns()
                if not data:
                    break
                self.bytes_received += len(data)
                self._take(decoder.feed(data), t_host)
        except BaseException as exc:
            self.error = exc
        finally:
            self._end()

    def _take(self, out: Any, t_host_ns: int) -> None:
        if self._streaming.is_set():
            self._deliver(out.events, self._filter_triggers(out.triggers), t_host_ns)

    def _enable_trigger(self, channel: int, on: bool) -> None:
        if not 0 <= channel <= 15:
            raise CameraError(f"trigger channel {channel} outside 0..15")


# -- metavision: the SDK ------------------------------------------------------------------------


def import_metavision_hal() -> Any:
    """The ``metavision_hal`` module, or CameraError saying the SDK is needed."""
    try:
        return importlib.import_module("metavision_hal")
    except ImportError as exc:
        raise CameraError(
            f"{SDK_MISSING}; import failed: {exc}. Install OpenEB or the Metavision SDK and source its setup_env.sh"
        ) from None


class MetavisionCamera(Camera):
    """A camera opened through the Metavision HAL Python API (``metavision_hal``).

    ``serial``: the camera's serial ("" = the first camera found). Streaming polls
    ``I_EventsStream`` in a reader thread and decodes each raw buffer with
    ``I_EventsStreamDecoder``; the CD and trigger decoder callbacks gather the buffer's events,
    which are delivered as one chunk stamped with the time the buffer was fetched.
    """

    backend = "metavision"

    #: labrig trigger channel -> name in ``I_TriggerIn.Channel``.
    TRIGGER_CHANNELS: ClassVar[dict[int, str]] = {0: "MAIN", 1: "AUX"}

    def __init__(
        self,
        serial: str = "",
        *,
        poll_sleep_s: float = 0.0005,
        clock: HostClock | None = None,
        queue_chunks: int = DEFAULT_QUEUE_CHUNKS,
        trigger_in: tuple[int, ...] = (0,),
    ) -> None:
        super().__init__(clock=clock, queue_chunks=queue_chunks, trigger_in=trigger_in)
        self.serial = serial
        self.poll_sleep_s = poll_sleep_s
        self._hal: Any = None
        self._device: Any = None
        self._stream: Any = None
        self._stream_decoder: Any = None
        self._thread: threading.Thread | None = None
        self._halt = threading.Event()
        self._cd_parts: list[npt.NDArray[Any]] = []
        self._tr_parts: list[npt.NDArray[Any]] = []

    def _facility(self, getter: str, what: str, required: bool = True) -> Any:
        method: Callable[[], Any] | None = getattr(self._device, getter, None)
        facility = method() if method is not None else None
        if facility is None and required:
            raise CameraError(f"the camera (serial {self.serial or 'first found'}) has no {what} facility ({getter})")
        return facility

    def _open(self) -> None:
        self._hal = import_metavision_hal()
        try:
            device = self._hal.DeviceDiscovery.open(self.serial)
        except Exception as exc:  # the SDK raises its own exception types
            raise CameraError(f"cannot open the camera {self.serial or '(first found)'}: {exc}") from None
        if device is None:
            raise CameraError(f"no camera {'with serial ' + self.serial if self.serial else 'found'}; is the EVK4 plugged in?")
        self._device = device
        geometry = self._facility("get_i_geometry", "geometry")
        hw = self._facility("get_i_hw_identification", "hardware identification", required=False)
        serial = str(hw.get_serial()) if hw is not None else self.serial
        sensor = ""
        fmt = "EVT3"
        fields: dict[str, str] = {}
        if hw is not None:
            info = hw.get_sensor_info()
            sensor = str(getattr(info, "name", ""))
            if hasattr(hw, "get_current_data_encoding_format"):
                fmt = str(hw.get_current_data_encoding_format())
            if hasattr(hw, "get_integrator"):
                fields["integrator"] = str(hw.get_integrator())
            if hasattr(hw, "get_system_info"):
                fields.update({str(k): str(v) for k, v in dict(hw.get_system_info()).items()})
        self._info = DeviceInfo(
            "metavision", serial, int(geometry.get_width()), int(geometry.get_height()), sensor, fmt, "usb", fields
        )
        biases = self._facility("get_i_ll_biases", "bias (I_LL_Biases)", required=False)
        if biases is not None:
            for name, value in dict(biases.get_all_biases()).items():
                if name in self._biases:
                    self._biases[name] = int(value)
        self._stream = self._facility("get_i_events_stream", "event stream (I_EventsStream)")
        self._stream_decoder = self._facility("get_i_events_stream_decoder", "stream decoder (I_EventsStreamDecoder)")
        self._facility("get_i_event_cd_decoder", "CD decoder").add_event_buffer_callback(self._on_cd)
        trig_decoder = self._facility("get_i_event_ext_trigger_decoder", "trigger decoder", required=False)
        if trig_decoder is not None:
            trig_decoder.add_event_buffer_callback(self._on_trigger)

    def _on_cd(self, buffer: npt.NDArray[Any]) -> None:
        if len(buffer):
            ev = np.empty(len(buffer), EVENT_DTYPE)
            for name in ("x", "y", "p", "t"):
                ev[name] = buffer[name]
            self._cd_parts.append(ev)

    def _on_trigger(self, buffer: npt.NDArray[Any]) -> None:
        if len(buffer):
            tr = np.empty(len(buffer), TRIGGER_DTYPE)
            for name in ("p", "t", "id"):
                tr[name] = buffer[name]
            self._tr_parts.append(tr)

    def _start(self) -> None:
        self._stream.start()
        self._halt.clear()
        self._thread = threading.Thread(target=self._run, name="camera-metavision", daemon=True)
        self._thread.start()

    def _stop(self) -> None:
        self._halt.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        self._stream.stop()

    def _close(self) -> None:
        self._device = self._stream = self._stream_decoder = None

    def _run(self) -> None:
        try:
            while not self._halt.is_set():
                ret = self._stream.poll_buffer()
                if ret < 0:
                    break
                if ret == 0:
                    time.sleep(self.poll_sleep_s)
                    continue
                raw = self._stream.get_latest_raw_data()
                t_host = self.clock.now_ns()
                if raw is None or len(raw) == 0:
                    continue
                self._cd_parts.clear()
                self._tr_parts.clear()
                self._stream_decoder.decode(raw)
                events = np.concatenate(self._cd_parts) if self._cd_parts else np.zeros(0, EVENT_DTYPE)
                triggers = np.concatenate(self._tr_parts) if self._tr_parts else np.zeros(0, TRIGGER_DTYPE)
                self._deliver(events, triggers, t_host)
        except BaseException as exc:
            self.error = exc
        finally:
            self._end()

    def _set_bias(self, name: str, value: int) -> None:
        if self._device is None:
            raise CameraError("open the camera before setting biases")
        biases = self._facility("get_i_ll_biases", "bias (I_LL_Biases)")
        if biases.set(name, int(value)) is False:
            raise CameraError(f"the camera refused {name} = {value}")

    def _set_roi(self, roi: Roi | None) -> None:
        i_roi = self._facility("get_i_roi", "region of interest (I_ROI)")
        if roi is None:
            i_roi.enable(False)
            return
        i_roi.set_window(self._hal.I_ROI.Window(roi.x, roi.y, roi.width, roi.height))
        i_roi.enable(True)

    def _enable_trigger(self, channel: int, on: bool) -> None:
        if channel not in self.TRIGGER_CHANNELS:
            raise CameraError(f"trigger channel {channel} unknown; the EVK4 has {sorted(self.TRIGGER_CHANNELS)} (0 main, 1 aux)")
        trig = self._facility("get_i_trigger_in", "trigger input (I_TriggerIn)")
        hal_channel = getattr(self._hal.I_TriggerIn.Channel, self.TRIGGER_CHANNELS[channel])
        ok = trig.enable(hal_channel) if on else trig.disable(hal_channel)
        if ok is False:
            raise CameraError(f"the camera refused to {'enable' if on else 'disable'} trigger input {channel}")


# -- opening and recording ------------------------------------------------------------------------


def open_camera(backend: str, **options: Any) -> Camera:
    """A camera of ``backend``: ``metavision`` (serial=""), ``raw`` (path, speed), ``sim`` (path).

    Returns it unopened; use it in a ``with`` block or call ``open()``.
    """
    if backend == "metavision":
        return MetavisionCamera(**options)
    if backend == "raw":
        return RawReplayCamera(**options)
    if backend == "sim":
        return SimCamera(**options)
    raise CameraError(f"unknown camera backend {backend!r}; choose one of {', '.join(BACKENDS)}")


@dataclass
class RecordStats:
    chunks: int = 0
    events: int = 0
    triggers: int = 0
    rejected_chunks: int = 0


def record_camera(
    camera: Camera,
    writer: Any,
    stop_event: threading.Event,
    *,
    poll_s: float = 0.05,
    on_chunk: Callable[[EventChunk], None] | None = None,
) -> RecordStats:
    """Move the camera's chunks into a RecordingWriter until ``stop_event`` is set or the stream ends.

    Events go through ``writer.put_events`` with their device time and the chunk's host
    receive time in the recording's time base (so the camera clock model is fitted at
    finalization); trigger edges go to the ``triggers`` stream. The camera and the writer must
    share the host clock. Starts the camera if it is not streaming; does not stop it.
    """
    t0_ns = int(writer.t0_host_ns)
    if not camera.streaming:
        camera.start()
    stats = RecordStats()
    while not stop_event.is_set():
        chunk = camera.read(timeout_s=poll_s)
        if chunk is None:
            if camera.ended:
                break
            continue
        t_host_us = (chunk.t_host_ns - t0_ns) // NS_PER_US
        ev = chunk.events
        ok = True
        if ev.size:
            ok = writer.put_events(ev["x"], ev["y"], ev["p"], ev["t"], t_host_us)
        if chunk.triggers.size:
            tr = chunk.triggers
            ok = writer.put("triggers", t_device_us=tr["t"], polarity=tr["p"], channel=tr["id"]) and ok
        stats.chunks += 1
        stats.events += int(ev.size)
        stats.triggers += int(chunk.triggers.size)
        stats.rejected_chunks += 0 if ok else 1
        if on_chunk is not None:
            on_chunk(chunk)
    return stats
