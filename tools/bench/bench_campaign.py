"""A 12-recording campaign on the virtual rig: recordings per minute with 1 and 2 workers.

Each worker is a recorder process with its own virtual rig in a child
process (the real drivers over ptys and the camera socket, as in a lab).
Reported per worker count: wall time, recordings per minute, and the ratio of
wall time to the sensor time recorded (the sum of the recordings' lengths):
1.0 would mean recording back to back with no overhead.
"""

from __future__ import annotations

import argparse
import json
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
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def run(workers: str = "1,2", progress: bool = True) -> dict[str, Any]:
    figures: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        campaign = Path(tmp) / "bench.toml"
        campaign.write_text(CAMPAIGN.format(protocol=ROOT / "protocols" / "probe.toml"))
        for n in (int(w) for w in workers.split(",")):
            out = Path(tmp) / f"w{n}"
            t = time.perf_counter()
            done = subprocess.run([sys.executable, "-m", "labrig.cli", "campaign", str(campaign), "--out", str(out),
                                   "--workers", str(n), "--json"], capture_output=True, text=True, check=False)
            wall = time.perf_counter() - t
            if done.returncode != 0:
                raise SystemExit(f"campaign with {n} workers failed:\n{done.stderr}")
            summary = json.loads(done.stdout)
            sensor_s = 0.0
            for path in sorted(out.glob("*.h5")):
                with Recording(path) as rec:
                    phases = rec.phases()
                    sensor_s += (phases[-1].t_end_us - phases[0].t_start_us) / 1e6 if phases else 0.0
            figures[f"workers_{n}"] = {
                "recordings": summary["recorded"], "wall_s": wall, "recordings_per_min": 60 * summary["recorded"] / wall,
                "sensor_s": sensor_s, "wall_per_sensor_s": wall / max(sensor_s, 1e-9), "aborted": summary["aborted"],
                "failed": summary["failed"],
            }
    return figures


def render(f: dict[str, Any]) -> None:
    rows = [[k.replace("_", " "), str(v["recordings"]), f"{v['wall_s']:.1f}", f"{v['recordings_per_min']:.2f}",
             f"{v['sensor_s']:.1f}", f"{v['wall_per_sensor_s']:.2f}", f"{v['aborted']}/{v['failed']}"]
            for k, v in f.items() if isinstance(v, dict)]
    emit("12-recording campaign on the virtual rig", ["run", "recordings", "wall (s)", "per min", "sensor (s)",
                                                      "wall / sensor", "aborted/failed"], rows,
         ["Sensor time: the recordings' lengths (approach to retract); wall time includes start-up, travel and tare."])


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
