"""Calibrate the default rig (the virtual one) end to end and write its files into calibration/.

The same commands a lab runs on its own rig, in order: camera intrinsics (a blinking dot-grid
target at many poses), extrinsics (the LED ring blinking), rig registration (touch-offs through
the real drivers), gel modulus (stepped indentations), contrast thresholds and the light's slope
response (the LED ring dimmed and brightened along ramps, then the calibration press, whose ground
truth needs the registration and the gel). Each records its scene on the virtual rig first. The files
(intrinsics.toml, extrinsics.toml, events.toml with events-thresholds.npz, rig-registration.toml,
gel.toml) ship with labrig; rerun this after changing calibration/rig.toml's [sim.*] truth.

Usage: python tools/calibrate_default_rig.py [--plots DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CALIBRATION = ROOT / "calibration"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plots", type=Path, help="write each step's plot into this directory")
    args = ap.parse_args(argv)
    steps = [
        ("intrinsics", ["--out", str(CALIBRATION / "intrinsics.toml")]),
        ("extrinsics", ["--intrinsics", str(CALIBRATION / "intrinsics.toml"), "--out", str(CALIBRATION / "extrinsics.toml")]),
        ("rig", ["--out", str(CALIBRATION / "rig-registration.toml")]),
        ("gel", ["--out", str(CALIBRATION / "gel.toml")]),
        ("events", ["--out", str(CALIBRATION / "events.toml")]),  # last: its calibration press needs the gel's
    ]
    summary = {}
    for name, options in steps:
        if args.plots is not None:
            args.plots.mkdir(parents=True, exist_ok=True)
            options = [*options, "--plot", str(args.plots / f"{name}.png")]
        command = [sys.executable, "-m", "labrig.cli", "calibrate", name, *options, "--json"]
        print("$", " ".join(command[2:]), file=sys.stderr)
        done = subprocess.run(command, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            print(done.stderr, file=sys.stderr)
            return done.returncode
        summary[name] = json.loads(done.stdout)
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
