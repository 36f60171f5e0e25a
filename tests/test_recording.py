"""Writer and reader round trips, clock models end to end, drops, slicing."""

from __future__ import annotations

import threading
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import SMALL_RUN

from labrig.clock import ManualClock, unwrap_counter
from labrig.errors import RecordingError
from labrig.recording import Recording, RecordingMetadata, RecordingWriter
from labrig.recording.layout import partial_path
from labrig.testing.synthetic import DeviceClock, SyntheticRun, record_synthetic


def all_camera_packets(run: SyntheticRun) -> tuple[np.ndarray, ...]:
    packets = list(run.camera_packets())
    return tuple(np.concatenate([p[i] for p in packets]) for i in range(4))


def test_every_stream_round_trips(small_recording: Path) -> None:
    x, _, _, t_dev = all_camera_packets(SMALL_RUN)
    ft = list(SMALL_RUN.ft_batches())
    with Recording(small_recording) as rec:
        assert rec.finalized and rec.exit_status == "complete"
        assert rec.attrs["schema"] == "labrig.recording" and rec.attrs["indenter"] == "sphere"
        assert rec.n_events == x.size
        assert np.array_equal(rec.column("events", "x"), x)
        assert np.array_equal(rec.column("events", "t_device_us"), t_dev)
        assert np.array_equal(rec.column("ft", "t_device_us"), np.concatenate([b["t_device_us"] for b in ft]))
        assert np.allclose(rec.column("ft", "force_n"), np.concatenate([b["force_n"] for b in ft]))
        assert rec.rows("cnc") == 30 and rec.rows("event_packets") == 3000
        names = [ph.name for ph in rec.phases()]
        assert names == ["approach", "normal_down", "wait", "shear", "wait", "shear_opposite", "wait", "normal_up", "retract"]
        assert rec.phases()[-1].t_end_us == 3_000_000
        assert rec.file["streams/events/x"].attrs["unit"] == "px"
    assert not partial_path(small_recording).exists()


def test_stored_clock_models_recover_the_true_clocks(small_recording: Path) -> None:
    """Camera: hardware triggers, <= 5 us. F/T: envelope of receive times, <= 50 us."""
    send_us = np.linspace(0, SMALL_RUN.duration_s * 1e6, 500)
    with Recording(small_recording) as rec:
        camera, ft = rec.clock_model("camera"), rec.clock_model("ft")
        assert camera.method == "triggers" and camera.n_triggers == 6
        camera_err = camera.to_host_us(SMALL_RUN.camera_clock.device_us(send_us)) - send_us
        assert np.abs(camera_err).max() <= 5.0
        assert ft.method == "envelope"
        ft_device = unwrap_counter(SMALL_RUN.ft_clock.device_us(send_us) % (1 << 32), 32)
        ft_err = ft.to_host_us(ft_device) - send_us - SMALL_RUN.ft_clock.min_latency_us
        assert np.abs(ft_err).max() <= 50.0
        # The F/T stamps wrap past 2**32 us during this run and are unwrapped.
        assert rec.column("ft", "t_device_us").min() < 1_000_000


def test_events_between_matches_a_full_scan(small_recording: Path) -> None:
    rng = np.random.default_rng(0)
    with Recording(small_recording) as rec:
        model = rec.clock_model("camera")
        t_all = model.to_host_us_int(rec.column("events", "t_device_us"))
        x_all = rec.column("events", "x")
        for t0 in rng.uniform(-5_000, 3_005_000, 40):
            t1 = t0 + rng.choice([10, 1_000, 10_000, 137_000])
            got = rec.events_between(t0, t1)
            mask = (t_all >= t0) & (t_all < t1)
            assert np.array_equal(got["t"], t_all[mask])
            assert np.array_equal(got["x"], x_all[mask])


def test_windows_read_in_order_come_from_the_read_ahead_block(small_recording: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """Sequential 10 ms windows through a small read-ahead block: the same events as a full scan, with
    one HDF5 read per column per block, across block boundaries and after a jump back."""
    from labrig.recording import reader

    monkeypatch.setattr(reader, "EVENT_READ_AHEAD_ROWS", 5_000)
    with Recording(small_recording) as rec:
        t_all = rec.clock_model("camera").to_host_us_int(rec.column("events", "t_device_us"))
        reads = []
        column = rec.column
        monkeypatch.setattr(rec, "column", lambda stream, name, *a: reads.append(name) or column(stream, name, *a))
        starts = [*range(0, 1_000_000, 10_000), 20_000]
        for t0 in starts:
            got = rec.events_between(t0, t0 + 10_000)
            assert np.array_equal(got["t"], t_all[(t_all >= t0) & (t_all < t0 + 10_000)])
        in_range = int(((t_all >= 0) & (t_all < 1_000_000)).sum())
        assert in_range > 3 * 5_000  # several blocks
        assert reads.count("x") <= in_range // 5_000 + 3 < len(starts)


def test_events_between_handles_timestamps_that_step_back(tmp_path: Path) -> None:
    """EVT3 streams merge sources: TIME_LOW may step back a few microseconds."""
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.integers(0, 40, 200_000)) + 10_000_000
    t = t - rng.integers(0, 6, t.size) * (rng.random(t.size) < 0.1)
    with RecordingWriter(tmp_path / "back.h5", clock=ManualClock()) as writer:
        for chunk in np.array_split(np.arange(t.size), 97):
            writer.put_events(t[chunk] % 1280, t[chunk] % 720, t[chunk] % 2, t[chunk], int(t[chunk][-1] - 9_000_000))
    with Recording(tmp_path / "back.h5") as rec:
        model = rec.clock_model("camera")
        host = model.to_host_us_int(t)
        for t0 in rng.uniform(host.min(), host.max(), 50):
            got = rec.events_between(t0, t0 + 2_500)
            assert np.array_equal(np.sort(got["t"]), np.sort(host[(host >= t0) & (host < t0 + 2_500)]))


def test_exception_inside_the_writer_block_marks_the_run_aborted(tmp_path: Path) -> None:
    path = tmp_path / "aborted.h5"
    with pytest.raises(RuntimeError, match="probe hit"):
        with RecordingWriter(path, RecordingMetadata(indenter="cylinder")) as writer:
            writer.put("cnc", t_host_us=1, position_mm=[0, 0, 0], feed_mm_min=0, state=b"Idle")
            writer.phase_begin("normal_down", 5)
            raise RuntimeError("probe hit the window")
    with Recording(path) as rec:
        assert rec.exit_status == "aborted"
        assert "probe hit" in rec.attrs["exit_reason"]
        assert rec.rows("cnc") == 1
        assert rec.phases()[0].name == "normal_down"


def test_a_full_queue_is_counted_and_reported(tmp_path: Path) -> None:
    path = tmp_path / "drops.h5"
    writer = RecordingWriter(path, queue_batches=2, flush_interval_s=5.0)
    writer.open()
    gate = threading.Event()
    # Hold the writer thread inside its first write so the queue fills up.
    original = writer._write

    def slow_write(*args, **kwargs):  # type: ignore[no-untyped-def]
        gate.wait(5)
        return original(*args, **kwargs)

    writer._write = slow_write  # type: ignore[method-assign]
    accepted = [writer.put("gcode", t_host_us=i, direction=0, line=b"G0 X0") for i in range(2000)]
    gate.set()
    result = writer.close()
    assert accepted.count(False) > 0
    assert result.dropped["gcode"] == accepted.count(False)
    with Recording(path) as rec:
        assert rec.rows("gcode") == accepted.count(True)
        drops = rec.stream("drops")
        assert drops["rows"].sum() == accepted.count(False)
        assert set(drops["reason"]) == {b"queue-full"}


class _CountingEvent(threading.Event):
    """An Event that counts its set() calls."""

    def __init__(self) -> None:
        super().__init__()
        self.sets = 0

    def set(self) -> None:
        self.sets += 1
        super().set()


def test_a_writer_that_is_not_woken_by_puts_still_writes_every_row(tmp_path: Path) -> None:
    # wake_on_put=False (virtual time): puts leave the writer thread to its poll, except when a queue is half
    # full, and every row still reaches the file.
    run = SyntheticRun(duration_s=0.5, peak_event_rate_hz=1e5, trigger_period_s=0)
    path = tmp_path / "polled.h5"
    writer = RecordingWriter(path, queue_batches=64, wake_on_put=False)
    writer._wake = wake = _CountingEvent()  # before the thread starts waiting on it
    writer.open()
    batches = list(run.ft_batches())
    for batch in batches[:10]:
        writer.put("ft", **batch)
    assert wake.sets == 0  # ten batches: below half of 64, nobody woke the thread
    gate = threading.Event()
    original = writer._add_pending

    def held(*args, **kwargs):  # type: ignore[no-untyped-def]
        gate.wait(5)  # the writer thread stays away from the queues while they fill
        return original(*args, **kwargs)

    writer._add_pending = held  # type: ignore[method-assign]
    for i in range(40):
        writer.put("gcode", t_host_us=i, direction=0, line=b"G0 X0")
    assert wake.sets >= 1  # the gcode queue reached 32 of 64: the thread was woken
    gate.set()
    for batch in batches[10:]:
        writer.put("ft", **batch)
    result = writer.close()
    assert not result.dropped
    with Recording(path) as rec:
        assert rec.rows("ft") == sum(len(b["t_host_us"]) for b in batches)
        assert rec.rows("gcode") == 40


class _WaitLog(threading.Event):
    """The writer's wake event, counting the waits begun once the writer was told to stop."""

    def __init__(self, stop: threading.Event) -> None:
        super().__init__()
        self.stop, self.waits_after_stop = stop, 0

    def wait(self, timeout: float | None = None) -> bool:
        if self.stop.is_set():
            self.waits_after_stop += 1
        return super().wait(timeout)


def test_a_closing_writer_writes_what_is_left_without_waiting_for_its_poll(tmp_path: Path) -> None:
    run = SyntheticRun(duration_s=0.2, peak_event_rate_hz=1e5, trigger_period_s=0)
    writer = RecordingWriter(tmp_path / "closing.h5", wake_on_put=False)
    writer._wake = wake = _WaitLog(writer._stop)
    writer.open()
    batches = list(run.ft_batches())
    for batch in batches:
        writer.put("ft", **batch)
    writer.close()
    assert wake.waits_after_stop == 0  # it used to sleep out one more poll (up to POLL_S) before writing
    with Recording(tmp_path / "closing.h5") as rec:
        assert rec.rows("ft") == sum(len(b["t_host_us"]) for b in batches)


def test_writer_refuses_to_overwrite_and_rejects_bad_rows(tmp_path: Path) -> None:
    path = tmp_path / "exists.h5"
    path.write_bytes(b"")
    with pytest.raises(RecordingError, match="already exists"):
        RecordingWriter(path).open()
    with pytest.raises(ValueError, match="unknown codec"):
        RecordingWriter(tmp_path / "x.h5", bulk_codec="rar")
    with RecordingWriter(tmp_path / "ok.h5") as writer:
        with pytest.raises(ValueError, match="missing columns"):
            writer.put("ft", t_host_us=1)
        with pytest.raises(ValueError, match="shape"):
            writer.put("cnc", t_host_us=1, position_mm=[1, 2], feed_mm_min=0, state=b"Idle")
        with pytest.raises(KeyError):
            writer.put("nonsense", a=1)


def test_online_clock_model_is_available_while_recording(tmp_path: Path) -> None:
    ft_clock = DeviceClock(origin_us=0, drift_ppm=50)
    run = SyntheticRun(duration_s=1.0, peak_event_rate_hz=1e5, trigger_period_s=0, ft_clock=ft_clock)
    with RecordingWriter(tmp_path / "live.h5", flush_interval_s=0.05) as writer:
        for batch in run.ft_batches():
            writer.put("ft", **batch)
        deadline = threading.Event()
        for _ in range(100):
            if writer.clock_model("ft") is not None and writer.clock_model("ft").n_pairs == 800:
                break
            deadline.wait(0.02)
        live = writer.clock_model("ft")
    assert live is not None and live.n_pairs == 800
    assert abs(live.drift_ppm + 50) < 5


def test_extra_truth_streams_live_under_truth(tmp_path: Path) -> None:
    from labrig.recording.schema import Column, StreamSpec

    truth = StreamSpec(
        "truth/markers",
        (Column("t_host_us", "<i8", "us", "time"), Column("position_px", "<f4", "px", "marker centres", (156, 2))),
        chunk_rows=64,
        description="true marker positions",
    )
    with RecordingWriter(tmp_path / "truth.h5", extra_streams=(truth,)) as writer:
        writer.put("truth/markers", t_host_us=[0, 1], position_px=np.ones((2, 156, 2)))
    with h5py.File(tmp_path / "truth.h5") as f:
        assert f["truth/markers/position_px"].shape == (2, 156, 2)
    with Recording(tmp_path / "truth.h5") as rec:
        assert rec.rows("truth/markers") == 2


def test_the_sims_truth_streams_use_their_own_codec(tmp_path: Path) -> None:
    import hdf5plugin

    from labrig.sim.truth import truth_streams

    streams = truth_streams(156)
    with RecordingWriter(tmp_path / "truth.h5", extra_streams=streams) as writer:
        writer.put("truth/markers", t_host_us=[0, 1], position_mm=np.ones((2, 156, 3)), position_px=np.ones((2, 156, 2)))
    with h5py.File(tmp_path / "truth.h5") as f:
        blosc2_filter = str(hdf5plugin.Blosc2.filter_id)
        assert blosc2_filter in f["truth/markers/position_px"]._filters
        assert blosc2_filter in f["truth/depth/depth_mm"]._filters
        assert f["streams/ft/force_n"].compression == "gzip"  # the rest stays portable
    with Recording(tmp_path / "truth.h5") as rec:
        np.testing.assert_array_equal(rec.column("truth/markers", "position_px"), np.ones((2, 156, 2)))


def test_synthetic_recording_through_each_portable_codec(tmp_path: Path) -> None:
    run = SyntheticRun(duration_s=0.5, peak_event_rate_hz=2e5)
    for codec in ("gzip", "lzf"):
        result = record_synthetic(tmp_path / f"{codec}.h5", run, bulk_codec=codec)
        with h5py.File(result.path) as f:
            assert f["streams/events/x"].compression == codec
            assert f["streams/events/x"].shape[0] == result.rows["events"] > 0
