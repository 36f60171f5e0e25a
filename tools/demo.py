"""`make demo`: the longest real path labrig has so far.

Today: synthetic device streams of one probing run (camera events, F/T, CNC,
protocol phases, trigger edges) go through the real recording writer, and
`labrig inspect` summarizes and plots the file. The virtual rig and the
campaign runner will replace the synthetic streams as they land.

Usage: python tools/demo.py OUT_DIR
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from rich.console import Console

from labrig.testing.synthetic import SyntheticRun, record_synthetic


def main(out_dir: Path) -> int:
    console = Console()
    shutil.rmtree(out_dir, ignore_errors=True)
    out_dir.mkdir(parents=True)
    recording = out_dir / "run-001.h5"
    with console.status("recording 8 s of synthetic streams through the writer"):
        result = record_synthetic(recording, SyntheticRun(duration_s=8.0, peak_event_rate_hz=2e6))
    console.print(f"[green]wrote[/] {result.path} ({result.rows['events']:,} events, {result.exit_status})")
    labrig = Path(sys.executable).with_name("labrig")
    command = [str(labrig), "inspect", str(recording), "--plot", str(out_dir / "run-001.png")]
    console.print(f"$ {' '.join(command)}", style="dim")
    return subprocess.call(command)


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "demo-out")))
