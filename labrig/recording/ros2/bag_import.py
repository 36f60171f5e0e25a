"""A ROS 2 bag (MCAP file or bag folder) into a labrig recording (``labrig import BAG OUT.h5 --events TOPIC ...``).

What each topic becomes (docs/ros2.md):

* the camera's ``EventPacket`` topic: ``events`` and the camera's trigger edges (``evt3``; ``mono``);
  each message gives two clock pairs for the camera's model: its first event was received by its header
  stamp (the driver stamps the arrival of the message's first buffer), its last by its log time (the
  message was published after its last buffer arrived);
* a ``trigger``-encoded ``EventPacket`` topic (older drivers): the camera's trigger edges;
* a ``WrenchStamped`` topic: the ``ft`` stream (the F/T sensor's reading, in its own axes); the header
  stamp is the sample's clock (``t_device_us``), the log time its receive time (``t_host_us``);
* a ``PoseStamped`` or ``TransformStamped`` topic, or a ``TFMessage`` topic (``/tf``) with the tool's child
  frame: the ``cnc`` stream (the tool reference point in the machine frame, m -> mm), at its header stamps;
* labrig's ``CncStatus`` topic: the ``cnc`` stream's state and feed, each pose taking the latest report
  stamped at or before it; labrig's ``GcodeLine`` topic: the ``gcode`` stream;
* labrig's ``Phase`` and ``TriggerEdge`` topics: ``phases`` and ``trigger_out``; ``/labrig/recording``:
  the root metadata a labrig bag carries (its time origin, indenter, rig, protocol, gel).

The recording's time base starts at the bag's metadata ``t0_host_ns`` (a labrig bag) or at the earliest
stamp of the topics taken. Every problem (a topic missing or of another type, an encoding labrig does not
read, a clock gap) is one :class:`LabrigError`, and no recording is left behind.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.clock import ManualClock
from labrig.errors import LabrigError
from labrig.recording import schema
from labrig.recording.ros2 import mapping, topics
from labrig.recording.ros2 import messages as M
from labrig.recording.ros2.bagfile import open_bag
from labrig.recording.ros2.event_packets import PacketDecoder
from labrig.recording.writer import RecordingMetadata, RecordingWriter

Progress = Callable[[int, int, str], None]
NS_PER_US = 1000
#: A topic's header stamps may step back this much (ns) before it counts as a clock gap.
STEP_BACK_TOLERANCE_NS = 1_000_000
#: Events put into the recording writer but not yet written, at most (backpressure).
MAX_IN_FLIGHT_EVENTS = 1 << 22
#: The pose topics taken by themselves (the bag's one of these types); a ``TFMessage`` topic only when named.
POSE_TYPES = (M.POSE_STAMPED, M.TRANSFORM_STAMPED)
#: The streams read whole before the events (everything but the camera), in the order they are read.
SMALL_STREAMS = ("wrench", "pose", "cnc_status", "gcode", "phases", "trigger_out")


@dataclass(frozen=True)
class BagTopics:
    """The topics to take (None: the bag's one topic of the type, where it has exactly one; else none).

    ``pose_frame``: the tool's child frame, for a pose topic of transforms (a ``TFMessage`` such as ``/tf``, or
    ``TransformStamped``): only the transforms to it are taken (None: the topic's one child frame)."""

    events: str | None = None
    wrench: str | None = None
    pose: str | None = None  # PoseStamped, TransformStamped, or a TFMessage topic (never chosen by itself)
    phases: str | None = None
    triggers: str | None = None  # a trigger-encoded EventPacket topic (older drivers); never chosen by itself
    trigger_out: str | None = None
    cnc_status: str | None = None
    gcode: str | None = None
    pose_frame: str | None = None


@dataclass(frozen=True)
class BagImportSummary:
    """What :func:`import_bag` wrote: the topics taken (stream -> topic), rows per stream, the span (s), bytes."""

    source: str
    output: str
    topics: dict[str, str]
    event_encoding: str
    events: int
    triggers: int
    wrenches: int
    poses: int
    cnc_status: int
    gcode_lines: int
    phases: int
    trigger_out: int
    duration_s: float
    width_px: int
    height_px: int
    skipped_words: int
    output_bytes: int
    elapsed_s: float
    warnings: tuple[str, ...] = field(default_factory=tuple)


@dataclass(frozen=True)
class LabInputs:
    """What a lab's bag does not carry and ``groundtruth`` needs: the indenter (its name and TOML definition)
    and the rig file's text. Empty: not given (a labrig bag brings its own)."""

    indenter: str = ""
    indenter_toml: str = ""
    rig_toml: str = ""


def _no_progress(done: int, total: int, unit: str) -> None:
    pass


def import_bag(bag: Path, output: Path, wanted: BagTopics = BagTopics(), *, lab: LabInputs = LabInputs(),
               max_gap_s: float = 1.0, overwrite: bool = False, progress: Progress | None = None) -> BagImportSummary:
    """Convert the ROS 2 bag ``bag`` into the labrig recording ``output`` (see the module docstring)."""
    if output.exists() and not overwrite:
        raise LabrigError(f"{output} exists; choose another name or pass --overwrite")
    if max_gap_s <= 0:
        raise LabrigError("--max-gap-s must be positive")
    start = time.perf_counter()
    reader = open_bag(bag)
    try:
        chosen = resolve_topics(bag, _topic_types(reader), wanted)
        small = _read_small_topics(bag, reader, chosen, wanted.pose_frame)
        meta = _metadata(reader)
        first_event_ns, width, height = _first_packet(reader, chosen["events"])
        if width and height:
            meta = {**meta, "extra_camera_width": width, "extra_camera_height": height}
        for name in ("wrench", "pose"):
            if name in chosen:
                check_stamps(chosen[name], small[name]["stamp_ns"], max_gap_s)
        check_overlap(chosen, small, first_event_ns, max_gap_s)
        t0 = int(meta["t0_host_ns"]) if "t0_host_ns" in meta else _earliest(small, first_event_ns, reader)
        summary = _write(bag, output, reader, chosen, small, meta, lab, t0, max_gap_s, overwrite, progress or _no_progress,
                         wanted.pose_frame)
    finally:
        reader.close()
    return BagImportSummary(**{**summary, "elapsed_s": time.perf_counter() - start})


def topic_messages(reader: Any, topic: str, msgtypes: tuple[str, ...] = ()) -> Iterator[tuple[Any, int, Any]]:
    """(connection, log time ns, raw CDR) of ``topic``'s messages (of ``msgtypes``, if given) in log-time order;
    nothing when the bag has no such topic (rosbags reads every topic for an empty list)."""
    connections = [c for c in reader.connections if c.topic == topic and (not msgtypes or c.msgtype in msgtypes)]
    if connections:
        yield from reader.messages(connections=connections)


def _topic_types(reader: Any) -> dict[str, str]:
    return {c.topic: c.msgtype for c in reader.connections}


def resolve_topics(bag: Path, available: dict[str, str], wanted: BagTopics) -> dict[str, str]:
    """stream -> topic for the topics given or found; a :class:`LabrigError` for one missing or of another type."""
    kinds: dict[str, tuple[tuple[str, ...], str]] = {
        "events": ((M.EVENT_PACKET,), "--events"), "wrench": ((M.WRENCH_STAMPED,), "--wrench"),
        "pose": ((*POSE_TYPES, M.TF_MESSAGE), "--pose"), "cnc_status": ((M.CNC_STATUS,), "--cnc-status"),
        "gcode": ((M.GCODE_LINE,), "--gcode"), "phases": ((M.PHASE,), "--phases"),
        "triggers": ((M.EVENT_PACKET,), "--triggers"), "trigger_out": ((M.TRIGGER_EDGE,), "--trigger-out")}
    listing = ", ".join(f"{t} ({m})" for t, m in sorted(available.items())) or "none"
    chosen: dict[str, str] = {}
    for stream, (types, option) in kinds.items():
        topic = getattr(wanted, stream)
        if topic is not None:
            if topic not in available:
                raise LabrigError(f"{bag} has no topic {topic} ({option}); its topics: {listing}")
            if available[topic] not in types:
                raise LabrigError(f"{bag}: {topic} is {available[topic]}, not {' or '.join(types)}; give another {option}")
            chosen[stream] = topic
            continue
        if stream == "triggers":
            continue
        if stream == "pose":
            types = POSE_TYPES  # /tf holds every frame of the robot: taken only when named
        candidates = sorted(t for t, m in available.items() if m in types and t not in chosen.values())
        if len(candidates) == 1:
            chosen[stream] = candidates[0]
        elif len(candidates) > 1:
            raise LabrigError(f"{bag} has {len(candidates)} {types[0]} topics ({', '.join(candidates)}); choose one "
                              f"with {option}")
    if "events" not in chosen:
        raise LabrigError(f"{bag} has no {M.EVENT_PACKET} topic (the camera's events); its topics: {listing}")
    if chosen.get("triggers") == chosen["events"]:
        raise LabrigError(f"{bag}: --triggers and --events name the same topic {chosen['events']}")
    if wanted.pose_frame is not None:
        if "pose" not in chosen:
            raise LabrigError(f"--pose-frame {wanted.pose_frame}: {bag} has no pose topic taken; name the topic of "
                              f"transforms with --pose (e.g. --pose /tf)")
        if available[chosen["pose"]] == M.POSE_STAMPED:
            raise LabrigError(f"--pose-frame applies to a topic of transforms ({M.TF_MESSAGE} or "
                              f"{M.TRANSFORM_STAMPED}); {chosen['pose']} is {M.POSE_STAMPED}, which has no child frame")
    return chosen


def _read_small_topics(bag: Path, reader: Any, chosen: dict[str, str], pose_frame: str | None
                       ) -> dict[str, dict[str, Any]]:
    """Every topic but the events, as arrays: stamps and log times (ns) and the values."""
    store = M.typestore()
    out: dict[str, dict[str, Any]] = {}
    for stream in SMALL_STREAMS:
        if stream not in chosen:
            continue
        rows: dict[str, list[Any]] = {"stamp_ns": [], "log_ns": [], "values": []}
        stamped = _tool_transforms(bag, chosen[stream], reader, pose_frame) if stream == "pose" else (
            (store.deserialize_cdr(raw, connection.msgtype), int(log_ns))
            for connection, log_ns, raw in topic_messages(reader, chosen[stream]))
        for msg, log_ns in stamped:
            rows["stamp_ns"].append(mapping.stamp_ns(msg.header.stamp))
            rows["log_ns"].append(log_ns)
            rows["values"].append(_values(stream, msg))
        stamps, log_times = np.array(rows["stamp_ns"], np.int64), np.array(rows["log_ns"], np.int64)
        order = np.argsort(stamps, kind="stable")  # the bag gives them in log-time order; a sample goes where its stamp puts it
        out[stream] = {"stamp_ns": stamps[order], "log_ns": log_times[order], "values": [rows["values"][i] for i in order]}
    return out


def _tool_transforms(bag: Path, topic: str, reader: Any, pose_frame: str | None) -> list[tuple[Any, int]]:
    """(pose message, log time ns) of the tool on a pose topic: every ``PoseStamped``; the ``TransformStamped``
    messages, alone or in a ``TFMessage`` (``/tf``), whose ``child_frame_id`` is ``pose_frame`` (None: the topic's
    one child frame). A :class:`LabrigError` that lists the child frames there are when the frame is not among
    them, or when none is given and there are several; and when the tool's transforms come from several parents."""
    store = M.typestore()
    poses: list[tuple[Any, int]] = []
    by_child: dict[str, list[tuple[Any, int]]] = {}
    for connection, log_ns, raw in topic_messages(reader, topic):
        msg = store.deserialize_cdr(raw, connection.msgtype)
        if connection.msgtype == M.POSE_STAMPED:
            poses.append((msg, int(log_ns)))
            continue
        for transform in (msg.transforms if connection.msgtype == M.TF_MESSAGE else (msg,)):
            child = str(transform.child_frame_id)
            kept = by_child.setdefault(child, [])
            if pose_frame is None or child == pose_frame:
                kept.append((transform, int(log_ns)))
    if not by_child:  # PoseStamped (resolve_topics refused --pose-frame for it), or no transforms at all
        if pose_frame is not None:
            raise LabrigError(f"{bag}: {topic} has no transform to the child frame {pose_frame!r} (--pose-frame); "
                              "it holds no transforms")
        return poses
    frames = sorted(by_child)
    listing = ", ".join(repr(f) for f in frames)
    if pose_frame is None:
        if len(frames) > 1:
            raise LabrigError(f"{bag}: {topic} holds transforms to {len(frames)} child frames ({listing}); choose the "
                              "tool's with --pose-frame")
        pose_frame = frames[0]
    if pose_frame not in by_child:
        raise LabrigError(f"{bag}: {topic} has no transform to the child frame {pose_frame!r} (--pose-frame); "
                          f"its child frames: {listing}")
    kept = by_child[pose_frame]
    parents = sorted({str(msg.header.frame_id) for msg, _ in kept})
    if len(parents) > 1:
        raise LabrigError(f"{bag}: {topic}'s transforms to {pose_frame!r} come from {len(parents)} parent frames "
                          f"({', '.join(repr(p) for p in parents)}); labrig takes the tool's pose in one frame")
    return kept


def _values(stream: str, msg: Any) -> Any:
    if stream == "wrench":
        return mapping.wrench_values(msg)
    if stream == "pose":
        return mapping.position_mm(msg), mapping.is_rotated(msg)
    if stream == "cnc_status":
        return mapping.cnc_status_values(msg)
    if stream == "gcode":
        return mapping.gcode_values(msg)
    if stream == "phases":
        return msg.name, mapping.stamp_ns(msg.end)
    return int(msg.polarity), mapping.stamp_ns(msg.latest) if msg.latest_known else None


def _metadata(reader: Any) -> dict[str, Any]:
    """The root metadata a labrig bag carries on ``/labrig/recording`` ({} for a lab's own bag)."""
    for connection, _, raw in topic_messages(reader, topics.RECORDING, (M.STRING,)):
        try:
            data = json.loads(M.typestore().deserialize_cdr(raw, connection.msgtype).data)
        except json.JSONDecodeError:
            return {}
        return data if isinstance(data, dict) else {}
    return {}


def _first_packet(reader: Any, topic: str) -> tuple[int | None, int, int]:
    """(header stamp ns, width px, height px) of the camera topic's first message ((None, 0, 0): it has none)."""
    for connection, _, raw in topic_messages(reader, topic):
        msg = M.typestore().deserialize_cdr(raw, connection.msgtype)
        return mapping.stamp_ns(msg.header.stamp), int(msg.width), int(msg.height)
    return None, 0, 0


def _earliest(small: dict[str, dict[str, Any]], first_event_ns: int | None, reader: Any) -> int:
    """The time origin of a lab's bag: the earliest stamp of the topics taken (ns)."""
    firsts = [int(s["stamp_ns"].min()) for s in small.values() if s["stamp_ns"].size]
    if first_event_ns is not None:
        firsts.append(first_event_ns)
    return min(firsts) if firsts else int(reader.start_time)


def check_stamps(topic: str, stamp_ns: npt.NDArray[np.int64], max_gap_s: float) -> None:
    """Refuse a topic whose header stamps jump forward by more than ``max_gap_s`` or step back (a clock gap:
    the driver restarted, the host clock was set)."""
    if stamp_ns.size < 2:
        return
    steps = np.diff(stamp_ns)
    bad = np.flatnonzero((steps > max_gap_s * 1e9) | (steps < -STEP_BACK_TOLERANCE_NS))
    if bad.size:
        i = int(bad[0])
        raise LabrigError(gap_message(topic, i + 1, int(steps[i]), int(stamp_ns[i] - stamp_ns[0]), max_gap_s))


def gap_message(topic: str, index: int, step_ns: int, at_ns: int, max_gap_s: float) -> str:
    return (f"clock gap: {topic}'s stamps jump by {step_ns / 1e9:+.3f} s at message {index} ({at_ns / 1e9:.3f} s in); "
            f"labrig takes one continuous run on one host clock: split the bag there (ros2 bag convert), or pass "
            f"--max-gap-s above {abs(step_ns) / 1e9:.3g} if the silence is real (now {max_gap_s:g} s)")


def check_overlap(chosen: dict[str, str], small: dict[str, dict[str, Any]], first_event_ns: int | None,
                  max_gap_s: float) -> None:
    """Refuse topics whose stamps do not overlap the camera's (they are not on one host clock)."""
    if first_event_ns is None:
        return
    for stream in ("wrench", "pose"):
        if stream not in small or not small[stream]["stamp_ns"].size:
            continue
        first, last = int(small[stream]["stamp_ns"][0]), int(small[stream]["stamp_ns"][-1])
        if first_event_ns > last + max_gap_s * 1e9 or first_event_ns < first - max_gap_s * 1e9 - _span(small, stream):
            raise LabrigError(
                f"clock gap: {chosen[stream]} is stamped {first / 1e9:.3f}-{last / 1e9:.3f} s and {chosen['events']} "
                f"from {first_event_ns / 1e9:.3f} s: they are not on one host clock; stamp both with the host's clock")


def _span(small: dict[str, dict[str, Any]], stream: str) -> int:
    stamps = small[stream]["stamp_ns"]
    return int(stamps[-1] - stamps[0]) if stamps.size else 0


def _lab_metadata(meta: dict[str, Any], lab: LabInputs, bag: Path, chosen: dict[str, str],
                  pose_frame: str | None = None) -> RecordingMetadata:
    """The recording's metadata: the labrig bag's own, with what the command line gives on top."""
    extra: dict[str, str | int | float | bool] = {
        k[len("extra_"):]: v for k, v in meta.items() if k.startswith("extra_") and isinstance(v, str | int | float | bool)}
    extra.update({"source_bag": str(bag), "source_format": "ros2-bag", "source_topics": json.dumps(chosen, sort_keys=True),
                  "host_time": "the bag's header stamps and log times, ns, less t0_host_ns"})
    if pose_frame is not None:
        extra["source_pose_frame"] = pose_frame
    return RecordingMetadata(
        indenter=lab.indenter or str(meta.get("indenter", "")),
        indenter_toml=lab.indenter_toml or (str(meta.get("indenter_definition", "")) if not lab.indenter else ""),
        protocol_toml=str(meta.get("protocol", "")), rig_toml=lab.rig_toml or str(meta.get("rig", "")),
        gel_toml=str(meta.get("gel", "")), extra=extra)


def _write(bag: Path, output: Path, reader: Any, chosen: dict[str, str], small: dict[str, dict[str, Any]],
           meta: dict[str, Any], lab: LabInputs, t0: int, max_gap_s: float, overwrite: bool,
           progress: Progress, pose_frame: str | None) -> dict[str, Any]:
    clock = ManualClock(t0)
    writer = RecordingWriter(output, _lab_metadata(meta, lab, bag, chosen, pose_frame), clock=clock, overwrite=overwrite,
                             wake_on_put=False)
    warnings: list[str] = []
    writer.open()
    try:
        camera = _put_events(reader, writer, chosen, t0, max_gap_s, progress)
        n_triggers = camera["triggers"]
        if "triggers" in chosen:
            n_triggers += _put_trigger_topic(reader, writer, chosen["triggers"])
        counts = _put_small(writer, small, t0, warnings, chosen)
        clock.set_ns(max(t0, camera["last_ns"], *(int(s["log_ns"].max()) for s in small.values() if s["log_ns"].size)))
    except BaseException:
        writer.close(schema.EXIT_ABORTED, "import failed", raise_on_fault=False)
        for path in (output, writer.partial):
            path.unlink(missing_ok=True)
        raise
    result = writer.close()
    if sum(result.dropped.values()):
        output.unlink(missing_ok=True)
        raise LabrigError(f"{sum(result.dropped.values())} rows could not be written to {output}")
    return {
        "source": str(bag), "output": str(output), "topics": dict(chosen), "event_encoding": camera["encoding"],
        "events": camera["events"], "triggers": n_triggers, "wrenches": counts["wrench"], "poses": counts["pose"],
        "cnc_status": counts["cnc_status"], "gcode_lines": counts["gcode"], "phases": counts["phases"],
        "trigger_out": counts["trigger_out"],
        "duration_s": (camera["last_ns"] - camera["first_ns"]) / 1e9 if camera["events"] else 0.0,
        "width_px": camera["width"], "height_px": camera["height"], "skipped_words": camera["skipped_words"],
        "output_bytes": output.stat().st_size, "warnings": tuple(warnings)}


def _put(writer: RecordingWriter, stream: str, **columns: Any) -> None:
    while not writer.put(stream, **columns):
        if writer.fault:
            raise LabrigError(f"writing {writer.path} failed: {writer.fault}")
        time.sleep(0.01)


def _put_events(reader: Any, writer: RecordingWriter, chosen: dict[str, str], t0: int, max_gap_s: float,
                progress: Progress) -> dict[str, Any]:
    """The camera topic into ``events`` (and its trigger edges into ``triggers``), two clock pairs a message."""
    store = M.typestore()
    topic = chosen["events"]
    total = sum(c.msgcount for c in reader.connections if c.topic == topic)
    decoder = PacketDecoder(topic)
    n_events = n_triggers = done = 0
    first_ns = last_ns = previous_ns = None
    width = height = 0
    progress(0, total, "messages")
    for connection, log_ns, raw in topic_messages(reader, topic):
        msg = store.deserialize_cdr(raw, connection.msgtype)
        stamp = mapping.stamp_ns(msg.header.stamp)
        if previous_ns is not None and (stamp - previous_ns > max_gap_s * 1e9 or stamp - previous_ns < -STEP_BACK_TOLERANCE_NS):
            raise LabrigError(gap_message(topic, done, stamp - previous_ns, previous_ns - (first_ns or previous_ns), max_gap_s))
        previous_ns = stamp
        first_ns = stamp if first_ns is None else first_ns
        last_ns = max(int(log_ns), last_ns or 0)
        width, height = int(msg.width), int(msg.height)
        packet = decoder.decode(msg.encoding, bool(msg.is_bigendian), int(msg.time_base), msg.events.tobytes(), width, height)
        if decoder.encoding == "trigger":
            raise LabrigError(f"{topic} holds trigger edges (encoding 'trigger'), not events; give it as --triggers "
                              "and the camera's event topic as --events")
        n_events += _put_packet(writer, packet.events, (stamp - t0) // NS_PER_US, (int(log_ns) - t0) // NS_PER_US, n_events)
        if packet.triggers.size:
            _put(writer, "triggers", t_device_us=packet.triggers["t"], polarity=packet.triggers["p"],
                 channel=packet.triggers["id"])
            n_triggers += packet.triggers.size
        done += 1
        if done % 256 == 0:
            progress(done, total, "messages")
    decoder.finish()
    progress(done, total, "messages")
    return {"events": n_events, "triggers": n_triggers, "encoding": decoder.encoding or "", "width": width,
            "height": height, "first_ns": first_ns or t0, "last_ns": last_ns or t0, "skipped_words": decoder.skipped_words}


def _put_packet(writer: RecordingWriter, events: npt.NDArray[Any], stamp_us: int, log_us: int, put_so_far: int) -> int:
    """One message's events as two recorded packets: its first event, received by the header stamp; the rest,
    received by the log time. Returns the events put."""
    if not events.size:
        return 0
    while put_so_far - writer.stats["events"].rows_written > MAX_IN_FLIGHT_EVENTS and not writer.fault:
        time.sleep(0.002)
    for part, host_us in ((events[:1], stamp_us), (events[1:], max(log_us, stamp_us))):
        if not part.size:
            continue
        while not writer.put_events(part["x"], part["y"], part["p"], part["t"], int(host_us)):
            if writer.fault:
                raise LabrigError(f"writing {writer.path} failed: {writer.fault}")
            time.sleep(0.01)
    return int(events.size)


def _put_trigger_topic(reader: Any, writer: RecordingWriter, topic: str) -> int:
    store = M.typestore()
    decoder = PacketDecoder(topic)
    n = 0
    for connection, _, raw in topic_messages(reader, topic):
        msg = store.deserialize_cdr(raw, connection.msgtype)
        packet = decoder.decode(msg.encoding, bool(msg.is_bigendian), int(msg.time_base), msg.events.tobytes(),
                                int(msg.width), int(msg.height))
        if decoder.encoding != "trigger":
            raise LabrigError(f"{topic} is in encoding {decoder.encoding!r}, not 'trigger'; give it as --events")
        if packet.triggers.size:
            _put(writer, "triggers", t_device_us=packet.triggers["t"], polarity=packet.triggers["p"],
                 channel=np.minimum(packet.triggers["id"], 255))
            n += packet.triggers.size
    return n


def _put_small(writer: RecordingWriter, small: dict[str, dict[str, Any]], t0: int, warnings: list[str],
               chosen: dict[str, str]) -> dict[str, int]:
    counts = dict.fromkeys(SMALL_STREAMS, 0)
    if "wrench" in small and small["wrench"]["stamp_ns"].size:
        s = small["wrench"]
        device_us = ((s["stamp_ns"] - s["stamp_ns"].min()) // NS_PER_US) % (1 << 32)
        force = np.array([v[0] for v in s["values"]], np.float32)
        torque = np.array([v[1] for v in s["values"]], np.float32)
        n = device_us.size
        _put(writer, "ft", t_device_us=device_us.astype(np.uint32), t_host_us=(s["log_ns"] - t0) // NS_PER_US,
             force_n=force, torque_nm=torque, status=np.zeros(n, np.uint16), temperature_c=np.full(n, np.nan, np.float32))
        counts["wrench"] = n
    if "pose" in small and small["pose"]["stamp_ns"].size:
        s = small["pose"]
        position = np.array([v[0] for v in s["values"]], np.float64)
        if any(v[1] for v in s["values"]):
            warnings.append(f"{chosen['pose']} turns the tool; labrig keeps its position only (the CNC translates)")
        state, feed = cnc_status_at(s["stamp_ns"], small.get("cnc_status"))
        _put(writer, "cnc", t_host_us=(s["stamp_ns"] - t0) // NS_PER_US, position_mm=position, feed_mm_min=feed,
             state=state)
        counts["pose"] = position.shape[0]
    if "cnc_status" in small:
        counts["cnc_status"] = int(small["cnc_status"]["stamp_ns"].size)
        if "pose" not in small and counts["cnc_status"]:
            warnings.append(f"{chosen['cnc_status']} is left out: the CNC's state and feed go with its pose, and no "
                            "pose topic was taken (--pose)")
    if "gcode" in small and small["gcode"]["stamp_ns"].size:
        s = small["gcode"]
        _put(writer, "gcode", t_host_us=(s["stamp_ns"] - t0) // NS_PER_US,
             direction=np.array([v[0] for v in s["values"]], np.uint8), line=np.array([v[1] for v in s["values"]], "S128"))
        counts["gcode"] = int(s["stamp_ns"].size)
    if "phases" in small:
        s = small["phases"]
        for start_ns, (name, end_ns) in zip(s["stamp_ns"].tolist(), s["values"]):
            writer.phase_begin(str(name), (start_ns - t0) // NS_PER_US)
            writer.phase_end((end_ns - t0) // NS_PER_US)
        counts["phases"] = int(s["stamp_ns"].size)
    if "trigger_out" in small and small["trigger_out"]["stamp_ns"].size:
        s = small["trigger_out"]
        latest = np.array([mapping.UNKNOWN_LATEST_US if v[1] is None else (v[1] - t0) // NS_PER_US for v in s["values"]],
                          np.int64)
        _put(writer, "trigger_out", t_host_us=(s["stamp_ns"] - t0) // NS_PER_US,
             polarity=np.array([v[0] for v in s["values"]], np.uint8), t_latest_host_us=latest)
        counts["trigger_out"] = int(s["stamp_ns"].size)
    return counts


def cnc_status_at(pose_stamp_ns: npt.NDArray[np.int64], status: dict[str, Any] | None
                  ) -> tuple[npt.NDArray[Any], npt.NDArray[np.float32]]:
    """(state S16, feed mm/min) of each pose: the latest ``CncStatus`` stamped at or before it (a labrig bag stamps
    both with the report's receive time); ``b""`` and NaN where no report came before, or none was taken."""
    n = pose_stamp_ns.size
    state, feed = np.full(n, b"", "S16"), np.full(n, np.nan, np.float32)
    if status is None or not status["stamp_ns"].size:
        return state, feed
    latest = np.searchsorted(status["stamp_ns"], pose_stamp_ns, side="right") - 1
    known = latest >= 0
    state[known] = np.array([status["values"][i][0] for i in latest[known]], "S16")
    feed[known] = np.array([status["values"][i][1] for i in latest[known]], np.float32)
    return state, feed
