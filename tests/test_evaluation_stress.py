"""`labrig evaluate --stress` on the reduced grid: the expected breakdowns (force beyond the linear range, event
noise), a linear-gel control, the report section, the cache, the command line."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from labrig.cli import app
from labrig.config import DEFAULT_CALIBRATION_DIR, RigConfig
from labrig.errors import LabrigError
from labrig.evaluation import stress
from labrig.evaluation.report import Report, check_report
from labrig.evaluation.stress import StressCurve, StressResult, breakdown_of, plan, run_stress, stress_summary
from labrig.evaluation.stress_axes import AXES, axis_named
from labrig.evaluation.stress_scene import StressScene
from labrig.executor import TaskResults, run_tasks
from labrig.indenters import Indenter

TESTED_AXES = ("force_range", "event_noise")


class Runner:
    """``run(kind, fn, tasks)`` for :func:`run_stress`: in this process, cached in ``cache``; keeps each run's stats."""

    def __init__(self, cache: Path) -> None:
        self.cache = cache
        self.runs: list[TaskResults] = []

    def __call__(self, kind: str, fn: Any, tasks: list[Any]) -> list[Any]:
        results = run_tasks(fn, tasks, workers=1, cache_dir=self.cache)
        self.runs.append(results)
        return list(results)


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("stress-cache")


@pytest.fixture(scope="module")
def suite(cache: Path) -> StressResult:
    """Force range and event noise on the reduced grid: five scenes (the default probe is shared)."""
    return run_stress(Runner(cache), grid="reduced", axes=[axis_named(k) for k in TESTED_AXES])


def curve(result: StressResult, axis: str, method: str) -> StressCurve:
    return next(c for c in result.curves if c.axis == axis and c.method == method)


def breaks(result: StressResult, axis: str, method: str) -> float | None:
    return next(b.value for b in result.breakdowns if b.axis == axis and b.method == method)


def test_forces_beyond_the_linear_range_break_the_linear_inverse_fem(suite: StressResult) -> None:
    forces = curve(suite, "force_range", "forces-linear")
    assert forces.values == [0.5, 1.0, 2.25]
    assert forces.error[-1] >= 2 * forces.error[0]  # % of the force: the stiffening gel outgrows the linear model
    assert 1.0 < breaks(suite, "force_range", "forces-linear") <= 2.25  # mm, beyond the gel calibration's 1.0 mm
    calibrated = curve(suite, "force_range", "forces-truth")  # the fitted stiffening extrapolates
    assert calibrated.error[-1] < forces.error[-1] / 2 and breaks(suite, "force_range", "forces-truth") is None
    peak = [facts.peak_normal_n for facts in suite.scenes["force_range"]]
    assert peak[0] < 2 < 10 < peak[-1]  # N: the deepest press is far beyond the calibration's 6 N


def test_a_linear_gel_does_not_break_along_the_force_range(cache: Path) -> None:
    """The control: with the sim's stiffening off, the relative force error does not grow with depth."""
    axis = replace(axis_named("force_range"), reduced=(0.5, 2.25))
    result = run_stress(Runner(cache), grid="reduced", axes=[axis], base=StressScene(stiffening=0.0))
    forces = curve(result, "force_range", "forces-linear")
    assert forces.error[-1] < forces.error[0] and breaks(result, "force_range", "forces-linear") is None


def test_event_noise_breaks_the_circle_fit_but_not_the_gated_tracker(suite: StressResult) -> None:
    assert curve(suite, "event_noise", "paper").values == [0.05, 2.0, 10.0]
    c = curve(suite, "event_noise", "circle-fit")
    point = breaks(suite, "event_noise", "circle-fit")
    assert point is not None and 0.05 < point <= 10.0  # Hz per pixel
    assert max(c.error[1:]) >= 2 * c.error[0]
    paper = curve(suite, "event_noise", "paper")  # its gates subtract the background noise
    assert breaks(suite, "event_noise", "paper") is None and max(paper.lost) == 0
    assert max(paper.error) < 1.6 * paper.error[0]
    scenes = suite.scenes["event_noise"]
    assert scenes[-1].events > 10 * scenes[0].events  # the noise is really there
    assert scenes[0] == suite.scenes["force_range"][1]  # the default probe, simulated once for both axes


def test_the_report_section_renders_and_checks(suite: StressResult, tmp_path: Path) -> None:
    report = Report("stress")
    stress.add_stress_to_report(report, suite)
    out = tmp_path / "report"
    report.write(out)
    assert check_report(out) == []
    results = json.loads((out / "results.json").read_text())
    assert len(results["tables"]["stress_breakdown"]["rows"]) == len(suite.breakdowns) == 8
    for key in ("stress_force_range_forces", "stress_event_noise_tracking", "stress_event_noise_forces"):
        assert key in results["figures"], key
        assert (out / results["figures"][key]["path"]).stat().st_size > 1000
    assert "Stability where methods fail" in (out / "index.html").read_text()
    summary = stress_summary(suite)
    assert set(summary) == {"force_range_mm", "event_noise_hz"}
    assert summary["force_range_mm"]["forces-truth"] == pytest.approx(breaks(suite, "force_range", "forces-truth"))
    assert set(summary["event_noise_hz"]) == {"paper", "paper-published", "circle-fit", "evetac", "forces-truth", "forces-linear"}


def test_a_rerun_comes_from_the_cache(suite: StressResult, cache: Path) -> None:
    runner = Runner(cache)
    again = run_stress(runner, grid="reduced", axes=[axis_named(k) for k in TESTED_AXES])
    assert runner.runs[-1].hits == 5 and runner.runs[-1].misses == 0
    assert [b.value for b in again.breakdowns] == [b.value for b in suite.breakdowns]


def test_the_default_probe_is_shared_and_every_window_measured_on_it() -> None:
    base = StressScene(shot_noise_rate_hz=0.05)
    scenes = plan(AXES, "reduced", base)
    default = [entry for entry in scenes if entry[0] == base]
    assert len(default) == 1
    _, windows, points = default[0]
    assert sorted(windows) == [10.0, 50.0, 200.0]  # the window axis runs on the default probe
    assert {axis.key for axis, _ in points} >= {"event_noise", "window_length", "force_range", "speed"}
    # the default probe; two more each for force range, speed, noise, contrast and dead region and for the
    # imperfect sensor's four axes (placement error, missing near and far, USB bursts: 0 is the default probe);
    # three for shear (0.25, 1, 3 mm: the default's 0.5 mm is not on the reduced grid) and the clock (unsynced from 0 min on);
    # the camera's response and light: three each for the threshold, slope gain and membrane (their reference values
    # are set, not the rig's), two each for the ON/OFF ratio and the hold (1 and 0.1 s: the default probe)
    assert len(scenes) == 1 + 5 * 2 + 4 * 2 + 2 * 3 + 3 * 3 + 2 * 2


def test_breakdown_by_doubling_or_by_lost_tracks() -> None:
    doubling = StressCurve("a", "tracking", "t", [1.0, 2.0, 3.0], [1.0, 1.5, 2.5], [0, 0, 0])
    b = breakdown_of(doubling)
    assert b.value == pytest.approx(2.5) and b.cause == "error x2" and b.tracks_lost_at is None
    losing = StressCurve("a", "tracking", "t", [1.0, 2.0, 3.0], [1.0, 1.2, 1.3], [1, 1, 4])
    b = breakdown_of(losing)
    assert b.value == 3.0 and b.cause == "tracks lost" and b.error_doubles_at is None
    steady = StressCurve("a", "forces", "f", [1.0, 2.0], [5.0, 6.0])
    assert breakdown_of(steady).value is None and breakdown_of(steady).cause == ""
    failed = StressCurve("a", "forces", "f", [1.0, 2.0], [5.0, float("nan")])
    assert breakdown_of(failed).value == 2.0  # no answer counts as broken


def test_an_axis_pushed_both_ways_breaks_on_each_side_of_its_reference() -> None:
    """Read from the reference sensor outwards: the error there is the baseline, under it ``below``, above it
    ``value``; lost tracks count against the reference's too."""
    curve = StressCurve("a", "forces", "f", [0.15, 0.18, 0.22, 0.30, 0.40], [9.0, 4.0, 2.0, 3.0, 5.0])
    b = breakdown_of(curve, reference=0.22)
    assert b.below == pytest.approx(0.18) and b.below_cause == "error x2"
    assert b.value == pytest.approx(0.30 + 0.10 * (4.0 - 3.0) / 2.0) and b.cause == "error x2"
    assert breakdown_of(curve).value is None  # read from the first value (a poor sensor) it only gets better
    lost = StressCurve("a", "tracking", "t", [1.0, 2.0, 3.0, 4.0], [1.0, 1.0, 1.0, 1.0], [3, 1, 1, 2])
    b = breakdown_of(lost, reference=2.0)
    assert (b.below, b.below_cause, b.value, b.cause) == (1.0, "tracks lost", 4.0, "tracks lost")
    held = breakdown_of(StressCurve("a", "forces", "f", [1.0, 2.5, 4.0], [1.5, 1.0, 1.9]), reference=2.5)
    assert (held.below, held.value, held.below_cause, held.cause) == (None, None, "", "")
    for axis in AXES:
        assert axis.reference is None or (axis.reference in axis.full and axis.reference in axis.reduced)
    assert axis_named("contrast_threshold").two_sided and axis_named("led_slope_gain").two_sided
    with pytest.raises(LabrigError, match="must be on both grids"):
        replace(axis_named("led_slope_gain"), reduced=(1.0, 4.0))


def test_every_axis_turns_a_real_knob() -> None:
    fields = set(StressScene.__dataclass_fields__) | {"window_ms"}
    for axis in AXES:
        assert axis.knob in fields, axis.key
        assert axis.reduced[0] == axis.full[0] and axis.reduced[-1] == axis.full[-1], axis.key
        assert list(axis.full) == sorted(axis.full) and set(axis.reduced) <= set(axis.full), axis.key
        assert axis.scene(axis.full[-1], StressScene()) != StressScene() or axis.knob == "window_ms", axis.key
    assert len({a.json_key for a in AXES}) == len(AXES)


def test_the_command_line_checks_the_grid(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["evaluate", str(tmp_path), "--stress", "--stress-grid", "huge"])
    assert isinstance(result.exception, LabrigError)  # `labrig` prints it, exit 2
    assert "--stress-grid must be full or reduced" in str(result.exception)


def test_stress_curves_hold_numbers(suite: StressResult) -> None:
    for c in suite.curves:
        assert len(c.error) == len(c.values) and np.all(np.isfinite(c.error)), (c.axis, c.method)


@pytest.fixture(scope="module")
def short_probe(tmp_path_factory: pytest.TempPathFactory, rig: RigConfig, sphere: Indenter) -> Path:
    """DATA for `labrig evaluate`: one short shallow press with its sidecar."""
    from labrig.dataset import sidecar_path
    from labrig.groundtruth import generate, write_sidecar
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    out = tmp_path_factory.mktemp("stress-data") / "probe.h5"
    path = probing_path(rig, sphere, depth_mm=0.5, shear_mm=0.2, normal_speed_mm_s=6.0, shear_speed_mm_s=6.0,
                        wait_s=0.05, approach_mm=0.1)
    record_live(out, rig, sphere, path, seed=5, realtime=False)
    write_sidecar(generate(out, rate_hz=100), sidecar_path(out))
    return out


def test_labrig_evaluate_stress_adds_the_section_and_the_summary(
    suite: StressResult, short_probe: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The command line's --stress: the suite (here the fixture's, not run again) in the report and --json."""
    from labrig.pipeline.depthnet import build_unet, export_onnx

    torch.manual_seed(0)
    model = tmp_path / "w2.onnx"
    export_onnx(build_unet(width=2).eval(), model, {"name": "w2", "scale_mm": 2.5, "window_ms": 10.0,
                                                   "loss": {"name": "contact"}, "architecture": {"width": 2}})
    asked: dict[str, Any] = {}

    def fake_run_stress(run: Any, **kwargs: Any) -> StressResult:
        asked.update(kwargs)
        return suite

    monkeypatch.setattr(stress, "run_stress", fake_run_stress)
    out = tmp_path / "report"
    result = CliRunner().invoke(app, ["evaluate", str(short_probe), "--model", str(model), "--window-ms", "20",
                                      "--no-table1", "--stress", "--stress-grid", "reduced", "--workers", "1",
                                      "--cache", str(tmp_path / "cache"), "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    assert asked == {"grid": "reduced", "axes": None, "model": str(model), "calibration_dir": DEFAULT_CALIBRATION_DIR}
    summary = json.loads(result.stdout)
    assert summary["report_problems"] == []
    assert summary["stress_breakdown"]["force_range_mm"]["forces-truth"] == pytest.approx(
        breaks(suite, "force_range", "forces-truth"))
    assert "Stability where methods fail" in (out / "index.html").read_text()


def test_the_command_line_names_the_axes_there_are(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["evaluate", str(tmp_path), "--stress-axes", "contrast_threshold,nope"])
    assert isinstance(result.exception, LabrigError)  # `labrig` prints it, exit 2
    assert "no stress axis 'nope'" in str(result.exception) and "hold" in str(result.exception)


def test_stress_axes_narrows_the_suite_to_the_axes_named(suite: StressResult, short_probe: Path, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    asked: dict[str, Any] = {}

    def fake_run_stress(run: Any, **kwargs: Any) -> StressResult:
        asked.update(kwargs)
        return suite

    from labrig.pipeline.depthnet import build_unet, export_onnx

    torch.manual_seed(0)
    model = tmp_path / "w2.onnx"
    export_onnx(build_unet(width=2).eval(), model, {"name": "w2", "scale_mm": 2.5, "window_ms": 10.0,
                                                   "loss": {"name": "contact"}, "architecture": {"width": 2}})
    monkeypatch.setattr(stress, "run_stress", fake_run_stress)
    result = CliRunner().invoke(app, ["evaluate", str(short_probe), "--model", str(model), "--window-ms", "20",
                                      "--no-table1", "--stress-axes", "hold,contrast_threshold", "--stress-grid",
                                      "reduced", "--workers", "1", "--cache", str(tmp_path / "cache"),
                                      "--out", str(tmp_path / "report"), "--json"])
    assert result.exit_code == 0, result.output
    assert [a.key for a in asked["axes"]] == ["hold", "contrast_threshold"]  # --stress-axes implies --stress


def test_stress_metrics_keep_the_axes_that_measure_them() -> None:
    from labrig.evaluation.evaluate import stress_axes_measured

    assert stress_axes_measured(None, None) is None
    tracking = stress_axes_measured(None, ("tracking",))
    assert tracking and all(a.metrics == ("tracking",) for a in tracking)
    assert {a.key for a in tracking} == {a.key for a in AXES if "tracking" in a.metrics}
    assert [a.metrics for a in stress_axes_measured(["speed", "hold"], ("forces",)) or []] == [("forces",), ("forces",)]
    with pytest.raises(LabrigError, match="no stress axis measures tracking"):
        stress_axes_measured(["hold"], ("tracking",))
