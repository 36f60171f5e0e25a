"""Bota codec: CRC, frame layout, commands and acknowledgements, boot text, sync and resync, fuzzing."""

from __future__ import annotations

import itertools
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labrig.devices.bota_protocol import (
    FRAME_SIZE,
    Ack,
    AppInit,
    BootInfo,
    BotaReceiver,
    CommandError,
    CommSetup,
    CommSetupLine,
    CrcError,
    FilterSetup,
    Frame,
    InfoLine,
    MatrixRow,
    Offsets,
    Status,
    SyncAcquired,
    SyncLost,
    TextLine,
    cmd_comm_setup,
    cmd_config_mode,
    cmd_filter,
    cmd_hardware_reset,
    cmd_matrix_row,
    cmd_offsets,
    cmd_run_mode,
    cmd_save,
    crc16_x25,
    decode_all,
    encode_ack,
    encode_boot_text,
    encode_frame,
    parse_command,
    status_names,
)

#: CRC-16/X-25 of a message followed by its own CRC (little-endian) is this constant.
X25_RESIDUE = 0x0F47


def frame(t_us: int, fz: float = 1.5, status: int = 0) -> Frame:
    return Frame(status, (0.25, -0.5, fz), (0.125, 0.0, -0.0625), t_us, 31.5)


def frames_bytes(n: int, t0: int = 1000, step: int = 1250) -> tuple[list[Frame], bytes]:
    fs = [frame((t0 + i * step) % 2**32, fz=float(i)) for i in range(n)]
    return fs, b"".join(encode_frame(f) for f in fs)


def only(events: list, kind: type) -> list:
    return [e for e in events if isinstance(e, kind)]


# -- CRC and frame layout ---------------------------------------------------------


def test_crc16_x25_check_value_and_residue() -> None:
    assert crc16_x25(b"123456789") == 0x906E
    assert crc16_x25(b"") == 0x0000
    data = b"\x01\x02\xaa\xff" * 8
    assert crc16_x25(data + crc16_x25(data).to_bytes(2, "little")) == X25_RESIDUE


@given(st.binary(max_size=80))
def test_crc16_x25_is_the_bitwise_definition(data: bytes) -> None:
    """The C-backed CRC against the definition: reflected poly 0x8408, bit by bit."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
    assert crc16_x25(data) == crc16_x25(bytearray(data)) == crc16_x25(memoryview(data)) == crc ^ 0xFFFF


def test_frame_layout_field_by_field() -> None:
    f = Frame(0x0005, (1.0, -2.0, 3.5), (0.25, 0.5, -0.75), 0xFFFF_FFF0, 27.25)
    data = encode_frame(f)
    assert len(data) == FRAME_SIZE == 37
    assert data[0] == 0xAA
    assert data[1:3] == b"\x05\x00"
    assert data[3:27] == b"".join(struct.pack("<f", v) for v in (1.0, -2.0, 3.5, 0.25, 0.5, -0.75))
    assert data[27:31] == b"\xf0\xff\xff\xff"
    assert data[31:35] == struct.pack("<f", 27.25)
    assert int.from_bytes(data[35:37], "little") == crc16_x25(data[1:35])
    assert crc16_x25(data[1:]) == X25_RESIDUE  # the header is outside the CRC
    assert decode_all(data)[-1] == f


def test_timestamp_is_taken_modulo_2_32() -> None:
    assert decode_all(encode_frame(frame(2**32 + 7)))[-1].t_device_us == 7


def test_status_bits() -> None:
    assert Status.THROTTLED is Status.APP_TOOK_TOO_LONG
    assert status_names(0) == []
    assert status_names(0b1111 | 0x100) == ["app_took_too_long", "overrange", "invalid_measurements", "raw_measurements"]
    assert frame(0, status=0x16).flags == Status.OVERRANGE | Status.INVALID_MEASUREMENTS


# -- commands ------------------------------------------------------------------------


def test_command_bytes() -> None:
    assert cmd_config_mode().encode() == b"C"
    assert cmd_run_mode().encode() == b"R"
    assert cmd_save().encode(b"\r\n") == b"s"
    assert cmd_hardware_reset().encode() == b"#"
    assert not cmd_hardware_reset().expects_ack and cmd_save().expects_ack
    assert cmd_comm_setup(CommSetup()).encode() == b"c,0,1,0,4\n"
    assert cmd_comm_setup(CommSetup(True, False, 0, 2)).encode(b"") == b"c,1,0,0,2"
    assert cmd_filter(FilterSetup(64)).encode() == b"f,64,0,0,1\n"
    assert cmd_filter(FilterSetup(2048, True, True, False)).encode() == b"f,2048,1,1,0\n"
    assert cmd_offsets(Offsets((1.2345, -0.0001, 0.0), (0.5, -0.25, 3.0))).encode() == b"b,1.234,0.000,0.000,0.500,-0.250,3.000\n"
    assert cmd_matrix_row(2, [1, 0, 0, 0, 0, -0.5]).encode() == b"m2,1.000000,0.000000,0.000000,0.000000,0.000000,-0.500000\n"


@pytest.mark.parametrize("sinc", [63, 2049, 0])
def test_sinc_length_is_validated(sinc: int) -> None:
    with pytest.raises(ValueError, match="sinc length"):
        FilterSetup(sinc)


def test_sample_rate_from_sinc_length() -> None:
    assert FilterSetup(64).sample_rate_hz == 800.0 and FilterSetup(64).period_us == 1250.0
    assert FilterSetup(512).period_us == 10_000.0


def test_bad_commands_are_refused_before_sending() -> None:
    with pytest.raises(ValueError):
        CommSetup(baud_code=7)
    with pytest.raises(ValueError):
        cmd_matrix_row(6, [0] * 6)
    with pytest.raises(ValueError, match="64"):
        cmd_matrix_row(0, [1e9] * 6)


def test_parse_command_as_the_sensor_does() -> None:
    assert parse_command("C") == ("C", None)
    assert parse_command("c,0,1,0,4\r") == ("c", CommSetup(False, True, 0, 4))
    assert parse_command("f,64,0,0,1") == ("f", FilterSetup(64, False, False, True))
    assert parse_command("b,1,2,3,4,5,6") == ("b", Offsets((1.0, 2.0, 3.0), (4.0, 5.0, 6.0)))
    assert parse_command("m5, 1.000000, 0,0,0,0, 2") == ("m", MatrixRow(5, (1.0, 0.0, 0.0, 0.0, 0.0, 2.0)))
    for text, rc in [("x", 1), ("p?", 1), ("f,10,0,0,1", 2), ("c,0,1,0", 2), ("c,0,1,0,9", 2), ("Cx", 2), ("b,1,2", 2)]:
        with pytest.raises(CommandError) as info:
            parse_command(text)
        assert info.value.rc == rc, text


def test_acknowledgements() -> None:
    assert encode_ack("C") == b"r,0,C,0\r\n"
    events = decode_all(b"r,0,C,0\r\nr,0,f,2\nr,1,?,1\r")
    assert events == [Ack(0, "C", 0), Ack(0, "f", 2), Ack(1, "?", 1)]
    assert events[0].ok and not events[1].ok


def test_boot_text_is_parsed() -> None:
    info = BootInfo(name="Rokubi Serial", serial_number="ABC123", firmware_version="1.4.2")
    text = encode_boot_text(info, CommSetup(baud_code=3))
    events = decode_all(b"\x00\xfe" + text)  # bootloader noise first
    assert events == [
        AppInit(),
        InfoLine("name", "Rokubi Serial"),
        InfoLine("serial_number", "ABC123"),
        InfoLine("firmware_version", "1.4.2"),
        CommSetupLine(CommSetup(baud_code=3)),
    ]
    parsed = BootInfo()
    for e in events:
        parsed = parsed.updated(e)
    assert parsed == BootInfo(True, "Rokubi Serial", "ABC123", "1.4.2", CommSetup(baud_code=3))


# -- sync ----------------------------------------------------------------------------------


def test_frames_decode_across_any_split() -> None:
    fs, data = frames_bytes(5)
    for size in (1, 2, 36, 37, 38, 100):
        rx = BotaReceiver()
        events = [e for i in range(0, len(data), size) for e in rx.feed(data[i : i + size])]
        assert only(events, Frame) == fs
        assert events[0] == SyncAcquired(0, False)
        assert rx.buffered_bytes == 0


def test_text_then_frames_then_text() -> None:
    fs, data = frames_bytes(3)
    events = decode_all(b"r,0,R,0\r\n" + data + b"r,0,C,0\r\n")
    assert events == [Ack(0, "R", 0), SyncAcquired(9, False), *fs, SyncLost("bad_header"), Ack(0, "C", 0)]


def test_resync_after_garbage() -> None:
    fs, data = frames_bytes(6)
    garbage = b"\x00\x13\xaa\x01\x02\xfe"
    rx = BotaReceiver()
    events = rx.feed(data[: 3 * 37] + garbage + data[3 * 37 :])
    assert only(events, Frame) == fs
    assert SyncLost("bad_header") in events and SyncAcquired(len(garbage), True) in events
    c = rx.counters()
    assert (c.frames, c.crc_errors, c.sync_losses, c.resyncs, c.skipped_bytes) == (6, 0, 1, 1, len(garbage))


def test_bad_crc_drops_the_frame_and_resyncs() -> None:
    fs, data = frames_bytes(5)
    bad = bytearray(data)
    bad[2 * 37 + 10] ^= 0x01  # one bit in the third frame's payload
    rx = BotaReceiver()
    events = rx.feed(bytes(bad))
    assert only(events, Frame) == fs[:2] + fs[3:]
    assert len(only(events, CrcError)) == 1 and SyncLost("bad_crc") in events and SyncAcquired(37, True) in events
    assert rx.counters().resyncs == 1 and rx.counters().skipped_bytes == 37


def test_truncated_frame_costs_one_frame() -> None:
    fs, data = frames_bytes(4)
    cut = data[:37] + data[37 : 37 + 20] + data[2 * 37 :]
    assert only(decode_all(cut), Frame) == [fs[0], *fs[2:]]


def test_no_lock_without_a_good_crc() -> None:
    _, data = frames_bytes(1)
    bad = bytearray(data)
    bad[-1] ^= 0xFF
    rx = BotaReceiver()
    assert only(rx.feed(bytes(bad) * 3), Frame) == []
    assert not rx.locked and rx.counters().frames == 0


def test_restart_sync_makes_the_next_lock_a_first_lock() -> None:
    _, data = frames_bytes(2)
    rx = BotaReceiver()
    rx.feed(data + b"r,0,C,0\r\n")
    rx.restart_sync()
    events = rx.feed(b"r,0,R,0\r\n" + data)
    assert SyncAcquired(9, False) in events and rx.counters().resyncs == 0


def test_garbage_text_is_bounded() -> None:
    rx = BotaReceiver(max_line_chars=16)
    rx.feed(b"A" * 100)
    assert rx.buffered_bytes == 0 and rx.counters().skipped_bytes == 100
    assert rx.feed(b"xyz") == [] and rx.buffered_bytes == 3
    assert rx.feed(b"\n") == [TextLine("xyz")]


# -- fuzzing ----------------------------------------------------------------------------------

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def feed_in_chunks(data: bytes, cuts: list[int]) -> tuple[BotaReceiver, list]:
    rx = BotaReceiver()
    events: list = []
    bounds = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
    for a, b in itertools.pairwise(bounds):
        events += rx.feed(data[a:b])
    return rx, events


def assert_frames_genuine(events: list, data: bytes) -> None:
    """Every decoded frame is 37 bytes of the input with a matching CRC."""
    for f in only(events, Frame):
        raw = encode_frame(f)
        assert raw in data, f
        assert crc16_x25(raw[1:]) == X25_RESIDUE


@FUZZ
@given(st.binary(max_size=600), st.lists(st.integers(0, 10_000), max_size=8))
def test_fuzz_random_bytes(data: bytes, cuts: list[int]) -> None:
    rx, events = feed_in_chunks(data, cuts)
    assert_frames_genuine(events, data)
    c = rx.counters()
    assert c.bytes_in == len(data) and rx.buffered_bytes <= max(FRAME_SIZE, rx.max_line_chars + 1)


@FUZZ
@given(
    n=st.integers(1, 12),
    damage=st.lists(
        st.tuples(st.integers(0, 10_000), st.sampled_from(["flip", "cut", "insert"]), st.binary(min_size=1, max_size=40)),
        max_size=4,
    ),
    cuts=st.lists(st.integers(0, 10_000), max_size=8),
)
def test_fuzz_damaged_frame_streams(n: int, damage: list[tuple[int, str, bytes]], cuts: list[int]) -> None:
    fs, clean = frames_bytes(n, t0=4_294_960_000)  # wraps on the way
    data = bytearray(clean)
    marks: list[int] = []  # ends of damaged spans, kept in step with later edits
    for where, kind, blob in damage:
        i = where % (len(data) + 1)
        if kind == "flip" and i < len(data):
            data[i] ^= blob[0] or 1
            marks.append(i + 1)
        elif kind == "cut":
            removed = len(data[i : i + len(blob)])
            del data[i : i + removed]
            marks = [m - removed if m > i + removed else min(m, i) for m in marks] + [i]
        else:
            data[i:i] = blob
            marks = [m + len(blob) if m > i else m for m in marks] + [i + len(blob)]
    last_damage = max(marks, default=-1)
    data = bytes(data)
    rx, events = feed_in_chunks(data, cuts)
    assert_frames_genuine(events, data)
    if not damage:
        assert only(events, Frame) == fs
        assert rx.counters().crc_errors == rx.counters().skipped_bytes == 0
    else:
        # Intact frames starting a frame's length past the last damage are all recovered.
        decoded = only(events, Frame)
        for f in fs:
            start = data.find(encode_frame(f))
            if start >= last_damage + FRAME_SIZE:
                assert f in decoded
