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
    from labrig.dataset import sidecar_path
    from labrig.groundtruth import generate, write_sidecar
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
            "--out", str(out), "--window-events", "30000", "--workers", "1", "--json", "--cache", str(tmp_path / "cache")]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["recordings"] == 2 and summary["report_problems"] == []
    for key in ("force_x_mae_n", "force_z_mae_n", "depth_total_mm", "pipeline_ms", "lost_tracks_per_sequence",
                "force_z_mae_true_depth_n", "position_total_mae_true_depth_px"):
        assert summary[key] is not None and summary[key] >= 0, key
    assert check_report(out) == []
    results = json.loads((out / "results.json").read_text())
    for table in ("table1", "table2", "table3", "force_by_range", "depth_by_range", "runtime", "label_errors",
                  "dense_forces", "tracking_truth"):
        assert table in results["tables"], table
        assert (out / "tables" / f"{table}.csv").exists()
    table2 = (out / "tables" / "table2.csv").read_text()
    assert "missing" not in table2 and table2.count("\n") == 3  # header + the two networks that exist
    assert next(iter(results["tables"])) == "headline"  # the answer first
    columns = [c["key"] for c in results["tables"]["headline"]["columns"]]
    headline = {row[columns[0]]: [row[c] for c in columns] for row in results["tables"]["headline"]["rows"]}
    assert headline["force z on the gel"][1] == pytest.approx(summary["force_z_mae_n"])
    assert headline["force z on the gel"][2] == 0.93 and headline["force z on the gel"][3] in ("better", "worse")
    assert summary["pipeline_window_ms_p95"] >= summary["pipeline_window_ms_median"] > 0
    assert summary["runtime_cores"] >= 1 and summary["runtime_load_1min"] >= 0
    for table in ("force_by_range", "depth_by_range"):
        assert ",0," not in (out / "tables" / f"{table}.csv").read_text().replace(" ", "")  # no empty rows
    html = (out / "index.html").read_text()
    assert "Table III" in html and "figures/force_by_range_plot.png" in html
    assert html.index("The answer") < html.index("Forces (Table III)")

    again = runner.invoke(app, args)  # every task from the cache
    assert again.exit_code == 0, again.output
    cache = json.loads(again.stdout)["cache"]
    assert set(cache) == {"forces", "forces-truth", "depth", "tracking", "labels"}
    assert all(" 0 computed" in line for line in cache.values()), cache
    assert set(summary["labels"]) == {"layer/lab", "halfspace/lab"}

    both = runner.invoke(app, [*args, "--label-poses", "lab,true"])  # the labels again with the sim's own gel pose
    assert both.exit_code == 0, both.output
    labels = json.loads(both.stdout)["labels"]
    assert set(labels) == {"layer/lab", "halfspace/lab", "layer/true", "halfspace/true"}
    assert all(row["recordings"] == 2 and row["mae_contact_mm"] >= 0 for row in labels.values())
    assert "true (the sim's)" in (out / "tables" / "label_errors.csv").read_text()


def test_evaluate_says_what_is_wrong(campaign: Path, tmp_path: Path) -> None:
    cases = [([str(tmp_path / "nowhere")], "no such folder"),
             ([str(campaign), "--split", "holdout"], "--split must be one of"),
             ([str(campaign), "--split", "val"], "no complete recording in the 'val' split"),
             ([str(campaign), "--window-events", "100", "--window-ms", "10"], "not both"),
             ([str(campaign), "--model", str(tmp_path / "x.onnx")], "no such file"),
             ([str(campaign), "--trackers", "paper,kalman"], "--trackers: kalman"),
             ([str(campaign), "--trackers", ","], "--trackers: none given"),
             ([str(campaign), "--label-poses", "lab,sideways"], "--label-poses: lab, sideways"),
             ([str(campaign), "--stress-metrics", "tracking,speed"], "--stress-metrics: tracking, speed"),
             ([str(campaign), "--calibration", str(tmp_path / "no-calibration")], "--calibration"),]
    bare = tmp_path / "bare"
    shutil.copytree(campaign, bare)
    for side in bare.glob("*.gt.h5"):
        side.unlink()
    cases.append(([str(bare)], "labrig groundtruth"))
    for args, message in cases:
        result = runner.invoke(app, ["evaluate", *args])
        assert isinstance(result.exception, LabrigError), (args, result.exception)  # `labrig` prints it, exit 2
        assert message in str(result.exception), (args, str(result.exception))


def test_sweep_charts_accuracy_against_latency(campaign: Path, models: Path, tmp_path: Path) -> None:
    from labrig.evaluation.report import Report
    from labrig.evaluation.sweep import add_sweep_to_report, run_sweep
    from labrig.executor import run_tasks
    from labrig.pipeline.depthnet import build_unet, export_onnx

    export_onnx(build_unet(width=4).eval(), models / "depth-w4-contact-10ms.onnx",
                {"name": "w4", "scale_mm": 2.5, "window_ms": 10.0, "loss": {"name": "contact"}, "architecture": {"width": 4}})

    def run(kind: str, fn, tasks):  # type: ignore[no-untyped-def]
        return list(run_tasks(fn, tasks, workers=1, cache_dir=tmp_path / "cache"))

    sweep = run_sweep([str(campaign / "r0.h5")], models / "depth-w2-contact-10ms.onnx", models, run,
                      calibration_dir="calibration", window_events=30_000, mesh_refinements=(1, 2))
    by_metric = {m: [p for p in sweep.points if p.metric == m] for m in ("tracking", "depth", "forces")}
    assert len(by_metric["tracking"]) == 20 and len(by_metric["forces"]) == 6
    assert {p.label for p in by_metric["depth"]} >= {"width 2", "width 4", "30 ms (w2)"}
    assert set(sweep.recommendations) == {"tracking", "depth", "forces"}
    for metric, chosen in sweep.recommendations.items():
        best = min(p.error for p in by_metric[metric])
        assert chosen.error <= best * 1.05 + 1e-12
        assert all(p.latency_ms >= chosen.latency_ms for p in by_metric[metric] if p.error <= best * 1.05)
    from labrig.evaluation.charts import knee_index

    for metric, points in by_metric.items():  # the knee is the front's (latencies are measured, so it may move)
        k = knee_index([p.latency_ms for p in points], [p.error for p in points])
        assert sweep.knees[metric] is (points[k] if k is not None else None)
    assert min(p.error for p in by_metric["tracking"] if "1x" in p.label) > 1.5 * min(p.error for p in by_metric["tracking"])
    report = Report("sweep")
    add_sweep_to_report(report, sweep)
    from labrig.evaluation.report import check_report

    report.write(tmp_path / "r")
    assert check_report(tmp_path / "r") == [] and (tmp_path / "r" / "figures" / "pareto_forces.png").exists()
    marks = (tmp_path / "r" / "tables" / "sweep_tracking.csv").read_text()
    assert "recommended" in marks and ("knee" in marks) == (sweep.knees["tracking"] is not None)
