"""`make demo`: the longest real path labrig has, on the virtual rig, ending in the evaluation report.

The demo campaign (protocols/demo.toml: 6 probing runs, sphere and cylinder) is recorded in
virtual time (each recording simulated in its own time: deterministic, and it finishes however
busy the machine is); `--through-drivers` serves it live to the real drivers instead (GRBL and
Bota over pseudo-terminals, the EVK4 as EVT3 over a socket), which needs a machine with cores
to spare. Then `labrig inspect` summarizes and plots one recording; `labrig groundtruth` makes
the depth-map sidecars from what a lab has (CNC pose, calibration, gel modulus); `labrig run`
streams one recording through the pipeline (tracker, the sim's true depth, inverse FEM) and
animates it; `labrig evaluate` feeds every recording to the pipeline with the bundled depth
network and writes the report.

A rerun resumes: the campaign records only what is missing, the ground truth and the
evaluation reuse what is current. `--fresh` starts over.

Usage: python tools/demo.py [OUT_DIR] [--through-drivers] [--fresh] [--campaign FILE]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from rich.console import Console

ROOT = Path(__file__).resolve().parent.parent
#: What the demo takes on a 2-core machine, virtual time / through the drivers (minutes).
EXPECTED_MIN = {"virtual time": 5, "through the drivers": 6}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", nargs="?", type=Path, default=Path("demo-out"), help="where everything goes")
    ap.add_argument("--through-drivers", action="store_true",
                    help="serve the campaign live to the real drivers (needs cores to spare)")
    ap.add_argument("--fresh", action="store_true", help="start over instead of resuming")
    ap.add_argument("--campaign", type=Path, default=ROOT / "protocols" / "demo.toml", help="the campaign to record")
    args = ap.parse_args(argv)
    console = Console()
    out_dir: Path = args.out_dir
    if args.fresh:
        shutil.rmtree(out_dir, ignore_errors=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    labrig = str(Path(sys.executable).with_name("labrig"))
    data = out_dir / "data"
    mode = "through the drivers" if args.through_drivers else "virtual time"
    workers = 2 if (os.cpu_count() or 1) >= 4 else 1  # a live virtual rig and its recorder use about 1.5 cores
    campaign = [labrig, "campaign", str(args.campaign), "--out", str(data)]
    campaign += ["--workers", str(workers)] if args.through_drivers else ["--virtual-time", "--workers", "2"]
    first = data / f"{_campaign_name(args.campaign)}-000.h5"
    report = out_dir / "report" / "index.html"
    console.print(f"[bold]labrig demo[/]: {args.campaign.name} recorded in {mode} "
                  f"(about {EXPECTED_MIN[mode]} min on 2 cores); the report will be {report}"
                  + ("" if args.through_drivers else "; --through-drivers: the real drivers instead"))
    steps = [
        [labrig, "sim", "tables"],
        campaign,
        [labrig, "inspect", str(first), "--plot", str(out_dir / "recording.png")],
        [labrig, "groundtruth", str(data), "--plot", str(out_dir / "groundtruth.png")],
        [labrig, "run", str(first), "--depth", "truth", "--out", str(out_dir / "forces.h5"),
         "--view", str(out_dir / "forces.gif")],
        [labrig, "evaluate", str(data), "--split", "all", "--out", str(out_dir / "report")],
    ]
    started = time.monotonic()
    for command in steps:
        console.print(f"$ {' '.join(command)}", style="dim")
        code = subprocess.call(command)
        if code:
            console.print(f"[red]the demo stopped at `{' '.join(command[1:3])}` (exit {code})[/]; rerun it to resume")
            return code
    console.print(f"[green]done[/] in {(time.monotonic() - started) / 60:.1f} min ({mode}). The report: {report}")
    return 0


def _campaign_name(path: Path) -> str:
    """The campaign's name (its recordings are NAME-000.h5, ...)."""
    import tomllib

    return str(tomllib.loads(path.read_text()).get("campaign", {}).get("name", path.stem))


if __name__ == "__main__":
    sys.exit(main())
