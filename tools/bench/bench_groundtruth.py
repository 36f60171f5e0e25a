"""Ground-truth generation speed: maps per second and the ratio of generation time to the recording's duration.

Setup (not timed): one simulated probing run per indenter (sphere, cylinder,
square, ridge; 1 mm deep, 1 mm shear) recorded into a temp dir, and each
model's contact table loaded from (or built into) the cache once.

Measured per recording and elastic model (layer, half-space), ``--repeat``
times, best kept: ``generate`` at ``--rate-hz`` (maps per second of
recording) and ``write_sidecar``. Figures: maps/s of the generation, maps/s
including the sidecar write, and time / recording duration (below 1: faster
than the data were recorded).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import bench_main, emit

RUNS = (("sphere", 1.0), ("cylinder", 1.0), ("square", 1.0), ("ridge", 1.0))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate-hz", type=float, default=100.0, help="maps per second of recording")
    ap.add_argument("--repeat", type=int, default=2, help="timed runs per case (best kept)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def run(rate_hz: float = 100.0, repeat: int = 2, progress: bool = True) -> dict[str, Any]:
    from labrig.config import load_rig
    from labrig.groundtruth import generate, write_sidecar
    from labrig.indenters import load_indenter
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    rig = load_rig()
    cases = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, depth in RUNS:
            indenter = load_indenter(name)
            path = Path(tmp) / f"{name}.h5"
            if progress:
                print(f"recording {name} ...", file=sys.stderr)
            tool = probing_path(rig, indenter, location_mm=(2.0, -1.5), depth_mm=depth, shear_mm=1.0, wait_s=0.3)
            record_live(path, rig, indenter, tool, realtime=False)
            for elastic in ("layer", "halfspace"):
                t = time.perf_counter()
                generate(path, elastic=elastic, rate_hz=rate_hz)  # warm: tables into memory
                warm_s = time.perf_counter() - t
                best_gen, best_all, n, duration_s, method, size = float("inf"), float("inf"), 0, 0.0, "", 0
                for _ in range(max(repeat, 1)):
                    t = time.perf_counter()
                    gt = generate(path, elastic=elastic, rate_hz=rate_hz)
                    t_gen = time.perf_counter() - t
                    side = write_sidecar(gt, Path(tmp) / f"{name}-{elastic}.gt.h5")
                    t_all = time.perf_counter() - t
                    best_gen, best_all = min(best_gen, t_gen), min(best_all, t_all)
                    n, method, size = int(gt.t_us.size), str(gt.attrs["contact_model"]), side.stat().st_size
                    duration_s = float(gt.t_us[-1] - gt.t_us[0]) / 1e6
                cases.append({
                    "indenter": name, "elastic": elastic, "method": method, "maps": n, "recording_s": duration_s,
                    "generate_s": best_gen, "with_write_s": best_all, "first_call_s": warm_s,
                    "maps_per_s": n / best_gen, "maps_per_s_with_write": n / best_all,
                    "time_per_recording_s": best_all / duration_s, "sidecar_mb": size / 1e6,
                })
    total_maps = sum(c["maps"] for c in cases)
    return {
        "rate_hz": rate_hz,
        "cases": cases,
        "maps_per_s_overall": total_maps / sum(c["with_write_s"] for c in cases),
        "time_per_recording_overall": sum(c["with_write_s"] for c in cases) / sum(c["recording_s"] for c in cases),
    }


def render(f: dict[str, Any]) -> None:
    emit(
        f"Ground-truth generation at {f['rate_hz']:g} maps per recording second (one core)",
        ["indenter", "model", "maps", "recording s", "maps/s", "maps/s + write", "time / recording", "sidecar MB",
         "first call s"],
        [[c["indenter"], f"{c['elastic']}/{c['method']}", f"{c['maps']}", f"{c['recording_s']:.2f}",
          f"{c['maps_per_s']:.0f}", f"{c['maps_per_s_with_write']:.0f}", f"{c['time_per_recording_s']:.3f}",
          f"{c['sidecar_mb']:.2f}", f"{c['first_call_s']:.2f}"] for c in f["cases"]],
        [f"overall: {f['maps_per_s_overall']:.0f} maps/s including the sidecar write; generation takes "
         f"{f['time_per_recording_overall']:.3f} x the recordings' duration. 'first call' includes loading "
         "(or building) the contact table."],
    )


SINGLE_THREAD = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def main(argv: list[str] | None = None) -> None:
    if argv is None and any(os.environ.get(var) != "1" for var in SINGLE_THREAD):
        os.environ.update(dict.fromkeys(SINGLE_THREAD, "1"))
        os.execv(sys.executable, [sys.executable, *sys.argv])  # numpy is loaded: start again, single-threaded
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
