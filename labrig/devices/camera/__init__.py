"""The event camera (Prophesee EVK4, IMX636): one interface, three backends, one module each.

>>> with open_camera("sim", path="/tmp/labrig-evk4.sock") as cam:   # doctest: +SKIP
...     cam.start()
...     for chunk in cam.chunks(timeout_s=1.0):
...         chunk.events["t"], chunk.triggers, chunk.t_host_ns

* ``metavision`` (:mod:`.metavision`): a real camera through the Metavision SDK / OpenEB Python
  module ``metavision_hal``, or a RAW file opened as a device through the SDK (``path=``), which
  checks an SDK install and labrig's path end to end without a camera.
* ``raw`` (:mod:`.raw`): replays a RAW file (EVT3 / EVT2) as if live, paced by the event times.
* ``sim`` (:mod:`.sim`): reads the EVT3 byte stream of the virtual rig's EVK4 twin from a Unix socket.

Every backend delivers :class:`EventChunk` s (events in EVENT_DTYPE with ``t`` = device time in
us, trigger edges in TRIGGER_DTYPE, ``t_host_ns`` = the host time they arrived) through the
bounded queue of :class:`Camera` (:mod:`.base`), which also holds biases (IMX636 names, offsets
from the factory default), the region of interest and the trigger inputs.
"""

from __future__ import annotations

from typing import Any

from labrig.devices.camera.base import (
    DEFAULT_QUEUE_CHUNKS,
    IMX636_ALLOWED_BIASES,
    IMX636_BIASES,
    TRIGGER_INPUTS,
    Camera,
    CameraError,
    CameraStats,
    DeviceInfo,
    EventChunk,
    Roi,
)
from labrig.devices.camera.metavision import SDK_MISSING, MetavisionCamera, MetavisionSdk, import_metavision_hal, metavision_sdk
from labrig.devices.camera.raw import RawReplayCamera
from labrig.devices.camera.sim import SimCamera

BACKENDS = ("metavision", "raw", "sim")

__all__ = [
    "BACKENDS",
    "DEFAULT_QUEUE_CHUNKS",
    "IMX636_ALLOWED_BIASES",
    "IMX636_BIASES",
    "SDK_MISSING",
    "TRIGGER_INPUTS",
    "Camera",
    "CameraError",
    "CameraStats",
    "DeviceInfo",
    "EventChunk",
    "MetavisionCamera",
    "MetavisionSdk",
    "RawReplayCamera",
    "Roi",
    "SimCamera",
    "import_metavision_hal",
    "metavision_sdk",
    "open_camera",
]


def open_camera(backend: str, **options: Any) -> Camera:
    """A camera of ``backend``: ``metavision`` (serial="" or path=FILE.raw), ``raw`` (path, speed), ``sim`` (path).

    Returns it unopened; use it in a ``with`` block or call ``open()``.
    """
    if backend == "metavision":
        return MetavisionCamera(**options)
    if backend == "raw":
        return RawReplayCamera(**options)
    if backend == "sim":
        return SimCamera(**options)
    raise CameraError(f"unknown camera backend {backend!r}; choose one of {', '.join(BACKENDS)}")
