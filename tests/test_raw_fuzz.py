"""Bad input never crashes a decoder: random bytes, corrupted and truncated encoded streams, garbage files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labrig.devices.raw import (
    MAX_SKIP_RUNS,
    Evt2Decoder,
    Evt3Decoder,
    RawFormatError,
    SkipReason,
    StreamDecoder,
    encode_evt2,
    encode_evt3,
    read_raw,
)
from labrig.devices.raw.synthetic import synthetic_events, synthetic_triggers

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
DECODERS = st.sampled_from([Evt3Decoder, Evt2Decoder])
_ENCODE = {Evt3Decoder: encode_evt3, Evt2Decoder: encode_evt2}


def check_invariants(dec: StreamDecoder, n_bytes: int, events: np.ndarray, width: int, height: int) -> None:
    ws = dec.word_bytes
    assert events.size == 0 or (events["x"].max() < width and events["y"].max() < height)
    assert events.size <= dec.max_events_per_word * (n_bytes // ws)
    skips = dec.skips
    if dec.skip_runs_total <= MAX_SKIP_RUNS:
        assert int(skips["words"].sum()) == dec.skipped_words
    assert np.all(skips["offset"] % ws == 0) and np.all(skips["offset"] >= 0)
    assert np.all(skips["offset"] + skips["words"] * ws <= n_bytes + ws - 1)
    assert np.all(np.diff(skips["offset"]) > 0)
    assert set(int(r) for r in skips["reason"]) <= {int(r) for r in SkipReason}
    assert dec.skipped_words <= -(-n_bytes // ws)


@FUZZ
@given(DECODERS, st.binary(max_size=4096), st.integers(1, 2048), st.integers(1, 2048))
def test_random_bytes(cls: type[StreamDecoder], data: bytes, width: int, height: int) -> None:
    dec = cls(width, height)
    out = dec.decode_all(data)
    check_invariants(dec, len(data), out.events, width, height)
    assert out.triggers["p"].max(initial=0) <= 1


@st.composite
def corrupted(draw: st.DrawFn) -> tuple[type[StreamDecoder], bytes, bytes, int]:
    """(decoder class, clean payload, corrupted payload, byte offset of the first change)."""
    cls = draw(DECODERS)
    seed = draw(st.integers(0, 2**16))
    n = draw(st.integers(1, 3000))
    ev = synthetic_events(n, duration_us=draw(st.sampled_from([10_000, 40_000_000])), seed=seed)
    tr = synthetic_triggers(draw(st.integers(0, 20)), duration_us=int(ev["t"][-1]) + 1, seed=seed)
    clean = _ENCODE[cls](ev, tr)
    data = bytearray(clean)
    first = len(data)
    for _ in range(draw(st.integers(1, 8))):
        kind = draw(st.sampled_from(["flip", "garbage", "cut", "drop"]))
        at = draw(st.integers(0, len(data)))
        if kind == "flip" and at < len(data):
            data[at] ^= draw(st.integers(1, 255))
        elif kind == "garbage":
            data[at:at] = draw(st.binary(min_size=1, max_size=64))
        elif kind == "cut":
            del data[at:]
        elif kind == "drop":
            del data[at : at + draw(st.integers(1, 7))]
        else:
            continue
        first = min(first, at)
    return cls, clean, bytes(data), first


@FUZZ
@given(corrupted())
def test_corrupted_streams_keep_their_clean_prefix(case: tuple[type[StreamDecoder], bytes, bytes, int]) -> None:
    cls, clean, data, first = case
    dec = cls(1280, 720)
    out = dec.decode_all(data)
    check_invariants(dec, len(data), out.events, 1280, 720)
    # everything decoded from the words before the first change comes out unchanged, in front
    whole_words = first - first % dec.word_bytes
    prefix = cls(1280, 720).decode_all(clean[:whole_words])
    np.testing.assert_array_equal(out.events[: prefix.events.size], prefix.events)
    np.testing.assert_array_equal(out.triggers[: prefix.triggers.size], prefix.triggers)


@settings(max_examples=60, deadline=None)
@given(st.binary(max_size=300), st.binary(max_size=600), st.sampled_from([None, "EVT3", "EVT2", "EVT21"]))
def test_garbage_files(tmp_path_factory: object, head: bytes, payload: bytes, fmt: str | None) -> None:
    path = Path(tmp_path_factory.mktemp("fuzz")) / "garbage.raw"  # type: ignore[attr-defined]
    path.write_bytes(b"% " + head + b"\n" + payload)
    try:
        raw = read_raw(path, format=fmt)
    except RawFormatError:
        return
    assert raw.format in ("EVT3", "EVT2")
    assert raw.skipped_words >= 0 and raw.events.dtype.names == ("x", "y", "p", "t")


@FUZZ
@given(st.binary(max_size=4096), st.integers(1, 2048), st.integers(1, 2048))
def test_evt3_event_count_bounds_what_any_words_decode_to(data: bytes, width: int, height: int) -> None:
    """The pass that sizes an EVT3 decode's one buffer counts at least the events the word loop writes."""
    from labrig.devices.raw import _evt3_kernels

    words = np.frombuffer(data[: len(data) // 2 * 2], "<u2")
    out = Evt3Decoder(width, height).decode_all(data)
    assert _evt3_kernels.count_events(words) >= out.events.size


def test_a_whole_evt3_file_of_vectors_decodes_into_one_buffer(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Vectors pack up to 12 events a word: sized by its count, the buffer never grows and is never joined."""
    from labrig.devices.raw import make_header, stream

    events = synthetic_events(200_000, 200_000, run_fraction=1.0, seed=1)
    path = tmp_path / "vectors.raw"
    path.write_bytes(make_header("EVT3", 1280, 720) + encode_evt3(events))
    assert path.stat().st_size / 2 < 0.8 * events.size  # more events than words: vectors
    joined = []
    monkeypatch.setattr(stream.np, "concatenate", lambda parts, *a, **k: joined.append(len(parts)) or np.hstack(parts))
    decoded = read_raw(path)
    assert joined == [] and np.array_equal(decoded.events, events)
