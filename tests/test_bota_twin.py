"""Bota twin on a manual time line: boot, commands, pacing, clock, measurements, faults."""

from __future__ import annotations

import numpy as np
import pytest

from labrig.devices.bota_protocol import (
    Ack,
    AppInit,
    CommSetup,
    CrcError,
    FilterSetup,
    Frame,
    Status,
    SyncLost,
    TextLine,
    decode_all,
)
from labrig.sim.bota_twin import BotaTwin, BotaTwinParams

BOOT_US = 10_000


def make(**overrides) -> BotaTwin:
    params = {"boot_delay_us": BOOT_US, "filter": FilterSetup(64), **overrides}
    wrench = params.pop("wrench_at", None)
    hook = params.pop("frame_hook", None)
    return BotaTwin(BotaTwinParams(**params), wrench_at=wrench, frame_hook=hook)


def run(twin: BotaTwin, t0_us: int, t1_us: int, step_us: int = 500) -> bytes:
    """What the twin sends while the host polls it every ``step_us`` from t0 to t1 (inclusive)."""
    return b"".join(twin.transmit(t) for t in range(t0_us, t1_us + 1, step_us))


def frames_of(data: bytes) -> list[Frame]:
    return [e for e in decode_all(data) if isinstance(e, Frame)]


def acks_of(data: bytes) -> list[Ack]:
    return [e for e in decode_all(data) if isinstance(e, Ack)]


def test_boots_then_streams_at_the_sinc_rate() -> None:
    twin = make()
    assert run(twin, 0, BOOT_US - 500) == b""
    out = run(twin, BOOT_US, BOOT_US + 1_000_000)
    events = decode_all(out)
    assert events[0] == AppInit() and twin.mode == "run" and twin.boots == 1
    frames = frames_of(out)
    assert len(frames) in (799, 800)
    assert set(np.diff([f.t_device_us for f in frames]).tolist()) == {1250}


def test_bytes_leave_at_the_baud_rate() -> None:
    twin = make()
    run(twin, 0, BOOT_US + 20_000, 20_000 + BOOT_US)  # boot text and a few frames are sent
    t_sample = twin.host_us_of(twin._next_sample_dev_us)
    twin.transmit(int(t_sample) - 1)
    partial = twin.transmit(int(t_sample) + 400)  # 37 bytes take 37 * 10 / 460800 s = 803 us
    assert 17 <= len(partial) <= 19 and partial[0] == 0xAA
    rest = twin.transmit(int(t_sample) + 900)
    assert len(partial + rest) == 37


def test_device_clock_offset_drift_and_wrap() -> None:
    twin = make(clock_offset_us=2**32 - 300_000, clock_drift_ppm=100.0)
    out = run(twin, 1_000_000, 1_000_000 + BOOT_US + 600_000)
    stamps = np.array([f.t_device_us for f in frames_of(out)], dtype=np.int64)
    assert stamps.max() > 2**32 - 2000 and stamps.min() < 300_000  # wrapped
    unwrapped = np.where(stamps < 2**31, stamps + 2**32, stamps)
    assert set(np.diff(unwrapped).tolist()) <= {1249, 1250, 1251}
    assert twin.device_us(1_000_000) == 2**32 - 300_000
    assert twin.device_us(2_000_000) == pytest.approx(2**32 - 300_000 + 1_000_100)
    assert twin.host_us_of(twin.device_us(1_234_567)) == pytest.approx(1_234_567)


def test_measurements_load_bias_noise_and_temperature() -> None:
    twin = make(wrench_at=lambda t_us: ((0.0, 0.0, -10.0), (0.0, 0.05, 0.0)), seed=3)
    frames = frames_of(run(twin, 0, BOOT_US + 2_000_000, 1000))
    force = np.array([f.force_n for f in frames])
    torque = np.array([f.torque_nm for f in frames])
    p = twin.params
    assert np.allclose(force.mean(0), np.add((0, 0, -10), p.force_bias_n), atol=0.01)
    assert np.allclose(torque.mean(0), np.add((0, 0.05, 0), p.torque_bias_nm), atol=2e-4)
    assert force.std(0) == pytest.approx([0.02] * 3, rel=0.15)
    assert torque.std(0) == pytest.approx([0.0005] * 3, rel=0.15)
    assert all(f.status == 0 for f in frames)
    assert 24.0 - 0.05 < frames[-1].temperature_c < 24.1


def test_bias_follows_the_warm_up() -> None:
    twin = make(self_heating_c=10.0, warmup_tau_s=1.0, force_noise_n=0.0, temperature_noise_c=0.0)
    run(twin, 0, BOOT_US + 5_000_000, 100_000)
    last = frames_of(run(twin, BOOT_US + 5_000_100, BOOT_US + 5_010_000))[-1]
    assert last.temperature_c == pytest.approx(34.0, abs=0.1)
    assert last.force_n[2] == pytest.approx(1.8 + 0.05 * 10.0, abs=0.01)


def test_same_seed_same_bytes() -> None:
    a, b = make(seed=9), make(seed=9)
    assert run(a, 0, 100_000) == run(b, 0, 100_000)
    assert run(make(seed=1), 0, 100_000) != run(make(seed=2), 0, 100_000)


def booted(**overrides) -> BotaTwin:
    twin = make(**overrides)
    run(twin, 0, BOOT_US + 5000)
    return twin


def talk(twin: BotaTwin, t_us: int, data: bytes, until_us: int | None = None) -> bytes:
    twin.receive(data, t_us)
    return run(twin, t_us, until_us or t_us + 5000, 100)


def test_config_mode_commands_and_acks() -> None:
    twin = booted()
    out = talk(twin, 20_000, b"C")
    assert acks_of(out) == [Ack(0, "C", 0)] and twin.mode == "config"
    assert frames_of(run(twin, 25_000, 60_000)) == []
    out = talk(twin, 60_000, b"c,0,1,0,4\nf,128,0,0,1\rb,1,2,3,0.1,0.2,0.3\nm0,2,0,0,0,0,0\nx\np?\nf,12,0,0,1\n")
    assert [(a.command, a.rc) for a in acks_of(out)] == [("c", 0), ("f", 0), ("b", 0), ("m", 0), ("x", 1), ("p", 1), ("f", 2)]
    assert twin.filter == FilterSetup(128) and twin.offsets.force_n == (1.0, 2.0, 3.0)
    out = talk(twin, 70_000, b"w", 85_000)  # ~450 bytes: 10 ms on the line
    lines = [e.text for e in decode_all(out) if isinstance(e, TextLine)]
    assert acks_of(out) == [Ack(0, "w", 0)]
    assert "f,128,0,0,1" in lines and "b,1.000,2.000,3.000,0.100,0.200,0.300" in lines
    out = talk(twin, 90_000, b"R", 110_000)
    assert acks_of(out) == [Ack(0, "R", 0)]
    frames = frames_of(out)
    assert np.diff([f.t_device_us for f in frames]).tolist() == [2500] * (len(frames) - 1)
    assert frames[0].force_n[0] == pytest.approx(2 * 0.35 + 1.0, abs=0.1)  # row 0 doubled, plus the offset


def test_commands_in_run_mode_are_refused() -> None:
    twin = booted()
    assert [(a.command, a.rc) for a in acks_of(talk(twin, 20_000, b"f,64,0,0,1\n"))] == [("f", 3)]
    assert twin.mode == "run"


def test_command_without_terminator_ends_after_an_idle_gap() -> None:
    twin = booted()
    talk(twin, 20_000, b"C")
    twin.receive(b"f,2", 30_000)
    twin.receive(b"56,0,0,1", 31_000)
    assert acks_of(run(twin, 31_000, 80_000)) == []
    assert acks_of(run(twin, 80_100, 82_000)) == [Ack(0, "f", 0)]
    assert twin.filter.sinc_length == 256


def test_stop_finishes_the_frame_on_the_line_then_acks() -> None:
    twin = booted()
    run(twin, BOOT_US + 5000, 30_000, 100)
    t_sample = int(twin.host_us_of(twin._next_sample_dev_us))
    head = run(twin, 30_100, t_sample + 300, 100)
    out = talk(twin, t_sample + 300, b"C")
    events = [e for e in decode_all(head + out) if isinstance(e, Frame | Ack)]
    assert isinstance(events[-1], Ack) and isinstance(events[-2], Frame)


def test_new_baud_rate_after_save_and_reset_only() -> None:
    twin = booted()
    talk(twin, 20_000, b"C")
    talk(twin, 30_000, b"c,0,1,0,3\n")
    assert twin.comm == CommSetup(baud_code=3) and twin.line_baud_rate == 460_800
    talk(twin, 40_000, b"s")
    twin.receive(b"#", 50_000)
    assert twin.mode == "booting"
    twin.receive(b"C", 55_000)  # the bootloader does not listen
    out = run(twin, 50_000, 50_000 + BOOT_US + 20_000, 100)
    assert twin.line_baud_rate == 230_400 and twin.mode == "run" and twin.boots == 2
    assert acks_of(out) == [] and AppInit() in decode_all(out)


def test_reset_without_save_keeps_the_saved_config() -> None:
    twin = booted()
    talk(twin, 20_000, b"C")
    talk(twin, 30_000, b"f,512,0,0,1\n")
    twin.receive(b"#", 40_000)
    run(twin, 40_000, 40_000 + BOOT_US + 1000)
    assert twin.filter == FilterSetup(64)


def test_throttled_when_the_line_is_too_slow() -> None:
    twin = booted(comm=CommSetup(baud_code=2))  # 115200 baud: 3.2 ms per frame, 1.25 ms period
    frames = frames_of(run(twin, BOOT_US + 5000, 500_000, 200))
    assert twin.samples_skipped > 0
    assert all(f.flags & Status.APP_TOOK_TOO_LONG for f in frames[1:])
    assert np.diff([f.t_device_us for f in frames]).min() > 1250


def test_overrange_clips_and_raw_mode_flags() -> None:
    twin = booted(wrench_at=lambda t: ((600.0, 0, 0), (0, 0, 0)), comm=CommSetup(calibrated=False))
    frames = frames_of(run(twin, BOOT_US + 5000, 40_000, 100))
    assert all(f.flags == Status.OVERRANGE | Status.RAW_MEASUREMENTS for f in frames)
    assert max(f.force_n[0] for f in frames) < 500.1


def test_fault_injection() -> None:
    twin = booted()
    twin.corrupt_frames(1)
    twin.set_status_bits(Status.INVALID_MEASUREMENTS)
    out = run(twin, BOOT_US + 5000, 30_000, 100)
    twin.inject_garbage(b"\x00\x01junk")
    events = decode_all(out + run(twin, 30_100, 40_000, 100))
    assert sum(isinstance(e, SyncLost) for e in events) == 2  # the bad CRC, then the garbage
    assert sum(isinstance(e, CrcError) for e in events) == 1
    frames = [e for e in events if isinstance(e, Frame)]
    assert len(frames) > 10 and all(f.flags & Status.INVALID_MEASUREMENTS for f in frames[1:])  # [0] was queued before
    hooked = booted(frame_hook=lambda data: data + b"!")
    assert hooked.frame_hook is not None
    assert frames_of(run(hooked, BOOT_US + 5000, 40_000, 100))


def read_both_ways(make_twin, reads_us: range) -> tuple[list[tuple[int, Frame]], list[tuple[int, Frame]]]:
    """(read time, frame) of the frames a host reading at ``reads_us`` gets: through the bytes and a
    receiver, and from :meth:`BotaTwin.read_frames` (the bytes whenever it declines)."""
    from labrig.devices.bota_protocol import BotaReceiver

    by_bytes, whole = [], []
    twin, receiver = make_twin(), BotaReceiver()
    for t in reads_us:
        by_bytes += [(t, e) for e in receiver.feed(twin.transmit(t)) if isinstance(e, Frame)]
    twin, receiver = make_twin(), BotaReceiver()
    for t in reads_us:
        frames = twin.read_frames(t)
        if frames is None:
            frames = [e for e in receiver.feed(twin.transmit(t)) if isinstance(e, Frame)]
        whole += [(t, f) for f in frames]
    return by_bytes, whole


def test_frames_read_whole_are_the_receivers_frames_at_the_same_reads() -> None:
    def loaded() -> BotaTwin:  # a load with float32 rounding to do, a drifting clock
        return make(wrench_at=lambda t: ((0.1 + t * 1e-7, -2.0 / 3.0, -5.0 - t * 1e-6), (1e-3, 0.0, 2e-3)), seed=4,
                    clock_drift_ppm=37.0, clock_offset_us=2**32 - 50_000)
    by_bytes, whole = read_both_ways(loaded, range(0, BOOT_US + 200_000, 1000))
    assert len(by_bytes) > 150 and whole == by_bytes
    twin = loaded()
    assert twin.read_frames(0) is None  # booting: the boot text goes through the receiver
    # Reads that land between a frame's bytes: a frame is handed over at the first read after its last byte.
    by_bytes, whole = read_both_ways(loaded, range(0, BOOT_US + 50_000, 290))
    assert whole == by_bytes


def test_frames_in_flight_go_out_as_bytes_when_the_line_carries_more() -> None:
    from labrig.devices.bota_protocol import BotaReceiver

    twin, receiver = make(seed=5), BotaReceiver()
    got: list[Frame] = []
    events: list = []
    t = 0
    while not (twin._whole and t > BOOT_US + 20_000):  # whole frames until one is on the line, not yet read
        t += 100
        frames = twin.read_frames(t)
        if frames is None:
            events += receiver.feed(twin.transmit(t))
        else:
            got += frames
    twin.inject_garbage(b"noise\r\n")
    assert twin.read_frames(t + 100) is None
    events += receiver.feed(twin.transmit(t + 5000))
    in_flight = [e for e in events if isinstance(e, Frame)]
    assert got and in_flight and not any(isinstance(e, (SyncLost, CrcError)) for e in events)  # whole and in order
    events += receiver.feed(twin.transmit(t + 10_000))  # the garbage, queued at t + 5000
    assert any(isinstance(e, SyncLost) for e in events)
    after = [e for e in events if isinstance(e, Frame)]
    reference = frames_of(run(make(seed=5), 0, t + 10_000, 100))
    assert sorted(after + got, key=lambda f: f.t_device_us) == reference  # none lost, none twice


def test_user_matrix_and_offsets_apply_to_every_sample() -> None:
    from labrig.devices.bota_protocol import cmd_matrix_row

    def with_matrix(rows: dict[int, list[float]]) -> list[Frame]:
        twin = booted(wrench_at=lambda t: ((1.0, 2.0, 3.0), (0.1, 0.2, 0.3)), force_noise_n=0.0, torque_noise_nm=0.0,
                      seed=2)
        talk(twin, 20_000, b"C")
        commands = "".join(cmd_matrix_row(i, row).text + "\n" for i, row in rows.items()) + "b,1,0,0,0,0,0.5\n"
        talk(twin, 30_000, commands.encode())
        return frames_of(talk(twin, 40_000, b"R", 60_000))

    plain, mixed = with_matrix({}), with_matrix({0: [0, 1, 0, 0, 0, 0], 5: [0, 0, 0, 0, 0, 2]})
    for a, b in zip(plain, mixed):
        assert b.force_n[0] == pytest.approx(a.force_n[1] + 1.0, abs=1e-6)  # row 0 reads gauge 1, plus its offset
        assert b.force_n[1:] == a.force_n[1:]
        assert b.torque_nm[2] == pytest.approx(2 * (a.torque_nm[2] - 0.5) + 0.5, abs=1e-6)
    assert len(plain) > 10 and plain[0].force_n[0] == pytest.approx(1.0 + 0.35 + 1.0, abs=0.05)
