"""``labrig evaluate --stress``: push each method along each stress axis on the virtual rig until it breaks.

Every (axis, value) of :data:`labrig.evaluation.stress_axes.AXES` is a short probing run on
the virtual rig with one knob pushed; the methods are measured on it against the sim's truth:

* tracking: the bundled tracker ("paper", 3x patch), the tracker as published
  ("paper-published", 1x), the circle-fit baseline ("circle-fit", 1x) and Evetac's published
  tracker ("evetac", its fixed ring band), each refined and at its best patch in Table I on
  the virtual rig: p95 true error (px) and tracks lost by the
  truth (ever more than 15 px off), :func:`labrig.evaluation.tracking.track_recording`;
* forces: the pipeline with the sim's true depth ("forces-truth", so the stress falls on
  tracking and the inverse FEM), the same with the paper's linear gel instead of the
  calibrated stiffening ("forces-linear") and, given a network, with it ("forces-model"): the mean
  norm of the error against the F/T sensor over the probing phases, as a percentage of the
  mean measured force (N in the results too), :func:`labrig.evaluation.forces.evaluate_forces`;
* depth (the imperfect sensor's axes, given a network): the network's mean error over the
  contact cells ("depth-model", mm), :func:`labrig.evaluation.depth.evaluate_depth`.

On a scene whose camera's contrast thresholds differ from the rig's, the lab recalibrates them
(:func:`labrig.evaluation.stress_calibration.calibrate_event_thresholds`): "forces-model" runs on
that calibration, and "forces-model-uncalibrated" on the rig's own (the thresholds of the reference
camera), so each such axis shows what the calibration buys.

On a scene whose gel is printed imperfectly (placement errors, missing markers) the methods
do not see the sim's markers: the scene is calibrated first, as a lab would
(:func:`labrig.evaluation.stress_calibration.calibrate_printed_markers`), and every method
runs on that calibration; the scene's facts score it (missing markers found, rest error).

A method breaks where its error reaches twice the error at the least-stressed value
(:func:`labrig.evaluation.charts.breakdown_point`) or, for trackers, where more tracks are
lost than there; None: it did not break within the grid.

One task per distinct scene (:func:`measure_scene`, through the cached executor): the
default probe, shared by the baselines of most axes and by every window length, is
simulated once and measured with every window and method asked of it.
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from matplotlib.lines import Line2D

from labrig.config import DEFAULT_CALIBRATION_DIR, DEFAULT_RIG
from labrig.dataset import sidecar_path
from labrig.evaluation import charts
from labrig.evaluation.depth import DepthTask, evaluate_depth
from labrig.evaluation.forces import ForceResult, ForceTask, evaluate_forces
from labrig.evaluation.report import Report
from labrig.evaluation.stress_axes import AXES, StressAxis
from labrig.evaluation.stress_calibration import calibrate_event_response, calibrate_printed_markers
from labrig.evaluation.stress_scene import SceneFacts, StressScene, record_scene, stressed_rig
from labrig.evaluation.tracking import TrackingTask, track_recording
from labrig.executor import Run
from labrig.sim.truth_config import sim_config

#: Tracker -> patch scale (marker diameters), refined: each tracker's best setting in Table I on the virtual rig.
TRACKERS = {"paper": 3.0, "paper-published": 1.0, "circle-fit": 1.0, "evetac": 1.0}  # evetac: scale unused
FORCES_TRUTH, FORCES_LINEAR, FORCES_MODEL = "forces-truth", "forces-linear", "forces-model"
FORCES_MODEL_UNCALIBRATED = "forces-model-uncalibrated"
DEPTH_MODEL = "depth-model"
FACTOR = 2.0


@dataclass(frozen=True)
class StressTask:
    """One scene (``StressScene`` fields as a dict) and what to measure on it: every window x method."""

    scene: dict[str, Any]
    windows_ms: tuple[float, ...] = (10.0,)
    trackers: tuple[str, ...] = tuple(TRACKERS)
    forces: bool = True
    model: str | None = None  # a depth network (.onnx) for "forces-model" and "depth-model"
    calibration_dir: str | None = DEFAULT_CALIBRATION_DIR
    depth: bool = False  # measure the network's depth error too (with ``model``)


@dataclass(frozen=True)
class TrackerStress:
    """One tracker on a stressed scene at one window length (see :class:`labrig.evaluation.tracking.TrackingResult`)."""

    error_p95_px: float | None
    error_median_px: float | None
    lost_by_truth: int | None
    lost_tracks: int


@dataclass(frozen=True)
class ForceStress:
    """One force method on a stressed scene at one window length, over its probing windows (:func:`force_errors`)."""

    error_pct: float  # mean |error| (norm) as a percentage of the mean |measured force|
    error_n: float  # mean |error| (norm), N
    error_z_n: float  # mean |error| along z, N
    measured_mean_n: float  # mean |measured force|, N
    windows: int


@dataclass(frozen=True)
class DepthStress:
    """The network's depth error on a stressed scene at one window length (:func:`labrig.evaluation.depth.evaluate_depth`)."""

    contact_mm: float  # mean over the windows in contact of the error over the contact cells
    total_mm: float  # mean over every window of the error over all cells
    windows: int


@dataclass(frozen=True)
class SceneMeasurement:
    """What :func:`measure_scene` found: the scene's facts and each method's errors, by window key
    (:func:`window_key` of the window in ms) and then by tracker, force or depth method."""

    scene: SceneFacts
    tracking: dict[str, dict[str, TrackerStress]]
    forces: dict[str, dict[str, ForceStress]]
    depth: dict[str, dict[str, DepthStress]] = field(default_factory=dict)


def measure_scene(task: StressTask | dict[str, Any]) -> SceneMeasurement:
    """Record the task's scene in a temporary folder and measure every window and method on it
    (on an imperfectly printed gel, after calibrating it: module docstring)."""
    task = task if isinstance(task, StressTask) else StressTask(**task)
    scene = StressScene(**task.scene)
    by_tracker: dict[str, dict[str, TrackerStress]] = {}
    by_method: dict[str, dict[str, ForceStress]] = {}
    by_depth: dict[str, dict[str, DepthStress]] = {}
    calibration_dir = task.calibration_dir
    with tempfile.TemporaryDirectory(prefix="labrig-stress-") as folder:
        recording = str(Path(folder) / "stress.h5")
        facts = record_scene(scene, recording)
        rig = stressed_rig(scene)
        if not sim_config(rig).markers.ideal:
            calibrated = calibrate_printed_markers(rig, task.calibration_dir, Path(folder) / "calibration", seed=scene.seed)
            calibration_dir = calibrated.directory
            found = set(calibrated.missing_found)
            facts = replace(facts, markers_missing_found=len(found & set(calibrated.missing_true)),
                            markers_missing_false=len(found - set(calibrated.missing_true)),
                            rest_error_rms_px=calibrated.rest_error_rms_px)
        uncalibrated_dir = calibration_dir
        if scene.changes_event_response:
            calibration_dir = calibrate_event_response(scene, calibration_dir, Path(folder) / "calibration")
        for window_ms in task.windows_ms:
            window_us = round(window_ms * 1000)
            tracking = {}
            for tracker in task.trackers:
                tracked = track_recording(TrackingTask(recording, tracker=tracker, patch_scale=TRACKERS[tracker],
                                                       refine=True, window_us=window_us, calibration_dir=calibration_dir))
                tracking[tracker] = TrackerStress(tracked.error_p95_px, tracked.error_median_px, tracked.lost_by_truth,
                                                  tracked.lost_tracks)
            by_tracker[window_key(window_ms)] = tracking
            depths = ([("truth", FORCES_TRUTH, None, calibration_dir), ("truth", FORCES_LINEAR, 0.0, calibration_dir)]
                      if task.forces else [])
            if task.forces and task.model:
                depths.append((task.model, FORCES_MODEL, None, calibration_dir))
                if scene.changes_event_response:
                    depths.append((task.model, FORCES_MODEL_UNCALIBRATED, None, uncalibrated_dir))
            forces = {}
            for depth, method, stiffening, folder_used in depths:
                pipeline = evaluate_forces(ForceTask(recording, depth, window_events=None, window_us=window_us,
                                                     calibration_dir=folder_used, stiffening=stiffening,
                                                     sidecar=str(sidecar_path(recording))))
                forces[method] = force_errors(pipeline)
            by_method[window_key(window_ms)] = forces
            if task.depth and task.model:
                errors = evaluate_depth(DepthTask(recording, task.model, window_events=None, window_us=window_us,
                                                  sidecar=str(sidecar_path(recording))))
                contact = errors.contact_mm[np.isfinite(errors.contact_mm)]
                by_depth[window_key(window_ms)] = {DEPTH_MODEL: DepthStress(
                    float(contact.mean()) if contact.size else float("nan"), float(np.mean(errors.total_mm)),
                    len(errors.total_mm))}
    return SceneMeasurement(facts, by_tracker, by_method, by_depth)


measure_scene.cache_version = "18"  # type: ignore[attr-defined]  # 18: the release settles whatever the step length; 17: the light's slope response calibrated with the thresholds; 16: the marker diameter through the run's camera; 15: the camera's response and light knobs, the events calibration; 14: the contrast thresholds weigh the brightness events; 13: the true depth between solves; 12: neighbours' moves; 11: lopsided gates follow neighbours, lag correction; 10: the paper tracker's polarity guard


def window_key(window_ms: float) -> str:
    return f"{float(window_ms):g}ms"


def force_errors(result: ForceResult) -> ForceStress:
    """Error of an :func:`evaluate_forces` result over its probing windows: mean |error| (N, norm and z) and
    the same as a percentage of the mean |measured force|."""
    probing = np.asarray(result.probing, bool)
    error = (result.predicted_n - result.measured_n)[probing]
    measured = np.linalg.norm(result.measured_n[probing], axis=1)
    if not len(error):
        return ForceStress(float("nan"), float("nan"), float("nan"), float("nan"), 0)
    norm = np.linalg.norm(error, axis=1)
    return ForceStress(error_pct=float(100 * norm.mean() / max(measured.mean(), 1e-9)), error_n=float(norm.mean()),
                       error_z_n=float(np.abs(error[:, 2]).mean()), measured_mean_n=float(measured.mean()),
                       windows=len(error))


# -- the suite ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Breakdown:
    """Where one method broke on one axis: ``value`` (axis unit; None: not within the grid) and why; on an axis
    pushed both ways from its reference, ``value`` is above the reference and ``below`` under it."""

    axis: str
    metric: str
    method: str
    value: float | None
    cause: str  # "error x2", "tracks lost", "" when it did not break
    error_doubles_at: float | None
    tracks_lost_at: float | None
    below: float | None = None
    below_cause: str = ""


@dataclass(frozen=True)
class StressCurve:
    """One method's error along one axis: ``error`` per value (px for tracking, % for forces), ``lost`` (trackers)."""

    axis: str
    metric: str
    method: str
    values: list[float]
    error: list[float]
    lost: list[int] | None = None
    error_n: list[float] | None = None


@dataclass(frozen=True)
class StressResult:
    """The stress suite: each method's curve and breakdown per axis, and each axis' scenes (None: the scene failed)."""

    grid: str
    axes: list[StressAxis]
    curves: list[StressCurve]
    breakdowns: list[Breakdown]
    scenes: dict[str, list[SceneFacts | None]] = field(default_factory=dict)  # axis -> facts per value


def plan(axes: Sequence[StressAxis], grid: str, base: StressScene) -> list[tuple[StressScene, list[float],
                                                                                    list[tuple[StressAxis, float]]]]:
    """Distinct scenes in first-use order: (scene, its windows, the (axis, value) points that use it)."""
    scenes: dict[StressScene, tuple[list[float], list[tuple[StressAxis, float]]]] = {}
    for axis in axes:
        for value in axis.values(grid):
            windows, points = scenes.setdefault(axis.scene(value, base), ([], []))
            if axis.window_ms(value) not in windows:
                windows.append(axis.window_ms(value))
            points.append((axis, value))
    return [(scene, windows, points) for scene, (windows, points) in scenes.items()]


def run_stress(run: Run, *, grid: str = "full", axes: Sequence[StressAxis] | None = None, model: str | None = None,
               calibration_dir: str | None = DEFAULT_CALIBRATION_DIR, base: StressScene | None = None) -> StressResult:
    """Every axis over its grid; ``run(kind, fn, tasks) -> results`` runs the tasks (parallel, cached).

    ``axes``: default :data:`AXES`; ``base``: the least-stressed scene (default: the default
    probe on ``calibration_dir``'s ``rig.toml``, else the bundled rig); ``model``: a depth
    network for "forces-model".
    """
    axes = list(AXES if axes is None else axes)
    base = base or StressScene(rig=rig_file(calibration_dir))
    rig = stressed_rig(base)
    if base.shot_noise_rate_hz is None:  # spelled out, so the noise axis' baseline is the default scene
        base = StressScene(**{**asdict(base), "shot_noise_rate_hz": sim_config(rig).events.shot_noise_rate_hz})
    scenes = plan(axes, grid, base)
    tasks = []
    for scene, windows, points in scenes:
        metrics = {metric for axis, _ in points for metric in axis.metrics}
        tasks.append(StressTask(asdict(scene), tuple(windows), trackers=tuple(TRACKERS) if "tracking" in metrics else (),
                                forces="forces" in metrics, model=model, calibration_dir=calibration_dir,
                                depth="depth" in metrics and model is not None))
    results = run("stress", measure_scene, tasks)
    measured: dict[tuple[str, float], tuple[SceneMeasurement | None, str]] = {}
    for (_, _, points), result in zip(scenes, results):
        for axis, value in points:
            measured[(axis.key, value)] = (result, window_key(axis.window_ms(value)))
    curves, breakdowns, facts = [], [], {}
    for axis in axes:
        values = list(axis.values(grid))
        facts[axis.key] = [_scene_facts(measured[(axis.key, v)][0]) for v in values]
        for metric in axis.metrics:
            for method in _methods(metric, model, axis):
                curve = _curve(axis, metric, method, values, measured)
                curves.append(curve)
                breakdowns.append(breakdown_of(curve, log_x=axis.log_x, reference=axis.reference))
    return StressResult(grid, list(axes), curves, breakdowns, facts)


def rig_file(calibration_dir: str | None) -> str:
    """The rig the stress scenes run on: ``calibration_dir/rig.toml`` if there is one, else the bundled rig."""
    candidate = Path(calibration_dir) / "rig.toml" if calibration_dir else None
    return str(candidate.resolve()) if candidate is not None and candidate.exists() else str(DEFAULT_RIG)


def _methods(metric: str, model: str | None, axis: StressAxis) -> list[str]:
    if metric == "tracking":
        return list(TRACKERS)
    if metric == "depth":
        return [DEPTH_MODEL] if model else []
    with_model = [FORCES_MODEL] + ([FORCES_MODEL_UNCALIBRATED] if axis.event_calibration else []) if model else []
    return [FORCES_TRUTH, FORCES_LINEAR, *with_model]


def _scene_facts(measurement: SceneMeasurement | None) -> SceneFacts | None:
    return measurement.scene if measurement is not None else None


def _curve(axis: StressAxis, metric: str, method: str, values: list[float],
           measured: dict[tuple[str, float], tuple[SceneMeasurement | None, str]]) -> StressCurve:
    error: list[float] = []
    lost: list[int] = []
    newtons: list[float] = []
    for value in values:
        result, window = measured[(axis.key, value)]
        if metric == "tracking":
            tracker = result.tracking.get(window, {}).get(method) if result is not None else None
            error.append(float(tracker.error_p95_px) if tracker and tracker.error_p95_px is not None else float("nan"))
            lost.append(int(tracker.lost_by_truth) if tracker and tracker.lost_by_truth is not None else -1)
        elif metric == "depth":
            depth = result.depth.get(window, {}).get(method) if result is not None else None
            error.append(depth.contact_mm if depth else float("nan"))
        else:
            by_method = result.forces.get(window, {}) if result is not None else {}
            forces = by_method.get(method)
            if forces is None and method == FORCES_MODEL_UNCALIBRATED:  # the rig's own thresholds: nothing to recalibrate
                forces = by_method.get(FORCES_MODEL)
            error.append(forces.error_pct if forces else float("nan"))
            newtons.append(forces.error_n if forces else float("nan"))
    return StressCurve(axis.key, metric, method, values, error, lost if metric == "tracking" else None,
                       newtons if metric == "forces" else None)


def breakdown_of(curve: StressCurve, factor: float = FACTOR, log_x: bool = False,
                 reference: float | None = None) -> Breakdown:
    """The first value, going out from the least-stressed one, where the error reaches ``factor`` x that value's
    or more tracks are lost than there. The least-stressed value is the curve's first, or ``reference`` (one of
    its values) on an axis pushed both ways: then ``value`` is read above it and ``below`` under it."""
    x, error = np.asarray(curve.values, float), np.asarray(curve.error, float)
    start = 0 if reference is None else int(np.argmin(np.abs(x - reference)))
    lost = None if curve.lost is None else np.asarray(curve.lost)
    log_x = log_x and bool(np.all(x > 0))

    def first_lost(side: npt.NDArray[np.int64]) -> float | None:
        if lost is None:
            return None
        more = side[lost[side] > lost[start]]
        return float(x[more[0]]) if more.size else None

    def earliest(doubles: float | None, lost_at: float | None, outward: int) -> tuple[float | None, str]:
        found = [(v, cause) for v, cause in ((doubles, "error x2"), (lost_at, "tracks lost")) if v is not None]
        return min(found, key=lambda item: outward * item[0]) if found else (None, "")

    low, doubles = charts.breakdown_points(x, error, reference, factor, None, log_x)
    lost_at = first_lost(np.arange(start, len(x)))
    value, cause = earliest(doubles, lost_at, 1)
    below, below_cause = None, ""
    if start > 0:
        below, below_cause = earliest(low, first_lost(np.arange(start, -1, -1)), -1)
    return Breakdown(curve.axis, curve.metric, curve.method, value, cause, doubles, lost_at, below, below_cause)


# -- report and summary ----------------------------------------------------------------------------


METRIC_LABELS = {"tracking": ("p95 tracking error", "px"), "forces": ("force error", "% of the force"),
                 "depth": ("depth error in contact", "mm")}


def add_stress_to_report(report: Report, result: StressResult) -> None:
    """Section "Stability where methods fail": one chart per axis and metric, the breakdown table, the scenes."""
    report.section("Stability where methods fail", "stress")
    report.add_text("stress_note", (
        f"Each axis pushes one knob of a short probing run on the virtual rig ({result.grid} grid; the default: a "
        "1 mm sphere press with 0.5 mm of shear at 3 mm/s, 10 ms windows). Tracking: p95 error against the sim's "
        "markers; forces: mean norm of the error against the F/T sensor over the probing phases, as a percentage "
        "of the mean measured force. A method breaks where its error doubles against the least-stressed value "
        "(diamond, dashed line) or, for trackers, where tracks are lost (ever more than 15 px off the truth) that "
        "were not lost there. None: no breakdown within the grid.\n\n"
        + "\n".join(f"- **{a.title}** ({a.x_name}, {a.unit}): {a.what}." for a in result.axes)))
    for axis in result.axes:
        for metric in axis.metrics:
            curves = [c for c in result.curves if c.axis == axis.key and c.metric == metric]
            if not curves:  # depth without a network
                continue
            name, unit = METRIC_LABELS[metric]
            lost = {c.method: c.lost for c in curves if c.lost}
            caption = "Tracks lost by the truth per value: " + "; ".join(
                f"{m} {', '.join(str(n) for n in v)}" for m, v in lost.items()) if lost else ""
            figure = charts.breakdown(np.asarray(curves[0].values), {c.method: np.asarray(c.error) for c in curves},
                                      x_name=axis.x_name, x_unit=axis.unit, error_name=name, error_unit=unit,
                                      factor=FACTOR, log_x=axis.log_x, reference=axis.reference)
            mark_breakdowns(figure, curves, [b for c in curves for b in result.breakdowns
                                             if (b.axis, b.metric, b.method) == (c.axis, c.metric, c.method)], axis.unit,
                            reference=axis.reference)
            report.add_figure(f"stress_{axis.key}_{metric}", f"{axis.title}: {name}", figure, caption=caption)
    titles = {a.key: a for a in result.axes}
    report.add_table("stress_breakdown", "Breakdown points", ["axis", "metric", "method", "breaks below", "breaks at",
                                                              "unit", "cause", "error x2 at", "tracks lost at"],
                     [[titles[b.axis].title, b.metric, b.method, b.below, b.value, titles[b.axis].unit,
                       "; ".join(c for c in (b.below_cause, b.cause) if c) or "did not break",
                       b.error_doubles_at, b.tracks_lost_at] for b in result.breakdowns],
                     caption="The first value (in the axis' unit) where the method's error doubles or it loses tracks, "
                             "going out from the least-stressed value: the first of the grid, or the reference sensor's on "
                             "an axis pushed both ways (breaks below: under it); a dash: not within the grid.")
    rows = []
    for axis in result.axes:
        for value, facts in zip(axis.values(result.grid), result.scenes.get(axis.key, [])):
            known = [facts.duration_s, facts.events, facts.peak_force_n, facts.slip_ratio_max, facts.clock_skew_max_ms] \
                if facts is not None else [None] * 5
            rows.append([axis.title, value, axis.unit, *known])
    report.add_table("stress_scenes", "Stressed scenes", ["axis", "value", "unit", "duration", "events", "peak force",
                                                           "slip ratio", "clock skew"], rows,
                     units={"duration": "s", "peak force": "N", "clock skew": "ms"},
                     caption="From the sim's truth: slip ratio = largest |tangential| / (friction x normal) force "
                             "from the shear to the unloading (1: gross slip); clock skew: the largest event time error of an "
                             "unsynced camera clock.")
    report.add_json("stress", {"grid": result.grid, "breakdown": stress_summary(result),
                               "curves": [asdict(c) for c in result.curves]})


def mark_breakdowns(figure: Any, curves: Sequence[StressCurve], breakdowns: Sequence[Breakdown], unit: str,
                    reference: float | None = None) -> None:
    """Finish a :func:`charts.breakdown` figure: a triangle where each tracker first loses tracks (its colour)
    and legend entries that give each method's breakdown, by doubling or by lost tracks (both sides of
    ``reference`` on an axis pushed both ways)."""
    ax = figure.axes[0]
    for i, (curve, b) in enumerate(zip(curves, breakdowns)):
        if b.tracks_lost_at is not None:
            k = curve.values.index(b.tracks_lost_at)
            ax.plot([b.tracks_lost_at], [curve.error[k]], marker="v", ms=10, ls="", zorder=5,
                    color=charts.CYCLE[i % len(charts.CYCLE)], markeredgecolor="black")
    handles, labels = ax.get_legend_handles_labels()
    labels = [_breakdown_label(c, b, unit, reference) for c, b in zip(curves, breakdowns)] + labels[len(curves):]
    if any(not np.all(np.isfinite(c.error)) for c in curves):
        handles.append(Line2D([], [], ls="", marker="x", color="#555555"))
        labels.append("no finite error (top edge)")
    if any(b.tracks_lost_at is not None for b in breakdowns):
        handles.append(Line2D([], [], ls="", marker="v", color="#555555", markeredgecolor="black"))
        labels.append("tracks lost (more than at the least stress)")
    ax.legend(handles, labels, fontsize=8, title=f"dotted: {FACTOR:g} x baseline error", title_fontsize=7)


def _breakdown_label(curve: StressCurve, b: Breakdown, unit: str, reference: float | None) -> str:
    """One method's legend entry: where it broke (and why), or the span it held over."""
    if reference is None or reference <= min(curve.values):
        return (f"{b.method}: breaks at {b.value:.3g} {unit} ({b.cause})" if b.value is not None
                else f"{b.method}: no breakdown up to {max(curve.values):.3g} {unit}")
    sides = [f"{side} {v:.3g} ({cause})" for side, v, cause in (("below at", b.below, b.below_cause),
                                                                  ("above at", b.value, b.cause)) if v is not None]
    return (f"{b.method}: breaks {', '.join(sides)} {unit}" if sides
            else f"{b.method}: no breakdown within {min(curve.values):.3g}-{max(curve.values):.3g} {unit}")


def stress_summary(result: StressResult) -> dict[str, dict[str, float | None]]:
    """``{axis_unit: {method: breakdown value or None}}`` (e.g. ``event_noise_hz``), for ``--json``; an axis pushed
    both ways from its reference adds ``{axis_unit}_below`` (the breakdown under the reference)."""
    axes = {a.key: a for a in result.axes}
    out: dict[str, dict[str, float | None]] = {}
    for b in result.breakdowns:
        axis = axes[b.axis]
        out.setdefault(axis.json_key, {})[b.method] = b.value
        if axis.two_sided:
            out.setdefault(f"{axis.json_key}_below", {})[b.method] = b.below
    return out
