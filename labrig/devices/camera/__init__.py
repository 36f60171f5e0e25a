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

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from labrig.clock import NS_PER_US
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
    "RecordStats",
    "Roi",
    "SimCamera",
    "import_metavision_hal",
    "metavision_sdk",
    "open_camera",
    "record_camera",
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

    Raises :class:`CameraError` if the stream broke (what arrived before is in the writer).

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
