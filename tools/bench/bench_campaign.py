"""A 12-recording campaign on the virtual rig: recordings per minute with 1 and 2 workers.

Each worker is a recorder process with its own virtual rig in a child
process (the real drivers over ptys and the camera socket, as in a lab).
Reported per worker count: wall time, recordings per minute, and the ratio of
wall time to the sensor time recorded (the sum of the recordings' lengths):
1.0 would mean recording back to back with no overhead.

``--beside CMD`` runs a shell command (e.g. ``make test``) beside each campaign, started with it
and stopped when it ends, to show what load does to a through-driver campaign. Every such run is
counted: lost (aborted or failed), short (kept short after its retries), retried (fell behind real
time at least once, then recorded again), and the command's own exit status. The target is no
run lost or short.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import bench_main, emit

from labrig.recording import Recording

ROOT = Path(__file__).resolve().parents[2]

CAMPAIGN = """
[campaign]
name = "bench"
seed = 7
protocol = "{protocol}"

[[group]]
indenters = ["sphere", "cylinder"]
locations_mm = [[0.0, 0.0], [-4.0, 2.0], [4.0, -2.0], [-3.0, -3.0], [3.0, 3.0], [0.0, 4.0]]
depth_mm = [1.0]
shear_mm = [0.5]
wait_s = [0.2]
"""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", default="1,2", help="worker counts to compare")
    ap.add_argument("--beside", default="", help="a shell command to run beside each campaign (e.g. 'make test')")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def _start_beside(command: str) -> subprocess.Popen[bytes] | None:
    """The load command in its own process group (so all its children can be stopped), output discarded."""
    if not command:
        return None
    return subprocess.Popen(command, shell=True, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)


def _stop_beside(load: subprocess.Popen[bytes] | None) -> int | None:
    """The load's exit status if it ended on its own, else None after stopping its process group."""
    if load is None or load.poll() is not None:
        return None if load is None else load.returncode
    os.killpg(load.pid, signal.SIGTERM)
    try:
        load.wait(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(load.pid, signal.SIGKILL)
        load.wait()
    return None


def _manifest_counts(out: Path) -> dict[str, Any]:
    """Runs retried after falling behind real time (the manifest's ``fell_behind`` column), and every run
    not complete or retried with its status, reason and what fell behind."""
    manifest = out / "manifest.csv"
    if not manifest.exists():
        return {"retried": 0, "problems": []}
    with manifest.open(newline="") as f:
        rows = list(csv.DictReader(f))
    return {"retried": sum(1 for row in rows if row.get("fell_behind")),
            "problems": [{k: row.get(k, "") for k in ("id", "status", "reason", "fell_behind")} for row in rows
                         if row.get("status") != "complete" or row.get("fell_behind")]}


def run(workers: str = "1,2", beside: str = "", progress: bool = True) -> dict[str, Any]:
    figures: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        campaign = Path(tmp) / "bench.toml"
        campaign.write_text(CAMPAIGN.format(protocol=ROOT / "protocols" / "probe.toml"))
        for n in (int(w) for w in workers.split(",")):
            out = Path(tmp) / f"w{n}"
            load = _start_beside(beside)
            t = time.perf_counter()
            try:
                done = subprocess.run([sys.executable, "-m", "labrig.cli", "campaign", str(campaign), "--out", str(out),
                                       "--workers", str(n), "--json"], capture_output=True, text=True, check=False)
            finally:
                wall = time.perf_counter() - t
                beside_status = _stop_beside(load)
            if not done.stdout.strip():
                raise SystemExit(f"campaign with {n} workers printed no summary:\n{done.stderr[-3000:]}")
            summary = json.loads(done.stdout)
            sensor_s = 0.0
            for path in sorted(out.glob("*.h5")):
                with Recording(path) as rec:
                    phases = rec.phases()
                    sensor_s += (phases[-1].t_end_us - phases[0].t_start_us) / 1e6 if phases else 0.0
            figures[f"workers_{n}"] = {
                "recordings": summary["recorded"], "wall_s": wall, "recordings_per_min": 60 * summary["recorded"] / wall,
                "sensor_s": sensor_s, "wall_per_sensor_s": wall / max(sensor_s, 1e-9), "aborted": summary["aborted"],
                "failed": summary["failed"], "short": summary.get("short", 0),
                "lost_or_short": summary["aborted"] + summary["failed"] + summary.get("short", 0),
                **_manifest_counts(out), "beside": beside,
                # None: still running when the campaign ended (stopped then), or no command
                "beside_exit_status": beside_status,
            }
    return figures


def render(f: dict[str, Any]) -> None:
    rows = [[k.replace("_", " "), str(v["recordings"]), f"{v['wall_s']:.1f}", f"{v['recordings_per_min']:.2f}",
             f"{v['sensor_s']:.1f}", f"{v['wall_per_sensor_s']:.2f}", f"{v['aborted']}/{v['failed']}/{v['short']}",
             str(v["retried"])]
            for k, v in f.items() if isinstance(v, dict)]
    notes = ["Sensor time: the recordings' lengths (approach to retract); wall time includes start-up, travel and tare."]
    for k, v in f.items():
        if isinstance(v, dict) and v.get("beside"):
            status = v["beside_exit_status"]
            notes.append(f"{k.replace('_', ' ')}: beside `{v['beside']}` "
                         + ("(still running at the campaign's end; stopped)" if status is None else f"(exit status {status})")
                         + f"; runs lost or short: {v['lost_or_short']} (target 0)")
        if isinstance(v, dict):
            notes.extend(f"{k.replace('_', ' ')}: {p['id']} {p['status']}"
                         + (f" ({p['reason']})" if p["reason"] else "")
                         + (f"; fell behind: {p['fell_behind']}" if p["fell_behind"] else "") for p in v["problems"])
    emit("12-recording campaign on the virtual rig", ["run", "recordings", "wall (s)", "per min", "sensor (s)",
                                                      "wall / sensor", "aborted/failed/short", "retried"], rows, notes)


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
