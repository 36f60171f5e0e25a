"""Encode -> decode gives the input back (EVT3 and EVT2), and the encoders keep the format contract.

Random streams (hypothesis) mix repeated times, small steps, gaps of many TIME_HIGH steps,
jumps of about a whole time-high loop (wraps), small backward steps, dense rows (vectors),
starts past the first loop, and triggers.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labrig.devices.raw import (
    EVENT_DTYPE,
    TRIGGER_DTYPE,
    Evt2Decoder,
    Evt3Decoder,
    encode_evt2,
    encode_evt3,
    read_raw,
    write_raw,
)
from labrig.devices.raw.synthetic import synthetic_events, synthetic_triggers

W, H = 1280, 720
LOOP3 = 1 << 24
LOOP2 = 1 << 34
SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@st.composite
def streams(draw: Any, loop_us: int, max_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(events, triggers): segments of events / triggers at one time each, the time moving between segments."""
    t = draw(st.one_of(st.integers(0, 5000), st.integers(0, 3 * loop_us)))
    events: list[tuple[int, int, int, int]] = []
    triggers: list[tuple[int, int, int]] = []
    for _ in range(draw(st.integers(0, 24))):
        move = draw(st.sampled_from(["same", "small", "steps", "wrap", "back"]))
        if move == "small":
            t += draw(st.integers(1, 5000))
        elif move == "steps":
            t += draw(st.integers(4096, 300 * 4096))
        elif move == "wrap":
            t += loop_us + draw(st.integers(-5000, 5000))
        elif move == "back":
            back = draw(st.integers(1, 40))
            if t - back >= 0 and (t - back) // loop_us == t // loop_us:
                t -= back
        what = draw(st.sampled_from(["single", "row", "row", "trigger"]))
        if what == "single":
            for _ in range(draw(st.integers(1, 4))):
                events.append((draw(st.integers(0, W - 1)), draw(st.integers(0, H - 1)), draw(st.integers(0, 1)), t))
        elif what == "row":
            y, p = draw(st.integers(0, H - 1)), draw(st.integers(0, 1))
            x0 = draw(st.integers(0, W - 64))
            xs = sorted(draw(st.sets(st.integers(x0, x0 + 63), min_size=1, max_size=64)))
            events.extend((x, y, p, t) for x in xs)
        else:
            triggers.append((draw(st.integers(0, 1)), t, draw(st.integers(0, max_id))))
    ev = np.array(events, dtype=[("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("t", "<i8")]).astype(EVENT_DTYPE)
    tr = np.zeros(len(triggers), TRIGGER_DTYPE)
    if triggers:
        arr = np.array(triggers)
        tr["p"], tr["t"], tr["id"] = arr[:, 0], arr[:, 1], arr[:, 2]
    return ev, tr


def evt3_words(payload: bytes) -> np.ndarray:
    return np.frombuffer(payload, "<u2").astype(np.int64)


def check_evt3_contract(w: np.ndarray, width: int, time_high_every: int, monotonic: bool) -> None:
    """Stream starts with TIME_HIGH(s) then TIME_LOW; vectors only as aligned 12-12-8 triplets; TIME_HIGH cadence."""
    typ = w >> 12
    if w.size == 0:
        return
    assert typ[0] == 0x8
    first_other = int(np.argmax(typ != 0x8))
    assert typ[first_other] == 0x6  # the first word after the leading TIME_HIGHs is a TIME_LOW
    assert (w[0] & 0xFF) != 0x25  # the first byte is not '%'
    base = np.flatnonzero(typ == 0x3)
    for b in base:
        assert (w[b] & 0x7FF) % 32 == 0 and (w[b] & 0x7FF) + 32 <= width
        assert list(typ[b + 1 : b + 4]) == [0x4, 0x4, 0x5]
    vect = np.flatnonzero((typ == 0x4) | (typ == 0x5))
    assert vect.size == 3 * base.size  # no vector word outside a triplet
    highs = np.flatnonzero(typ == 0x8)
    after = highs + 1
    after = after[after < w.size]
    assert np.all(np.isin(typ[after], (0x8, 0x6)))  # a TIME_LOW follows every TIME_HIGH
    assert np.max(np.diff(np.append(highs, w.size))) <= time_high_every + 7
    if monotonic:
        raw = w[highs[first_other - 1 :]] & 0xFFF if first_other > 0 else w[highs] & 0xFFF
        steps = np.diff(raw) % 4096
        assert np.all(steps <= 1)  # every TIME_HIGH step is written (4095 -> 0 marks a wrap)


@SETTINGS
@given(
    streams(LOOP3, 15),
    st.integers(1, 600),
    st.sampled_from([0, 2, 5, 32]),
)
def test_evt3_round_trip(stream: tuple[np.ndarray, np.ndarray], every: int, vector_min: int) -> None:
    ev, tr = stream
    payload = encode_evt3(ev, tr, width=W, height=H, time_high_every=every, vector_min=vector_min)
    dec = Evt3Decoder(W, H)
    out = dec.decode_all(payload)
    np.testing.assert_array_equal(out.events, ev)
    np.testing.assert_array_equal(out.triggers, tr)
    assert dec.skipped_words == 0 and dec.dropped_events == 0
    t = np.concatenate([ev["t"], tr["t"]])
    check_evt3_contract(evt3_words(payload), W, every, monotonic=bool(np.all(np.diff(np.sort(t)) >= 0) and _in_order(ev, tr)))


def _in_order(ev: np.ndarray, tr: np.ndarray) -> bool:
    return bool(np.all(np.diff(ev["t"]) >= 0) and np.all(np.diff(tr["t"]) >= 0))


def reference_evt2(ev: np.ndarray, tr: np.ndarray) -> bytes:
    """A plain-Python EVT2 writer for time-sorted items whose times stay in the first loop."""
    items = sorted([(int(e["t"]), 0, i) for i, e in enumerate(ev)] + [(int(r["t"]), -1, j) for j, r in enumerate(tr)])
    words: list[int] = []
    high = None
    for t, kind, k in items:
        if high is None and ((t >> 6) & 0xFF) == 0x25:
            words.append((0x8 << 28) | ((t >> 6) - 1))
        if t >> 6 != high:
            words.append((0x8 << 28) | (t >> 6))
            high = t >> 6
        if kind < 0:
            words.append((0xA << 28) | ((t & 63) << 22) | (int(tr["id"][k]) << 8) | int(tr["p"][k]))
        else:
            e = ev[k]
            words.append((int(e["p"]) << 28) | ((t & 63) << 22) | (int(e["x"]) << 11) | int(e["y"]))
    return np.array(words, "<u4").tobytes()


@SETTINGS
@given(streams(LOOP2, 31))
def test_evt2_round_trip(stream: tuple[np.ndarray, np.ndarray]) -> None:
    ev, tr = stream
    payload = encode_evt2(ev, tr, width=W, height=H)
    dec = Evt2Decoder(W, H)
    out = dec.decode_all(payload)
    np.testing.assert_array_equal(out.events, ev)
    np.testing.assert_array_equal(out.triggers, tr)
    assert dec.skipped_words == 0


@SETTINGS
@given(streams(LOOP3, 31))
def test_evt2_is_the_minimal_canonical_stream(stream: tuple[np.ndarray, np.ndarray]) -> None:
    ev, tr = stream
    t = np.concatenate([ev["t"], tr["t"]])
    if t.size and (t.max() >= LOOP2 or not _in_order(ev, tr)):
        return
    # items at one time: events before triggers in the encoder, triggers first in the reference when earlier
    if np.intersect1d(ev["t"], tr["t"]).size:
        return
    assert encode_evt2(ev, tr) == reference_evt2(ev, tr)


def test_wraps_and_long_gaps_on_a_large_stream(tmp_path: Path) -> None:
    ev = synthetic_events(200_000, duration_us=40_000_000, seed=3)  # two 24-bit wraps
    tr = synthetic_triggers(300, duration_us=40_000_000, seed=3)
    for fmt in ("EVT3", "EVT2"):
        path = tmp_path / f"big_{fmt}.raw"
        size = write_raw(path, ev, tr, format=fmt)
        assert size == path.stat().st_size
        raw = read_raw(path)
        assert raw.format == fmt and raw.geometry == (W, H) and raw.header.has_end
        np.testing.assert_array_equal(raw.events, ev)
        np.testing.assert_array_equal(raw.triggers, tr)
        assert raw.skipped_words == 0
    assert read_raw(tmp_path / "big_EVT3.raw").time_high_loops == 2


def test_first_byte_is_never_a_header_percent() -> None:
    ev = np.zeros(1, EVENT_DTYPE)
    ev["t"] = 0x25 << 12  # TIME_HIGH 0x025 would start the payload with b"%"
    payload = encode_evt3(ev)
    assert payload[:1] != b"%"
    np.testing.assert_array_equal(Evt3Decoder().decode_all(payload).events, ev)
    ev["t"] = 0x25 << 6
    payload = encode_evt2(ev)
    assert payload[:1] != b"%"
    np.testing.assert_array_equal(Evt2Decoder().decode_all(payload).events, ev)


def test_vectors_are_used_for_dense_rows() -> None:
    ev = np.zeros(32, EVENT_DTYPE)
    ev["x"] = np.arange(64, 96)
    ev["y"], ev["p"], ev["t"] = 5, 1, 1000
    w = evt3_words(encode_evt3(ev))
    assert list(w >> 12) == [0x8, 0x6, 0x0, 0x3, 0x4, 0x4, 0x5]
    assert list(w[-3:] & 0xFFF) == [0xFFF, 0xFFF, 0xFF]
    # the last block of a 1270-wide sensor does not fit 32 pixels: single events
    row = ev[:22].copy()
    row["x"] = np.arange(1248, 1270)
    w = evt3_words(encode_evt3(row, width=1270))
    assert not np.any(np.isin(w >> 12, (0x3, 0x4, 0x5)))
    np.testing.assert_array_equal(Evt3Decoder(1270, H).decode_all(w.astype("<u2").tobytes()).events, row)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [("x", W, "x >= width"), ("y", H, "y >= height"), ("p", 2, "p not 0/1"), ("t", -1, "negative event t")],
)
def test_encoder_rejects_bad_events(field: str, value: int, message: str) -> None:
    ev = np.zeros(3, [("x", "i4"), ("y", "i4"), ("p", "i4"), ("t", "i8")])
    ev[field][1] = value
    for encode in (encode_evt3, encode_evt2):
        with pytest.raises(ValueError, match=message):
            encode(ev)


def test_encoder_rejects_bad_triggers_and_impossible_times() -> None:
    tr = np.zeros(1, TRIGGER_DTYPE)
    tr["id"] = 16
    with pytest.raises(ValueError, match="trigger id"):
        encode_evt3(np.zeros(0, EVENT_DTYPE), tr)
    encode_evt2(np.zeros(0, EVENT_DTYPE), tr)  # EVT2 has 5-bit ids
    ev = np.zeros(2, EVENT_DTYPE)
    ev["t"] = [LOOP3 + 10, LOOP3 - 10]  # back across a wrap
    with pytest.raises(ValueError, match="event 1"):
        encode_evt3(ev)
    ev["t"] = [4090 * 4096, 10]  # back by more than 4085 TIME_HIGH steps in one loop
    with pytest.raises(ValueError, match="event 1"):
        encode_evt3(ev)
    with pytest.raises(ValueError, match="structured"):
        encode_evt3(np.zeros(3))
