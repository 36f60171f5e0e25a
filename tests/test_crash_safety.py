"""Faults never lose recorded data: kill -9 mid-recording, and a full disk."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from crash_child import expected_events

from labrig.errors import RecordingError
from labrig.recording import Recording, recover
from labrig.recording.layout import partial_path
from labrig.recording.reader import TruncatedRecording

CHILD = Path(__file__).with_name("crash_child.py")


def start_child(path: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, str(CHILD), str(path), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    )


def assert_prefix_of_what_was_written(rec: Recording) -> None:
    x, t = expected_events(rec.n_events)
    assert np.array_equal(rec.column("events", "x"), x)
    assert np.array_equal(rec.column("events", "t_device_us"), t)


def test_kill_9_keeps_everything_up_to_the_last_flush(tmp_path: Path) -> None:
    path = tmp_path / "killed.h5"
    child = start_child(path, "run")
    committed: list[int] = []
    assert child.stdout is not None
    while len(committed) < 8:
        line = child.stdout.readline()
        assert line, child.stderr.read() if child.stderr else "child exited"
        committed.append(int(line))
    os.kill(child.pid, signal.SIGKILL)
    child.wait(10)
    # Lines the child printed before it died are all commits that reached the disk.
    committed += [int(v) for v in child.stdout.read().split()]
    last_commit = committed[-1]
    assert last_commit > 0

    partial = partial_path(path)
    assert partial.exists() and not path.exists()
    with Recording(partial) as rec:
        assert not rec.finalized and rec.exit_status == "recording"
        assert rec.n_events >= last_commit
        assert_prefix_of_what_was_written(rec)

    result = subprocess.run(
        [sys.executable, "-m", "labrig.cli", "recover", str(partial), "--json"], capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["path"] == str(path) and report["rows"]["events"] >= last_commit
    assert not partial.exists()
    with Recording(path) as rec:
        assert rec.finalized and rec.exit_status == "crashed-recovered"
        assert rec.n_events == report["rows"]["events"]
        assert rec.rows("ft") > 0 and rec.clock_model("ft").method == "envelope"
        assert_prefix_of_what_was_written(rec)
    with pytest.raises(RecordingError, match="no such file"):
        recover(partial)


def test_disk_guard_stops_cleanly_and_finalizes(tmp_path: Path) -> None:
    """A file-size limit stands in for a full disk: the guard sees it coming."""
    path = tmp_path / "full.h5"
    child = start_child(path, "guard", str(24 << 20))
    out, err = child.communicate(timeout=120)
    assert child.returncode == 0, err
    final = json.loads(out.strip().splitlines()[-1])
    assert final["status"] == "aborted" and "disk full" in final["reason"]
    with Recording(path) as rec:
        assert rec.finalized and rec.exit_status == "aborted"
        assert "disk full" in rec.attrs["exit_reason"]
        assert rec.n_events > 1_000_000
        assert_prefix_of_what_was_written(rec)
        assert set(rec.stream("drops")["reason"]) <= {b"disk-full"}
    assert path.stat().st_size <= 24 << 20


def test_write_failure_on_a_full_disk_keeps_committed_data(tmp_path: Path) -> None:
    """With the guard off, the write itself fails (EFBIG); commits still say what is safe.

    After a failed write HDF5 may crash the process on its next call; the
    child then dies like a kill -9, and the data must be just as safe.
    """
    path = tmp_path / "nospace.h5"
    child = start_child(path, "nospace", str(16 << 20))
    out, _ = child.communicate(timeout=120)
    lines = out.strip().splitlines()
    if child.returncode == 0:
        fault = json.loads(lines.pop())["fault"]
        assert "disk full" in fault and "labrig recover" in fault
    else:
        assert child.returncode == -signal.SIGSEGV
    last_commit = int(lines[-1])
    partial = partial_path(path)
    try:
        with Recording(partial) as rec:
            assert rec.n_events >= last_commit > 0
            assert_prefix_of_what_was_written(rec)
    except TruncatedRecording as short:
        # The failed flush had already moved the end-of-file mark past what
        # reached the disk; the reader says so and recover mends it.
        assert short.stored_eof > short.eof == 16 << 20
        assert "labrig recover" in str(short)
    recovered = recover(partial)
    with Recording(recovered.path) as rec:
        assert rec.exit_status == "crashed-recovered" and rec.n_events >= last_commit
        assert_prefix_of_what_was_written(rec)
