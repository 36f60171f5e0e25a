"""Write docs/results.md: `labrig evaluate` on named data, each section with the commands that made it.

    .venv/bin/python tools/results_md.py [--only NAME,NAME] [--model default] [--out docs/results.md]

Each entry of :data:`EVALUATIONS` names its data (a campaign file, the folder it is recorded into, the
split), the commands that make the data and the evaluation. The tool runs each evaluation (cached: a
rerun computes only what changed) into ``reports/NAME/`` and renders the tables the entry names from
the report's ``results.json``. An entry whose data are missing is left out with the commands that
make them; the tool then exits 1.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
LABRIG = [sys.executable, "-m", "labrig.cli"]


@dataclass(frozen=True)
class Entry:
    """One named evaluation: ``campaign`` recorded into ``data`` (relative to the repository)."""

    name: str
    title: str
    campaign: str
    data: str
    tables: tuple[str, ...]
    split: str = "test"
    indenters: str = ""  # the indenters file its ground truth needs, if not the default

    def make_data(self) -> list[str]:
        groundtruth = f"labrig groundtruth {self.data} --workers 2"
        if self.indenters:
            groundtruth += f" --indenters {self.indenters}"
        return [f"labrig campaign {self.campaign} --out {self.data} --virtual-time --workers 2", groundtruth]

    def evaluate(self, model: str) -> list[str]:
        return ["evaluate", self.data, "--split", self.split, "--model", model, "--no-table1", "--workers", "2",
                "--out", f"reports/{self.name}", "--json"]


EVALUATIONS = (
    Entry("paper", "The paper campaign's test split (the paper's comparison)", "protocols/paper.toml",
          "data/paper-vt", ("headline", "table3", "force_by_range")),
    Entry("sensor-check", "The sensor check: four indenters, 1.0-1.5 mm presses, the reference camera",
          "protocols/sensor-check.toml", "data/sensor-check", ("headline", "force_by_indenter")),
    Entry("sensor-check-thresholds-030", "The sensor check on a less sensitive camera (thresholds 0.30 / 0.30, "
          "calibrated)", "protocols/sensor-check-thresholds-030.toml", "data/sensor-check-thresholds-030",
          ("headline",)),
    Entry("shape-check", "Shapes held out of training beside the four standard indenters",
          "protocols/shape-check.toml", "data/shape-check", ("headline", "force_by_indenter"),
          indenters="protocols/shapes.toml"),
    Entry("hold", "Presses held 60 s", "protocols/hold.toml", "data/hold", ("headline", "hold")),
)


def format_cell(value: Any) -> str:
    """A table cell: numbers to 3 significant digits, a missing value as a dash."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, bool) or not isinstance(value, int | float):
        return str(value).replace("|", "\\|")
    if isinstance(value, int) or float(value).is_integer():
        return str(int(value))
    return f"{value:.3g}"


def markdown_table(table: dict[str, Any]) -> str:
    """One table of a report's ``results.json`` (``columns`` with name and unit, ``rows`` by key) as markdown."""
    columns = table["columns"]
    header = [c["name"] + (f" ({c['unit']})" if c.get("unit") else "") for c in columns]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(columns)]
    for row in table["rows"]:
        lines.append("| " + " | ".join(format_cell(_cell(row.get(c["key"]))) for c in columns) + " |")
    return "\n".join(lines)


def _cell(value: Any) -> Any:
    if isinstance(value, dict) and "mean" in value:  # a mean +- std cell
        mean, std = value.get("mean"), value.get("std")
        return f"{format_cell(mean)} ± {format_cell(std)}" if std is not None else mean
    return value


def section(entry: Entry, results: dict[str, Any], evaluate_command: str) -> str:
    """An entry's section: title, the commands, the data's description, its tables."""
    meta = results.get("meta", {})
    lines = [f"## {entry.title}", "", "```sh", *entry.make_data(), evaluate_command, "```", "",
             f"{meta.get('recordings', '?')} recordings of the {entry.split} split, the network "
             f"`{meta.get('model', '?')}`, {meta.get('evaluation windows', '?')} per window; "
             f"made {meta.get('generated_utc', '?')} on {meta.get('machine', '?')}.", ""]
    for key in entry.tables:
        table = results.get("tables", {}).get(key)
        if table is None:
            continue
        lines += [f"**{table['title']}**", "", markdown_table(table), ""]
        if table.get("caption"):
            lines += [table["caption"], ""]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="", help="comma-separated entry names (default: all)")
    ap.add_argument("--model", default="default", help="the network evaluated (default: the bundled one)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results.md")
    args = ap.parse_args(argv)
    names = {n.strip() for n in args.only.split(",") if n.strip()}
    unknown = names - {e.name for e in EVALUATIONS}
    if unknown:
        ap.error(f"--only: no entry named {', '.join(sorted(unknown))}; the entries: "
                 f"{', '.join(e.name for e in EVALUATIONS)}")
    sections, missing = [], []
    for entry in EVALUATIONS:
        if names and entry.name not in names:
            continue
        if not (ROOT / entry.data / "manifest.csv").exists():
            missing.append(entry)
            continue
        command = entry.evaluate(args.model)
        print(f"{entry.name}: labrig {' '.join(command)}", file=sys.stderr)
        done = subprocess.run([*LABRIG, *command], cwd=ROOT, stdout=subprocess.DEVNULL)
        if done.returncode != 0:
            print(f"{entry.name}: labrig evaluate exited {done.returncode}", file=sys.stderr)
            return done.returncode
        results = json.loads((ROOT / "reports" / entry.name / "results.json").read_text())
        sections.append(section(entry, results, "labrig " + " ".join(command[:-1])))
    header = ["# Results", "",
              "Written by `python tools/results_md.py` from `labrig evaluate`'s `results.json` on the named data "
              f"below ({datetime.now(UTC):%Y-%m-%d}); edit the tool, not this file. Forces are the force on the "
              "gel in the gel frame; every data set is recorded on the virtual rig in virtual time.", ""]
    for entry in missing:
        header += [f"*{entry.title}*: not measured, its data are missing (`{'`, then `'.join(entry.make_data())}`).",
                   ""]
    args.out.write_text("\n".join(header + sections).rstrip() + "\n")
    print(f"wrote {args.out}", file=sys.stderr)
    return 1 if missing else 0


if __name__ == "__main__":
    sys.exit(main())
