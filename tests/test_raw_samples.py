"""The two real Prophesee recordings decode to the published counts and spans, and agree with the `evt3` package."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from labrig.devices.raw import EVENT_DTYPE, Evt2Decoder, Evt3Decoder, encode_evt2, encode_evt3, iter_raw, read_raw

DATA = Path(os.environ.get("LABRIG_EVT_DATA", Path(__file__).resolve().parents[2] / "shared" / "data" / "evt"))
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"real RAW samples not found at {DATA} (set LABRIG_EVT_DATA)")

EVT3_SAMPLE = DATA / "evt3_sample.raw"
EVT2_SAMPLE = DATA / "evt2_sample.raw"


def test_dtype_is_labrigs_event_dtype() -> None:
    from labrig.sim.events import EVENT_DTYPE as SIM_DTYPE

    assert EVENT_DTYPE == SIM_DTYPE


def test_evt3_sample_counts_and_span() -> None:
    raw = read_raw(EVT3_SAMPLE)
    assert raw.format == "EVT3" and raw.geometry == (1280, 720)
    assert raw.events.dtype == EVENT_DTYPE
    assert raw.events.size == 219_596
    t = raw.events["t"]
    assert (t[0], t[-1], t.min(), t.max()) == (11_718_656, 11_727_457, 11_718_656, 11_727_457)
    assert raw.triggers.size == 0
    assert raw.skipped_words == 0 and raw.skips.size == 0 and raw.dropped_events == 0
    assert raw.events["x"].max() < 1280 and raw.events["y"].max() < 720


def test_evt3_sample_equals_evt3_package() -> None:
    evt3 = pytest.importorskip("evt3", reason="the `evt3` PyPI package (test oracle) is not installed: pip install evt3")
    ours = read_raw(EVT3_SAMPLE).events
    theirs, triggers = evt3.decode_file_with_triggers(str(EVT3_SAMPLE))
    np.testing.assert_array_equal(ours["x"], np.asarray(theirs.x))
    np.testing.assert_array_equal(ours["y"], np.asarray(theirs.y))
    np.testing.assert_array_equal(ours["p"], np.asarray(theirs.polarity))
    np.testing.assert_array_equal(ours["t"], np.asarray(theirs.timestamp).astype(np.int64))
    assert len(np.asarray(triggers.timestamp)) == 0


def test_evt2_sample_counts_and_span() -> None:
    raw = read_raw(EVT2_SAMPLE)
    assert raw.format == "EVT2" and raw.geometry == (640, 480)
    assert raw.events.size == 539_481
    t = raw.events["t"]
    assert (t.min(), t.max()) == (1_317_888, 1_367_888)
    assert raw.triggers.size == 0 and raw.skipped_words == 0 and raw.dropped_events == 0


@pytest.mark.parametrize(("path", "chunk"), [(EVT3_SAMPLE, 4093), (EVT2_SAMPLE, 65_537)])
def test_samples_stream_in_odd_chunks(path: Path, chunk: int) -> None:
    whole = read_raw(path).events
    streamed = np.concatenate([d.events for d in iter_raw(path, chunk_bytes=chunk)])
    np.testing.assert_array_equal(streamed, whole)


def test_samples_reencode_round_trip() -> None:
    ev3 = read_raw(EVT3_SAMPLE).events
    np.testing.assert_array_equal(Evt3Decoder(1280, 720).decode_all(encode_evt3(ev3)).events, ev3)
    ev2 = read_raw(EVT2_SAMPLE).events
    np.testing.assert_array_equal(Evt2Decoder(640, 480).decode_all(encode_evt2(ev2, width=640, height=480)).events, ev2)
