"""A labrig recording as a ROS 2 bag (``labrig export REC --bag OUT.mcap``).

Every message is stamped on the recording's host clock (``t0_host_ns`` + its host time): the camera's
packets with the receive time of their first recorded packet (as the Metavision driver stamps them) and
logged at their last one's (when the driver would publish); the F/T samples with their sample time
through the recording's F/T clock model, logged at their receive time; the CNC's status reports (its pose
on ``/cnc/pose``, its state and feed on ``/cnc/status``), its G-code conversation (``/cnc/gcode``),
phases and trigger edges at their host times. The recording's root metadata (indenter, rig, protocol, gel, source) travels
as JSON on ``/labrig/recording`` so that a labrig bag imports back whole.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.devices.raw import TRIGGER_DTYPE
from labrig.errors import LabrigError
from labrig.eventtypes import EVENT_DTYPE
from labrig.recording.reader import Recording
from labrig.recording.ros2 import mapping, topics
from labrig.recording.ros2 import messages as M
from labrig.recording.ros2.bagfile import BagWriter
from labrig.recording.ros2.event_packets import DEFAULT_PACKET_US, PacketEncoder, group_packets

#: ``progress(done, total, unit)``.
Progress = Callable[[int, int, str], None]
#: Event rows read from the recording at once.
READ_BLOCK_ROWS = 1 << 20
#: The EVK4's sensor (IMX636), for recordings that do not name their camera's size.
DEFAULT_SENSOR = (1280, 720)
#: Root attributes carried on ``/labrig/recording`` (and every ``extra_*``).
METADATA_KEYS = ("t0_host_ns", "indenter", "indenter_definition", "protocol", "rig", "gel", "created", "labrig_version")


@dataclass(frozen=True)
class BagExportSummary:
    """What :func:`export_bag` wrote: messages per topic, the camera packets' mean span (ms), bytes."""

    recording: str
    output: str
    events: int
    event_packets: int
    packet_ms_mean: float
    triggers: int
    wrenches: int
    poses: int
    cnc_status: int
    gcode_lines: int
    phases: int
    trigger_out: int
    messages: int
    output_bytes: int
    elapsed_s: float


def sensor_size(attrs: dict[str, Any]) -> tuple[int, int]:
    """The camera's (width, height) px: the recording's ``extra_camera_*``, else the EVK4's."""
    return (int(attrs.get("extra_camera_width", DEFAULT_SENSOR[0])), int(attrs.get("extra_camera_height", DEFAULT_SENSOR[1])))


def recording_metadata(attrs: dict[str, Any]) -> str:
    """The JSON text on ``/labrig/recording``: the root attributes a bag needs to import back whole."""
    keep = {k: v for k, v in attrs.items() if k in METADATA_KEYS or k.startswith("extra_")}
    return json.dumps(keep, sort_keys=True)


def _no_progress(done: int, total: int, unit: str) -> None:
    pass


def export_bag(recording: Path, output: Path, *, packet_us: int = DEFAULT_PACKET_US, overwrite: bool = False,
               progress: Progress | None = None) -> BagExportSummary:
    """Write ``recording`` as a ROS 2 bag in MCAP storage at ``output`` (see the module docstring)."""
    if not recording.exists():
        raise LabrigError(f"{recording}: no such recording")
    if packet_us <= 0:
        raise LabrigError("--packet-ms must be positive")
    report = progress or _no_progress
    start = time.perf_counter()
    with Recording(recording) as rec, BagWriter(output, overwrite=overwrite) as bag:
        attrs = rec.attrs
        t0 = int(attrs.get("t0_host_ns", 0))
        store = bag.store
        bag.topic(topics.RECORDING, M.STRING)
        bag.write(topics.RECORDING, t0, mapping.string(store, recording_metadata(attrs)))
        n_packets, span_us, n_triggers = _export_events(rec, bag, t0, packet_us, report)
        n_wrenches = _export_ft(rec, bag, t0)
        n_poses = _export_cnc(rec, bag, t0)
        n_gcode = _export_gcode(rec, bag, t0)
        n_phases = _export_phases(rec, bag, t0)
        n_out = _export_trigger_out(rec, bag, t0)
        n_events = rec.n_events
    return BagExportSummary(
        recording=str(recording), output=str(output), events=n_events, event_packets=n_packets,
        packet_ms_mean=span_us / n_packets / 1000 if n_packets else 0.0, triggers=n_triggers, wrenches=n_wrenches,
        poses=n_poses, cnc_status=n_poses, gcode_lines=n_gcode, phases=n_phases, trigger_out=n_out,
        messages=bag.messages, output_bytes=bag.bytes_written,
        elapsed_s=time.perf_counter() - start)


def _export_events(rec: Recording, bag: BagWriter, t0: int, packet_us: int, report: Progress) -> tuple[int, int, int]:
    """The camera's packets on ``/event_camera/events``: (messages, summed host span us, trigger edges)."""
    width, height = sensor_size(rec.attrs)
    packets = rec.stream("event_packets")
    groups = group_packets(packets["end_row"], packets["t_host_us"], packet_us)
    triggers = _camera_triggers(rec)
    bag.topic(topics.EVENTS, M.EVENT_PACKET)
    encoder = PacketEncoder(width, height)
    block: tuple[int, npt.NDArray[Any]] = (0, np.zeros(0, EVENT_DTYPE))
    k = span = 0
    total = rec.n_events
    report(0, total, "events")
    for seq, group in enumerate(groups):
        if group.end_row > block[0] + block[1].size:
            block = (group.first_row, _read_events(rec, group.first_row, max(group.end_row, group.first_row + READ_BLOCK_ROWS)))
        events = block[1][group.first_row - block[0]:group.end_row - block[0]]
        last = seq == len(groups) - 1
        k_end = triggers.size if last else int(np.searchsorted(triggers["t"], int(events["t"].max()), side="right"))
        payload = encoder.encode(events, triggers[k:max(k, k_end)])
        k = max(k, k_end)
        msg = mapping.event_packet(bag.store, mapping.host_ns(t0, group.first_host_us), topics.CAMERA_FRAME, seq, width,
                                   height, payload)
        bag.write(topics.EVENTS, mapping.host_ns(t0, group.last_host_us), msg)
        span += group.last_host_us - group.first_host_us
        if seq % 64 == 63 or last:
            report(group.end_row, total, "events")
    if not groups and triggers.size:  # trigger edges but no events: one packet of their own
        stamp = int(packets["t_host_us"][-1]) if packets["t_host_us"].size else 0
        payload = encoder.encode(np.zeros(0, EVENT_DTYPE), triggers)
        msg = mapping.event_packet(bag.store, mapping.host_ns(t0, stamp), topics.CAMERA_FRAME, 0, width, height, payload)
        bag.write(topics.EVENTS, mapping.host_ns(t0, stamp), msg)
        return 1, 0, int(triggers.size)
    return len(groups), span, int(triggers.size)


def _read_events(rec: Recording, a: int, b: int) -> npt.NDArray[Any]:
    b = min(b, rec.n_events)
    out = np.zeros(b - a, EVENT_DTYPE)
    for name, column in (("x", "x"), ("y", "y"), ("p", "p"), ("t", "t_device_us")):
        out[name] = rec.column("events", column, a, b)
    return out


def _camera_triggers(rec: Recording) -> npt.NDArray[Any]:
    rows = rec.stream("triggers")
    triggers = np.zeros(rows["t_device_us"].size, TRIGGER_DTYPE)
    triggers["t"], triggers["p"], triggers["id"] = rows["t_device_us"], rows["polarity"], rows["channel"]
    if np.any(triggers["id"] > 15):
        raise LabrigError(f"{rec.path}: EVT 3.0 carries trigger channels 0..15 only")
    return triggers[np.argsort(triggers["t"], kind="stable")]


def _export_ft(rec: Recording, bag: BagWriter, t0: int) -> int:
    if not rec.rows("ft"):
        return 0
    ft = rec.ft()
    bag.topic(topics.WRENCH, M.WRENCH_STAMPED)
    for t_us, t_host_us, force, torque in zip(ft["t_us"].tolist(), ft["t_host_us"].tolist(), ft["force_n"], ft["torque_nm"]):
        msg = mapping.wrench_stamped(bag.store, mapping.host_ns(t0, t_us), topics.FT_FRAME, force, torque)
        bag.write(topics.WRENCH, mapping.host_ns(t0, t_host_us), msg)
    return int(ft["t_us"].size)


def _export_cnc(rec: Recording, bag: BagWriter, t0: int) -> int:
    """Each status report twice, at its receive time: the position on ``/cnc/pose`` (a standard PoseStamped that
    Foxglove and RViz draw) and the state and feed on ``/cnc/status``. Returns the reports."""
    if not rec.rows("cnc"):
        return 0
    cnc = rec.stream("cnc")
    bag.topic(topics.POSE, M.POSE_STAMPED)
    bag.topic(topics.CNC_STATUS, M.CNC_STATUS)
    for t_us, p, state, feed in zip(cnc["t_host_us"].tolist(), cnc["position_mm"], cnc["state"].tolist(),
                                    cnc["feed_mm_min"].tolist()):
        t_ns = mapping.host_ns(t0, t_us)
        bag.write(topics.POSE, t_ns, mapping.pose_stamped(bag.store, t_ns, topics.CNC_FRAME, p))
        bag.write(topics.CNC_STATUS, t_ns, mapping.cnc_status(bag.store, t_ns, topics.CNC_FRAME, state, feed))
    return int(cnc["t_host_us"].size)


def _export_gcode(rec: Recording, bag: BagWriter, t0: int) -> int:
    """The G-code conversation on ``/cnc/gcode``, each line at the host time it was sent or received."""
    if not rec.rows("gcode"):
        return 0
    rows = rec.stream("gcode")
    bag.topic(topics.GCODE, M.GCODE_LINE)
    for t_us, direction, line in zip(rows["t_host_us"].tolist(), rows["direction"].tolist(), rows["line"].tolist()):
        t_ns = mapping.host_ns(t0, t_us)
        bag.write(topics.GCODE, t_ns, mapping.gcode_line(bag.store, t_ns, topics.CNC_FRAME, direction, line))
    return int(rows["t_host_us"].size)


def _export_phases(rec: Recording, bag: BagWriter, t0: int) -> int:
    phases = rec.phases()
    if not phases:
        return 0
    bag.topic(topics.PHASES, M.PHASE)
    for ph in phases:
        t_ns = mapping.host_ns(t0, ph.t_start_us)
        bag.write(topics.PHASES, t_ns, mapping.phase(bag.store, t_ns, mapping.host_ns(t0, ph.t_end_us), ph.name))
    return len(phases)


def _export_trigger_out(rec: Recording, bag: BagWriter, t0: int) -> int:
    if not rec.rows("trigger_out"):
        return 0
    rows = rec.stream("trigger_out")
    latest = rows.get("t_latest_host_us", np.full(rows["t_host_us"].size, mapping.UNKNOWN_LATEST_US))
    bag.topic(topics.TRIGGER_OUT, M.TRIGGER_EDGE)
    for t_us, polarity, t_latest in zip(rows["t_host_us"].tolist(), rows["polarity"].tolist(), latest.tolist()):
        t_ns = mapping.host_ns(t0, t_us)
        known = None if t_latest == mapping.UNKNOWN_LATEST_US else mapping.host_ns(t0, t_latest)
        bag.write(topics.TRIGGER_OUT, t_ns, mapping.trigger_edge(bag.store, t_ns, polarity, known))
    return int(rows["t_host_us"].size)
