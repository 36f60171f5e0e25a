"""The camera interface (labrig.devices.camera): raw replay, the sim backend against Evk4Twin over a
real Unix socket, and record_camera (the metavision backend: test_camera_metavision.py)."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labrig.devices.camera import (
    CameraError,
    EventChunk,
    RawReplayCamera,
    SimCamera,
    open_camera,
)
from labrig.devices.raw import TRIGGER_DTYPE, Evt3Decoder, Evt3StreamEncoder, write_raw
from labrig.eventtypes import EVENT_DTYPE
from labrig.protocol.routing import record_camera
from labrig.sim.evk4_twin import Evk4Twin

LOOP_US = 1 << 24


pytestmark = pytest.mark.usefixtures("time_limit_20s")


def make_events(n: int, t0: int, span_us: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ev = np.zeros(n, EVENT_DTYPE)
    ev["x"] = rng.integers(0, 1280, n)
    ev["y"] = rng.integers(0, 720, n)
    ev["p"] = rng.integers(0, 2, n)
    ev["t"] = np.sort(rng.integers(t0, t0 + span_us, n))
    return ev


def triggers(pairs: list[tuple[int, int, int]]) -> np.ndarray:
    out = np.zeros(len(pairs), TRIGGER_DTYPE)
    for i, (t, p, ch) in enumerate(pairs):
        out[i] = (p, t, ch)
    return out


def wait_for(predicate: Any, timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.005)


def collect(
    cam: Any, n_events: int, n_triggers: int = 0, timeout_s: float = 3.0
) -> tuple[np.ndarray, np.ndarray, list[EventChunk]]:
    chunks: list[EventChunk] = []
    deadline = time.monotonic() + timeout_s
    while sum(c.events.size for c in chunks) < n_events or sum(c.triggers.size for c in chunks) < n_triggers:
        if time.monotonic() > deadline:
            break
        chunk = cam.read(timeout_s=0.2)
        if chunk is not None:
            chunks.append(chunk)
    ev = np.concatenate([c.events for c in chunks]) if chunks else np.zeros(0, EVENT_DTYPE)
    tr = np.concatenate([c.triggers for c in chunks]) if chunks else np.zeros(0, TRIGGER_DTYPE)
    return ev, tr, chunks


# -- raw ---------------------------------------------------------------------------------------


@pytest.fixture
def raw_file(tmp_path: Path) -> tuple[Path, np.ndarray, np.ndarray]:
    ev = make_events(20_000, 5_000_000, 200_000)
    tr = triggers([(5_010_000, 1, 0), (5_100_000, 0, 0), (5_150_000, 1, 1)])
    path = tmp_path / "rec.raw"
    write_raw(path, ev, tr, header={"serial_number": "00ca0009"})
    return path, ev, tr


def test_raw_replay_as_fast_as_possible_gives_the_file(raw_file: tuple[Path, np.ndarray, np.ndarray]) -> None:
    path, ev, tr = raw_file
    with RawReplayCamera(path, speed=None, read_bytes=4099) as cam:
        assert cam.info.serial == "00ca0009" and (cam.info.width, cam.info.height) == (1280, 720)
        assert cam.info.backend == "raw" and cam.info.format == "EVT3"
        cam.start()
        got_ev, got_tr, chunks = collect(cam, ev.size, tr.size)
        assert cam.read(timeout_s=1.0) is None and cam.ended
    assert np.array_equal(got_ev, ev) and np.array_equal(got_tr, tr)
    host = [c.t_host_ns for c in chunks]
    assert host == sorted(host) and len(chunks) > 5


def test_raw_replay_paced_in_real_time(raw_file: tuple[Path, np.ndarray, np.ndarray]) -> None:
    path, ev, _ = raw_file  # 200 ms of events
    with RawReplayCamera(path, speed=2.0, packet_us=1000) as cam:
        t = time.monotonic()
        cam.start()
        got, _, chunks = collect(cam, ev.size)
        elapsed = time.monotonic() - t
    assert got.size == ev.size
    assert 0.085 <= elapsed < 0.6, elapsed  # 200 ms at 2x
    # packets of 1 ms device time, delivered about when their time has come
    spans = [int(c.events["t"][-1] - c.events["t"][0]) for c in chunks if c.events.size]
    assert max(spans) < 1000
    dev = np.array([c.t_device_us for c in chunks], float)
    host = np.array([c.t_host_ns for c in chunks], float) / 1e3
    lag = (host - host[0]) - (dev - dev[0]) / 2.0
    assert np.percentile(np.abs(lag), 90) < 20_000


def test_raw_roi_biases_and_bad_files(raw_file: tuple[Path, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    path, ev, _ = raw_file
    with RawReplayCamera(path, speed=None) as cam:
        cam.set_roi(100, 50, 300, 200)
        cam.set_bias("bias_diff_on", 20)
        assert cam.get_biases()["bias_diff_on"] == 20 and cam.get_bias("bias_hpf") == 0
        with pytest.raises(CameraError, match="outside its range"):
            cam.set_bias("bias_hpf", -1)
        with pytest.raises(CameraError, match="unknown bias"):
            cam.set_bias("bias_foo", 0)
        with pytest.raises(CameraError, match="does not fit"):
            cam.set_roi(1200, 0, 100, 10)
        cam.start()
        got, _, _ = collect(cam, 1, timeout_s=1.0)
        got = np.concatenate([got, *[c.events for c in cam.chunks(timeout_s=0.5)]])
    inside = (ev["x"] >= 100) & (ev["x"] < 400) & (ev["y"] >= 50) & (ev["y"] < 250)
    assert np.array_equal(got, ev[inside]) and cam.stats.roi_filtered_events == int((~inside).sum())
    with pytest.raises(CameraError, match="no such RAW file"):
        RawReplayCamera(tmp_path / "missing.raw").open()
    (tmp_path / "junk.raw").write_bytes(b"\x00\x01" * 100)
    with pytest.raises(CameraError, match="format"):
        RawReplayCamera(tmp_path / "junk.raw").open()
    with pytest.raises(CameraError, match="unknown camera backend"):
        open_camera("usb3")


# -- sim: Evk4Twin over a Unix socket ---------------------------------------------------------------


@pytest.fixture
def twin(tmp_path: Path) -> Iterator[Evk4Twin]:
    tw = Evk4Twin(tmp_path / "evk4.sock").start()
    yield tw
    tw.close()


def test_stream_encoder_joins_chunks_across_wraps_and_gaps() -> None:
    """Chunk boundaries inside one TIME_HIGH, at a 24-bit wrap, and after a silence of several loops."""
    enc = Evt3StreamEncoder()
    starts = [LOOP_US - 9000, LOOP_US - 8990, LOOP_US - 100, LOOP_US + 50, 3 * LOOP_US + 123, 3 * LOOP_US + 4096 * 7]
    parts = [make_events(300, t0, 40, seed=i) for i, t0 in enumerate(starts)]
    stream = b"".join(enc.encode(p, np.zeros(0, TRIGGER_DTYPE)) for p in parts)
    dec = Evt3Decoder(1280, 720)
    out = dec.decode_all(stream)
    assert np.array_equal(out.events, np.concatenate(parts)) and dec.skipped_words == 0


def test_sim_camera_decodes_the_twin_stream_exactly(twin: Evk4Twin) -> None:
    cam = SimCamera(twin.path, recv_bytes=4097)  # odd reads split words across recv calls
    with cam:
        cam.enable_trigger_in(1)
        cam.start()
        assert twin.wait_connected(2.0)
        assert cam.info.backend == "sim" and (cam.info.width, cam.info.height) == (1280, 720)
        sent_ev, sent_tr = [], []
        t = LOOP_US - 5000  # crosses the 24-bit wrap
        for k in range(40):
            ev = make_events(2000, t, 500, seed=k)
            tr = triggers([(t + 100, 1, 0), (t + 400, 0, k % 2)])
            assert twin.feed(ev, tr)
            sent_ev.append(ev)
            sent_tr.append(tr)
            t += 500 if k != 20 else 30_000_000  # and a silence of almost two loops
        twin.feed(make_events(10, t, 5, seed=99), [(t + 1, 1)])  # triggers as (t, polarity) pairs
        exp_ev = np.concatenate([*sent_ev, make_events(10, t, 5, seed=99)])
        exp_tr = np.concatenate([*sent_tr, triggers([(t + 1, 1, 0)])])
        got_ev, got_tr, _ = collect(cam, exp_ev.size, exp_tr.size)
    assert np.array_equal(got_ev, exp_ev)
    assert np.array_equal(got_tr, exp_tr)
    assert twin.bytes_sent == cam.bytes_received + len(_header_of(twin))
    assert twin.dropped_events == 0 and twin.events_sent == exp_ev.size


def _header_of(twin: Evk4Twin) -> bytes:
    from labrig.devices.raw import make_header

    return make_header("EVT3", twin.width, twin.height, twin.header_fields)


def test_sim_trigger_channels_follow_trigger_in(twin: Evk4Twin) -> None:
    with SimCamera(twin.path, trigger_in=()) as cam:
        cam.start()
        assert twin.wait_connected(2.0)
        twin.feed(make_events(5, 1000, 10), triggers([(1001, 1, 0), (1002, 0, 1)]))
        _, tr, _ = collect(cam, 5, 0, timeout_s=1.0)
        assert tr.size == 0
        cam.enable_trigger_in(0)
        twin.feed(make_events(5, 2000, 10), triggers([(2001, 1, 0), (2002, 0, 1)]))
        _, tr, _ = collect(cam, 5, 1, timeout_s=1.0)
        assert tr["id"].tolist() == [0]


def test_twin_handles_disconnect_and_reconnect(twin: Evk4Twin) -> None:
    first = SimCamera(twin.path).open()
    first.start()
    assert twin.wait_connected(2.0)
    ev1 = make_events(1000, 10_000, 1000, seed=1)
    twin.feed(ev1)
    got1, _, _ = collect(first, ev1.size)
    assert np.array_equal(got1, ev1)
    first.close()
    wait_for(lambda: not twin.connected)
    assert not twin.feed(make_events(100, 20_000, 10))  # nobody listening: discarded
    assert twin.unclaimed_events == 100
    with SimCamera(twin.path) as second:
        second.start()
        assert twin.wait_connected(2.0)
        ev2 = make_events(1000, 50_000_000, 1000, seed=2)  # past a wrap: absolute time survives
        twin.feed(ev2)
        got2, _, _ = collect(second, ev2.size)
    assert np.array_equal(got2, ev2) and twin.connections == 2


def test_twin_never_blocks_the_feeder_and_counts_drops(tmp_path: Path) -> None:
    with Evk4Twin(tmp_path / "slow.sock", max_buffered_events=50_000) as tw:
        lazy = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        lazy.connect(str(tw.path))  # connects and never reads
        assert tw.wait_connected(2.0)
        ev = make_events(10_000, 0, 1000)
        t = time.perf_counter()
        worst = 0.0
        for k in range(300):
            chunk = ev.copy()
            chunk["t"] += k * 1000
            t1 = time.perf_counter()
            tw.feed(chunk)
            worst = max(worst, time.perf_counter() - t1)
        total = time.perf_counter() - t
        assert tw.dropped_events > 0
        assert worst < 0.05 and total < 1.5, (worst, total)
        lazy.close()
        wait_for(lambda: not tw.connected)


def test_sim_stream_ends_when_the_twin_closes(tmp_path: Path) -> None:
    tw = Evk4Twin(tmp_path / "gone.sock").start()
    cam = SimCamera(tw.path).open()
    cam.start()
    assert tw.wait_connected(2.0)
    tw.close()
    assert cam.read(timeout_s=2.0) is None and cam.ended
    cam.close()
    with pytest.raises(CameraError, match="cannot connect"):
        SimCamera(tmp_path / "nobody.sock", connect_timeout_s=0.1).open()


def test_twin_rejects_events_the_stream_cannot_carry(twin: Evk4Twin) -> None:
    bad = make_events(3, 0, 10)
    bad["x"][1] = 1280
    with pytest.raises(ValueError, match="outside"):
        twin.feed(bad)


# -- recording -------------------------------------------------------------------------------------


def test_record_camera_puts_events_and_triggers_into_a_recording(twin: Evk4Twin, tmp_path: Path) -> None:
    from labrig.recording import Recording, RecordingWriter

    out = tmp_path / "cam.h5"
    sent = []
    with SimCamera(twin.path) as cam, RecordingWriter(out, min_free_bytes=None) as writer:
        stop = threading.Event()
        result: dict[str, Any] = {}
        thread = threading.Thread(target=lambda: result.update(stats=record_camera(cam, writer, stop)))
        thread.start()
        assert twin.wait_connected(2.0)
        for k in range(20):
            ev = make_events(500, 1_000_000 + k * 2000, 2000, seed=k)
            twin.feed(ev, [(1_000_000 + k * 2000 + 7, k % 2)])
            sent.append(ev)
            time.sleep(0.002)
        wait_for(lambda: cam.stats.events >= 20 * 500 and cam.stats.triggers >= 20)
        time.sleep(0.1)
        stop.set()
        thread.join(5)
    stats = result["stats"]
    assert stats.events == 10_000 and stats.triggers == 20 and stats.rejected_chunks == 0
    with Recording(out) as rec:
        events = rec.stream("events")
        assert np.array_equal(events["t_device_us"], np.concatenate(sent)["t"])
        assert np.array_equal(events["x"], np.concatenate(sent)["x"])
        trig = rec.stream("triggers")
        assert trig["polarity"].tolist() == [k % 2 for k in range(20)]
        assert rec.rows("event_packets") >= 1
        host = rec.stream("event_packets")["t_host_us"]
        assert np.all(np.diff(host) >= 0) and host[0] >= 0
