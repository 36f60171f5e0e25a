"""A stand-in for Prophesee's ``metavision_hal`` Python module, behaving as OpenEB 5.x does.

Tests install it in ``sys.modules`` when the real SDK is missing. Each behaviour below was read
from OpenEB's sources (``hal/python/bindings/*.cpp``, ``hal/cpp/src/facilities/*.cpp``, the EVT
decoders and the IMX636 plugin), not guessed:

* ``DeviceDiscovery.open(serial)`` returns a device, or None when no camera has that serial
  ("" = the first); ``open_raw_file(path)`` opens a RAW file as a device (RuntimeError if it
  cannot); ``list()`` returns the serials.
* ``I_EventsStream``: ``poll_buffer()`` returns 1 while a buffer waits and takes nothing, 0 when
  none is ready, -1 once the stream is stopped (``stop()``, a file's end, a camera lost) and no
  buffer waits; ``get_latest_raw_data()`` takes the oldest buffer and returns a ``RawBuffer``
  whose only method is ``size()`` (bytes; an empty one when nothing waits); ``stop()`` drops
  the waiting buffers.
* ``I_EventsStreamDecoder.decode(raw_buffer)`` takes a ``RawBuffer`` only. Times are shifted as
  the SDK's decoders shift them (EVT3: the first TIME_HIGH less one, times 4096 us; EVT2: the
  first TIME_HIGH times 64 us); words before the first TIME_HIGH are skipped.
* The CD decoder calls back with a copied array (x u2, y u2, p i2, t i8; 16 bytes an event); the
  trigger decoder with a view of its own memory (p i2, t i8, id i2; 24 bytes), valid only during
  the callback: this fake overwrites it afterwards, so an adapter that keeps it reads garbage.
* ``I_TriggerIn.Channel`` is an enum (MAIN = 0, AUX = 1, LOOPBACK = 2); ``enable(channel)`` is
  False for a channel the device lacks; ``get_available_channels()`` maps the device's channels
  to the event ids their edges carry (an EVK4: {MAIN: 0}; an EVK2: {MAIN: 1}).
* ``I_LL_Biases.set`` raises RuntimeError for an unknown bias or a value outside the recommended
  range; ``get_bias_info`` gives the recommended and allowed ranges.
* A file device has no ``I_LL_Biases``, ``I_ROI`` or ``I_TriggerIn`` (their getters return None);
  its ``get_connection_type()`` is ``File``.
"""

from __future__ import annotations

import enum
import threading
import types
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.devices.camera.base import IMX636_ALLOWED_BIASES, IMX636_BIASES
from labrig.devices.raw import Evt2Decoder, Evt3Decoder, read_header

#: The SDK's event layouts (``EventCD``, ``EventExtTrigger``), with their C struct padding.
SDK_CD_DTYPE = np.dtype({"names": ["x", "y", "p", "t"], "formats": ["<u2", "<u2", "<i2", "<i8"],
                         "offsets": [0, 2, 4, 8], "itemsize": 16})
SDK_TRIGGER_DTYPE = np.dtype({"names": ["p", "t", "id"], "formats": ["<i2", "<i8", "<i2"],
                              "offsets": [0, 8, 16], "itemsize": 24})

#: What the file data transfer hands over at a time, in bytes.
FILE_BUFFER_BYTES = 1 << 16


class Channel(enum.IntEnum):
    """``metavision_hal.I_TriggerIn.Channel``."""

    MAIN = 0
    AUX = 1
    LOOPBACK = 2


@dataclass
class FakeCamera:
    """One camera the fake SDK can open: its identity, trigger inputs and the EVT3 bytes it sends.

    ``trigger_ids``: channel -> event id of its edges (EVK4 {MAIN: 0}; EVK2 {MAIN: 1}). Buffers
    pushed with :meth:`push` wait for the stream as USB transfers do; :meth:`unplug` ends the
    stream as a lost device does.
    """

    serial: str = "00ca0009"
    sensor: str = "IMX636"
    integrator: str = "Prophesee"
    connection: str = "USB"
    width: int = 1280
    height: int = 720
    trigger_ids: dict[Channel, int] = field(default_factory=lambda: {Channel.MAIN: 0})
    buffers: list[bytes] = field(default_factory=list)
    _stream: _EventsStream | None = None

    def push(self, data: bytes) -> None:
        """Another transfer from the camera (EVT3 bytes); it waits until the stream is started."""
        if self._stream is not None:
            self._stream.arrive(data)
        else:
            self.buffers.append(data)

    def unplug(self) -> None:
        """The camera disappears: the stream stops once its waiting buffers are taken."""
        if self._stream is not None:
            self._stream.lose()


class RawBuffer:
    """``metavision_hal.RawBuffer``: the SDK's buffer of raw bytes; only ``size()`` is bound."""

    def __init__(self, data: bytes = b"") -> None:
        self._data = bytes(data)

    def size(self) -> int:
        return len(self._data)


class _EventsStream:
    """``I_EventsStream`` over a queue of buffers (the data transfer fills it)."""

    def __init__(self, initial: list[bytes], *, ends_by_itself: bool) -> None:
        self._lock = threading.Lock()
        self._initial = list(initial)
        self._available: deque[bytes] = deque()
        self._stopped = True
        self._ends_by_itself = ends_by_itself  # a file's transfer stops at its end

    def start(self) -> None:
        with self._lock:
            self._stopped = False
            self._available.extend(self._initial)
            self._initial = []
            if self._ends_by_itself:
                self._stopped = True  # the whole file is transferred; the stream ends when it is taken

    def stop(self) -> None:
        with self._lock:
            self._available.clear()
            self._stopped = True

    def arrive(self, data: bytes) -> None:
        with self._lock:
            if self._stopped and not self._ends_by_itself:
                self._initial.append(data)
            else:
                self._available.append(data)

    def lose(self) -> None:
        with self._lock:
            self._stopped = True

    def poll_buffer(self) -> int:
        with self._lock:
            if self._available:
                return 1
            return -1 if self._stopped else 0

    def wait_next_buffer(self) -> int:
        raise NotImplementedError("the fake SDK serves poll_buffer only")

    def get_latest_raw_data(self) -> RawBuffer:
        with self._lock:
            return RawBuffer(self._available.popleft() if self._available else b"")


class _EventDecoder:
    """``I_EventDecoder_EventCD`` / ``I_EventDecoder_EventExtTrigger``: buffer callbacks."""

    def __init__(self, *, copies: bool) -> None:
        self.callbacks: list[Callable[[npt.NDArray[Any]], Any]] = []
        self.copies = copies

    def add_event_buffer_callback(self, cb: Callable[[npt.NDArray[Any]], Any]) -> int:
        self.callbacks.append(cb)
        return len(self.callbacks) - 1

    def forward(self, array: npt.NDArray[Any]) -> None:
        for cb in self.callbacks:
            cb(array.copy() if self.copies else array)
        if not self.copies:
            array.view(np.uint8)[:] = 0xA5  # the SDK reuses this memory after the callback


class _StreamDecoder:
    """``I_EventsStreamDecoder`` (``metavision_hal.I_Decoder``) with the SDK's time shift."""

    def __init__(self, fmt: str, width: int, height: int, cd: _EventDecoder, trigger: _EventDecoder) -> None:
        self.fmt = fmt
        self._decoder = Evt3Decoder(width, height) if fmt == "EVT3" else Evt2Decoder(width, height)
        self._cd, self._trigger = cd, trigger
        self._shift_us: int | None = None
        self._last_t = -1

    def decode(self, raw: RawBuffer) -> None:
        if not isinstance(raw, RawBuffer):
            raise TypeError(f"decode(): incompatible function arguments; got {type(raw).__name__}, expected RawBuffer")
        data = raw._data
        if self._shift_us is None:
            self._shift_us = _first_time_high_shift_us(data, self.fmt)
        out = self._decoder.feed(data)
        shift = self._shift_us or 0
        cd = np.zeros(out.events.size, SDK_CD_DTYPE)
        for name in ("x", "y", "p", "t"):
            cd[name] = out.events[name]
        cd["t"] -= shift
        trig = np.zeros(out.triggers.size, SDK_TRIGGER_DTYPE)
        for name in ("p", "t", "id"):
            trig[name] = out.triggers[name]
        trig["t"] -= shift
        if cd.size:
            self._last_t = int(cd["t"][-1])
            half = cd.size // 2  # the SDK calls back per decoded batch, several per buffer
            self._cd.forward(cd[:half])
            self._cd.forward(cd[half:])
        if trig.size:
            self._trigger.forward(trig)

    def get_last_timestamp(self) -> int:
        return self._last_t


def _first_time_high_shift_us(data: bytes, fmt: str) -> int | None:
    """The SDK decoders' time shift, from the first TIME_HIGH word in ``data`` (None: none yet)."""
    if fmt == "EVT3":
        words = np.frombuffer(data[: len(data) // 2 * 2], "<u2")
        hits = np.flatnonzero((words >> 12) == 0x8)
        if not hits.size:
            return None
        t = int(words[hits[0]] & 0xFFF)
        return max(t - 1, 0) << 12
    words32 = np.frombuffer(data[: len(data) // 4 * 4], "<u4")
    hits = np.flatnonzero((words32 >> 28) == 0x8)
    return int(words32[hits[0]] & 0x0FFFFFFF) << 6 if hits.size else None


class _Biases:
    """``I_LL_Biases`` of an IMX636 (offsets from the factory default; the recommended range is enforced)."""

    def __init__(self) -> None:
        self.values = dict.fromkeys(IMX636_BIASES, 0)
        self.log: list[tuple[str, int]] = []

    def _known(self, bias_name: str) -> None:
        if bias_name not in self.values:
            raise RuntimeError(f'Unavailable bias: "{bias_name}".')

    def set(self, bias_name: str, bias_value: int) -> bool:
        self._known(bias_name)
        lo, hi = IMX636_BIASES[bias_name]
        if not lo <= bias_value <= hi:
            raise RuntimeError(f'Invalid value {bias_value} for bias "{bias_name}". Value should be within range [{lo}, {hi}].')
        self.values[bias_name] = int(bias_value)
        self.log.append((bias_name, int(bias_value)))
        return True

    def get(self, bias_name: str) -> int:
        self._known(bias_name)
        return self.values[bias_name]

    def get_all_biases(self) -> dict[str, int]:
        return dict(self.values)

    def get_bias_info(self, bias_name: str) -> Any:
        self._known(bias_name)
        recommended, allowed = IMX636_BIASES[bias_name], IMX636_ALLOWED_BIASES[bias_name]
        return types.SimpleNamespace(get_bias_range=lambda: recommended, get_bias_recommended_range=lambda: recommended,
                                     get_bias_allowed_range=lambda: allowed, is_modifiable=lambda: True)


class _TriggerIn:
    def __init__(self, ids: dict[Channel, int]) -> None:
        self.ids = dict(ids)
        self.enabled: set[Channel] = set()

    def enable(self, channel: Channel) -> bool:
        if not isinstance(channel, Channel):
            raise TypeError(f"enable(): incompatible function arguments; got {type(channel).__name__}, expected Channel")
        if channel not in self.ids:
            return False
        self.enabled.add(channel)
        return True

    def disable(self, channel: Channel) -> bool:
        if channel not in self.ids:
            return False
        self.enabled.discard(channel)
        return True

    def is_enabled(self, channel: Channel) -> bool:
        return channel in self.enabled

    def get_available_channels(self) -> dict[Channel, int]:
        return dict(self.ids)


class _Roi:
    def __init__(self) -> None:
        self.window: tuple[int, int, int, int] | None = None
        self.enabled = False

    def set_window(self, roi: Any) -> None:
        self.window = (roi.x, roi.y, roi.width, roi.height)

    def enable(self, enable: bool) -> bool:
        self.enabled = bool(enable)
        return True


class Device:
    """``metavision_hal.Device``: facility getters; None for a facility the device lacks."""

    def __init__(self, *, serial: str, sensor: str, integrator: str, connection: str, fmt: str, width: int, height: int,
                 buffers: list[bytes], ends_by_itself: bool, trigger_ids: dict[Channel, int] | None) -> None:
        self.serial, self.sensor, self.integrator, self.connection = serial, sensor, integrator, connection
        self.fmt, self.width, self.height = fmt, width, height
        self.stream = _EventsStream(buffers, ends_by_itself=ends_by_itself)
        self.cd_decoder = _EventDecoder(copies=True)
        self.trigger_decoder = _EventDecoder(copies=False)
        self.stream_decoder = _StreamDecoder(fmt, width, height, self.cd_decoder, self.trigger_decoder)
        live = trigger_ids is not None
        self.biases = _Biases() if live else None
        self.roi = _Roi() if live else None
        self.trigger_in = _TriggerIn(trigger_ids) if trigger_ids is not None else None

    def get_i_geometry(self) -> Any:
        return types.SimpleNamespace(get_width=lambda: self.width, get_height=lambda: self.height)

    def get_i_hw_identification(self) -> Any:
        info = types.SimpleNamespace(name=self.sensor, major_version=4, minor_version=2)
        system = {"Serial": self.serial, "Integrator": self.integrator, "Sensor Name": self.sensor,
                  "Available Data Encoding Formats": self.fmt, "Current Data Encoding Format": self.fmt,
                  "Connection": self.connection}
        return types.SimpleNamespace(
            get_serial=lambda: self.serial, get_sensor_info=lambda: info, get_current_data_encoding_format=lambda: self.fmt,
            get_integrator=lambda: self.integrator, get_system_info=lambda: dict(system),
            get_connection_type=lambda: self.connection,
        )

    def get_i_ll_biases(self) -> _Biases | None:
        return self.biases

    def get_i_roi(self) -> _Roi | None:
        return self.roi

    def get_i_trigger_in(self) -> _TriggerIn | None:
        return self.trigger_in

    def get_i_events_stream(self) -> _EventsStream:
        return self.stream

    def get_i_events_stream_decoder(self) -> _StreamDecoder:
        return self.stream_decoder

    def get_i_event_cd_decoder(self) -> _EventDecoder:
        return self.cd_decoder

    def get_i_event_ext_trigger_decoder(self) -> _EventDecoder:
        return self.trigger_decoder


def fake_metavision_hal(cameras: list[FakeCamera] | None = None, *, file_buffer_bytes: int = FILE_BUFFER_BYTES
                        ) -> types.ModuleType:
    """A ``metavision_hal`` module that sees ``cameras`` (default: one EVK4 with no data) and opens RAW files.

    The module's ``opened`` list holds every device it opened, for tests to inspect.
    """
    cams = list(cameras) if cameras is not None else [FakeCamera()]
    hal = types.ModuleType("metavision_hal")
    opened: list[Device] = []

    def open_device(serial: str) -> Device | None:
        cam = cams[0] if serial == "" and cams else next((c for c in cams if c.serial == serial), None)
        if cam is None:
            return None
        device = Device(serial=cam.serial, sensor=cam.sensor, integrator=cam.integrator, connection=cam.connection,
                        fmt="EVT3", width=cam.width, height=cam.height, buffers=cam.buffers, ends_by_itself=False,
                        trigger_ids=cam.trigger_ids)
        cam.buffers = []
        cam._stream = device.stream
        opened.append(device)
        return device

    def open_raw_file(raw_file: str) -> Device:
        path = Path(raw_file)
        if not path.is_file():
            raise RuntimeError(f"Opening RAW file at {raw_file} failed: file does not exist")
        header = read_header(str(path))
        fmt = (header.format_name() or "").upper()
        if fmt not in ("EVT3", "EVT2"):
            raise RuntimeError(f"Opening RAW file at {raw_file} failed: unsupported format {fmt or '(none)'}")
        width, height = header.geometry() or (1280, 720)
        payload = path.read_bytes()[header.size:]
        buffers = [payload[i : i + file_buffer_bytes] for i in range(0, len(payload), file_buffer_bytes)]
        f = header.fields
        device = Device(serial=f.get("serial_number", ""), sensor=f.get("sensor_name", ""),
                        integrator=f.get("camera_integrator_name", f.get("integrator_name", "")), connection="File",
                        fmt=fmt, width=width, height=height, buffers=buffers, ends_by_itself=True, trigger_ids=None)
        opened.append(device)
        return device

    class Window:
        def __init__(self, x: int, y: int, width: int, height: int) -> None:
            self.x, self.y, self.width, self.height = x, y, width, height

    hal.DeviceDiscovery = types.SimpleNamespace(  # type: ignore[attr-defined]
        open=open_device, open_raw_file=open_raw_file, list=lambda: [c.serial for c in cams])
    hal.I_TriggerIn = types.SimpleNamespace(Channel=Channel)  # type: ignore[attr-defined]
    hal.I_ROI = types.SimpleNamespace(Window=Window)  # type: ignore[attr-defined]
    hal.RawBuffer = RawBuffer  # type: ignore[attr-defined]
    hal.opened = opened  # type: ignore[attr-defined]
    return hal
