"""Virtual-time campaigns against through-driver ones, side by side in one run.

One campaign (the paper protocol's probing run at a few locations) recorded four ways:
through the drivers with 1 worker (real time), and in virtual time with 1 and 2 local workers
and on a 2-worker Dask LocalCluster. Reported per way: wall time, CPU time (the command's and
its workers' processes), recordings per core-minute (recordings / CPU minutes), simulated
seconds per wall second and per CPU second (the real-time factor per core; the issue's target
is >= 3), and the 1 -> 2 worker speed-up.
"""

from __future__ import annotations

import argparse
import json
import resource
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
name = "bench-vt"
seed = 11
protocol = "{protocol}"

[[group]]
indenters = ["sphere"]
locations_mm = {locations}
depth_mm = [1.0]
"""
LOCATIONS = [[0.0, 0.0], [-4.0, 2.0], [4.0, -2.0], [-3.0, -3.0], [3.0, 3.0], [0.0, 4.0]]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=4, help="recordings per way (at most 6)")
    ap.add_argument("--skip-drivers", action="store_true", help="leave out the through-driver campaign")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _sensor_s(out: Path) -> float:
    total = 0.0
    for path in sorted(out.glob("*.h5")):
        if path.name.endswith(".gt.h5"):
            continue
        with Recording(path) as rec:
            phases = rec.phases()
            total += (phases[-1].t_end_us - phases[0].t_start_us) / 1e6 if phases else 0.0
    return total


def _campaign(campaign: Path, out: Path, *extra: str) -> tuple[dict[str, Any], float, float]:
    cpu0, t0 = _children_cpu_s(), time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "labrig.cli", "campaign", str(campaign), "--out", str(out), "--json",
                           *extra], capture_output=True, text=True, check=False)
    wall, cpu = time.perf_counter() - t0, _children_cpu_s() - cpu0
    if done.returncode != 0:
        raise SystemExit(f"campaign {' '.join(extra)} failed:\n{done.stderr}")
    return json.loads(done.stdout), wall, cpu


def _figures(summary: dict[str, Any], out: Path, wall: float, cpu: float) -> dict[str, Any]:
    n, sensor = summary["recorded"], _sensor_s(out)
    return {"recordings": n, "failed": summary["failed"] + summary["aborted"], "wall_s": wall, "cpu_s": cpu,
            "sensor_s": sensor, "per_core_min": 60 * n / cpu if cpu > 0 else 0.0,
            "sim_s_per_wall_s": sensor / wall, "sim_s_per_cpu_s": sensor / cpu if cpu > 0 else 0.0}


def run(recordings: int = 4, skip_drivers: bool = False, progress: bool = True) -> dict[str, Any]:
    from dask.distributed import LocalCluster

    figures: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        campaign = Path(tmp) / "bench.toml"
        campaign.write_text(CAMPAIGN.format(protocol=ROOT / "protocols" / "probe.toml",
                                            locations=json.dumps(LOCATIONS[: max(1, min(recordings, len(LOCATIONS)))])))
        ways: list[tuple[str, tuple[str, ...]]] = [("virtual_time_1_worker", ("--virtual-time", "--workers", "1")),
                                                   ("virtual_time_2_workers", ("--virtual-time", "--workers", "2"))]
        if not skip_drivers:
            ways.insert(0, ("drivers_1_worker", ("--workers", "1")))
        for name, extra in ways:
            out = Path(tmp) / name
            summary, wall, cpu = _campaign(campaign, out, *extra)
            figures[name] = _figures(summary, out, wall, cpu)
        out = Path(tmp) / "dask"
        cpu0 = _children_cpu_s()
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
            summary, wall, cpu = _campaign(campaign, out, "--virtual-time", "--scheduler", cluster.scheduler_address)
        figures["virtual_time_dask_2_workers"] = _figures(summary, out, wall, _children_cpu_s() - cpu0)
    one, two = figures["virtual_time_1_worker"], figures["virtual_time_2_workers"]
    figures["speedup_1_to_2_workers"] = one["wall_s"] / two["wall_s"]
    if "drivers_1_worker" in figures:
        figures["virtual_vs_drivers_per_core_min"] = one["per_core_min"] / max(figures["drivers_1_worker"]["per_core_min"], 1e-9)
    return figures


def render(f: dict[str, Any]) -> None:
    rows = [[k.replace("_", " "), str(v["recordings"]), str(v["failed"]), f"{v['wall_s']:.1f}", f"{v['cpu_s']:.1f}",
             f"{v['sensor_s']:.1f}", f"{v['per_core_min']:.2f}", f"{v['sim_s_per_wall_s']:.2f}", f"{v['sim_s_per_cpu_s']:.2f}"]
            for k, v in f.items() if isinstance(v, dict)]
    notes = [f"1 -> 2 local workers: {f['speedup_1_to_2_workers']:.2f}x wall"]
    if "virtual_vs_drivers_per_core_min" in f:
        notes.append(f"virtual time vs drivers, recordings per core-minute: {f['virtual_vs_drivers_per_core_min']:.2f}x")
    notes.append("CPU: the command's processes and its workers' (Dask: the cluster's); sim s per CPU s is the "
                 "real-time factor per core (target >= 3)")
    emit("campaign: virtual time vs through the drivers", ["way", "recordings", "failed", "wall (s)", "CPU (s)", "sensor (s)",
                                                           "per core-min", "sim s / wall s", "sim s / CPU s"], rows, notes)


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
