"""The evaluation report (HTML, CSV, JSON, checks, terminal summary) and its charts."""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure
from rich.console import Console

from labrig.evaluation import charts
from labrig.evaluation.report import MeanStd, Report, check_report, format_cell, print_summary, to_jsonable

FORCE_ROWS = [
    ["x", MeanStd(0.14, 0.12, 812), MeanStd(1.59, 4.62)],
    ["y", MeanStd(0.10, 0.13, 812), MeanStd(1.55, 4.24)],
    ["z", MeanStd(0.93, 1.00, 812), None],
    {"Axis": "Total", "Force": MeanStd(0.94, 1.00), "Position": MeanStd(2.47, 6.19)},
]


def small_figure() -> Figure:
    fig = Figure(figsize=(3, 2))
    ax = fig.subplots()
    ax.plot([0, 1, 2], [0.3, 0.1, 0.2])
    ax.set_xlabel("time (s)")
    ax.set_ylabel("force (N)")
    return fig


def sample_report(image: Path) -> Report:
    report = Report("Evaluation <of> test & split", meta={"dataset": "data/", "split": "test"})
    report.add_text("intro", "Windows of **10 ms**; raw numbers in [results.json](results.json).\n\n- one\n- `two <b>`")
    report.section("Forces")
    report.add_table(
        "force_errors",
        "Force and contact position errors",
        ["Axis", "Force", "Position"],
        FORCE_ROWS,
        caption="mean ± std over test windows",
        units={"Force": "N", "Position": "px"},
    )
    report.add_table(
        "lost_tracks",
        "Lost tracks per sequence",
        ["Patch size", "Lost", "Error"],
        [[2.0, 3, 0.12345], [3.0, np.int64(0), float("nan")], [4.0, 12, np.float32(1.5)]],
        units={"Patch size": "marker diameters", "Error": "px"},
    )
    report.add_figure("force_time", "Net force over time", small_figure(), caption="predicted vs measured")
    report.section("Runtime")
    report.add_figure("runtime", "Stage latencies", image)
    report.add_table("runtime", "Stage latencies", ["stage", "latency"], [["forces", 9.6]], units={"latency": "ms"})
    report.add_json("depth_error_mm", {"per_window": np.array([0.1, 0.2, np.nan]), "count": np.int64(3)})
    return report


@pytest.fixture()
def written(tmp_path: Path) -> Path:
    image = tmp_path / "runtime.png"
    small_figure().savefig(image)
    out = tmp_path / "report"
    sample_report(image).write(out)
    return out


def test_written_report_has_page_tables_figures_and_json(written: Path) -> None:
    assert check_report(written) == []
    page = (written / "index.html").read_text(encoding="utf-8")
    assert "Evaluation &lt;of&gt; test &amp; split" in page
    assert "<code>two &lt;b&gt;</code>" in page
    assert "0.14 ± 0.12" in page and "0.93 ± 1.00" in page
    assert 'class="missing"' in page
    assert "<script" not in page and "<link" not in page and "url(" not in page
    assert (written / "figures" / "force_time.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (written / "figures" / "runtime.png").stat().st_size > 0

    results = json.loads((written / "results.json").read_text(encoding="utf-8"))
    assert set(results) >= {"title", "meta", "sections", "tables", "figures", "text", "data", "files"}
    table = results["tables"]["force_errors"]
    assert [c["key"] for c in table["columns"]] == ["axis", "force_n", "position_px"]
    assert table["rows"][0]["force_n"] == {"mean": 0.14, "std": 0.12, "n": 812}
    assert table["rows"][2]["position_px"] is None
    assert results["tables"]["lost_tracks"]["rows"][1]["error_px"] is None
    assert results["data"]["depth_error_mm"] == {"per_window": [0.1, 0.2, None], "count": 3}
    assert results["figures"]["runtime"]["path"] == "figures/runtime.png"
    assert [s["key"] for s in results["sections"]] == ["top", "forces", "runtime"]
    assert results["sections"][2]["items"] == [{"kind": "figure", "key": "runtime"}, {"kind": "table", "key": "runtime"}]


def test_csv_round_trips_the_numbers(written: Path) -> None:
    with (written / "tables" / "force_errors.csv").open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["axis", "force_n_mean", "force_n_std", "position_px_mean", "position_px_std"]
    for row, expected in zip(rows, FORCE_ROWS):
        cells = list(expected.values()) if isinstance(expected, dict) else expected
        assert row["axis"] == cells[0]
        assert float(row["force_n_mean"]) == cells[1].mean and float(row["force_n_std"]) == cells[1].std
    assert rows[2]["position_px_mean"] == "" and rows[2]["position_px_std"] == ""

    with (written / "tables" / "lost_tracks.csv").open(newline="", encoding="utf-8") as f:
        lost = list(csv.DictReader(f))
    assert list(lost[0]) == ["patch_size_marker_diameters", "lost", "error_px"]
    assert float(lost[0]["error_px"]) == 0.12345 and lost[1]["error_px"] == "" and int(lost[2]["lost"]) == 12


def test_check_report_finds_a_missing_image(written: Path) -> None:
    (written / "figures" / "runtime.png").unlink()
    problems = check_report(written)
    assert any("figures/runtime.png" in p for p in problems)


def test_check_report_finds_broken_html(written: Path) -> None:
    page = written / "index.html"
    text = page.read_text(encoding="utf-8")
    page.write_text(text.replace("</table>", "", 1), encoding="utf-8")
    assert any("</div> closes" in p or "never closed" in p for p in check_report(written))
    page.write_text(text[: len(text) // 2], encoding="utf-8")
    assert any("never closed" in p for p in check_report(written))
    page.write_text(text.replace('href="#table-force_errors"', 'href="#nowhere"'), encoding="utf-8")
    assert any("#nowhere" in p for p in check_report(written))
    page.write_text(text.replace('href="results.json"', 'href="/etc/hostname"'), encoding="utf-8")
    assert any("absolute path /etc/hostname" in p for p in check_report(written))


def test_check_report_finds_a_missing_csv_and_page(written: Path) -> None:
    (written / "tables" / "lost_tracks.csv").unlink()
    assert any("lost_tracks.csv" in p for p in check_report(written))
    (written / "index.html").unlink()
    assert check_report(written) == [f"{written / 'index.html'}: missing (never written, or the writer stopped before the end)"]


def test_rewrite_removes_files_the_new_report_drops(written: Path) -> None:
    (written / "notes.txt").write_text("mine")
    Report("Smaller").add_table("only", "Only table", ["a"], [[1.0]]).write(written)
    assert not (written / "tables" / "force_errors.csv").exists()
    assert not (written / "figures" / "runtime.png").exists()
    assert (written / "notes.txt").read_text() == "mine"
    assert check_report(written) == []


def test_failed_write_leaves_no_page(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "report"
    Report("First").add_text("a", "first").write(out)
    monkeypatch.setattr("labrig.evaluation.report.table_csv", lambda table: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        Report("Second").add_table("t", "T", ["a"], [[1.0]]).write(out)
    assert not (out / "index.html").exists()
    assert not [p for p in out.rglob("*.tmp")]


def test_builder_rejects_bad_keys_and_rows() -> None:
    report = Report("r").add_text("same", "x").section("Same", key="same").add_table("same", "T", ["a"], [[1]])
    with pytest.raises(ValueError, match="section key 'same' is already used"):
        report.section("Same")
    with pytest.raises(ValueError, match="table key 'same' is already used"):
        report.add_table("same", "T", ["a"], [[1]])
    with pytest.raises(ValueError, match="letters, digits"):
        report.add_text("../escape", "x")
    with pytest.raises(ValueError, match="2 cells for 1 columns"):
        report.add_table("t", "T", ["a"], [[1, 2]])
    with pytest.raises(ValueError, match="no column: \\['b'\\]"):
        report.add_table("w", "W", ["a"], [{"a": 1, "b": 2}])
    with pytest.raises(ValueError, match="no column named"):
        report.add_table("u", "U", ["a"], [[1]], units={"b": "N"})
    with pytest.raises(TypeError):
        report.add_table("v", "V", ["a"], [[object()]])


def test_links_other_than_web_and_relative_are_left_as_text(tmp_path: Path) -> None:
    report = Report("r").add_text("t", "[click](javascript:alert(1)) and [ok](https://example.org)")
    page = report.write(tmp_path).read_text(encoding="utf-8")
    assert 'href="javascript' not in page and 'href="https://example.org"' in page


def test_cell_formatting() -> None:
    assert format_cell(None) == "\u2013"
    assert format_cell(MeanStd(0.091, 0.081)) == "0.091 ± 0.081"
    assert format_cell(MeanStd(12.3456, 1.2)) == "12.3 ± 1.2"
    assert format_cell(3) == "3"
    assert format_cell(0.5, 2) == "0.50"
    assert format_cell(1234567.0) == "1.23e+06"
    assert str(MeanStd.of([1.0, 3.0, np.nan])) == "2.0 ± 1.0"
    assert format_cell(MeanStd(0.14, float("nan"))) == "0.140"
    assert MeanStd.of([np.nan]).n == 0
    assert to_jsonable({"a": np.float64(np.inf), "b": (np.int32(2), Path("x"))}) == {"a": None, "b": [2, "x"]}


def test_print_summary_renders_tables(tmp_path: Path) -> None:
    image = tmp_path / "runtime.png"
    small_figure().savefig(image)
    report = sample_report(image)
    console = Console(record=True, width=120, color_system=None)
    print_summary(report, console)
    text = console.export_text()
    assert "Force (N)" in text and "0.14 ± 0.12" in text and "Lost tracks per sequence" in text
    assert "2 figures" in text


@pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed")
def test_chromium_renders_the_page(written: Path, tmp_path: Path) -> None:
    from PIL import Image

    shot = tmp_path / "page.png"
    subprocess.run(
        [
            "chromium", "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--no-first-run", f"--user-data-dir={tmp_path / 'profile'}", "--window-size=1100,1400",
            f"--screenshot={shot}", (written / "index.html").as_uri(),
        ],
        check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    pixels = np.asarray(Image.open(shot).convert("L"), dtype=float)
    assert pixels.std() > 10, "the screenshot is blank"


# -- charts ---------------------------------------------------------------------------------------


def test_pareto_front_and_knee_on_a_clear_elbow() -> None:
    latency = [1.0, 2.0, 3.0, 6.0, 10.0, 4.0]
    error = [1.0, 0.25, 0.2, 0.15, 0.1, 0.9]
    assert charts.pareto_front(latency, error).tolist() == [0, 1, 2, 3, 4]
    assert charts.knee_index(latency, error) == 1
    assert charts.knee_index([1.0, 2.0, 3.0], [3.0, 2.0, 1.0]) is None
    assert charts.knee_index([1.0, 2.0], [2.0, 1.0]) is None


def test_pareto_labels_one_setting_reached_by_two_knobs_once() -> None:
    points = [("width 4", 11.6, 0.21), ("10 ms (w4)", 11.6, 0.21), ("width 8", 13.7, 0.27)]
    texts = [t.get_text() for t in charts.pareto(points, error_name="depth MAE", error_unit="mm").axes[0].texts]
    assert sorted(texts) == ["width 4 = 10 ms (w4)", "width 8"]


def test_recommend_takes_the_fastest_within_tolerance() -> None:
    points = [("w4", 1.0, 0.40), ("w8", 2.0, 0.103), ("w16", 5.0, 0.100), ("w32", 9.0, 0.099), ("broken", 0.5, float("nan"))]
    assert charts.recommend(points).label == "w8"
    assert charts.recommend(points, tolerance=0.015).label == "w16"
    assert charts.recommend([("a", 2.0, 0.1), ("b", 2.0, 0.09)]).label == "b"
    with pytest.raises(ValueError):
        charts.recommend([("x", float("nan"), 1.0)])


def test_breakdown_point() -> None:
    x = [0.0, 1.0, 2.0, 4.0]
    assert charts.breakdown_point(x, [1.0, 1.2, 1.5, 1.9]) is None
    assert charts.breakdown_point(x, [1.0, 1.5, 3.0, 4.0]) == pytest.approx(1.0 + 0.5 / 1.5)
    assert charts.breakdown_point([4.0, 0.0, 2.0, 1.0], [4.0, 1.0, 3.0, 1.5]) == pytest.approx(1.0 + 0.5 / 1.5)
    assert charts.breakdown_point(x, [1.0, 1.5, 3.0, 4.0], baseline=0.5) == 0.0
    assert charts.breakdown_point(x, [1.0, 1.2, float("nan"), 4.0]) == 2.0
    assert charts.breakdown_point([1.0, 10.0, 100.0], [1.0, 1.0, 3.0], log_x=True) == pytest.approx(10.0**1.5)
    assert charts.breakdown_point(x, [1.0, 1.1, 1.3, 1.4], factor=1.25) == pytest.approx(2.0 - 0.05 / 0.2)
    with pytest.raises(ValueError, match="baseline"):
        charts.breakdown_point(x, [0.0, 1.0, 2.0, 3.0])


def test_a_breakdown_chart_draws_a_method_whose_baseline_failed() -> None:
    """A method with no error at the least stress (its scene failed) is drawn without a breakdown, not refused."""
    figure = charts.breakdown(np.array([1.0, 2.0, 3.0]), {"ok": np.array([1.0, 1.5, 3.0]),
                                                          "failed": np.array([np.nan, 2.0, 2.5])},
                              x_name="x", x_unit="u", error_name="e", error_unit="%")
    labels = [t.get_text() for t in figure.axes[0].get_legend().get_texts()]
    assert any(label.startswith("failed: no baseline") for label in labels)
    assert any(label.startswith("ok: breaks at") for label in labels)


def test_a_breakdown_below_the_reference_is_read_from_it_downwards() -> None:
    x = [1.0, 1.5, 2.5, 3.0, 4.0]
    error = [4.0, 2.5, 1.0, 1.5, 3.0]
    # below 2.5: 2 x 1.0 is reached between 1.5 (2.5) and 2.5 (1.0), at 2.5 - (2 - 1) / (2.5 - 1) = 1.833...
    assert charts.breakdown_point_below(x, error, 2.5) == pytest.approx(2.5 - 1.0 / 1.5)
    assert charts.breakdown_point_below(x, [1.5, 1.2, 1.0, 9.0, 9.0], 2.5) is None  # only above it
    assert charts.breakdown_point_below([1.0, 10.0, 100.0], [3.0, 1.0, 1.0], 100.0, log_x=True) == pytest.approx(
        10.0**0.5)
    figure = charts.breakdown(np.array(x), {"m": np.array(error)}, x_name="x", x_unit="u", error_name="e",
                              error_unit="%", reference=2.5)
    labels = [t.get_text() for t in figure.axes[0].get_legend().get_texts()]
    assert labels[0] == "m: breaks below at 1.83, above at 3.33 u" and "reference 2.5 u" in labels


def test_group_by_range() -> None:
    groups = charts.group_by_range([0.5, 1.0, 2.0, 3.0, -1.0, np.nan], [1, 2, 3, 4, 5, 6], [0.0, 1.0, 2.0])
    assert [g.tolist() for g in groups] == [[1.0], [2.0, 3.0]]


def png_ok(path: Path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5000


def test_charts_write_pngs(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    force = {"x": rng.uniform(0, 4, 400), "y": rng.uniform(0, 4, 400), "z": rng.uniform(0, 20, 400)}
    error = {k: np.abs(rng.normal(0, 0.1 + 0.05 * v)) for k, v in force.items()}
    bins = {"x": [0, 1, 2, 3, 4], "y": [0, 1, 2, 3, 4], "z": [0, 5, 10, 15, 20]}
    labels = {"value_name": "ground-truth |F|", "value_unit": "N", "error_name": "absolute error", "error_unit": "N"}
    charts.error_by_range(force, error, bins, **labels, out=tmp_path / "box.png")
    depth = rng.uniform(0, 2, 300)
    charts.error_by_range(
        depth, rng.normal(0, 0.1, 300), [0, 0.5, 1, 1.5, 2, 2.5], value_name="ground-truth depth", value_unit="mm",
        error_name="depth error", error_unit="mm", kind="violin", out=tmp_path / "violin.png",
    )  # fmt: skip
    points = [("w4", 1.0, 0.4), ("w8", 2.0, 0.2), ("w16", 4.0, 0.15), ("w32", 9.0, 0.14), ("slow", 5.0, 0.3)]
    charts.pareto(points, error_name="force MAE", error_unit="N", out=tmp_path / "pareto.png")
    noise = [0.0, 1.0, 2.0, 4.0]
    charts.breakdown(
        noise, {"paper tracker": [0.3, 0.35, 0.5, 0.9], "Evetac baseline": [0.4, 0.9, np.nan, np.nan]},
        x_name="event noise rate", x_unit="Hz/px", error_name="tracking error", error_unit="px", out=tmp_path / "breakdown.png",
    )  # fmt: skip
    t = np.linspace(0.0, 3.0, 300)
    measured = np.c_[np.sin(t), np.cos(t), 5 * t]
    t_pred = t[::10]
    charts.time_series(
        t, measured, measured[::10] + 0.1, t_predicted_s=t_pred, phases=[("Normal Down", 0.2, 1.0)], out=tmp_path / "ts.png"
    )
    charts.runtime_bars({"SAE": rng.normal(0.8, 0.1, 50), "tracking": 4.6, "forces": [9.0, 12.0]}, out=tmp_path / "runtime.png")
    for name in ("box", "violin", "pareto", "breakdown", "ts", "runtime"):
        assert png_ok(tmp_path / f"{name}.png"), name


def test_chart_axes_have_units() -> None:
    fig = charts.time_series([0.0, 1.0], [[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]], [[1.0, 2.0, 3.0], [1.5, 2.0, 3.0]])
    labels = [ax.get_ylabel() for ax in fig.axes] + [fig.axes[-1].get_xlabel()]
    assert labels == ["Fx (N)", "Fy (N)", "Fz (N)", "time (s)"]
    assert "MAE 0.25 N" in [t.get_text() for t in fig.axes[0].texts]
    fig = charts.pareto([("a", 1.0, 1.0)], error_name="depth MAE", error_unit="mm", budget_ms=None)
    assert (fig.axes[0].get_xlabel(), fig.axes[0].get_ylabel()) == ("latency per window (ms)", "depth MAE (mm)")


def test_the_control_section_shows_each_held_run_and_charts_the_first(tmp_path: Path) -> None:
    from types import SimpleNamespace

    from labrig.evaluation.control import ControlRun
    from labrig.evaluation.report_sections import _control_section

    t = np.linspace(-0.5, 3.0, 3501)
    fz = np.clip(t, 0.0, 0.6) / 0.6 * 5.0
    target = np.where(t >= 0.0, 5.0, np.nan)
    run = ControlRun("held.h5", 5.0, "ft", 0.48, 1.2, 0.7, 0.03, float("nan"), 100.0, 1_000_000,
                     (("approach", -0.5, 0.0), ("normal_down", 0.0, 1.0), ("wait", 1.0, 3.0)), t, fz, target,
                     reading_scatter_n=0.02)
    report = Report("control")
    report.section("Forces")
    _control_section(report, SimpleNamespace(control=[run], forces=[]))  # type: ignore[arg-type]
    out = tmp_path / "report"
    report.write(out)
    assert check_report(out) == []
    results = json.loads((out / "results.json").read_text(encoding="utf-8"))
    row = results["tables"]["control"]["rows"][0]
    assert row["recording"] == "held.h5" and row["overshoot_pct"] == 1.2 and row["hold_rms_estimate_n"] is None
    assert row["hold_rms_f_t_n"] == 0.03 and row["loop_rate_hz"] == 100.0 and row["reading_scatter_n"] == 0.02
    assert (out / "figures" / "control_series.png").stat().st_size > 0
