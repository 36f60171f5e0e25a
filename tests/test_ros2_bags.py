"""ROS 2 bags in and out (labrig.recording.ros2): a recording's round trip through a bag, the EVT 3.0 packets
against an independent decoder, and every bad input as one line."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_runner import run_labrig as run

from labrig.recording import Recording
from labrig.recording.ros2 import messages as M
from labrig.recording.ros2 import topics

pytest.importorskip("rosbags")

MP = pytest.MonkeyPatch
Cap = pytest.CaptureFixture[str]


@pytest.fixture(scope="module")
def exported(small_recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from labrig.recording.ros2.bag_export import export_bag

    out = tmp_path_factory.mktemp("bags") / "small.mcap"
    export_bag(small_recording, out)
    return out


def _events(rec: Recording) -> dict[str, np.ndarray]:
    return {c: rec.column("events", c) for c in ("x", "y", "p", "t_device_us")}


def test_export_then_import_gives_the_recording_back(small_recording: Path, tmp_path: Path, monkeypatch: MP,
                                                     capsys: Cap) -> None:
    bag = tmp_path / "run.mcap"
    code, out, err = run(monkeypatch, capsys, "export", small_recording, "--bag", bag, "--json")
    assert code == 0, err
    exported = json.loads(out)
    assert exported["events"] > 1_000_000 and 1.0 <= exported["packet_ms_mean"] <= 5.0
    assert bag.is_file() and not list(tmp_path.glob("*.partial*"))
    code, out, err = run(monkeypatch, capsys, "import", bag, tmp_path / "back.h5", "--json")
    assert code == 0, err
    imported = json.loads(out)
    assert imported["event_encoding"] == "evt3" and imported["topics"]["events"] == topics.EVENTS
    assert exported["cnc_status"] == exported["poses"] == imported["cnc_status"] == imported["poses"] > 0
    assert exported["gcode_lines"] == imported["gcode_lines"] > 0
    assert imported["topics"]["cnc_status"] == topics.CNC_STATUS and imported["topics"]["gcode"] == topics.GCODE
    with Recording(small_recording) as a, Recording(tmp_path / "back.h5") as b:
        for column, values in _events(a).items():
            assert np.array_equal(values, _events(b)[column]), column
        for stream in ("triggers", "trigger_out"):
            ours, theirs = a.stream(stream), b.stream(stream)
            assert ours["t_device_us" if stream == "triggers" else "t_host_us"].size > 0
            assert all(np.array_equal(ours[k], theirs[k]) for k in ours), stream
        fa, fb = a.ft(), b.ft()
        assert np.array_equal(fa["force_n"], fb["force_n"]) and np.array_equal(fa["torque_nm"], fb["torque_nm"])
        assert np.array_equal(fa["t_host_us"], fb["t_host_us"])
        assert np.abs(fa["t_us"] - fb["t_us"]).max() <= 1  # the sample times, through each one's F/T clock model
        assert np.array_equal(a.column("cnc", "t_host_us"), b.column("cnc", "t_host_us"))
        assert np.allclose(a.column("cnc", "position_mm"), b.column("cnc", "position_mm"), rtol=0, atol=1e-9)
        # the CNC's state and feed come back from /cnc/status, its G-code conversation from /cnc/gcode
        assert b"Run" in set(a.column("cnc", "state").tolist()) and np.nanmax(a.column("cnc", "feed_mm_min")) == 48
        assert np.array_equal(a.column("cnc", "state"), b.column("cnc", "state"))
        assert np.array_equal(a.column("cnc", "feed_mm_min"), b.column("cnc", "feed_mm_min"))
        assert a.rows("gcode") > 0 and all(np.array_equal(v, b.stream("gcode")[k]) for k, v in a.stream("gcode").items())
        assert a.phases() == b.phases() and len(a.phases()) > 3
        assert b.attrs["t0_host_ns"] == a.attrs["t0_host_ns"] and b.attrs["indenter"] == a.attrs["indenter"]
        assert b.attrs["indenter_definition"] == a.attrs["indenter_definition"] and b.attrs["rig"] == a.attrs["rig"]
        # the events' host times: the same camera clock model, fitted on the bag's packets
        ea, eb = a.events_between(0, 3e6), b.events_between(0, 3e6)
        assert ea.size == eb.size and np.abs(ea["t"] - eb["t"]).max() <= 1


def test_the_cnc_status_and_gcode_are_topics_of_their_own(exported: Path, small_recording: Path) -> None:
    """/cnc/status: one CncStatus per status report, at the pose's stamp, the state as GRBL reported it and the feed
    in m/s; /cnc/gcode: the lines sent (direction 0) and the answers (1), each at its host time."""
    from rosbags.rosbag2 import Reader

    store = M.typestore()
    got: dict[str, list[Any]] = {topics.CNC_STATUS: [], topics.POSE: [], topics.GCODE: []}
    with Reader(exported) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types[topics.CNC_STATUS] == M.CNC_STATUS and types[topics.GCODE] == M.GCODE_LINE
        connections = [c for c in reader.connections if c.topic in got]
        for connection, log_ns, raw in reader.messages(connections=connections):
            msg = store.deserialize_cdr(raw, connection.msgtype)
            got[connection.topic].append((log_ns, msg))
    with Recording(small_recording) as rec:
        t0, cnc, gcode = rec.attrs["t0_host_ns"], rec.stream("cnc"), rec.stream("gcode")
    status, poses = got[topics.CNC_STATUS], got[topics.POSE]
    assert len(status) == len(poses) == cnc["t_host_us"].size
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in status]
    assert stamps == [t0 + 1000 * t for t in cnc["t_host_us"].tolist()] == [log for log, _ in status]
    assert stamps == [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in poses]
    assert [m.state for _, m in status] == [v.decode() for v in cnc["state"].tolist()]
    assert all(m.header.frame_id == topics.CNC_FRAME for _, m in status)
    np.testing.assert_allclose([m.feed_m_s for _, m in status], cnc["feed_mm_min"].astype(np.float64) / 60_000, rtol=1e-12)
    assert max(m.feed_m_s for _, m in status) == pytest.approx(48 / 60_000)  # the synthetic run's 48 mm/min
    lines = got[topics.GCODE]
    assert [(m.direction, m.line) for _, m in lines] == [(d, v.decode()) for d, v in zip(gcode["direction"].tolist(),
                                                                                          gcode["line"].tolist())]
    assert [log for log, _ in lines] == [t0 + 1000 * t for t in gcode["t_host_us"].tolist()]
    assert lines[0][1].line.startswith("G1 ") and lines[0][1].direction == 0 and lines[1][1].line == "ok"


def test_the_packets_are_real_evt3(exported: Path, small_recording: Path) -> None:
    """The bag's EventPacket payloads, joined, decode with an independent EVT 3.0 decoder (the evt3 package)."""
    evt3 = pytest.importorskip("evt3")
    from rosbags.rosbag2 import Reader

    store = M.typestore()
    payloads, stamps, logs = [], [], []
    with Reader(exported) as reader:
        connections = [c for c in reader.connections if c.topic == topics.EVENTS]
        assert connections[0].msgtype == M.EVENT_PACKET
        for connection, log_ns, raw in reader.messages(connections=connections):
            msg = store.deserialize_cdr(raw, connection.msgtype)
            assert msg.encoding == "evt3" and msg.time_base == 0 and (msg.width, msg.height) == (1280, 720)
            payloads.append(msg.events.tobytes())
            stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
            logs.append(log_ns)
    assert all(s <= log for s, log in zip(stamps, logs)) and np.all(np.diff(logs) > 0)
    theirs = evt3.decode_bytes(b"".join(payloads))
    with Recording(small_recording) as rec:
        ours = _events(rec)
    np.testing.assert_array_equal(np.asarray(theirs.x), ours["x"])
    np.testing.assert_array_equal(np.asarray(theirs.y), ours["y"])
    np.testing.assert_array_equal(np.asarray(theirs.polarity), ours["p"])
    np.testing.assert_array_equal(np.asarray(theirs.timestamp).astype(np.int64), ours["t_device_us"])


def test_a_bag_folder_round_trips_too(small_recording: Path, tmp_path: Path) -> None:
    from labrig.recording.ros2.bag_export import export_bag
    from labrig.recording.ros2.bag_import import import_bag

    folder = tmp_path / "run_bag"
    export_bag(small_recording, folder, packet_us=5000)
    assert (folder / "metadata.yaml").is_file()
    summary = import_bag(folder, tmp_path / "back.h5")
    with Recording(small_recording) as a, Recording(tmp_path / "back.h5") as b:
        assert summary.events == a.n_events and np.array_equal(_events(a)["t_device_us"], _events(b)["t_device_us"])


# -- a lab's own bag, written with rosbags' own writer -------------------------------------------------


def write_lab_bag(recording: Path, bag: Path, *, encoding: str = "evt3", storage: str = "mcap",
                  epoch_ns: int = 1_700_000_000 * 10**9, usb_bytes: int = 8192, pose_as: str = "PoseStamped") -> None:
    """A bag as a lab's ROS 2 stack records one (rosbags' Writer, its own type store): the camera as the
    Metavision driver publishes it (evt3 cut at USB-transfer boundaries, not at word groups; or mono), the F/T
    as WrenchStamped, the CNC in metres, every stamp on the system clock (epoch ns). ``pose_as``: the CNC as
    ``PoseStamped`` on /arm/tool_pose, ``TransformStamped`` (child frame tool0) on /arm/tool_tf, or ``TFMessage``
    on /tf as a robot's tf broadcaster sends it: machine -> tool0 among other frames (base_link -> machine,
    machine -> camera_link), two transforms a message and a lone one between."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from labrig.devices.raw import Evt3Decoder, encode_evt3
    from labrig.eventtypes import EVENT_DTYPE

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(M.EVENT_PACKET_MSG, M.EVENT_PACKET))
    T = store.types
    with Recording(recording) as rec:
        events = np.zeros(rec.n_events, EVENT_DTYPE)
        for name, column in (("x", "x"), ("y", "y"), ("p", "p"), ("t", "t_device_us")):
            events[name] = rec.column("events", column)
        camera = rec.clock_model("camera")
        ft = rec.ft()
        cnc_t, cnc_p = rec.column("cnc", "t_host_us"), rec.column("cnc", "position_mm")

    def stamp(t_ns: int) -> Any:
        return T["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)

    def host_ns(device_us: int) -> int:
        return epoch_ns + int(camera.to_host_us_int(device_us)) * 1000

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(bag, version=8, storage_plugin=plugin) as writer:
        cam = writer.add_connection("/event_camera/events", M.EVENT_PACKET, typestore=store)
        packets: list[tuple[int, int, bytes, int]] = []  # (stamp, log, payload, time_base)
        if encoding == "evt3":
            payload = encode_evt3(events)
            decoder = Evt3Decoder(1280, 720)
            last_t = int(events["t"][0])
            for a in range(0, len(payload), usb_bytes):
                piece = payload[a:a + usb_bytes]
                got = decoder.feed(piece).events
                first_t = int(got["t"][0]) if got.size else last_t
                last_t = int(got["t"].max()) if got.size else last_t
                packets.append((host_ns(first_t) + 300_000, host_ns(last_t) + 500_000, piece, 0))
        else:
            for a in range(0, events.size, 4000):
                part = events[a:a + 4000]
                base_ns = int(part["t"][0]) * 1000
                dt = (part["t"].astype(np.uint64) * np.uint64(1000) - np.uint64(base_ns))
                words = (part["p"].astype(np.uint64) << np.uint64(63)) | (part["y"].astype(np.uint64) << np.uint64(48)) \
                    | (part["x"].astype(np.uint64) << np.uint64(32)) | dt
                packets.append((host_ns(int(part["t"][0])) + 300_000, host_ns(int(part["t"][-1])) + 500_000,
                                words.astype("<u8").tobytes(), base_ns))
        for seq, (t_stamp, t_log, piece, time_base) in enumerate(packets):
            msg = T[M.EVENT_PACKET](header=T["std_msgs/msg/Header"](stamp=stamp(t_stamp), frame_id="event_camera"),
                                    height=720, width=1280, seq=seq, time_base=time_base, encoding=encoding,
                                    is_bigendian=False, events=np.frombuffer(piece, np.uint8))
            writer.write(cam, t_log, store.serialize_cdr(msg, M.EVENT_PACKET))
        wrench = writer.add_connection("/bota/wrench", "geometry_msgs/msg/WrenchStamped", typestore=store)
        for t_us, t_host, f, tq in zip(ft["t_us"].tolist(), ft["t_host_us"].tolist(), ft["force_n"], ft["torque_nm"]):
            v = T["geometry_msgs/msg/Vector3"]
            msg = T["geometry_msgs/msg/WrenchStamped"](
                header=T["std_msgs/msg/Header"](stamp=stamp(epoch_ns + t_us * 1000), frame_id="bota"),
                wrench=T["geometry_msgs/msg/Wrench"](force=v(*map(float, f)), torque=v(*map(float, tq))))
            writer.write(wrench, epoch_ns + t_host * 1000, store.serialize_cdr(msg, "geometry_msgs/msg/WrenchStamped"))
        if pose_as == "PoseStamped":
            pose = writer.add_connection("/arm/tool_pose", "geometry_msgs/msg/PoseStamped", typestore=store)
            for t_us, p in zip(cnc_t.tolist(), cnc_p):
                msg = T["geometry_msgs/msg/PoseStamped"](
                    header=T["std_msgs/msg/Header"](stamp=stamp(epoch_ns + t_us * 1000), frame_id="machine"),
                    pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](*(float(v) / 1000 for v in p)),
                                                     orientation=T["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0)))
                writer.write(pose, epoch_ns + t_us * 1000, store.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))
            return

        def transform(t_ns: int, parent: str, child: str, xyz_m: Any) -> Any:
            return T["geometry_msgs/msg/TransformStamped"](
                header=T["std_msgs/msg/Header"](stamp=stamp(t_ns), frame_id=parent), child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](*map(float, xyz_m)),
                                                           rotation=T["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0)))

        tools = [(epoch_ns + t_us * 1000, transform(epoch_ns + t_us * 1000, "machine", "tool0", p / 1000))
                 for t_us, p in zip(cnc_t.tolist(), cnc_p)]
        if pose_as == "TransformStamped":
            tool_tf = writer.add_connection("/arm/tool_tf", "geometry_msgs/msg/TransformStamped", typestore=store)
            for t_ns, msg in tools:
                writer.write(tool_tf, t_ns, store.serialize_cdr(msg, "geometry_msgs/msg/TransformStamped"))
            return
        tf = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=store)
        for k, (t_ns, tool) in enumerate(tools):
            others = [transform(t_ns, "base_link", "machine", (0.1, 0.0, 0.5)), transform(t_ns, "machine", "camera_link",
                                                                                         (0.0, 0.0, -0.03))]
            writer.write(tf, t_ns, store.serialize_cdr(T["tf2_msgs/msg/TFMessage"](transforms=[others[k % 2], tool]),
                                                       "tf2_msgs/msg/TFMessage"))
            writer.write(tf, t_ns + 1000, store.serialize_cdr(T["tf2_msgs/msg/TFMessage"](transforms=[others[0]]),
                                                              "tf2_msgs/msg/TFMessage"))


@pytest.mark.parametrize(("encoding", "storage"), [("evt3", "mcap"), ("mono", "sqlite3")])
def test_a_labs_bag_imports(small_recording: Path, tmp_path: Path, encoding: str, storage: str, monkeypatch: MP,
                            capsys: Cap) -> None:
    bag = tmp_path / "lab_bag"
    write_lab_bag(small_recording, bag, encoding=encoding, storage=storage)
    code, out, err = run(monkeypatch, capsys, "import", bag, tmp_path / "lab.h5", "--events", "/event_camera/events",
                         "--wrench", "/bota/wrench", "--pose", "/arm/tool_pose", "--indenter", "sphere", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["event_encoding"] == encoding and summary["skipped_words"] == 0
    with Recording(small_recording) as a, Recording(tmp_path / "lab.h5") as b:
        assert all(np.array_equal(v, _events(b)[k]) for k, v in _events(a).items())
        assert np.array_equal(a.ft()["force_n"], b.ft()["force_n"]) and b.attrs["indenter"] == "sphere"
        assert np.allclose(a.column("cnc", "position_mm"), b.column("cnc", "position_mm"), rtol=0, atol=1e-9)
        # the origin is the earliest stamp: the host times keep their spacing
        assert np.array_equal(np.diff(a.column("cnc", "t_host_us")), np.diff(b.column("cnc", "t_host_us")))
        assert b.clock_model("camera").method == "envelope"
    code, out, err = run(monkeypatch, capsys, "inspect", tmp_path / "lab.h5", "--json")
    assert code == 0, err
    assert json.loads(out)["events"] == summary["events"] and json.loads(out)["ft_samples"] == summary["wrenches"]


@pytest.mark.parametrize("pose_as", ["TFMessage", "TransformStamped"])
def test_the_tool_pose_imports_from_tf_by_its_child_frame(small_recording: Path, tmp_path: Path, pose_as: str,
                                                          monkeypatch: MP, capsys: Cap) -> None:
    """A lab that records the tool only on /tf: --pose /tf --pose-frame tool0 takes the machine -> tool0 transforms
    among the robot's others; a TransformStamped topic is taken as it is."""
    bag = tmp_path / "lab.mcap"
    write_lab_bag(small_recording, bag, pose_as=pose_as)
    pose_topic = "/tf" if pose_as == "TFMessage" else "/arm/tool_tf"
    code, out, err = run(monkeypatch, capsys, "import", bag, tmp_path / "lab.h5", "--pose", pose_topic, "--pose-frame",
                         "tool0", "--json")
    assert code == 0, err
    summary = json.loads(out)
    with Recording(small_recording) as a, Recording(tmp_path / "lab.h5") as b:
        assert summary["poses"] == a.rows("cnc") == b.rows("cnc") and summary["topics"]["pose"] == pose_topic
        assert np.allclose(a.column("cnc", "position_mm"), b.column("cnc", "position_mm"), rtol=0, atol=1e-9)
        assert np.array_equal(np.diff(a.column("cnc", "t_host_us")), np.diff(b.column("cnc", "t_host_us")))
        assert b.attrs["extra_source_pose_frame"] == "tool0"


def test_a_tf_pose_frame_that_is_not_there_lists_the_frames_that_are(small_recording: Path, tmp_path: Path,
                                                                      monkeypatch: MP, capsys: Cap) -> None:
    bag = tmp_path / "lab.mcap"
    write_lab_bag(small_recording, bag, pose_as="TFMessage")
    cases = [
        (("--pose", "/tf", "--pose-frame", "tool_flange"),
         "/tf has no transform to the child frame 'tool_flange' (--pose-frame); its child frames: 'camera_link', "
         "'machine', 'tool0'"),
        (("--pose", "/tf"), "/tf holds transforms to 3 child frames ('camera_link', 'machine', 'tool0'); choose the "
                            "tool's with --pose-frame"),
        (("--pose-frame", "tool0"), "--pose-frame tool0: "),  # /tf is never taken by itself
        (("--pose", "/bota/wrench", "--pose-frame", "tool0"), "/bota/wrench is geometry_msgs/msg/WrenchStamped, not"),
    ]
    for args, expected in cases:
        code, out, err = run(monkeypatch, capsys, "import", bag, tmp_path / "a.h5", *args)
        assert code == 2, (args, out, err)
        line = " ".join(err.split())
        assert expected in line and "Traceback" not in err and err.strip().startswith("error:"), (args, err)
        assert not list(tmp_path.glob("a.h5*")), args


# -- one line for every bad input ----------------------------------------------------------------------


def test_bad_bags_and_topics_are_one_line(exported: Path, small_recording: Path, tmp_path: Path, monkeypatch: MP,
                                          capsys: Cap) -> None:
    not_a_bag = tmp_path / "notes.mcap"
    not_a_bag.write_text("hello")
    gap_bag = tmp_path / "gap"
    write_gap_bag(gap_bag)
    two_parents = tmp_path / "two_parents.mcap"
    write_gap_bag(two_parents, tool_parents=("machine", "world"))
    mono_bag = tmp_path / "evt2"
    write_lab_bag(small_recording, mono_bag, encoding="mono")
    _rename_encoding(mono_bag, tmp_path / "evt2.mcap")
    cases = [
        (("import", exported, tmp_path / "a.h5", "--events", "/camera/events"), "has no topic /camera/events"),
        (("import", exported, tmp_path / "a.h5", "--wrench", "/cnc/pose"), "/cnc/pose is geometry_msgs/msg/PoseStamped, not"),
        (("import", gap_bag, tmp_path / "a.h5"), "clock gap: /ft_sensor/wrench's stamps jump by +5.001 s at message 3"),
        (("import", tmp_path / "evt2.mcap", tmp_path / "a.h5"), "event encoding 'evt2' is not read by labrig"),
        (("import", small_recording, tmp_path / "a.h5", "--events", "/x"), "apply to a ROS 2 bag"),
        (("export", small_recording, "--bag", exported), "exists; choose another name or pass --overwrite"),
        (("export", small_recording), "give one of --raw"),
        (("import", exported, tmp_path / "a.h5", "--indenter", "no-such-indenter"), "no-such-indenter"),
        (("import", exported, tmp_path / "a.h5", "--pose-frame", "tool0"),
         "--pose-frame applies to a topic of transforms (tf2_msgs/msg/TFMessage or geometry_msgs/msg/TransformStamped); "
         "/cnc/pose is geometry_msgs/msg/PoseStamped"),
        (("import", two_parents, tmp_path / "a.h5", "--pose", "/tf", "--pose-frame", "tool0"),
         "/tf's transforms to 'tool0' come from 2 parent frames ('machine', 'world')"),
    ]
    for args, expected in cases:
        code, out, err = run(monkeypatch, capsys, *args)
        assert code == 2, (args, out, err)
        line = " ".join(err.split())
        assert expected in line and "Traceback" not in err and err.strip().startswith("error:"), (args, err)
        assert not (tmp_path / "a.h5").exists() and not list(tmp_path.glob("a.h5*")), args


def test_without_rosbags_the_commands_say_what_to_install(small_recording: Path, tmp_path: Path, monkeypatch: MP,
                                                          capsys: Cap) -> None:
    M.typestore.cache_clear()
    monkeypatch.setitem(sys.modules, "rosbags", None)
    try:
        code, _, err = run(monkeypatch, capsys, "export", small_recording, "--bag", tmp_path / "x.mcap")
    finally:
        M.typestore.cache_clear()
    assert code == 2 and "pip install 'labrig[ros2]'" in err and len(err.strip().splitlines()) <= 2


def write_gap_bag(path: Path, tool_parents: tuple[str, ...] = ()) -> None:
    """A minimal bag whose F/T stamps jump 5 s (the driver restarted, or the clock was set); with ``tool_parents``, a
    /tf whose transforms to tool0 come from each of those parent frames in turn."""
    from labrig.eventtypes import EVENT_DTYPE
    from labrig.recording.ros2 import mapping
    from labrig.recording.ros2.bagfile import BagWriter
    from labrig.recording.ros2.event_packets import PacketEncoder

    with BagWriter(path) as bag:
        bag.topic(topics.EVENTS, M.EVENT_PACKET)
        bag.topic(topics.WRENCH, M.WRENCH_STAMPED)
        encoder = PacketEncoder(1280, 720)
        for i in range(10):
            ev = np.zeros(3, EVENT_DTYPE)
            ev["t"] = 1000 * i + np.arange(3)
            t_ns = 10**9 + i * 10**6
            bag.write(topics.EVENTS, t_ns, mapping.event_packet(bag.store, t_ns, "cam", i, 1280, 720,
                                                                encoder.encode(ev, np.zeros(0, _trigger_dtype()))))
        for i in range(5):
            t_ns = 10**9 + i * 10**6 + (5 * 10**9 if i >= 3 else 0)
            bag.write(topics.WRENCH, t_ns, mapping.wrench_stamped(bag.store, t_ns, "ft", (0, 0, 1), (0, 0, 0)))
        if tool_parents:
            bag.topic("/tf", M.TF_MESSAGE)
            for i in range(4):
                t_ns = 10**9 + i * 10**6
                tool = M.typestore().types[M.TRANSFORM_STAMPED](
                    header=mapping.header(bag.store, t_ns, tool_parents[i % len(tool_parents)]), child_frame_id="tool0",
                    transform=bag.store.types["geometry_msgs/msg/Transform"](
                        translation=mapping.vector3(bag.store, (0, 0, 0.01)),
                        rotation=bag.store.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
                bag.write("/tf", t_ns, bag.store.types[M.TF_MESSAGE](transforms=[tool]))


def _trigger_dtype() -> np.dtype:
    from labrig.devices.raw import TRIGGER_DTYPE

    return TRIGGER_DTYPE


def _rename_encoding(bag: Path, out: Path) -> None:
    """Copy ``bag``'s camera topic into ``out`` with encoding 'evt2' (an encoding labrig does not read from a bag)."""
    from rosbags.rosbag2 import Reader

    from labrig.recording.ros2.bagfile import BagWriter

    store = M.typestore()
    with Reader(bag) as reader, BagWriter(out) as writer:
        writer.topic("/event_camera/events", M.EVENT_PACKET)
        connections = [c for c in reader.connections if c.topic == "/event_camera/events"]
        for n, (connection, log_ns, raw) in enumerate(reader.messages(connections=connections)):
            msg = store.deserialize_cdr(raw, connection.msgtype)
            msg.encoding = "evt2"
            writer.write("/event_camera/events", log_ns, msg)
            if n > 5:
                break


def test_a_labs_bag_runs_through_groundtruth_and_evaluate(sphere_press: Path, tmp_path: Path, monkeypatch: MP,
                                                          capsys: Cap) -> None:
    """The virtual rig's press as a lab's stack would record it (no labrig metadata, no phases, epoch stamps):
    import with the indenter and the rig file, then ground truth and the evaluation run on it."""
    from labrig.config import DEFAULT_RIG

    write_lab_bag(sphere_press, tmp_path / "lab.mcap")
    code, out, err = run(monkeypatch, capsys, "import", tmp_path / "lab.mcap", tmp_path / "lab.h5", "--indenter", "sphere",
                         "--rig", DEFAULT_RIG, "--json")
    assert code == 0, err
    assert json.loads(out)["phases"] == 0
    code, out, err = run(monkeypatch, capsys, "groundtruth", tmp_path / "lab.h5", "--json")
    assert code == 0, err
    assert (tmp_path / "lab.gt.h5").is_file()
    code, out, err = run(monkeypatch, capsys, "evaluate", tmp_path / "lab.h5", "--split", "all", "--workers", "1",
                         "--no-table1", "--out", tmp_path / "report", "--cache", tmp_path / "cache", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["recordings"] == 1 and summary["report_problems"] == []
    assert summary["force_z_mae_n"] is not None and summary["force_z_mae_n"] >= 0


def test_mono_and_trigger_words_decode_as_event_camera_codecs_lays_them_out() -> None:
    """mono: polarity bit 63, y 48-62, x 32-47, dt 0-31; trigger: edge 63, id 48-62, dt 0-31; t = time_base + dt (ns)."""
    from labrig.recording.ros2.event_packets import PacketDecoder, decode_mono, decode_trigger

    word = (1 << 63) | (719 << 48) | (1279 << 32) | 2_500
    events = decode_mono(np.array([word, 7 << 32], "<u8").tobytes(), time_base_ns=5_000_000)
    assert events.tolist() == [(1279, 719, 1, 5_002), (7, 0, 0, 5_000)]
    edges = decode_trigger(np.array([(1 << 63) | (3 << 48) | 1_000_999], "<u8").tobytes(), time_base_ns=0)
    assert edges.tolist() == [(1, 1_000, 3)]
    decoder = PacketDecoder("/cam")
    decoder.decode("mono", False, 0, np.array([word], "<u8").tobytes(), 1280, 720)
    from labrig.errors import LabrigError

    with pytest.raises(LabrigError, match="a packet in 'evt3' among packets in 'mono'"):
        decoder.decode("evt3", False, 0, b"", 1280, 720)
    with pytest.raises(LabrigError, match="big-endian"):
        PacketDecoder("/cam").decode("mono", True, 0, b"", 1280, 720)
