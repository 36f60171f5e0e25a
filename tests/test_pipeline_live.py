"""`labrig run --live`: windows over camera chunks, the real-time runner, the rig session's chunk
listeners, a probing run on the virtual rig through the real drivers, Ctrl-C, bad inputs."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.devices.camera import EventChunk
from labrig.devices.raw import TRIGGER_DTYPE
from labrig.eventtypes import EVENT_DTYPE
from labrig.indenters import Indenter
from labrig.live.runner import LiveRunner
from labrig.live.sources import ChunkTap
from labrig.pipeline import depth_sources, results, run_setup, runtime
from labrig.pipeline.brightness import signed_counts
from labrig.pipeline.windows import EventWindower, windows_from_chunks

ROOT = Path(__file__).resolve().parent.parent

# A shallow, fast probing run (about 3 s of sequence) with a +x shear.
QUICK_PROTOCOL = """
[probe]
indenter = "sphere"
location_mm = [0.0, 0.0]
[approach]
start_height_mm = 0.4
speed_mm_s = 1.0
contact_force_n = 0.1
max_travel_mm = 1.5
[normal]
depth_mm = 0.8
speed_mm_s = 2.0
[wait]
duration_s = 0.2
[shear]
direction_deg = 0.0
distance_mm = 0.5
speed_mm_s = 2.0
[retract]
height_mm = 1.0
speed_mm_s = 5.0
"""


def _events(t_us: Any) -> np.ndarray:
    t = np.asarray(t_us, np.int64)
    ev = np.zeros(t.size, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = t, 700, 400, np.arange(t.size) % 2
    return ev


def _chunks(t_us: np.ndarray, cuts: list[int]) -> list[EventChunk]:
    """Chunks of the events split at ``cuts`` (indices), arriving at host times 1000, 2000, ... ns."""
    parts = np.split(t_us, cuts)
    return [EventChunk(_events(p), np.zeros(0, TRIGGER_DTYPE), 1000 * (k + 1)) for k, p in enumerate(parts)]


def _labrig(*args: str | Path, cwd: Path = ROOT, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "labrig.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd)


# -- windows over chunks (pure) -------------------------------------------------------------------------


def test_time_windows_tile_a_stream_whose_chunks_do_not_align_with_them() -> None:
    rng = np.random.default_rng(1)
    # 12.3 ms .. 95 ms, nothing between 38 and 71 ms (three empty windows)
    t = np.sort(np.concatenate([rng.integers(12_300, 38_000, 3000), rng.integers(71_000, 95_000, 2000)]))
    cuts = sorted(rng.choice(np.arange(1, t.size), 17, replace=False).tolist())
    chunks = _chunks(t, cuts)
    wins = list(windows_from_chunks(chunks, window_us=10_000))
    assert [w.t0_us for w in wins] == list(range(10_000, 100_000, 10_000))
    assert all(a.t1_us == b.t0_us for a, b in itertools.pairwise(wins))
    assert [w.events.size for w in wins[3:6]] == [0, 0, 0]  # 40-70 ms: the gap
    assert wins[2].events.size > 0 and wins[6].events.size > 0
    for w in wins[:-1]:
        assert np.array_equal(w.events["t"], t[(t >= w.t0_us) & (t < w.t1_us)])
    assert wins[-1].t1_us == t[-1] + 1  # the partial last window ends at its last event
    assert sum(w.events.size for w in wins) == t.size
    # each window's host time is the arrival of the chunk holding the first event past its end
    arrival = np.repeat([c.t_host_ns for c in chunks], [c.events.size for c in chunks])
    for w in wins[:-1]:
        assert w.t_host_ns == arrival[np.searchsorted(t, w.t1_us)]


def test_count_windows_end_at_the_next_windows_first_event_and_drop_the_partial_tail() -> None:
    t = np.arange(0, 10_500 * 3, 3)  # 10,500 events
    wins = list(windows_from_chunks(_chunks(t, [777, 2500, 2501, 9000]), window_us=None, window_events=1000))
    assert len(wins) == 10 and all(w.events.size == 1000 for w in wins)
    assert all(w.t1_us == t[1000 * (k + 1)] for k, w in enumerate(wins))
    exact = list(windows_from_chunks(_chunks(t[:3000], [1200]), window_us=None, window_events=1000))
    assert len(exact) == 3 and exact[-1].t1_us == t[2999] + 1  # an exact tail is a whole window


def test_late_events_join_the_open_window_and_a_clock_jump_starts_a_new_grid() -> None:
    windower = EventWindower(window_us=10_000)
    assert [w.events.size for w in windower.push(_events([1_000, 9_000, 12_000]))] == [2]
    late = windower.push(_events([9_500, 13_000, 25_000]))  # 9.5 ms arrives after the 10-20 ms window opened
    assert [(w.t0_us, w.events.size) for w in late] == [(10_000, 3)]
    jumped = windower.push(_events([26_000, 60_000_000, 60_004_000]))  # the camera restarted its clock
    assert [(w.t0_us, w.t1_us, w.events.size) for w in jumped] == [(20_000, 26_001, 2)]
    assert windower.time_jumps == 1
    assert [(w.t0_us, w.t1_us, w.events.size) for w in windower.flush()] == [(60_000_000, 60_004_001, 2)]


def test_a_stream_ends_cleanly() -> None:
    assert list(windows_from_chunks([], window_us=10_000)) == []
    only_triggers = EventChunk(np.zeros(0, EVENT_DTYPE), np.zeros(2, TRIGGER_DTYPE), 5)
    assert list(windows_from_chunks([only_triggers], window_us=10_000)) == []
    windower = EventWindower(window_us=10_000)
    windower.push(_events([5, 6]))
    assert len(windower.flush()) == 1 and windower.flush() == []
    with pytest.raises(ValueError):
        EventWindower(window_us=10_000, window_events=5)
    with pytest.raises(ValueError):
        EventWindower(window_us=0)


def test_the_tap_never_blocks_and_counts_what_it_drops() -> None:
    tap = ChunkTap(max_chunks=2)
    chunks = _chunks(np.arange(30), [10, 20])
    for chunk in chunks:
        tap(chunk)
    assert tap.stats.chunks == 2 and tap.stats.dropped_chunks == 1 and tap.stats.dropped_events == 10
    tap.close()
    tap(chunks[0])  # after close: ignored
    assert not tap.ended and tap.read(0.01) is chunks[0] and tap.read(0.01) is chunks[1]
    assert tap.read(0.01) is None and tap.ended


# -- the runner ---------------------------------------------------------------------------------------


class _FlatDepth(depth_sources.DepthSource):
    """A depth source that needs the SAE (like the network) and keeps what it saw."""

    name = "flat"
    needs_sae = True
    window_us = None

    def __init__(self) -> None:
        self.seen: list[float] = []

    def depth_mm(self, sae_grid: Any, t0_us: int, t1_us: int, n_events: int) -> np.ndarray:
        self.seen.append(float(sae_grid.sum()))
        return np.zeros((90, 112), np.float32)


class _ListSource:
    """Chunks from a list, then the end of the stream; ``pause_before`` {index: seconds} delays some."""

    def __init__(self, chunks: list[EventChunk], pause_before: dict[int, float] | None = None) -> None:
        self.chunks = list(chunks)
        self.pause_before = pause_before or {}
        self.served = 0

    def read(self, timeout_s: float | None = None) -> EventChunk | None:
        if not self.chunks:
            return None
        time.sleep(self.pause_before.get(self.served, 0.0))
        self.served += 1
        return self.chunks.pop(0)

    @property
    def ended(self) -> bool:
        return not self.chunks


@pytest.fixture(scope="module")
def setup(rig: RigConfig) -> run_setup.PipelineSetup:
    return run_setup.setup_for_rig(rig, calibration_dir=None)


def _marker_events(setup: run_setup.PipelineSetup, t0_us: int, n_windows: int) -> np.ndarray:
    """Events on the first marker's rest pixel, 200 per 10 ms."""
    x, y = np.round(setup.rest_px[0]).astype(int)
    t = np.arange(t0_us, t0_us + n_windows * 10_000, 50)
    ev = _events(t)
    ev["x"], ev["y"] = x, y
    return ev


def _window_chunks(setup: run_setup.PipelineSetup, host_ns: list[int]) -> list[EventChunk]:
    """One chunk per 10 ms window of marker events, arriving at ``host_ns``."""
    events = _marker_events(setup, 0, len(host_ns))
    return [EventChunk(events[k * 200:(k + 1) * 200], np.zeros(0, TRIGGER_DTYPE), t) for k, t in enumerate(host_ns)]


def test_a_window_older_than_the_max_lag_is_tracked_but_skipped(setup: run_setup.PipelineSetup) -> None:
    depth = _FlatDepth()
    pipe = runtime.Pipeline(setup, depth)
    now, minute = time.monotonic_ns(), 60 * 10**9
    # the second chunk arrived a minute ago (the pipeline was stuck), so the first window, which
    # it closed, is stale; the others arrive "in the future" (never stale, never late); a pause
    # after the stale one lets the back stage meet it alone
    chunks = _window_chunks(setup, [now + minute, now - minute, now + minute, now + minute, now + minute])
    runner = LiveRunner(pipe, _ListSource(chunks, {2: 0.3}), window_us=10_000, max_lag_ms=100)
    results = list(runner.run())
    s = runner.stats
    assert s.windows == 5 and s.skipped == 1 and s.processed == 4 == len(results)
    assert [r.t0_us for r in results] == [10_000, 20_000, 30_000, 40_000]
    assert s.late == 0 and s.end_reason == "the stream ended"
    assert all(v > 0 for v in depth.seen)  # each window's own SAE reached the depth source


def test_a_stale_backlog_is_skipped_up_to_the_newest_window(setup: run_setup.PipelineSetup) -> None:
    pipe = runtime.Pipeline(setup, _FlatDepth())
    now, minute = time.monotonic_ns(), 60 * 10**9
    # windows 0-4 closed by chunks that arrived a minute ago; window 5 by a fresh one, 6 at the end
    chunks = _window_chunks(setup, [now - minute] * 6 + [now + minute])
    runner = LiveRunner(pipe, _ListSource(chunks), window_us=10_000, max_lag_ms=100)
    done = [r.t0_us // 10_000 for r in runner.run()]
    # the back stage never computes a stale window; once behind it jumps to the newest queued
    assert done in ([5, 6], [6]) and runner.stats.skipped == 7 - len(done)


def test_skipping_the_window_depth_was_due_on_leaves_the_gel_flat_until_the_next(
        setup: run_setup.PipelineSetup) -> None:
    """1 ms windows with depth every 10 ms: a live run that skips its first windows (the one whose depth was due
    among them) processes the next ones on a flat gel, without an SAE, until depth is due again."""
    depth = _FlatDepth()
    now, minute = time.monotonic_ns(), 60 * 10**9
    events = _marker_events(setup, 0, 3)  # 30 ms
    chunks = [EventChunk(events[k * 20:(k + 1) * 20], np.zeros(0, TRIGGER_DTYPE), now - minute if k < 3 else now + minute)
              for k in range(30)]
    runner = LiveRunner(runtime.Pipeline(setup, depth, depth_every_us=10_000), _ListSource(chunks, {3: 0.3}),
                        window_us=1_000, max_lag_ms=100)
    results = list(runner.run())
    assert runner.stats.skipped >= 2 and results and results[0].t0_us < 10_000
    assert all(not r.depth_mm.any() and np.isfinite(r.forces_n).all() for r in results)
    assert len(depth.seen) == 2  # depth ran where due again: at 10 and 20 ms


class _CountingDepth(_FlatDepth):
    """A depth source that integrates the signed counts (like the brightness network) and keeps what it observed."""

    needs_counts = True

    def __init__(self) -> None:
        super().__init__()
        self.observed_t1_us: list[int] = []
        self.total = np.zeros((90, 112), np.float32)

    def observe(self, positions_px: Any, rest_px: Any, counts: Any, t1_us: int) -> None:
        self.observed_t1_us.append(t1_us)
        self.total += counts


def test_skipped_windows_still_reach_the_depth_sources_state(setup: run_setup.PipelineSetup) -> None:
    """Every window's signed counts reach the depth source once and in order, skipped or not."""
    depth = _CountingDepth()
    now, minute = time.monotonic_ns(), 60 * 10**9
    chunks = _window_chunks(setup, [now - minute] * 6 + [now + minute])
    for chunk in chunks:
        chunk.events["p"] = 1  # all ON: the counts add up
    every_event = np.concatenate([c.events for c in chunks])
    runner = LiveRunner(runtime.Pipeline(setup, depth), _ListSource(chunks), window_us=10_000, max_lag_ms=100)
    results = list(runner.run())
    assert runner.stats.skipped >= 5 and len(results) <= 2
    assert len(depth.observed_t1_us) == runner.stats.windows == 7
    assert depth.observed_t1_us[:-1] == [10_000 * (k + 1) for k in range(6)]  # in order; the last ends at the stream's end
    np.testing.assert_allclose(depth.total, signed_counts(every_event, setup.rig.roi))
    assert depth.total.any()


def test_the_front_runs_ahead_without_overwriting_the_sae_the_back_stage_reads(setup: run_setup.PipelineSetup) -> None:
    pipe = runtime.Pipeline(setup, _FlatDepth())
    ev = _marker_events(setup, 0, 2)
    first = pipe.front(0, 10_000, ev[:200])
    before = first.sae.copy()
    pipe.front(10_000, 20_000, ev[:0])  # an empty window next
    assert np.array_equal(first.sae, before) and before.sum() > 0


def test_the_runner_stops_on_request_and_keeps_the_partial_window(setup: run_setup.PipelineSetup) -> None:
    class Endless:
        ended = False

        def __init__(self) -> None:
            self.t = 0

        def read(self, timeout_s: float | None = None) -> EventChunk | None:
            time.sleep(0.001)
            self.t += 1000
            return EventChunk(_events(np.arange(self.t - 1000, self.t, 100)), np.zeros(0, TRIGGER_DTYPE),
                              time.monotonic_ns())

    stop = threading.Event()
    runner = LiveRunner(runtime.Pipeline(setup, _FlatDepth()), Endless(), window_us=10_000)
    results = []
    for r in runner.run(stop=stop):
        results.append(r)
        if len(results) == 3:
            stop.set()
    assert runner.stats.end_reason == "stopped" and len(results) >= 3
    assert runner.stats.windows == runner.stats.processed + runner.stats.skipped
    timed = LiveRunner(runtime.Pipeline(setup, _FlatDepth()), Endless(), window_us=10_000)
    assert len(list(timed.run(seconds=0.2))) > 3 and timed.stats.end_reason == "seconds reached"


def test_session_listeners_get_every_chunk_and_a_failing_one_is_removed(rig: RigConfig, sphere: Indenter) -> None:
    from labrig.protocol.rigfile import DeviceConfig
    from labrig.protocol.safety import SafetyLimits
    from labrig.protocol.session import RigSession

    chunks = _chunks(np.arange(300), [100, 200])

    class Camera:
        ended = False

        def read(self, timeout_s: float | None = None) -> EventChunk | None:
            if chunks:
                return chunks.pop(0)
            self.ended = True
            return None

    session = RigSession(rig, DeviceConfig(), SafetyLimits(), indenter=sphere)  # not opened: no devices
    session.camera = Camera()  # type: ignore[assignment]
    got: list[EventChunk] = []

    def broken(chunk: EventChunk) -> None:
        raise RuntimeError("listener bug")

    session.add_chunk_listener(broken)
    session.add_chunk_listener(got.append)
    session._pump_camera()  # the pump's loop, here until the fake camera ends
    assert len(got) == 3 and session.camera_events == 300
    assert isinstance(session.listener_error, RuntimeError) and session._listeners.callbacks == (got.append,)


def test_session_ft_listeners_get_every_sample_after_the_monitor_and_a_failing_one_is_removed(
        rig: RigConfig, sphere: Indenter) -> None:
    from labrig.devices.bota_stream import FtSample
    from labrig.protocol.rigfile import DeviceConfig
    from labrig.protocol.safety import SafetyLimits
    from labrig.protocol.session import RigSession

    session = RigSession(rig, DeviceConfig(), SafetyLimits(), indenter=sphere)  # not opened: samples handed in below
    got: list[tuple[FtSample, float]] = []

    def broken(sample: FtSample) -> None:
        raise RuntimeError("listener bug")

    session.add_ft_listener(broken)
    session.add_ft_listener(lambda s: got.append((s, float(session.monitor.last_n[2]))))
    samples = [FtSample(1250 * i, 10**9 + 1_250_000 * i, (0.0, 0.0, -0.1 * i), (0.0, 0.0, 0.0), 0, 25.0)
               for i in range(5)]
    for sample in samples:
        session._on_ft(sample)
    assert [s for s, _ in got] == samples and [fz for _, fz in got] == [s.force_n[2] for s in samples]  # monitor first
    assert isinstance(session.listener_error, RuntimeError) and len(session._ft_listeners.callbacks) == 1


# -- the command ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained width-2 U-Net exported to ONNX (its depth is meaningless)."""
    import torch

    from labrig.pipeline.depthnet import build_unet, export_onnx

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("model") / "tiny.onnx"
    return export_onnx(build_unet(width=2), path, {"name": "tiny", "scale_mm": 2.5, "window_ms": 10.0,
                                                  "loss": {"name": "contact"}})


def _in_plane_mm(positions_px: np.ndarray, rig: RigConfig) -> np.ndarray:
    """Tracked in-plane marker displacements on the gel surface (depth 0), (W, M, 2) mm: tracking only."""
    from labrig.pipeline import displacement

    setup = run_setup.setup_for_rig(rig, calibration_dir=rig.path.parent)
    rest = rig.markers.rest_positions_mm()
    return np.array([displacement.displacements_mm(p, 0.0, setup.camera, rest, rig.roi)[:, :2] for p in positions_px])


def test_live_run_during_a_probing_run_on_the_virtual_rig(tiny_model: Path, rig: RigConfig, tmp_path: Path) -> None:
    """Through the real drivers: the live pipeline keeps up, covers the run, tracks the commanded
    shear; the F/T sensor is the reference (the untrained network's forces are not judged). The live view
    (--view-server) sends every F/T sample the session saw, the recording's among them."""
    from labrig.recording import Recording

    protocol = tmp_path / "quick.toml"
    protocol.write_text(QUICK_PROTOCOL)
    out, rec_path = tmp_path / "live.h5", tmp_path / "run.h5"
    result = _labrig("run", "--live", "--protocol", protocol, "--model", tiny_model, "--out", out,
                     "--save-recording", rec_path, "--view-server", "--view-port", "0", "--json")
    assert result.returncode == 0, result.stderr
    assert "virtual rig" in result.stderr
    s = json.loads(result.stdout)
    assert s["virtual_rig"] and s["source"] == "virtual rig (embedded)" and s["live"]
    assert s["probe"]["exit_status"] == "complete", s["probe"]["reason"]
    # real time: every window tracked, most with forces, results within the max lag, nothing dropped
    assert s["windows_tracked"] == s["windows_processed"] + s["windows_skipped"]
    assert abs(s["windows_tracked"] * 0.01 - s["stream_s"]) < 0.011
    assert s["windows_processed"] >= 0.3 * s["windows_tracked"] and s["dropped_chunks"] == 0  # a loaded 2-core machine skips some
    assert s["latency_median_ms"] < 100 and s["real_time_factor"] < 1.0
    data = results.load_result(out)
    assert data["attrs"]["windows"] == s["windows"] == len(data["t0_us"]) and data["attrs"]["live"] == 1
    assert np.all(data["t1_us"] > data["t0_us"]) and np.all(np.diff(data["t0_us"]) > 0)
    # the windows cover the recorded run (device time mapped through its camera clock): from before
    # the approach to the recording's last event (a virtual rig lagging behind real time on a loaded
    # machine may deliver its last events after the recording has stopped waiting for them)
    with Recording(rec_path) as rec:
        camera = rec.clock_model("camera")
        phases = {p.name: p for p in rec.phases()}
        t_host = camera.to_host_us(data["t1_us"])
        last_event_us = camera.to_host_us(rec.column("events", "t_device_us", rec.n_events - 1))[0]
        ft_fz = rec.column("ft", "force_n")[:, 2]
        ft_host_us = rec.column("ft", "t_host_us")
    # the live view got the F/T at the sensor's rate (800 Hz), not the run's 10 Hz progress reports
    view = s["view_server"]
    assert ft_host_us.size > 0.9 * 800 * (ft_host_us[-1] - ft_host_us[0]) / 1e6
    assert view["wrenches_published"] >= ft_host_us.size and view["wrenches_skipped"] == 0
    assert t_host[0] < phases["approach"].t_start_us and t_host[-1] > last_event_us - 250_000
    # the F/T reference: the sphere pressed 0.8 mm; the comparison ran over the recorded windows
    c = s["ft_comparison"]
    assert c["windows_compared"] > 100 and 1.5 < c["ft_peak_normal_force_n"] < 15
    assert c["ft_peak_normal_force_n"] == pytest.approx(ft_fz.max(), rel=0.1)
    # tracking (independent of the network) follows the commanded +x shear
    u = _in_plane_mm(data["positions_px"], rig)
    moving = np.argsort(np.abs(u).max(axis=(0, 2)))[-20:]
    shift = u[:, moving].mean(axis=1)
    k = int(np.argmax(shift[:, 0]))
    assert shift[k, 0] > 0.1 and abs(shift[k, 1]) < 0.3 * shift[k, 0]
    assert phases["shear"].t_start_us < t_host[k] < phases["normal_up"].t_start_us


def test_ctrl_c_closes_the_result_file_and_prints_the_summary(tiny_model: Path, small_recording: Path,
                                                             tmp_path: Path) -> None:
    """Camera only: a RAW replay (in real time) as the rig's camera, stopped by SIGINT."""
    from labrig.recording.convert import export_raw

    raw = tmp_path / "camera.raw"
    export_raw(small_recording, raw, progress=False)
    rig_text = (ROOT / "calibration" / "rig.toml").read_text()
    rig_text = rig_text.replace('camera = "sim"', 'camera = "raw"').replace('camera_path = ""', f'camera_path = "{raw}"')
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_text)
    out = tmp_path / "live.h5"
    proc = subprocess.Popen([sys.executable, "-m", "labrig.cli", "run", "--live", "--rig", str(rig_file),
                             "--model", str(tiny_model), "--out", str(out), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    deadline = time.monotonic() + 60
    while not out.exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)  # the result file opens with the first window
    time.sleep(0.5)
    os.kill(proc.pid, signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    s = json.loads(stdout)
    assert s["end_reason"] == "stopped" and "stopping" in stderr and s["source"] == f"camera raw {raw}"
    assert 0.3 < s["stream_s"] < 2.9 and s["windows_processed"] > 0.5 * s["windows_tracked"] and s["dropped_chunks"] == 0
    data = results.load_result(out)
    assert data["attrs"]["windows"] == s["windows"] == len(data["t0_us"]) > 20


def test_bad_inputs_say_what_to_do_in_one_line(small_recording: Path, tmp_path: Path) -> None:
    gone = tmp_path / "gone"
    rig_text = (ROOT / "calibration" / "rig.toml").read_text().replace('camera_path = ""', f'camera_path = "{gone}/evk4"')
    (tmp_path / "rig.toml").write_text(rig_text)
    cases = [
        (("run", small_recording, "--live"), ROOT, "or --live, not both"),
        (("run",), ROOT, "give a recording"),
        (("run", "--live", "--depth", "truth"), ROOT, "--depth truth"),
        (("run", "--live", "--seconds", "0"), ROOT, "--seconds must be positive"),
        (("run", "--live", "--seconds", "5"), ROOT, "one probing run"),
        (("run", small_recording, "--seconds", "5"), ROOT, "only apply to --live"),
        (("run", "--live", "--rig", tmp_path / "rig.toml", "--seconds", "1"), ROOT, "no such socket"),
        (("run", "--live", "--model", tmp_path / "none.onnx"), ROOT, "no such depth network"),
    ]
    procs = [subprocess.Popen([sys.executable, "-m", "labrig.cli", *map(str, args)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, cwd=cwd) for args, cwd, _ in cases]
    for (args, _, expected), proc in zip(cases, procs, strict=True):
        _, stderr = proc.communicate(timeout=120)
        lines = [line for line in stderr.splitlines() if line.strip()]
        assert proc.returncode == 2, (args, stderr)
        assert "Traceback" not in stderr and lines[0].startswith("error:"), (args, stderr)
        assert expected in " ".join(lines), (args, stderr)


def test_no_depth_network_says_what_to_do(monkeypatch: pytest.MonkeyPatch) -> None:
    from labrig.cli.run_live import _default_model
    from labrig.errors import LabrigError

    def nothing(folder: str = "models") -> Path:
        raise LabrigError("no depth network in models/")

    monkeypatch.setattr(depth_sources, "default_model_path", nothing)
    with pytest.raises(LabrigError, match=r"pass --model X\.onnx, or train one with `labrig train DATA/`"):
        _default_model()


def test_a_camera_whose_stream_breaks_stops_the_live_run_with_its_reason(setup: run_setup.PipelineSetup,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """`labrig run --live` on an EVK4 that is unplugged mid-run: the run raises the camera's error."""
    import sys

    from labrig.devices.camera import CameraError, open_camera
    from labrig.devices.raw import encode_evt3
    from labrig.testing.fake_metavision import FakeCamera, fake_metavision_hal

    camera = FakeCamera()
    monkeypatch.setitem(sys.modules, "metavision_hal", fake_metavision_hal([camera]))
    camera.push(encode_evt3(_marker_events(setup, 1_000_000, 5), np.zeros(0, TRIGGER_DTYPE)))
    with open_camera("metavision") as cam:
        cam.start()
        runner = LiveRunner(runtime.Pipeline(setup, _FlatDepth()), cam, window_us=10_000, max_lag_ms=None)
        results = []
        with pytest.raises(CameraError, match="stopped streaming"):
            for result in runner.run(seconds=10):
                results.append(result)
                if len(results) == 2:
                    camera.unplug()
    assert len(results) >= 2


def test_the_live_network_runs_in_a_thread_with_a_second_core_and_in_steps_on_one() -> None:
    from labrig.cli.run_live import depth_lane_for, usable_cores

    assert depth_lane_for(None, 1) == depth_lane_for(None, 8) == "window"
    assert depth_lane_for(10_000, 2) == "thread"
    assert depth_lane_for(10_000, 1) == "steps"
    assert usable_cores() >= 1


def test_a_live_probing_run_holds_its_force_on_the_live_estimate(tmp_path: Path) -> None:
    """Through the real drivers with ``feedback = "events"``: the live pipeline's estimate (the bundled network)
    is the loop's feedback; the run completes and the F/T sensor, the reference, sees the target held."""
    from labrig.evaluation.control import control_run
    from labrig.protocol.feedback import EVENTS_READING_NOISE_N
    from labrig.recording import Recording

    protocol = tmp_path / "held.toml"
    protocol.write_text(QUICK_PROTOCOL.replace("depth_mm = 0.8", "force_n = 3.0\nhold_s = 0.6")
                        .replace("distance_mm = 0.5", "distance_mm = 0.0")
                        + '[control]\nfeedback = "events"\nstale_after_s = 0.5\n')
    rec_path = tmp_path / "held.h5"
    result = _labrig("run", "--live", "--protocol", protocol, "--save-recording", rec_path, "--json")
    assert result.returncode == 0, result.stderr
    s = json.loads(result.stdout)
    assert s["probe"]["exit_status"] == "complete", s["probe"]["reason"]
    with Recording(rec_path) as rec:
        assert rec.attrs["extra_control_feedback"] == "events"
        assert rec.attrs["extra_control_reading_noise_n"] == EVENTS_READING_NOISE_N  # the events default, recorded
        ages_ms = rec.column("control", "reading_age_us") / 1e3
    assert 0 < np.median(ages_ms) < 500
    run = control_run(rec_path)
    assert run is not None and run.feedback == "events" and run.hold_rms_n_ft < 1.0
