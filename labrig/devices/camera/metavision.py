"""The ``metavision`` camera backend: a Prophesee camera, or a RAW file, through the Metavision HAL.

Written against OpenEB's Python bindings (``hal/python/bindings``; OpenEB 5.x):

* ``DeviceDiscovery.open(serial)`` opens a camera ("" = the first found; None when there is
  none), ``DeviceDiscovery.open_raw_file(path)`` a RAW file as a device; ``list()`` gives the
  serials of the cameras the plugins see.
* ``I_EventsStream.poll_buffer()`` is 1 while a buffer waits (it takes nothing), 0 when none is
  ready, -1 once the stream is stopped (``stop()``, end of file, device lost) and every buffer
  was taken; ``get_latest_raw_data()`` takes the oldest buffer and returns it as a
  ``RawBuffer`` (its only method is ``size()``; empty when none waits), which
  ``I_EventsStreamDecoder.decode`` takes as it is.
* The CD and external-trigger decoders call back with numpy arrays (CD: x u2, y u2, p i2, t i8;
  trigger: p i2, t i8, id i2). The trigger array is a view of the SDK's memory, valid only during
  the callback: both are copied at once. Times are the decoder's, shifted to start near zero.
* ``I_TriggerIn.Channel`` is an enum (MAIN, AUX, LOOPBACK); ``get_available_channels()`` maps
  the channels a device has to the event id its edges carry (an EVK4: MAIN -> 0 only).
* ``I_HW_Identification.get_connection_type()`` says how the data arrives (e.g. ``File``), and
  ``get_system_info()`` reports the rest under the SDK's keys (``Integrator``, ``Serial``, ...).

A file device has no biases, region of interest or trigger inputs: the region of interest is
applied in software and the file's trigger edges are replayed as recorded.
"""

from __future__ import annotations

import importlib
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.clock import HostClock
from labrig.devices.camera.base import DEFAULT_QUEUE_CHUNKS, Camera, CameraError, DeviceInfo, Roi
from labrig.devices.camera.raw import FILE_TRIGGER_INPUTS
from labrig.devices.raw import TRIGGER_DTYPE
from labrig.eventtypes import EVENT_DTYPE

SDK_MISSING = "the metavision backend needs the Metavision SDK / OpenEB from Prophesee (Python module metavision_hal)"

#: Where OpenEB installs its HAL plugins, below an install prefix.
PLUGIN_SUBDIR = Path("lib") / "metavision" / "hal" / "plugins"


def import_metavision_hal() -> Any:
    """The ``metavision_hal`` module, or CameraError saying the SDK is needed."""
    try:
        return importlib.import_module("metavision_hal")
    except ImportError as exc:
        raise CameraError(
            f"{SDK_MISSING}; import failed: {exc}. Install OpenEB or the Metavision SDK and source its setup_env.sh"
        ) from None


class MetavisionCamera(Camera):
    """A camera (``serial``; "" = the first found) or a RAW file (``path``) opened through the HAL.

    Streaming polls ``I_EventsStream`` in a reader thread and decodes each raw buffer with
    ``I_EventsStreamDecoder``; the decoder callbacks gather the buffer's events, delivered as one
    chunk stamped with the host time the buffer was taken. A camera's stream that ends without
    :meth:`stop` (unplugged, a USB error) is a failure; a file's ends at its last buffer.
    """

    backend = "metavision"

    def __init__(
        self,
        serial: str = "",
        *,
        path: str | os.PathLike[str] | None = None,
        poll_sleep_s: float = 0.0005,
        clock: HostClock | None = None,
        queue_chunks: int = DEFAULT_QUEUE_CHUNKS,
        trigger_in: tuple[str | int, ...] = ("main",),
    ) -> None:
        super().__init__(clock=clock, queue_chunks=queue_chunks, trigger_in=trigger_in)
        self.serial = serial
        self.path = Path(path) if path is not None else None
        self.poll_sleep_s = poll_sleep_s
        self._hal: Any = None
        self._device: Any = None
        self._stream: Any = None
        self._stream_decoder: Any = None
        self._trigger_facility: Any = None
        self._channels: dict[int, Any] = {}  # event id -> I_TriggerIn.Channel
        self._thread: threading.Thread | None = None
        self._halt = threading.Event()
        self._cd_parts: list[npt.NDArray[Any]] = []
        self._tr_parts: list[npt.NDArray[Any]] = []

    @property
    def is_file(self) -> bool:
        return self.path is not None

    def _what(self) -> str:
        return f"the RAW file {self.path}" if self.path is not None else f"the camera {self.serial or '(first found)'}"

    def _facility(self, getter: str, what: str, required: bool = True) -> Any:
        method: Callable[[], Any] | None = getattr(self._device, getter, None)
        facility = method() if method is not None else None
        if facility is None and required:
            raise CameraError(f"{self._what()} has no {what} facility ({getter})")
        return facility

    def _open(self) -> None:
        self._hal = import_metavision_hal()
        try:
            if self.path is not None:
                if not self.path.is_file():
                    raise CameraError(f"{self.path}: no such RAW file")
                device = self._hal.DeviceDiscovery.open_raw_file(os.fspath(self.path))
            else:
                device = self._hal.DeviceDiscovery.open(self.serial)
        except CameraError:
            raise
        except Exception as exc:  # the SDK raises its own exception types (RuntimeError from HalException)
            raise CameraError(f"cannot open {self._what()}: {exc}") from None
        if device is None:
            if self.path is not None:
                raise CameraError(f"the SDK could not open {self.path} as a RAW file")
            raise CameraError(f"no camera {'with serial ' + self.serial if self.serial else 'found'}; is the EVK4 plugged in "
                              "and its plugin installed? (`labrig devices` lists what the SDK sees)")
        self._device = device
        self._info = self._identify()
        biases = self._facility("get_i_ll_biases", "bias (I_LL_Biases)", required=False)
        if biases is not None:
            for name, value in dict(biases.get_all_biases()).items():
                if name in self._biases:
                    self._biases[name] = int(value)
        self._trigger_facility = self._facility("get_i_trigger_in", "trigger input (I_TriggerIn)", required=False)
        if self._trigger_facility is not None:
            self._channels = {int(event_id): channel
                              for channel, event_id in dict(self._trigger_facility.get_available_channels()).items()}
        self._stream = self._facility("get_i_events_stream", "event stream (I_EventsStream)")
        self._stream_decoder = self._facility("get_i_events_stream_decoder", "stream decoder (I_EventsStreamDecoder)")
        self._facility("get_i_event_cd_decoder", "CD decoder").add_event_buffer_callback(self._on_cd)
        trig_decoder = self._facility("get_i_event_ext_trigger_decoder", "trigger decoder", required=False)
        if trig_decoder is not None:
            trig_decoder.add_event_buffer_callback(self._on_trigger)

    def _identify(self) -> DeviceInfo:
        geometry = self._facility("get_i_geometry", "geometry")
        hw = self._facility("get_i_hw_identification", "hardware identification", required=False)
        if hw is None:
            return DeviceInfo("metavision", self.serial, int(geometry.get_width()), int(geometry.get_height()), "", "",
                              "file" if self.path else "")
        return DeviceInfo(
            "metavision",
            str(hw.get_serial()),
            int(geometry.get_width()),
            int(geometry.get_height()),
            str(hw.get_sensor_info().name),
            str(hw.get_current_data_encoding_format()),
            str(hw.get_connection_type()),
            {str(k): str(v) for k, v in dict(hw.get_system_info()).items()},
        )

    def _on_cd(self, buffer: npt.NDArray[Any]) -> None:
        if buffer.size:
            ev = np.empty(buffer.size, EVENT_DTYPE)
            for name in ("x", "y", "p", "t"):
                ev[name] = buffer[name]
            self._cd_parts.append(ev)

    def _on_trigger(self, buffer: npt.NDArray[Any]) -> None:
        if buffer.size:
            tr = np.empty(buffer.size, TRIGGER_DTYPE)
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
        self._device = self._stream = self._stream_decoder = self._trigger_facility = None

    def _run(self) -> None:
        try:
            lost = self._poll_buffers()
        except Exception as exc:
            self._fail("reading the event stream failed", exc)
            return
        if lost:
            self._fail("the camera stopped streaming (unplugged, or a USB error); check the cable and `labrig devices`")
        else:
            self._end()

    def _poll_buffers(self) -> bool:
        """Take and decode buffers until halted or the stream ends; True if a camera's stream ended by itself."""
        stream, decoder = self._stream, self._stream_decoder
        while not self._halt.is_set():
            ret = stream.poll_buffer()
            if ret < 0:
                return not self.is_file and not self._halt.is_set()
            if ret == 0:
                time.sleep(self.poll_sleep_s)
                continue
            raw = stream.get_latest_raw_data()
            t_host = self.clock.now_ns()
            if raw.size() == 0:
                continue
            self._cd_parts.clear()
            self._tr_parts.clear()
            decoder.decode(raw)
            events = np.concatenate(self._cd_parts) if self._cd_parts else np.zeros(0, EVENT_DTYPE)
            triggers = np.concatenate(self._tr_parts) if self._tr_parts else np.zeros(0, TRIGGER_DTYPE)
            if not self.is_file:
                triggers = self._filter_triggers(triggers)
            self._deliver(events, triggers, t_host)
        return False

    def _set_bias(self, name: str, value: int) -> None:
        if self._device is None:
            raise CameraError("open the camera before setting biases")
        biases = self._facility("get_i_ll_biases", "bias (I_LL_Biases)")
        try:
            accepted = biases.set(name, int(value))
        except Exception as exc:  # out of the device's range, or unknown to it
            raise CameraError(f"the camera refused {name} = {value}: {exc}") from None
        if accepted is False:
            raise CameraError(f"the camera refused {name} = {value}")

    def _set_roi(self, roi: Roi | None) -> None:
        i_roi = self._facility("get_i_roi", "region of interest (I_ROI)", required=not self.is_file)
        if i_roi is None:
            return  # a file: the base class keeps only the events inside
        if roi is None:
            i_roi.enable(False)
            return
        i_roi.set_window(self._hal.I_ROI.Window(roi.x, roi.y, roi.width, roi.height))
        i_roi.enable(True)

    def trigger_inputs(self) -> dict[str, int]:
        if self._trigger_facility is None:
            return dict(FILE_TRIGGER_INPUTS) if self.is_file else {}
        return {str(channel.name).lower(): event_id for event_id, channel in self._channels.items()}

    def _enable_trigger(self, event_id: int, on: bool) -> None:
        if self._trigger_facility is None:
            if self.is_file:
                return  # a file replays the edges it holds
            raise CameraError(f"{self._what()} has no trigger input (I_TriggerIn)")
        channel = self._channels[event_id]
        ok = self._trigger_facility.enable(channel) if on else self._trigger_facility.disable(channel)
        if ok is False:
            raise CameraError(f"the camera refused to {'enable' if on else 'disable'} trigger input "
                              f"{str(channel.name).lower()}")


# -- the SDK install, for `labrig devices` ---------------------------------------------------------------


@dataclass(frozen=True)
class MetavisionSdk:
    """What this host's Metavision SDK / OpenEB offers labrig.

    ``plugin_dirs``: where the HAL looks for camera plugins (``MV_HAL_PLUGIN_PATH``, then the
    install's ``lib/metavision/hal/plugins``); ``plugins``: the plugin libraries found there;
    ``cameras``: the serials ``DeviceDiscovery.list()`` returns.
    """

    importable: bool
    module_path: str = ""
    error: str = ""
    plugin_dirs: tuple[str, ...] = ()
    plugins: tuple[str, ...] = ()
    cameras: tuple[str, ...] = ()


def metavision_sdk() -> MetavisionSdk:
    """Whether ``metavision_hal`` imports, which plugins the HAL would load and which cameras it sees."""
    try:
        hal = importlib.import_module("metavision_hal")
    except ImportError as exc:
        return MetavisionSdk(False, error=f"{SDK_MISSING}; import failed: {exc}")
    module_path = str(getattr(hal, "__file__", "") or "")
    dirs = plugin_search_dirs(module_path)
    plugins = sorted({p.name for d in dirs if d.is_dir() for p in d.iterdir() if _is_plugin(p.name)})
    try:
        cameras = tuple(str(s) for s in hal.DeviceDiscovery.list())
        error = ""
    except Exception as exc:  # a broken plugin can make discovery raise
        cameras, error = (), f"camera discovery failed: {exc}"
    return MetavisionSdk(True, module_path, error, tuple(str(d) for d in dirs), tuple(plugins), cameras)


def plugin_search_dirs(module_path: str = "") -> list[Path]:
    """``MV_HAL_PLUGIN_PATH``'s folders, then the plugin folder of the install holding ``module_path``."""
    dirs = [Path(p) for p in os.environ.get("MV_HAL_PLUGIN_PATH", "").split(os.pathsep) if p]
    if module_path:
        for parent in Path(module_path).resolve().parents:
            candidate = parent / PLUGIN_SUBDIR
            if candidate.is_dir():
                dirs.append(candidate)
                break
    for prefix in (Path("/usr/local"), Path("/usr")):
        candidate = prefix / PLUGIN_SUBDIR
        if candidate.is_dir():
            dirs.append(candidate)
    unique: list[Path] = []
    for d in dirs:
        if d not in unique:
            unique.append(d)
    return unique


def _is_plugin(name: str) -> bool:
    return "hal_plugin" in name and name.endswith((".so", ".dll", ".dylib"))
