"""Device data into a recording: the one place that knows which stream each device's data goes to.

Drivers hand out samples stamped on the host clock and know nothing of recordings; these
functions put them into a :class:`~labrig.recording.RecordingWriter` in its time base (host us
since ``writer.t0_host_ns``, see :mod:`labrig.clock`): F/T samples into ``ft``, GRBL status
reports into ``cnc``, the G-code conversation into ``gcode``, camera chunks into ``events`` and
their trigger edges into ``triggers``. Devices and the writer must share the host clock.
:class:`~labrig.protocol.session.RigSession` routes with them, and so does anything that records
without a session (:func:`record_camera`, benchmarks).

Each ``put_*`` returns False when the writer had to drop rows (counted by the writer).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy.typing as npt

from labrig.clock import NS_PER_US
from labrig.devices.bota_stream import FtSample
from labrig.devices.camera import Camera, EventChunk
from labrig.devices.grbl_channel import StatusSample
from labrig.protocol.force_loop import HeldMove
from labrig.recording import RecordingWriter


def put_control(writer: RecordingWriter, t_host_ns: int, held: HeldMove, reading_n: float, reading_age_ns: int,
                end_mm: npt.ArrayLike) -> None:
    """One segment of a held move into the ``control`` stream (:data:`~labrig.protocol.force_loop.CONTROL_STREAM`):
    commanded at ``t_host_ns`` from ``reading_n`` (N), ``reading_age_ns`` old, ending at ``end_mm`` (machine mm)."""
    check = held.slip_check
    writer.put("control", t_host_us=(t_host_ns - writer.t0_host_ns) // NS_PER_US, target_n=held.loop.target_n,
               feedback_n=reading_n, reading_age_us=reading_age_ns // 1000, speed_mm_s=held.speed_mm_s,
               stiffness_n_per_mm=held.last.stiffness_n_per_mm, clipped=int(held.last.clipped), position_mm=end_mm,
               tangential_n=math.nan if held.contact is None else held.contact.tangential_n,
               slip_share=math.nan if check is None else check.share,
               friction_ratio=math.nan if check is None else check.friction_ratio,
               stiffness_ratio=math.nan if check is None else check.stiffness_ratio,
               following_ratio=math.nan if check is None else check.following_ratio,
               slipping=int(check is not None and check.slipping), slip_cue="" if check is None else check.cue)


def put_ft(writer: RecordingWriter, sample: FtSample) -> bool:
    """One F/T sample into ``ft``: ``t_host_us`` in the recording's time base, ``t_device_us`` the raw counter."""
    return writer.put(
        "ft",
        t_device_us=sample.t_device_us,
        t_host_us=(sample.t_host_ns - writer.t0_host_ns) // NS_PER_US,
        force_n=sample.force_n,
        torque_nm=sample.torque_nm,
        status=sample.status,
        temperature_c=sample.temperature_c,
    )


def put_ft_rows(writer: RecordingWriter, samples: list[FtSample]) -> bool:
    """F/T samples into ``ft`` as one batch: the rows :func:`put_ft` would put one by one."""
    if not samples:
        return True
    t0_us = writer.t0_host_ns
    return writer.put(
        "ft",
        t_device_us=[s.t_device_us for s in samples],
        t_host_us=[(s.t_host_ns - t0_us) // NS_PER_US for s in samples],
        force_n=[s.force_n for s in samples],
        torque_nm=[s.torque_nm for s in samples],
        status=[s.status for s in samples],
        temperature_c=[s.temperature_c for s in samples],
    )


def ft_sink(writer: RecordingWriter) -> Callable[[FtSample], None]:
    """An ``on_sample`` for :class:`~labrig.devices.bota.BotaSensor` that puts each sample into ``ft``.

    The sensor must stamp on the writer's clock (``BotaSensor(..., clock=writer.clock)``).
    """

    def put(sample: FtSample) -> None:
        put_ft(writer, sample)

    return put


def put_cnc(writer: RecordingWriter, sample: StatusSample, *, time_base_ns: int = 0) -> bool:
    """One GRBL status report into ``cnc``. ``time_base_ns``: the driver's ``time_base_ns``
    (its host times are us since then; 0: the host clock's own origin)."""
    row = sample.columns()
    row["t_host_us"] = sample.t_host_us - (writer.t0_host_ns - time_base_ns) // NS_PER_US
    return writer.put("cnc", **row)


def put_gcode(writer: RecordingWriter, t_host_us: int, direction: int, line: bytes, *, time_base_ns: int = 0) -> bool:
    """One line of the G-code conversation into ``gcode`` (``direction`` 0 sent, 1 received; at
    most 128 bytes kept). ``t_host_us`` in the driver's time base ``time_base_ns``."""
    t_us = t_host_us - (writer.t0_host_ns - time_base_ns) // NS_PER_US
    return writer.put("gcode", t_host_us=t_us, direction=direction, line=line[:128])


def put_chunk(writer: RecordingWriter, chunk: EventChunk) -> bool:
    """One camera chunk: its events into ``events`` (device time, and the chunk's host arrival
    time for the camera clock model fitted at finalization), its trigger edges into ``triggers``."""
    t_host_us = (chunk.t_host_ns - writer.t0_host_ns) // NS_PER_US
    ok = True
    events = chunk.events
    if events.size:
        ok = writer.put_events(events["x"], events["y"], events["p"], events["t"], t_host_us)
    if chunk.triggers.size:
        triggers = chunk.triggers
        ok = writer.put("triggers", t_device_us=triggers["t"], polarity=triggers["p"], channel=triggers["id"]) and ok
    return ok


@dataclass
class RecordStats:
    """What :func:`record_camera` moved: chunks, events, trigger edges, chunks the writer dropped."""

    chunks: int = 0
    events: int = 0
    triggers: int = 0
    rejected_chunks: int = 0


def record_camera(
    camera: Camera,
    writer: RecordingWriter,
    stop_event: threading.Event,
    *,
    poll_s: float = 0.05,
    on_chunk: Callable[[EventChunk], None] | None = None,
) -> RecordStats:
    """Move the camera's chunks into a recording (:func:`put_chunk`) until ``stop_event`` is set or the stream ends.

    Raises :class:`~labrig.devices.camera.CameraError` if the stream broke (what arrived before
    is in the writer). The camera and the writer must share the host clock. Starts the camera if
    it is not streaming; does not stop it.
    """
    if not camera.streaming:
        camera.start()
    stats = RecordStats()
    while not stop_event.is_set():
        chunk = camera.read(timeout_s=poll_s)
        if chunk is None:
            if camera.ended:
                break
            continue
        ok = put_chunk(writer, chunk)
        stats.chunks += 1
        stats.events += int(chunk.events.size)
        stats.triggers += int(chunk.triggers.size)
        stats.rejected_chunks += 0 if ok else 1
        if on_chunk is not None:
            on_chunk(chunk)
    return stats
