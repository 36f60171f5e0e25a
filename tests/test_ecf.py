"""ECF chunk codec and Metavision HDF5 reading without the HDF5 plugin (labrig.devices.ecf)."""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import pytest

from labrig.devices.ecf import (
    MAX_CHUNK_EVENTS,
    EcfError,
    _indexes,
    decode_ecf_chunk,
    encode_ecf_chunk,
    iter_metavision_chunks,
    read_metavision_hdf5,
    write_metavision_hdf5,
)
from labrig.devices.raw import TRIGGER_DTYPE, read_raw
from labrig.eventtypes import EVENT_DTYPE

DATA = Path(os.environ.get("LABRIG_EVT_DATA", Path(__file__).resolve().parents[2] / "shared" / "data" / "evt"))
needs_samples = pytest.mark.skipif(not DATA.is_dir(), reason=f"real samples not found at {DATA} (set LABRIG_EVT_DATA)")

MODES = ("ys_xs_ps_packed", "xs_ps_packed", "masked")


pytestmark = pytest.mark.usefixtures("time_limit_20s")


def _events(n: int, seed: int = 1, *, runs: bool = False) -> np.ndarray:
    """Events with all the codec's corner cases: ties, big gaps, long runs of one y / p / t."""
    rng = np.random.default_rng(seed)
    ev = np.zeros(n, EVENT_DTYPE)
    steps = rng.choice([0, 0, 0, 1, 3, 14, 15, 16, 300, 70_000, 1 << 40], size=n)
    ev["t"] = 5 + np.cumsum(steps)
    ev["y"] = rng.integers(0, 2048, n)
    ev["x"] = rng.integers(0, 2048, n)
    ev["p"] = rng.integers(0, 2, n)
    if runs:  # long rows of neighbours with one y, p and t
        for start in range(0, n - 200, 400):
            k = rng.integers(2, 200)
            ev["y"][start : start + k] = ev["y"][start]
            ev["p"][start : start + k] = ev["p"][start]
            ev["t"][start : start + k] = ev["t"][start]
            ev["x"][start : start + k] = (ev["x"][start] % 1400) + np.cumsum(rng.integers(1, 4, k))
    ev["t"] = np.maximum.accumulate(ev["t"])
    return ev


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("n", [0, 1, 2, 3, 5, 17, 4099])
def test_every_mode_round_trips(mode: str, n: int) -> None:
    for runs in (False, True):
        ev = _events(n, seed=n, runs=runs)
        assert np.array_equal(decode_ecf_chunk(encode_ecf_chunk(ev, mode)), ev), (mode, n, runs)


def test_largest_chunk_and_long_runs_use_the_count_escapes() -> None:
    ev = np.zeros(MAX_CHUNK_EVENTS, EVENT_DTYPE)
    ev["t"] = 1_000_000  # one time run of 65535 events (u16 count)
    ev["y"][: MAX_CHUNK_EVENTS // 2] = 7  # y runs beyond 31 and p runs beyond 127
    ev["x"] = np.arange(MAX_CHUNK_EVENTS) % 2048
    ev["p"][::1000] = 1
    for mode in MODES:
        data = encode_ecf_chunk(ev, mode)
        assert np.array_equal(decode_ecf_chunk(data), ev), mode
    with pytest.raises(ValueError, match="at most"):
        encode_ecf_chunk(np.zeros(MAX_CHUNK_EVENTS + 1, EVENT_DTYPE))


def test_auto_mode_picks_masked_for_rows_of_neighbours_and_packed_for_scatter() -> None:
    rows = _events(4000, runs=True)
    rows["y"] = np.repeat(np.arange(40), 100)
    rows["x"] = np.tile(np.arange(100) * 2 // 2 + 10, 40)
    scatter = _events(4000, seed=3)
    assert decode_ecf_chunk(data := encode_ecf_chunk(rows)).size == 4000
    assert (int.from_bytes(data[:4], "little") & 3) == 0  # masked x
    assert (int.from_bytes(encode_ecf_chunk(scatter)[:4], "little") & 3) == 2  # (y, x, p) packed


def test_time_going_back_is_clamped_like_the_codec() -> None:
    ev = _events(8)
    ev["t"] = [10, 20, 19, 25, 25, 24, 40, 41]
    out = decode_ecf_chunk(encode_ecf_chunk(ev, "masked"))
    assert out["t"].tolist() == [10, 20, 20, 25, 25, 25, 40, 41]
    assert np.array_equal(out[["x", "y", "p"]], ev[["x", "y", "p"]])


def test_truncated_and_corrupt_chunks_raise() -> None:
    data = encode_ecf_chunk(_events(1000, runs=True), "masked")
    for cut in (0, 5, 12, 40, len(data) // 2, len(data) - 1):
        with pytest.raises(EcfError):
            decode_ecf_chunk(data[:cut])
    bad = bytearray(data)
    bad[0:4] = ((70_000 << 2) | 0).to_bytes(4, "little")
    with pytest.raises(EcfError, match="more than"):
        decode_ecf_chunk(bytes(bad))
    small = bytearray(data)
    small[0:4] = ((3 << 2) | 0).to_bytes(4, "little")  # count smaller than the runs: corrupt
    with pytest.raises(EcfError):
        decode_ecf_chunk(bytes(small))


def test_write_and_read_a_metavision_file_with_triggers(tmp_path: Path) -> None:
    ev = _events(40_000, runs=True)
    ev["x"] %= 1280
    ev["y"] %= 720
    ev["t"] = 1_000_000 + np.cumsum(np.random.default_rng(5).integers(0, 20, ev.size))  # 0.4 s, 200 index buckets
    tr = np.zeros(3, TRIGGER_DTYPE)
    tr["t"], tr["p"], tr["id"] = [100, 200, 300], [1, 0, 1], [0, 0, 1]
    path = tmp_path / "x.hdf5"
    write_metavision_hdf5(path, ev, tr, attrs={"geometry": "1280x720"}, mode="masked", chunk_events=16384)
    got = read_metavision_hdf5(path)
    assert np.array_equal(got.events, ev) and np.array_equal(got.triggers, tr)
    assert got.geometry == (1280, 720) and got.chunks == 3
    assert sum(c.size for c in iter_metavision_chunks(path)) == ev.size
    with h5py.File(path) as f:  # plain h5py cannot go through the ECF filter
        assert f["CD/events"].id.get_create_plist().get_filter(0)[0] == 0x8ECF
        with pytest.raises(OSError):
            f["CD/events"][:10]


def test_files_that_are_not_metavision_hdf5(tmp_path: Path) -> None:
    with pytest.raises(EcfError, match="no such file"):
        read_metavision_hdf5(tmp_path / "missing.hdf5")
    (tmp_path / "text.hdf5").write_text("hello")
    with pytest.raises(EcfError, match="not an HDF5 file"):
        read_metavision_hdf5(tmp_path / "text.hdf5")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["data"] = np.arange(3)
    with pytest.raises(EcfError, match="not a Metavision"):
        read_metavision_hdf5(tmp_path / "other.h5")


@needs_samples
def test_shared_hdf5_gives_exactly_the_events_of_the_raw_file() -> None:
    mv = read_metavision_hdf5(DATA / "evt3_sample.metavision.hdf5")
    raw = read_raw(DATA / "evt3_sample.raw")
    assert mv.events.size == 219_596 and mv.chunks == 14
    assert np.array_equal(mv.events, raw.events)
    assert mv.triggers.size == 0 and mv.geometry == (1280, 720)


@needs_samples
def test_indexes_written_like_the_shared_file() -> None:
    path = DATA / "evt3_sample.metavision.hdf5"
    with h5py.File(path) as f:
        stored = f["CD/indexes"][:]
    ours = _indexes(read_metavision_hdf5(path).events["t"])
    assert ours.tolist() == stored.tolist()
