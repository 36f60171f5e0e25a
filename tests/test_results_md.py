"""tools/results_md.py: docs/results.md from evaluation reports, the commands beside each table."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

TOOL = Path(__file__).resolve().parent.parent / "tools" / "results_md.py"


def _tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("results_md", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


TABLE = {"title": "Force and contact position errors", "caption": "Mean ± std over windows.",
         "columns": [{"key": "axis", "name": "axis", "unit": ""}, {"key": "force_n", "name": "force", "unit": "N"},
                     {"key": "paper_force_n", "name": "paper force", "unit": "N"},
                     {"key": "windows", "name": "windows", "unit": ""}],
         "rows": [{"axis": "x", "force_n": {"mean": 0.0961, "std": 0.0624, "n": None}, "paper_force_n": 0.14,
                   "windows": 12},
                  {"axis": "a|b", "force_n": {"mean": 1.23456, "std": None}, "paper_force_n": float("nan")}]}


def test_a_report_table_renders_as_markdown_with_units_mean_std_and_dashes() -> None:
    tool = _tool()
    lines = tool.markdown_table(TABLE).splitlines()
    assert lines[0] == "| axis | force (N) | paper force (N) | windows |"
    assert lines[1] == "|---|---|---|---|"
    assert lines[2] == "| x | 0.0961 ± 0.0624 | 0.14 | 12 |"
    assert lines[3] == "| a\\|b | 1.23 | - | - |"


def test_a_section_leads_with_the_commands_that_made_its_data_and_its_evaluation() -> None:
    tool = _tool()
    entry = next(e for e in tool.EVALUATIONS if e.name == "shape-check")
    results = {"meta": {"recordings": 24, "model": "m.onnx", "evaluation windows": "20,000 events"},
               "tables": {"headline": TABLE}}
    text = tool.section(entry, results, "labrig evaluate data/shape-check --split test")
    assert text.index("labrig campaign protocols/shape-check.toml") < text.index("--indenters protocols/shapes.toml")
    assert text.index("labrig evaluate data/shape-check") < text.index("| axis |")
    assert "24 recordings of the test split" in text and "Mean ± std over windows." in text


def test_missing_data_are_named_with_their_commands_and_the_tool_exits_1(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    tool = _tool()
    monkeypatch.setattr(tool, "ROOT", tmp_path)  # no campaign folder there: nothing is evaluated
    out = tmp_path / "results.md"
    assert tool.main(["--only", "hold,paper", "--out", str(out)]) == 1
    text = out.read_text()
    assert "`labrig campaign protocols/hold.toml --out data/hold --virtual-time --workers 2`" in text
    assert "Presses held 60 s" in text and "paper campaign" in text and "sensor check" not in text
    with pytest.raises(SystemExit):
        tool.main(["--only", "nonesuch", "--out", str(out)])
