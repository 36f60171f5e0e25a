"""`make demo` finishes on a busy machine, resumes when rerun, and ends with the report's path."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BUSY = "import time\nend = time.monotonic() + 900\nwhile time.monotonic() < end:\n    pass\n"


def test_the_demo_finishes_beside_two_busy_processes_and_resumes(tmp_path: Path) -> None:
    campaign = tmp_path / "one.toml"
    campaign.write_text(f'[campaign]\nname = "one"\nseed = 1\nprotocol = "{ROOT / "protocols" / "probe.toml"}"\n'
                        "[split]\ntrain = 0\nval = 0\ntest = 1\n"
                        '[[group]]\nindenters = ["sphere"]\nlocations_mm = [[0.0, 0.0]]\ndepth_mm = [1.0]\n'
                        "shear_mm = [0.5]\nwait_s = [0.2]\n")
    out = tmp_path / "demo"
    command = [sys.executable, str(ROOT / "tools" / "demo.py"), str(out), "--campaign", str(campaign)]
    busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(2)]
    try:
        first = subprocess.run(command, capture_output=True, text=True, timeout=1500)
    finally:
        for process in busy:
            process.kill()
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    report = out / "report" / "index.html"
    assert report.exists() and (out / "forces.gif").exists() and (out / "data" / "one-000.gt.h5").exists()
    assert "virtual time" in first.stdout and str(report) in first.stdout.replace("\n", "")
    recorded = (out / "data" / "one-000.h5").stat().st_mtime_ns
    again = subprocess.run(command, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert (out / "data" / "one-000.h5").stat().st_mtime_ns == recorded  # resumed: nothing recorded again
