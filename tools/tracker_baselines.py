"""Table I and the tracking stress axes for every tracker on small virtual-rig data (docs/evaluation.md, "Baselines").

Records ``--presses`` short sphere presses on the default virtual rig into ``--out`` (kept
there: a rerun reuses them and the result cache), tracks each with every tracker of
Table I (10 ms windows; patch 1-5x, refined and plain; Evetac's published tracker has one
band and runs once per refinement), then runs the stress suite's tracking axes on the
reduced grid. Prints both tables (``--json``: the rows and the breakdown points).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

from labrig.config import load_rig
from labrig.evaluation.stress import run_stress, stress_summary
from labrig.evaluation.stress_axes import AXES
from labrig.evaluation.tracking import (
    FIXED_BAND_TRACKERS,
    TABLE_PATCH_SCALES,
    TRACKERS,
    table_lost_tracks,
    table_tasks,
    track_recording,
)
from labrig.executor import run_tasks
from labrig.indenters import load_indenter
from labrig.sim.live import record_live
from labrig.sim.motion import probing_path

#: (location mm, depth mm, shear mm, shear direction deg) of each press, 4 mm/s: tests/test_evaluation_tracking.py's three
PRESSES = (((0.0, 0.0), 0.8, 0.4, 0.0), ((3.0, -2.0), 1.0, 0.5, 90.0), ((-3.0, 2.0), 0.6, 0.3, 225.0),
           ((2.0, 3.0), 1.2, 0.6, 135.0), ((-2.0, -3.0), 0.9, 0.5, 300.0))


def record_presses(folder: Path, count: int) -> list[str]:
    rig, sphere = load_rig(), load_indenter("sphere")
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, (location, depth, shear, direction) in enumerate(PRESSES[:count]):
        path = folder / f"press{k}.h5"
        if not path.exists():
            tool = probing_path(rig, sphere, location_mm=location, depth_mm=depth, shear_mm=shear,
                                shear_direction_deg=direction, normal_speed_mm_s=4.0, shear_speed_mm_s=4.0, wait_s=0.05)
            record_live(path, rig, sphere, tool, seed=k, realtime=False)
        paths.append(str(path))
    return paths


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("data/tracker-baselines"), help="recordings and the result cache")
    ap.add_argument("--presses", type=int, default=3, choices=range(1, len(PRESSES) + 1))
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--no-stress", action="store_true", help="Table I only")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    cache = args.out / "cache"
    paths = record_presses(args.out, args.presses)
    tasks = [t for tracker in TRACKERS for t in table_tasks(
        paths, patch_scales=TABLE_PATCH_SCALES[:1] if tracker in FIXED_BAND_TRACKERS else TABLE_PATCH_SCALES,
        tracker=tracker)]
    rows = table_lost_tracks(run_tasks(track_recording, tasks, workers=args.workers, cache_dir=cache))
    out: dict[str, Any] = {"table1": rows}
    if not args.no_stress:
        axes = [replace(a, metrics=("tracking",)) for a in AXES if "tracking" in a.metrics]

        def run(kind: str, fn: Any, stress_tasks: Any) -> Any:
            return run_tasks(fn, stress_tasks, workers=args.workers, cache_dir=cache)

        result = run_stress(run, grid="reduced", axes=axes)
        out["stress_breakdown"] = stress_summary(result)
        out["stress_curves"] = [{"axis": c.axis, "method": c.method, "values": c.values, "p95_px": c.error, "lost": c.lost}
                                for c in result.curves]
    if args.json:
        print(json.dumps(out, indent=1, default=float))
        return
    for r in rows:
        print(f"{r['tracker']:16s} refine={r['refine']!s:5s} {r['patch_scale']:g}x  lost {r['lost_mean']:.1f}±{r['lost_std']:.1f}"
              f"  [by truth {r['lost_by_truth_mean']:.1f}]  p95 {r['error_p95_px_mean']:.2f} px  {r['track_ms_median']:.3f} ms")
    for c in out.get("stress_curves", []):
        print(f"{c['axis']:16s} {c['method']:16s} " + "  ".join(
            f"{v:g}: {e:.2f} px ({n} lost)" for v, e, n in zip(c["values"], c["p95_px"], c["lost"])))
    for axis, methods in out.get("stress_breakdown", {}).items():
        print(f"breaks {axis:24s} " + "  ".join(f"{m}: {'-' if v is None else f'{v:.3g}'}" for m, v in methods.items()))


if __name__ == "__main__":
    main()
