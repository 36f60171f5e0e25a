"""`make demo`: the longest real path labrig has so far.

Today: one probing run (sphere, 1.5 mm deep, +/-1 mm shear) on the virtual rig
(contact mechanics, optics, event camera; `labrig sim probe`), recorded with its
truth through the real recording writer, then `labrig inspect` summarizes and
plots it. Campaigns, ground truth, evaluation and a report join as they land.

Usage: python tools/demo.py OUT_DIR
"""

from __future__ import annotations

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
    recording = out_dir / "sphere.h5"
    steps = [
        [labrig, "sim", "tables"],
        [labrig, "sim", "probe", str(recording), "--indenter", "sphere", "--depth-mm", "1.5", "--shear-mm", "1.0"],
        [labrig, "inspect", str(recording), "--plot", str(out_dir / "sphere.png")],
    ]
    for command in steps:
        console.print(f"$ {' '.join(command)}", style="dim")
        code = subprocess.call(command)
        if code:
            return code
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "demo-out")))
