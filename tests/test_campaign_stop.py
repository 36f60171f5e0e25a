"""Stopping `labrig campaign` (Ctrl-C, SIGTERM): workers reaped, partial recordings finalized as
aborted, the manifest resumable."""

from __future__ import annotations

import contextlib
import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

CAMPAIGN = """
[campaign]
name = "stoppable"
seed = 5
protocol = "slow.toml"

[[group]]
indenters = ["sphere"]
locations_mm = [[0.0, 0.0], [3.0, -2.0], [-3.0, 2.0], [2.0, 2.0]]
depth_mm = [0.6]
"""

SLOW = """
[probe]
indenter = "sphere"
[approach]
start_height_mm = 0.4
speed_mm_s = 1.0
max_travel_mm = 1.5
[normal]
depth_mm = 0.6
speed_mm_s = 1.0
[wait]
duration_s = 3.0
[shear]
distance_mm = 0.0
[retract]
height_mm = 1.0
"""


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(FileNotFoundError, ProcessLookupError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.add(child)
            todo.append(child)
    return found


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize(("how", "workers"), [("SIGTERM", 2), ("SIGINT-group", 2), ("SIGTERM", 1)])
def test_a_stopped_campaign_reaps_its_workers_finalizes_and_stays_resumable(tmp_path: Path, how: str, workers: int) -> None:
    (tmp_path / "slow.toml").write_text(SLOW)
    (tmp_path / "stoppable.toml").write_text(CAMPAIGN)
    out = tmp_path / "data"
    proc = subprocess.Popen([sys.executable, "-m", "labrig.cli", "campaign", str(tmp_path / "stoppable.toml"), "--out",
                             str(out), "--workers", str(workers), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    family: set[int] = set()
    try:
        deadline = time.monotonic() + 150
        while time.monotonic() < deadline and len(list(out.glob("**/*.h5.partial"))) < workers:
            time.sleep(0.1)
        assert len(list(out.glob("**/*.h5.partial"))) >= workers, "the campaign never got to recording"
        time.sleep(0.5)
        family = _descendants(proc.pid)
        if how == "SIGINT-group":  # a terminal's Ctrl-C reaches every process of the group
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=90)
        assert proc.returncode == 1, stderr
        assert "run the same command again to resume" in stderr and "Traceback" not in stderr
        time.sleep(1.0)
        assert not {p for p in family if _alive(p)}, "processes left behind"
        assert not list(out.glob("**/*.h5.partial")), "a partial recording was not finalized"
        with (out / "manifest.csv").open(newline="") as f:
            rows = list(csv.DictReader(f))
        statuses = [r["status"] for r in rows]
        assert statuses.count("aborted") >= 1 and "failed" not in statuses, statuses
        for row in rows:
            if row["status"] == "aborted":
                assert "stopped" in row["reason"] and (out / row["file"]).exists()
        from labrig.recording import Recording

        with Recording(out / next(r["file"] for r in rows if r["status"] == "aborted")) as rec:
            assert rec.exit_status == "aborted"
        from labrig.config import load_rig
        from labrig.indenters import DEFAULT_INDENTERS, load_indenters
        from labrig.protocol import load_campaign
        from labrig.protocol.campaign import Manifest, pending_jobs

        rig = load_rig()
        plan = load_campaign(tmp_path / "stoppable.toml", rig, load_indenters())
        manifest = Manifest(out, plan)
        todo = {p.id for job in pending_jobs(plan, manifest, out, rig_path=rig.path, indenters_path=DEFAULT_INDENTERS,
                                             protocol_toml="", workers=1) for p in job.plans}
        assert todo == {r["id"] for r in rows if r["status"] != "complete"}  # a rerun redoes exactly these
    finally:
        for pid in {proc.pid, *family}:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.wait()
