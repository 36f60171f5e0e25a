"""Validate ground-truth maps against the virtual rig's true normal displacement (/truth/depth).

For each simulated recording, elastic model (layer, half-space) and gel pose
(the registration in calibration/, or the nominal pose without one, and the sim's true pose as a
perfect registration), the maps of ``labrig groundtruth`` are compared with the
true field on the same network grid at the frames where the indenter touches
the gel: mean absolute error in and out of the true contact (mm), the 95th
percentile out of contact, the contact masks' IoU, and the indentation error.

    .venv/bin/python tools/groundtruth_validation.py              # records 4 short runs first
    .venv/bin/python tools/groundtruth_validation.py A.h5 B.h5 --json

The truth is read here only; the generator never reads it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from dataclasses import asdict
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from labrig.evaluation.groundtruth_error import GroundTruthErrorTask, evaluate_groundtruth

RUNS = (("sphere", 1.5), ("cylinder", 1.0), ("square", 1.0), ("ridge", 1.0))


def make_recordings(folder: Path) -> list[Path]:
    from labrig.config import load_rig
    from labrig.indenters import load_indenter
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    rig = load_rig()
    out = []
    for name, depth in RUNS:
        indenter = load_indenter(name)
        path = folder / f"{name}.h5"
        tool = probing_path(rig, indenter, location_mm=(2.0, -1.5), depth_mm=depth, shear_mm=1.0, wait_s=0.3)
        record_live(path, rig, indenter, tool, realtime=False)
        out.append(path)
    return out


def validate(path: Path, elastic: str, pose: str) -> dict[str, float | str]:
    result = evaluate_groundtruth(GroundTruthErrorTask(str(path), elastic, pose))
    return {"recording": path.name, **asdict(result), "indentation_err_max_mm": result.indentation_error_max_mm}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("recordings", nargs="*", type=Path, help="simulated recordings (default: record 4 runs)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        paths = args.recordings or make_recordings(Path(tmp))
        rows = [validate(p, elastic, pose) for p in paths for pose in ("lab", "true") for elastic in ("layer", "halfspace")]
    if args.json:
        sys.stdout.write(json.dumps(rows, indent=2) + "\n")
        return 0
    head = f"{'indenter':9} {'model':21} {'pose':8} {'in':>7} {'out':>7} {'p95 out':>8} {'total':>7} {'IoU':>5} {'|dd|max':>8}"
    print(head + "\n" + "-" * len(head))
    for r in rows:
        print(f"{r['indenter']:9} {r['elastic'] + '/' + r['method']:21} {r['pose']:8} {r['mae_contact_mm']:7.3f} "
              f"{r['mae_noncontact_mm']:7.3f} {r['p95_noncontact_mm']:8.3f} {r['mae_total_mm']:7.3f} {r['mask_iou']:5.2f} "
              f"{r['indentation_err_max_mm']:8.3f}")
    print("errors in mm over frames in contact; in / out: inside / outside the true contact")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
