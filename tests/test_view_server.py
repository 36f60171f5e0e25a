"""The live view server (labrig run --live --view-server): a headless WebSocket client subscribes and checks the
channels, their schemas, what the messages hold and their rates."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.errors import LabrigError
from labrig.indenters import Indenter
from labrig.pipeline.ros2_messages import point_cloud_columns
from labrig.pipeline.runtime import WindowResult
from labrig.recording.ros2 import messages as M
from labrig.recording.ros2 import topics

pytest.importorskip("foxglove")
pytest.importorskip("websockets")
pytest.importorskip("rosbags")

pytestmark = pytest.mark.serial  # rates against the wall clock

ROOT = Path(__file__).resolve().parents[1]
CHANNELS = {topics.FORCE_FIELD: M.POINT_CLOUD2, topics.NET_FORCE: M.WRENCH_STAMPED, topics.DEPTH: M.IMAGE,
            topics.TRACKS: M.POINT_CLOUD2, topics.WRENCH: M.WRENCH_STAMPED}
M_MARKERS = 156


def _window(i: int) -> WindowResult:
    forces = np.zeros((M_MARKERS, 3))
    forces[:, 2] = -0.01 * i
    return WindowResult(i, i * 10_000, (i + 1) * 10_000, 1000, np.full((M_MARKERS, 2), 100.0 + i), np.ones(M_MARKERS, bool),
                        np.full((M_MARKERS, 3), 0.001 * i), forces, forces.sum(axis=0), np.full(2, np.nan),
                        np.full(2, np.nan), np.full((90, 112), 0.01 * i, np.float32))


def test_the_server_streams_every_window_at_the_pipelines_rate() -> None:
    from labrig.live.view_server import ViewServer
    from labrig.testing.foxglove_client import FoxgloveClient

    rest = np.random.default_rng(0).normal(size=(M_MARKERS, 3))
    with ViewServer(rest, port=0) as server, FoxgloveClient(server.url, keep_payloads=True) as client:
        assert {t: r.schema_name for t, r in client.topics.items()} == CHANNELS
        assert all(r.encoding == "cdr" for r in client.topics.values())
        start = time.monotonic()
        for i in range(200):  # 100 windows a second, as 10 ms windows come
            server.publish(_window(i))
            if i % 10 == 0:
                server.publish_wrench((0.0, 0.0, -1.0 - i))
            time.sleep(max(0.0, start + (i + 1) * 0.01 - time.monotonic()))
        deadline = time.monotonic() + 5
        while len(client.topics[topics.FORCE_FIELD].arrivals_s) < 200 and time.monotonic() < deadline:
            time.sleep(0.02)
    stats = server.stats()
    assert stats.windows_published == 200 and stats.windows_skipped == 0 and stats.wrenches_published == 20
    for topic in (topics.FORCE_FIELD, topics.NET_FORCE, topics.DEPTH, topics.TRACKS):
        received = client.topics[topic]
        assert len(received.arrivals_s) == 200, topic
        assert received.rate_hz() == pytest.approx(100, rel=0.15), topic
        assert np.all(np.diff(received.log_times_ns) > 0)
    assert len(client.topics[topics.WRENCH].arrivals_s) == 20
    store = M.typestore()  # the payloads decode as the ROS 2 messages they claim to be
    field = store.deserialize_cdr(client.topics[topics.FORCE_FIELD].payloads[150], M.POINT_CLOUD2)
    columns = point_cloud_columns(field)
    assert np.allclose(columns["x"], (rest[:, 0] + 0.150) / 1000, atol=1e-7) and np.allclose(columns["fz"], -1.5)
    net = store.deserialize_cdr(client.topics[topics.NET_FORCE].payloads[150], M.WRENCH_STAMPED)
    assert net.wrench.force.z == pytest.approx(-1.5 * M_MARKERS) and net.header.frame_id == topics.GEL_FRAME
    depth = store.deserialize_cdr(client.topics[topics.DEPTH].payloads[150], M.IMAGE)
    assert np.allclose(np.asarray(depth.data, np.uint8).view("<f4"), 1.5)
    ft = store.deserialize_cdr(client.topics[topics.WRENCH].payloads[-1], M.WRENCH_STAMPED)
    assert ft.wrench.force.z == -191.0 and ft.header.frame_id == topics.FT_FRAME


def test_a_slow_view_drops_its_oldest_windows_never_the_pipelines_time() -> None:
    """publish() never blocks: windows beyond the short queue push the oldest out and are counted."""
    from labrig.live.view_server import QUEUE_WINDOWS, ViewServer

    server = ViewServer(np.zeros((M_MARKERS, 3)), port=0)
    hold = threading.Event()
    server._thread = threading.Thread(target=hold.wait)  # a server thread that does not drain the queue
    server._thread.start()
    start = time.perf_counter()
    for i in range(QUEUE_WINDOWS + 30):
        server.publish(_window(i))
    assert time.perf_counter() - start < 0.5
    assert server.stats().windows_skipped == 30
    hold.set()
    server._thread.join()
    server._thread = None


def test_labrig_run_live_serves_the_view(small_recording: Path, tmp_path: Path) -> None:
    """End to end: a RAW replay as the rig's camera, `labrig run --live --view-server --view-port 0`; the client
    gets a force field for every window the pipeline computed, at the pipeline's rate."""
    import torch

    from labrig.pipeline.depthnet import build_unet, export_onnx
    from labrig.recording.convert import export_raw
    from labrig.testing.foxglove_client import FoxgloveClient

    torch.manual_seed(0)
    model = export_onnx(build_unet(width=2), tmp_path / "tiny.onnx",
                        {"name": "tiny", "scale_mm": 2.5, "window_ms": 10.0, "loss": {"name": "contact"}})
    raw = tmp_path / "camera.raw"
    export_raw(small_recording, raw)
    rig_text = (ROOT / "calibration" / "rig.toml").read_text()
    rig_file = tmp_path / "rig.toml"
    rig_text = rig_text.replace('camera = "sim"', 'camera = "raw"').replace('camera_path = ""', f'camera_path = "{raw}"')
    rig_file.write_text(rig_text)
    proc = subprocess.Popen([sys.executable, "-m", "labrig.cli", "run", "--live", "--rig", str(rig_file), "--model",
                             str(model), "--seconds", "2.5", "--view-server", "--view-port", "0", "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stderr is not None
    url = None
    deadline = time.monotonic() + 120
    lines: list[str] = []
    while url is None and time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        if found := re.search(r"ws://[\d.]+:\d+", line):
            url = found.group(0)
    assert url is not None, "".join(lines)
    with FoxgloveClient(url) as client:
        stdout, stderr = proc.communicate(timeout=120)
        time.sleep(0.2)
    assert proc.returncode == 0, stderr
    s = json.loads(stdout)
    assert set(client.topics) == set(CHANNELS)
    view = s["view_server"]
    fields = client.topics[topics.FORCE_FIELD]
    # every window goes out at 10 ms windows, but for one shorter than the view's 10 ms (the stream's last)
    assert view["windows_published"] + view["windows_thinned"] == s["windows_processed"]
    assert view["windows_thinned"] <= 1 and view["windows_skipped"] == 0
    # the client connected a moment after the server started: it misses at most the first windows
    assert len(fields.arrivals_s) >= 0.9 * view["windows_published"] and len(fields.arrivals_s) > 100
    pipeline_rate = s["windows_processed"] / s["stream_wall_s"]
    assert fields.rate_hz() == pytest.approx(pipeline_rate, rel=0.2)


def test_a_1_khz_pipeline_is_thinned_to_the_views_rate_before_it_costs_anything() -> None:
    """1 ms windows at the default 100 Hz: one window in ten goes to the server's queue, the rest are counted as
    thinned; at max_rate_hz 0 every window goes."""
    from labrig.live.view_server import ViewServer

    rest = np.zeros((M_MARKERS, 3))
    for rate_hz, sent in ((100.0, 10), (0.0, 100)):
        server = ViewServer(rest, port=0, max_rate_hz=rate_hz)  # not started: publish only queues
        offered = []
        server._offer = offered.append  # type: ignore[method-assign]
        for i in range(100):
            window = _window(i)
            server.publish(replace(window, t0_us=i * 1000, t1_us=(i + 1) * 1000))
        assert len(offered) == sent and server.windows_thinned == 100 - sent
    with pytest.raises(LabrigError, match="the view's rate must be zero"):
        ViewServer(rest, max_rate_hz=-1.0)


def test_every_ft_sample_reaches_the_view_at_the_sensors_rate(rig: RigConfig, sphere: Indenter) -> None:
    """The Bota driver on its twin over a pty (800 Hz, as on the rig) feeds a rig session, whose F/T listener hands
    every sample to the view: a client receives /ft_sensor/wrench at the sensor's rate, one message a sample stamped
    with its own host time (moved to the system clock by one offset) and holding its reading, while every window of a
    100 Hz pipeline still goes out."""
    from labrig.devices.bota import BotaSensor, BotaSettings
    from labrig.devices.bota_stream import FtSample
    from labrig.live.view_server import ViewServer
    from labrig.protocol.rigfile import DeviceConfig
    from labrig.protocol.safety import SafetyLimits
    from labrig.protocol.session import RigSession
    from labrig.sim.bota_twin import BotaTwin, BotaTwinParams
    from labrig.sim.serial_pty import TwinServer
    from labrig.testing.foxglove_client import FoxgloveClient

    session = RigSession(rig, DeviceConfig(), SafetyLimits(), indenter=sphere)  # not opened: the F/T alone, below
    twin = BotaTwin(BotaTwinParams(boot_delay_us=50_000), wrench_at=lambda t_us: ((0.0, 0.0, -1e-6 * t_us), (0.0,) * 3))
    ports = TwinServer({"ft": twin}).start()
    samples: list[FtSample] = []
    try:
        deadline = time.monotonic() + 5
        while twin.mode != "run" and time.monotonic() < deadline:
            time.sleep(0.005)
        sensor = BotaSensor(ports.paths["ft"], clock=session.clock, on_sample=session._on_ft, char_gap_s=0.001)
        sensor.connect(boot_timeout_s=2.0)
        sensor.configure(BotaSettings())  # the session's settings: 51200 / 64 = 800 Hz
        with ViewServer(np.zeros((M_MARKERS, 3)), port=0) as server, FoxgloveClient(server.url, keep_payloads=True) as client:
            session.add_ft_listener(server.ft_listener(session.clock))
            session.add_ft_listener(samples.append)
            sensor.start()
            start = time.monotonic()
            for i in range(150):  # 1.5 s of 10 ms windows alongside
                server.publish(_window(i))
                time.sleep(max(0.0, start + (i + 1) * 0.01 - time.monotonic()))
            sensor.stop()
            wrenches = client.topics[topics.WRENCH]
            deadline = time.monotonic() + 5
            while len(wrenches.arrivals_s) < len(samples) and time.monotonic() < deadline:
                time.sleep(0.02)
        sensor.close()
    finally:
        ports.stop()
    stats = server.stats()
    sample_host_ns = np.array([s.t_host_ns for s in samples], np.int64)
    sensor_rate_hz = (len(samples) - 1) / ((sample_host_ns[-1] - sample_host_ns[0]) / 1e9)
    assert len(samples) > 1000 and sensor_rate_hz == pytest.approx(800, rel=0.05)
    assert stats.wrenches_published == len(samples) == len(wrenches.arrivals_s)
    assert stats.wrenches_skipped == 0 and stats.windows_skipped == 0 and stats.windows_published == 150
    assert wrenches.rate_hz() == pytest.approx(sensor_rate_hz, rel=0.1)  # as the client receives them
    store = M.typestore()
    msgs = [store.deserialize_cdr(p, M.WRENCH_STAMPED) for p in wrenches.payloads]
    stamps = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs], np.int64)
    assert np.array_equal(stamps, wrenches.log_times_ns)
    offset = stamps - sample_host_ns
    assert np.all(offset == offset[0]) and abs(offset[0] - (time.time_ns() - time.monotonic_ns())) < 50_000_000
    assert [m.wrench.force.z for m in msgs] == [s.force_n[2] for s in samples]
    assert all(m.header.frame_id == topics.FT_FRAME for m in msgs)
