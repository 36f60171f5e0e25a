"""Streaming decoders: any chunking gives the one-call result; decoding semantics on hand-made words; skip log."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.devices.raw import (
    Evt2Decoder,
    Evt3Decoder,
    SkipReason,
    StreamDecoder,
    make_header,
    read_raw,
)


def w3(kind: str, value: int = 0, bit11: int = 0) -> int:
    """One EVT3 word."""
    code = {"AY": 0x0, "EMY": 0x1, "AX": 0x2, "VB": 0x3, "V12": 0x4, "V8": 0x5, "TL": 0x6, "C4": 0x7, "TH": 0x8, "TRIG": 0xA}
    code |= {"OTH": 0xE, "C12": 0xF, "BAD": 0xB}
    return (code[kind] << 12) | (bit11 << 11) | value


def pack3(words: list[int]) -> bytes:
    return np.array(words, "<u2").tobytes()


#: Every EVT3 feature in one small stream (geometry 1280x720).
# fmt: off
EVT3_ALL_WORDS = (
    [
        w3("AY", 3), w3("AX", 7), w3("TL", 5),  # before the first TIME_HIGH: skipped
        w3("TH", 4094), w3("AX", 1),  # an event at the base (y 0 by default)
        w3("TL", 100), w3("AY", 10), w3("AX", 20, 1), w3("AX", 21),
        w3("VB", 32, 1), w3("V12", 0b101), w3("V12", 0xFFF), w3("V8", 0x81),  # a triplet
        w3("OTH", 0x14), w3("C12", 0x123), w3("C12", 0x456), w3("C4", 0x7),  # an ERC counter group
        w3("TRIG", (3 << 8) | 1),
        w3("TL", 90), w3("AX", 22),  # TIME_LOW going back: kept
        w3("TH", 4094), w3("AX", 23),  # a repeated TIME_HIGH resets the low part
        w3("TH", 4095), w3("TL", 4000), w3("AX", 24),
        w3("TH", 0), w3("TL", 1), w3("AX", 25),  # 24-bit wrap
        w3("TRIG", (15 << 8) | 0),
        w3("EMY", 4), w3("AX", 26), w3("VB", 0), w3("V12", 1), w3("AY", 11), w3("AX", 27),  # EM mode: no CD events
        w3("BAD", 1), w3("C12", 5),  # unknown type, stray CONTINUED
        w3("AX", 1500), w3("AY", 800), w3("AX", 3),  # outside the geometry
        w3("AY", 12), w3("VB", 1248, 1), w3("V12", 0xFFF), w3("V12", 0xFFF), w3("V8", 0xFF),  # base + 32 = 1280: fits
    ]
)
# fmt: on
EVT3_ALL = pack3(EVT3_ALL_WORDS)

EVT3_ALL_EVENTS = [
    (1, 0, 0, 4094 << 12),
    (20, 10, 1, (4094 << 12) + 100),
    (21, 10, 0, (4094 << 12) + 100),
    *[(x, 10, 1, (4094 << 12) + 100) for x in [32, 34, *range(44, 56), 56, 63]],
    (22, 10, 0, (4094 << 12) + 90),
    (23, 10, 0, 4094 << 12),
    (24, 10, 0, (4095 << 12) + 4000),
    (25, 10, 0, (1 << 24) + 1),
    (27, 11, 0, (1 << 24) + 1),
    *[(x, 12, 1, (1 << 24) + 1) for x in range(1248, 1280)],
]


def decode_in_pieces(
    cls: type[StreamDecoder], data: bytes, cuts: list[int], **kw: int
) -> tuple[StreamDecoder, np.ndarray, np.ndarray]:
    dec = cls(**kw)
    outs = []
    prev = 0
    for cut in [*sorted(cuts), len(data)]:
        outs.append(dec.feed(data[prev:cut]))
        prev = cut
    dec.finish()
    return dec, np.concatenate([o.events for o in outs]), np.concatenate([o.triggers for o in outs])


def assert_same_decoders(a: StreamDecoder, b: StreamDecoder) -> None:
    assert a.skipped_words == b.skipped_words and a.dropped_events == b.dropped_events
    assert a.others_words == b.others_words and a.time_high_loops == b.time_high_loops
    np.testing.assert_array_equal(a.skips, b.skips)
    from labrig.devices.raw import _state

    keep = np.arange(_state.N_SLOTS) != _state.WORD_OFF  # where the last call's words began
    np.testing.assert_array_equal(a.state[keep], b.state[keep])


def test_evt3_semantics_on_every_word_type() -> None:
    dec = Evt3Decoder(1280, 720)
    out = dec.decode_all(EVT3_ALL)
    got = [tuple(int(v) for v in e) for e in out.events]
    assert got == EVT3_ALL_EVENTS
    assert [tuple(int(v) for v in r) for r in out.triggers] == [(1, (4094 << 12) + 100, 3), (0, (1 << 24) + 1, 15)]
    assert dec.time_high_loops == 1 and dec.others_words == 4 and dec.dropped_events == 2
    reasons = [SkipReason(int(r)) for r in dec.skips["reason"]]
    assert reasons == [
        SkipReason.BEFORE_TIME_HIGH,
        SkipReason.UNKNOWN_TYPE,
        SkipReason.ORPHAN_CONTINUED,
        SkipReason.OUT_OF_GEOMETRY,
        SkipReason.OUT_OF_GEOMETRY,
    ]
    assert list(dec.skips["offset"][:1]) == [0] and list(dec.skips["words"]) == [3, 1, 1, 1, 1]
    assert dec.skipped_words == 7


def test_evt3_semantics_match_the_evt3_package(tmp_path: Path) -> None:
    evt3 = pytest.importorskip("evt3", reason="the `evt3` PyPI package (test oracle) is not installed: pip install evt3")
    # the oracle has no geometry filter and its own EM handling: compare on the in-geometry CD part
    data = pack3(EVT3_ALL_WORDS[: EVT3_ALL_WORDS.index(w3("EMY", 4))])
    path = tmp_path / "all.raw"
    path.write_bytes(make_header("EVT3", 1280, 720) + data)
    ours = read_raw(path)
    theirs, trig = evt3.decode_file_with_triggers(str(path))
    np.testing.assert_array_equal(ours.events["x"], np.asarray(theirs.x))
    np.testing.assert_array_equal(ours.events["y"], np.asarray(theirs.y))
    np.testing.assert_array_equal(ours.events["p"], np.asarray(theirs.polarity))
    np.testing.assert_array_equal(ours.events["t"], np.asarray(theirs.timestamp).astype(np.int64))
    np.testing.assert_array_equal(ours.triggers["t"], np.asarray(trig.timestamp).astype(np.int64))
    np.testing.assert_array_equal(ours.triggers["p"], np.asarray(trig.value))
    np.testing.assert_array_equal(ours.triggers["id"], np.asarray(trig.id))


def test_skip_offsets_are_file_offsets(tmp_path: Path) -> None:
    head = make_header("EVT3", 1280, 720)
    payload = pack3(
        [w3("AX", 1), w3("AY", 2), w3("TH", 1), w3("TL", 0), w3("AX", 5), w3("BAD"), w3("BAD"), w3("C12"), w3("AX", 1400)]
    )
    path = tmp_path / "bad.raw"
    path.write_bytes(head + payload + b"\x01")  # a trailing partial word
    raw = read_raw(path)
    h = len(head)
    assert raw.payload_offset == h
    assert [tuple(int(v) for v in s) for s in raw.skips] == [
        (h, 2, SkipReason.BEFORE_TIME_HIGH),
        (h + 10, 2, SkipReason.UNKNOWN_TYPE),
        (h + 14, 1, SkipReason.ORPHAN_CONTINUED),
        (h + 16, 1, SkipReason.OUT_OF_GEOMETRY),
        (h + 18, 1, SkipReason.TRUNCATED),
    ]
    assert raw.skipped_words == 7 and raw.events.size == 1 and raw.skip_runs_total == 5


def test_evt2_semantics() -> None:
    def cd(p: int, x: int, y: int, t: int) -> int:
        return (p << 28) | ((t & 63) << 22) | (x << 11) | y

    # fmt: off
    words = [
        cd(1, 5, 5, 3),  # before the first TIME_HIGH
        (0x8 << 28) | 10, cd(1, 5, 6, 3), cd(0, 639, 479, 63),
        (0xE << 28) | 0x14, 0xF << 28, 0xF << 28,  # OTHERS + CONTINUED
        (0xA << 28) | (7 << 22) | (31 << 8) | 1,  # trigger id 31
        (0x8 << 28) | ((1 << 28) - 1), cd(0, 1, 1, 0),
        (0x8 << 28) | 2, cd(1, 2, 2, 1),  # 34-bit wrap
        0xF << 28, 0x3 << 28, cd(0, 640, 0, 0),  # stray CONTINUED, unknown type, outside 640x480
    ]
    # fmt: on
    dec = Evt2Decoder(640, 480)
    out = dec.decode_all(np.array(words, "<u4").tobytes())
    loop = 1 << 34
    assert [tuple(int(v) for v in e) for e in out.events] == [
        (5, 6, 1, 643),
        (639, 479, 0, 640 + 63),
        (1, 1, 0, ((1 << 28) - 1) << 6),
        (2, 2, 1, loop + 128 + 1),
    ]
    assert [tuple(int(v) for v in r) for r in out.triggers] == [(1, 647, 31)]
    assert dec.time_high_loops == 1 and dec.others_words == 3 and dec.dropped_events == 1
    assert [int(r) for r in dec.skips["reason"]] == [1, 3, 2, 4]


@pytest.mark.parametrize("cls", [Evt3Decoder, Evt2Decoder])
def test_every_single_split_offset_gives_the_one_call_result(cls: type[StreamDecoder]) -> None:
    if cls is Evt3Decoder:
        data = EVT3_ALL + b"\x07"
    else:
        rng = np.random.default_rng(5)
        words = rng.integers(0, 2**32, 60, dtype=np.uint64).astype("<u4")
        words[3] = (0x8 << 28) | 77
        data = words.tobytes() + b"\x01\x02"
    ref, ref_ev, ref_tr = decode_in_pieces(cls, data, [], width=1280, height=720)
    for cut in range(len(data) + 1):
        dec, ev, tr = decode_in_pieces(cls, data, [cut], width=1280, height=720)
        np.testing.assert_array_equal(ev, ref_ev)
        np.testing.assert_array_equal(tr, ref_tr)
        assert_same_decoders(dec, ref)


@settings(max_examples=150, deadline=None)
@given(
    st.sampled_from([Evt3Decoder, Evt2Decoder]), st.binary(min_size=0, max_size=600), st.lists(st.integers(0, 600), max_size=12)
)
def test_any_chunking_of_any_bytes_gives_the_one_call_result(cls: type[StreamDecoder], data: bytes, cuts: list[int]) -> None:
    ref, ref_ev, ref_tr = decode_in_pieces(cls, data, [], width=640, height=480)
    dec, ev, tr = decode_in_pieces(cls, data, [min(c, len(data)) for c in cuts], width=640, height=480)
    np.testing.assert_array_equal(ev, ref_ev)
    np.testing.assert_array_equal(tr, ref_tr)
    assert_same_decoders(dec, ref)


def test_feed_accepts_numpy_and_memoryview_and_refuses_after_finish() -> None:
    dec = Evt3Decoder()
    a = dec.feed(np.frombuffer(EVT3_ALL[:41], np.uint8)).events
    b = dec.feed(memoryview(EVT3_ALL)[41:]).events
    dec.finish()
    assert np.concatenate([a, b]).size == Evt3Decoder().decode_all(EVT3_ALL).events.size
    with pytest.raises(RuntimeError):
        dec.feed(b"\x00\x80")


def test_event_buffer_grows_for_vector_dense_streams() -> None:
    # 8 events per word: more than the first buffer guess (one event per word)
    triplet = [w3("VB", 0), w3("V12", 0xFFF), w3("V12", 0xFFF), w3("V8", 0xFF)]
    data = pack3([w3("TH", 1), w3("TL", 0), w3("AY", 1)] + triplet * 5000)
    out = Evt3Decoder(1280, 720).decode_all(data)
    assert out.events.size == 32 * 5000
    np.testing.assert_array_equal(out.events["x"], np.tile(np.arange(32), 5000))
    many_triggers = pack3([w3("TH", 1)] + [w3("TRIG", 1)] * 1000)
    assert Evt3Decoder().decode_all(many_triggers).triggers.size == 1000
