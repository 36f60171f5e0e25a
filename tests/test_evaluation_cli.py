"""`labrig evaluate` end to end on a tiny simulated campaign: tables, charts, the report and its checks."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from labrig.cli import app
from labrig.config import RigConfig
from labrig.errors import LabrigError
from labrig.evaluation.report import check_report
from labrig.indenters import load_indenter

runner = CliRunner()


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory, rig: RigConfig) -> Path:
    """Two short simulated probes (sphere, cylinder) in the test split, with sidecars and a manifest."""
    from labrig.groundtruth import generate, sidecar_path, write_sidecar
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    folder = tmp_path_factory.mktemp("eval-campaign")
    lines = ["id,split,status,file,sha256"]
    for i, (name, depth) in enumerate((("sphere", 1.0), ("cylinder", 0.6))):
        indenter = load_indenter(name)
        tool = probing_path(rig, indenter, location_mm=(1.0, -1.0), depth_mm=depth, shear_mm=0.4, normal_speed_mm_s=4.0,
                            shear_speed_mm_s=4.0, wait_s=0.05)
        record_live(folder / f"r{i}.h5", rig, indenter, tool, seed=i, realtime=False)
        write_sidecar(generate(folder / f"r{i}.h5", rate_hz=100), sidecar_path(folder / f"r{i}.h5"))
        lines.append(f"r{i},test,complete,r{i}.h5,")
    lines.append("r9,train,pending,,")
    (folder / "manifest.csv").write_text("\n".join(lines) + "\n")
    return folder


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Untrained width-2 networks: the 10 ms contact-aware one and the 30 ms one of Table II."""
    from labrig.pipeline.depthnet import build_unet, export_onnx

    folder = tmp_path_factory.mktemp("models")
    torch.manual_seed(0)
    for window in (10.0, 30.0):
        export_onnx(build_unet(width=2).eval(), folder / f"depth-w2-contact-{window:g}ms.onnx",
                    {"name": "w2", "scale_mm": 2.5, "window_ms": window, "loss": {"name": "contact"},
                     "architecture": {"width": 2}})
    return folder


def test_evaluate_writes_a_checked_report(campaign: Path, models: Path, tmp_path: Path) -> None:
    out = tmp_path / "report"
    args = ["evaluate", str(campaign), "--model", str(models / "depth-w2-contact-10ms.onnx"), "--models", str(models),
            "--out", str(out), "--window-events", "30000", "--workers", "1", "--json"]
    result = runner.invoke(app, args, env={"LABRIG_CACHE": str(tmp_path / "cache")})
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["recordings"] == 2 and summary["report_problems"] == []
    for key in ("force_x_mae_n", "force_z_mae_n", "depth_total_mm", "pipeline_ms", "lost_tracks_per_sequence"):
        assert summary[key] is not None and summary[key] >= 0, key
    assert check_report(out) == []
    results = json.loads((out / "results.json").read_text())
    for table in ("table1", "table2", "table3", "force_by_range", "depth_by_range", "runtime", "label_errors",
                  "dense_forces", "tracking_truth"):
        assert table in results["tables"], table
        assert (out / "tables" / f"{table}.csv").exists()
    table2 = (out / "tables" / "table2.csv").read_text()
    assert table2.count("missing") == 4  # 5, 50, 70 ms contact-aware and the uniform loss have no model here
    html = (out / "index.html").read_text()
    assert "Table III" in html and "figures/force_by_range_plot.png" in html

    again = runner.invoke(app, args, env={"LABRIG_CACHE": str(tmp_path / "cache")})  # every task from the cache
    assert again.exit_code == 0, again.output
    cache = json.loads(again.stdout)["cache"]
    assert set(cache) == {"forces", "depth", "tracking", "labels"}
    assert all(" 0 computed" in line for line in cache.values()), cache


def test_evaluate_says_what_is_wrong(campaign: Path, tmp_path: Path) -> None:
    cases = [([str(tmp_path / "nowhere")], "no such folder"),
             ([str(campaign), "--split", "holdout"], "--split must be one of"),
             ([str(campaign), "--split", "val"], "no complete recording in the 'val' split"),
             ([str(campaign), "--window-events", "100", "--window-ms", "10"], "not both"),
             ([str(campaign), "--model", str(tmp_path / "x.onnx")], "no such file")]
    bare = tmp_path / "bare"
    shutil.copytree(campaign, bare)
    for side in bare.glob("*.gt.h5"):
        side.unlink()
    cases.append(([str(bare)], "labrig groundtruth"))
    for args, message in cases:
        result = runner.invoke(app, ["evaluate", *args])
        assert isinstance(result.exception, LabrigError), (args, result.exception)  # `labrig` prints it, exit 2
        assert message in str(result.exception), (args, str(result.exception))
