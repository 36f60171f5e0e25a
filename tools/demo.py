"""`make demo`: the longest real path labrig has so far.

Today: the demo campaign (protocols/demo.toml: 6 probing runs, sphere and
cylinder) on the virtual rig, through the real drivers (GRBL and Bota over
pseudo-terminals, the EVK4 as EVT3 over a socket), rigs in parallel where cores allow,
recorded with the truth; `labrig inspect` summarizes and plots one recording;
`labrig groundtruth` makes the depth-map sidecars from what a lab has (CNC pose,
calibration, gel modulus); `labrig run` streams one recording through the
pipeline (tracker, the sim's true depth, inverse FEM) and animates it;
`labrig evaluate` feeds every recording to the pipeline with the bundled depth
network and writes the report (demo-out/report/index.html).

Usage: python tools/demo.py OUT_DIR
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from rich.console import Console


def main(out_dir: Path) -> int:
    console = Console()
    shutil.rmtree(out_dir, ignore_errors=True)
    out_dir.mkdir(parents=True)
    labrig = str(Path(sys.executable).with_name("labrig"))
    data = out_dir / "data"
    workers = 2 if (os.cpu_count() or 1) >= 4 else 1  # a virtual rig and its recorder use about 1.5 cores
    campaign = Path(__file__).resolve().parent.parent / "protocols" / "demo.toml"
    steps = [
        [labrig, "sim", "tables"],
        [labrig, "campaign", str(campaign), "--out", str(data), "--workers", str(workers)],
        [labrig, "inspect", str(data / "demo-000.h5"), "--plot", str(out_dir / "demo-000.png")],
        [labrig, "groundtruth", str(data), "--plot", str(out_dir / "groundtruth.png")],
        [labrig, "run", str(data / "demo-000.h5"), "--depth", "truth", "--out", str(out_dir / "demo-000.forces.h5"),
         "--view", str(out_dir / "demo-000.gif")],
        [labrig, "evaluate", str(data), "--split", "all", "--out", str(out_dir / "report")],
    ]
    for command in steps:
        console.print(f"$ {' '.join(command)}", style="dim")
        code = subprocess.call(command)
        if code:
            return code
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "demo-out")))
