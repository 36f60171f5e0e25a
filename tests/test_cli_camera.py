"""``labrig import`` / ``labrig export``: camera files to recordings and back (labrig.recording.convert)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from cli_runner import run_labrig as run

from labrig.devices.ecf import write_metavision_hdf5
from labrig.devices.raw import TRIGGER_DTYPE, read_header, read_raw, write_raw
from labrig.eventtypes import EVENT_DTYPE
from labrig.recording import Recording

DATA = Path(os.environ.get("LABRIG_EVT_DATA", Path(__file__).resolve().parents[2] / "shared" / "data" / "evt"))
needs_samples = pytest.mark.skipif(not DATA.is_dir(), reason=f"real samples not found at {DATA} (set LABRIG_EVT_DATA)")

MP = pytest.MonkeyPatch
Cap = pytest.CaptureFixture[str]

IMPORT_KEYS = {
    "source", "source_format", "output", "events", "triggers", "t_first_device_us", "t_last_device_us", "duration_s",
    "width_px", "height_px", "skipped_words", "output_bytes", "elapsed_s",
}
EXPORT_KEYS = {
    "recording", "output", "format", "events", "triggers", "width_px", "height_px", "output_bytes", "bytes_per_event",
    "elapsed_s",
}


@pytest.fixture(autouse=True)
def _time_limit() -> Iterator[None]:
    def expire(*_: object) -> None:
        raise TimeoutError("test ran over its 30 s limit")

    old = signal.signal(signal.SIGALRM, expire)
    signal.alarm(30)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


def synthetic(n: int = 30_000, seed: int = 4) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ev = np.zeros(n, EVENT_DTYPE)
    ev["x"], ev["y"], ev["p"] = rng.integers(0, 1280, n), rng.integers(0, 720, n), rng.integers(0, 2, n)
    ev["t"] = np.sort(rng.integers((1 << 24) - 200_000, (1 << 24) + 300_000, n))  # crosses the 24-bit wrap
    tr = np.zeros(4, TRIGGER_DTYPE)
    tr["t"] = [(1 << 24) - 150_000, (1 << 24) - 100_000, (1 << 24) + 10, (1 << 24) + 250_000]
    tr["p"], tr["id"] = [1, 0, 1, 0], [0, 0, 1, 0]
    return ev, tr


def test_raw_import_export_round_trip(tmp_path: Path, monkeypatch: MP, capsys: Cap) -> None:
    ev, tr = synthetic()
    src = tmp_path / "cam.raw"
    write_raw(src, ev, tr, header={"serial_number": "00ca0042"})
    code, out, err = run(monkeypatch, capsys, "import", src, tmp_path / "rec.h5", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert set(summary) == IMPORT_KEYS
    assert summary["events"] == ev.size and summary["triggers"] == tr.size and summary["source_format"] == "EVT3"
    assert summary["t_first_device_us"] == int(ev["t"][0]) and summary["skipped_words"] == 0
    with Recording(tmp_path / "rec.h5") as rec:
        assert rec.exit_status == "complete"
        assert np.array_equal(rec.column("events", "t_device_us"), ev["t"])
        assert np.array_equal(rec.column("triggers", "channel"), tr["id"])
        attrs = rec.attrs
        assert attrs["extra_source_format"] == "EVT3" and attrs["extra_source_serial"] == "00ca0042"
        assert attrs["extra_source_file"] == str(src)

    code, out, err = run(monkeypatch, capsys, "export", tmp_path / "rec.h5", "--raw", tmp_path / "out.raw", "--json")
    assert code == 0, err
    assert set(json.loads(out)) == EXPORT_KEYS
    back = read_raw(tmp_path / "out.raw")
    assert np.array_equal(back.events, ev) and np.array_equal(back.triggers, tr)
    assert back.skipped_words == 0
    header = read_header(str(tmp_path / "out.raw"))
    keys = list(header.fields)
    assert header.has_end and keys == sorted(keys)
    assert header.fields["format"] == "EVT3;height=720;width=1280" and header.fields["evt"] == "3.0"
    assert header.fields["geometry"] == "1280x720" and header.fields["serial_number"] == "00ca0042"


def test_human_output_and_evt2_source(tmp_path: Path, monkeypatch: MP, capsys: Cap) -> None:
    ev, tr = synthetic(5000)
    write_raw(tmp_path / "cam2.raw", ev, tr, format="EVT2", width=1280, height=720)
    code, out, _ = run(monkeypatch, capsys, "import", tmp_path / "cam2.raw", tmp_path / "r.h5")
    assert code == 0 and "imported 5,000 events and 4 trigger edges" in out and "EVT2" in out
    code, out, _ = run(monkeypatch, capsys, "export", tmp_path / "r.h5", "--raw", tmp_path / "r.raw")
    assert code == 0 and "exported 5,000 events" in out
    back = read_raw(tmp_path / "r.raw")
    assert back.format == "EVT3" and np.array_equal(back.events, ev) and np.array_equal(back.triggers, tr)


def test_metavision_hdf5_import_with_triggers(tmp_path: Path, monkeypatch: MP, capsys: Cap) -> None:
    ev, tr = synthetic(40_000, seed=8)
    write_metavision_hdf5(tmp_path / "mv.hdf5", ev, tr, attrs={"geometry": "1280x720", "serial_number": "00ca0001"})
    code, out, err = run(monkeypatch, capsys, "import", tmp_path / "mv.hdf5", tmp_path / "mv.h5", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["source_format"] == "metavision-hdf5" and summary["events"] == ev.size and summary["triggers"] == 4
    with Recording(tmp_path / "mv.h5") as rec:
        assert np.array_equal(rec.column("events", "x"), ev["x"])
        assert np.array_equal(rec.column("triggers", "t_device_us"), tr["t"])
        assert rec.attrs["extra_source_serial"] == "00ca0001"


@needs_samples
def test_shared_samples_import_the_same_and_round_trip(
    tmp_path: Path, monkeypatch: MP, capsys: Cap
) -> None:
    assert run(monkeypatch, capsys, "import", DATA / "evt3_sample.raw", tmp_path / "a.h5", "--json")[0] == 0
    assert run(monkeypatch, capsys, "import", DATA / "evt3_sample.metavision.hdf5", tmp_path / "b.h5", "--json")[0] == 0
    with Recording(tmp_path / "a.h5") as a, Recording(tmp_path / "b.h5") as b:
        assert a.rows("events") == b.rows("events") == 219_596
        for col in ("x", "y", "p", "t_device_us"):
            assert np.array_equal(a.column("events", col), b.column("events", col))
    assert run(monkeypatch, capsys, "export", tmp_path / "a.h5", "--raw", tmp_path / "a.raw")[0] == 0
    assert np.array_equal(read_raw(tmp_path / "a.raw").events, read_raw(DATA / "evt3_sample.raw").events)


def test_bad_input_gives_one_clear_line(tmp_path: Path, monkeypatch: MP, capsys: Cap) -> None:
    (tmp_path / "notes.txt").write_text("not events\n")
    ev, _ = synthetic(100)
    write_raw(tmp_path / "ok.raw", ev)
    (tmp_path / "taken.h5").write_bytes(b"")
    write_metavision_hdf5(tmp_path / "mv.hdf5", ev)
    cases = [
        (("import", tmp_path / "missing.raw", tmp_path / "o.h5"), "no such file"),
        (("import", tmp_path / "notes.txt", tmp_path / "o.h5"), "neither a Prophesee RAW file"),
        (("import", tmp_path / "ok.raw", tmp_path / "taken.h5"), "exists"),
        (("export", tmp_path / "missing.h5", "--raw", tmp_path / "o.raw"), "no such file"),
        (("export", tmp_path / "mv.hdf5", "--raw", tmp_path / "o.raw"), "not a labrig recording"),
        (("export", tmp_path / "notes.txt", "--raw", tmp_path / "o.raw"), "notes.txt"),
    ]
    for args, message in cases:
        code, out, err = run(monkeypatch, capsys, *args)
        assert code == 2, (args, out, err)
        assert message in err and "Traceback" not in err, (args, err)
    assert not (tmp_path / "o.h5").exists() and not (tmp_path / "o.raw").exists()


def test_entry_point_prints_no_traceback(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "labrig.cli", "import", str(tmp_path / "nope.hdf5"), str(tmp_path / "o.h5")],
        capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 2 and "error:" in proc.stderr and "no such file" in proc.stderr
    assert "Traceback" not in proc.stderr
