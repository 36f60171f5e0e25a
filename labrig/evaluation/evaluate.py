"""``labrig evaluate``: a campaign's recordings through the pipeline, measured as the paper did and beyond.

:func:`evaluate_campaign` plans every per-recording task (tracking for Table I, depth for
Table II and the per-range analysis, forces for Table III, label errors on the virtual
rig), runs them through :func:`labrig.executor.run_tasks` (parallel, cached) and
keeps their results (frozen dataclasses) in an :class:`Evaluation` with the headline numbers;
:mod:`labrig.evaluation.report_sections` turns that into the report.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from labrig.config import DEFAULT_CALIBRATION_DIR
from labrig.dataset import (
    ALL_SPLITS,
    SPLITS,
    DatasetRecording,
    open_data,
    require_groundtruth,
    require_present,
    sidecar_path,
)
from labrig.errors import LabrigError
from labrig.evaluation import stress as stress_suite
from labrig.evaluation import tables
from labrig.evaluation.control import ControlRun, control_runs
from labrig.evaluation.depth import DepthResult, DepthTask, evaluate_depth
from labrig.evaluation.forces import ForceResult, ForceTask, evaluate_forces
from labrig.evaluation.groundtruth_error import (
    LABEL_POSES,
    GroundTruthErrorResult,
    GroundTruthErrorTask,
    evaluate_groundtruth,
)
from labrig.evaluation.hold import hold_summary
from labrig.evaluation.stress import StressResult
from labrig.evaluation.stress_axes import AXES as STRESS_AXES
from labrig.evaluation.stress_axes import METRICS as STRESS_METRICS
from labrig.evaluation.stress_axes import StressAxis, axis_named
from labrig.evaluation.sweep import SweepResult, run_sweep
from labrig.evaluation.tracking import (
    FIXED_BAND_TRACKERS,
    TABLE_PATCH_SCALES,
    TrackingResult,
    table_lost_tracks,
    table_tasks,
    track_recording,
)
from labrig.executor import Run, run_tasks
from labrig.models import BUNDLED, bundled_model_path, model_path
from labrig.pipeline.model_card import ModelCard, card_path, find_models
from labrig.pipeline.windows import PAPER_WINDOW_EVENTS, WindowArgs, WindowSpec
from labrig.recording import Recording
from labrig.recording.quality import camera_shortfall_s

SPLIT_CHOICES = (*SPLITS, ALL_SPLITS)  # --split
PAPER = {"force_x_mae_n": 0.14, "force_y_mae_n": 0.10, "force_z_mae_n": 0.93, "force_total_mae_n": 0.94,
         "position_total_mae_px": 2.47, "depth_total_mm": 0.091, "depth_contact_mm": 0.265, "lost_tracks": 2.8}
Progress = Callable[[str, int, int], None]
#: Table I's trackers (``--trackers``) and their names in the report; the default is the first two.
TABLE1_TRACKERS = {"paper-published": "as published", "paper": "bundled (event gates)", "circle-fit": "circle fit",
                   "evetac": "Evetac (published)"}
DEFAULT_TABLE1_TRACKERS = ("paper-published", "paper")


@dataclass
class EvaluationSettings:
    """What ``labrig evaluate`` measures and how; paths as given on the command line."""

    data: Path
    split: str = "test"
    model: Path | None = None  # default: the bundled network
    models_dir: Path | None = None  # Table II's models (cards give window and loss)
    window_events: int | None = PAPER_WINDOW_EVENTS
    window_ms: float | None = None
    calibration_dir: Path | None = Path(DEFAULT_CALIBRATION_DIR)
    workers: int | None = None
    scheduler: str | None = None
    cache_dir: Path | None = None
    use_cache: bool = True
    patch_scales: tuple[float, ...] = TABLE_PATCH_SCALES
    table1: bool = True
    trackers: tuple[str, ...] = DEFAULT_TABLE1_TRACKERS  # Table I's trackers (keys of TABLE1_TRACKERS)
    label_errors: bool = True
    #: The gel poses the labels are made with: "lab" (the registration in the calibration folder), "true" (the
    #: sim's own: a perfect registration, which shows what the registration costs the labels).
    label_poses: tuple[str, ...] = ("lab",)
    sweep: bool = False
    sweep_recordings: int | None = 4  # the sweep's recordings: the first N of the split (None: all)
    stress: bool = False  # the stress suite on the virtual rig (labrig.evaluation.stress)
    stress_grid: str = "full"  # or "reduced"
    stress_axes: tuple[str, ...] | None = None  # the axes' keys (labrig.evaluation.stress_axes); None: every axis
    stress_metrics: tuple[str, ...] | None = None  # only these of the axes' metrics (tracking, forces, depth); None: all

    def check(self) -> None:
        if self.split not in SPLIT_CHOICES:
            raise LabrigError(f"--split must be one of {', '.join(SPLIT_CHOICES)}, not {self.split!r}")
        WindowSpec.from_options(self.window_ms, self.window_events, default_ms=None)
        if self.models_dir is not None and not Path(self.models_dir).is_dir():
            raise LabrigError(f"--models {self.models_dir}: not a folder (give the folder tools/depth_sweep.py wrote)")
        unknown = [t for t in self.trackers if t not in TABLE1_TRACKERS]
        if unknown or not self.trackers:
            raise LabrigError(f"--trackers: {', '.join(unknown) or 'none given'}; use a comma-separated list of "
                              f"{', '.join(TABLE1_TRACKERS)}")
        if self.stress_grid not in ("full", "reduced"):
            raise LabrigError(f"--stress-grid must be full or reduced, not {self.stress_grid!r}")
        for key in self.stress_axes or ():
            axis_named(key)  # one line naming the axes there are
        if self.stress_metrics is not None and (not self.stress_metrics
                                                or any(m not in STRESS_METRICS for m in self.stress_metrics)):
            raise LabrigError(f"--stress-metrics: {', '.join(self.stress_metrics) or 'none given'}; use a "
                              f"comma-separated list of {', '.join(STRESS_METRICS)}")
        if not self.label_poses or any(p not in LABEL_POSES for p in self.label_poses):
            raise LabrigError(f"--label-poses: {', '.join(self.label_poses) or 'none given'}; use lab, true or lab,true")
        if self.model is not None and not model_path(self.model).exists():
            raise LabrigError(f"--model {self.model}: no such file (give a depth network .onnx with its .json card, "
                              f"or a bundled one: {', '.join(BUNDLED)})")
        if self.model is not None:
            ModelCard.load(card_path(model_path(self.model)))  # a bad card: one line now, not after the tasks

    @property
    def window_us(self) -> int | None:
        return None if self.window_ms is None else round(self.window_ms * 1000)


@dataclass
class Evaluation:
    """Everything measured: per-recording results by kind, the pooled tables, the report once written."""

    settings: EvaluationSettings
    recordings: list[Path]
    model: Path
    tracking: list[TrackingResult | None] = field(default_factory=list)
    depth: dict[str, list[DepthResult]] = field(default_factory=dict)  # model path -> per recording
    forces: list[ForceResult] = field(default_factory=list)
    forces_truth: list[ForceResult] = field(default_factory=list)  # the sim's depth maps instead of the network's
    control: list[ControlRun] = field(default_factory=list)  # the recordings a force loop ran in
    labels: list[GroundTruthErrorResult] = field(default_factory=list)
    table2_models: dict[tuple[str, float], str | None] = field(default_factory=dict)
    cache: dict[str, str] = field(default_factory=dict)  # kind -> "hits/misses" summary
    sweep: SweepResult | None = None  # with --sweep
    stress: StressResult | None = None  # with --stress
    summary: dict[str, Any] = field(default_factory=dict)
    camera_short_s: dict[str, float] = field(default_factory=dict)  # recording -> events missing at the end (s)


def campaign_recordings(data: Path, split: str) -> list[DatasetRecording]:
    """The complete recordings of ``split`` ("all": every split) in a campaign folder, or one recording,
    each with its ground truth."""
    source = open_data(data)
    if isinstance(source, DatasetRecording):
        recordings = [source]
    else:
        recordings = source.require(split)
        require_present(recordings, data)
    require_groundtruth(recordings, data)
    return recordings


def default_model() -> Path:

    return bundled_model_path()


def table2_models(models_dir: Path | None, width: int | None) -> dict[tuple[str, float], str | None]:
    """Each Table II row's model in ``models_dir`` (by its card's loss and window; the given width
    first), None where missing."""
    found: dict[tuple[str, float], str | None] = {row: None for row in tables.TABLE2_ROWS}
    if models_dir is None:
        return found
    cards = find_models(models_dir)
    for loss, window in tables.TABLE2_ROWS:
        matching = [c for c in cards if c.loss == loss and abs(c.window_ms - window) < 1e-6]
        matching.sort(key=lambda c: (c.width != width, str(c.onnx)))
        found[(loss, window)] = str(matching[0].onnx) if matching else None
    return found


def evaluate_campaign(settings: EvaluationSettings, progress: Progress | None = None) -> Evaluation:
    """Run every task of the evaluation (parallel, cached) and pool the results."""
    settings.check()
    recordings = [r.path for r in campaign_recordings(settings.data, settings.split)]
    model = model_path(settings.model) if settings.model is not None else default_model()
    width = ModelCard.load(card_path(model)).width
    ev = Evaluation(settings, recordings, model, table2_models=table2_models(settings.models_dir, width))
    run = _runner(settings, ev, progress)
    calibration = str(settings.calibration_dir) if settings.calibration_dir is not None else None
    windows: WindowArgs = {"window_events": settings.window_events, "window_us": settings.window_us}
    paths = [str(p) for p in recordings]

    ev.forces = run("forces", evaluate_forces, [ForceTask(p, str(model), calibration_dir=calibration,
                                                          sidecar=str(sidecar_path(p)), **windows) for p in paths])
    ev.control = control_runs(paths, ev.forces)
    depth_models = [str(model), *sorted({m for m in ev.table2_models.values() if m and m != str(model)})]
    depth_tasks = [DepthTask(p, m, sidecar=str(sidecar_path(p)), calibration_dir=calibration, **windows)
                   for m in depth_models for p in paths]
    results = run("depth", evaluate_depth, depth_tasks)
    for m in depth_models:
        ev.depth[m] = [r for t, r in zip(depth_tasks, results) if t.model == m]
    if settings.table1:
        ev.tracking = run("tracking", track_recording,
                          [t for tracker in settings.trackers for t in table_tasks(
                              paths, patch_scales=settings.patch_scales[:1] if tracker in FIXED_BAND_TRACKERS
                              else settings.patch_scales, calibration_dir=calibration, tracker=tracker)])
    simulated, ev.camera_short_s = _scan_recordings(paths)
    if simulated:
        ev.forces_truth = run("forces-truth", evaluate_forces, [
            ForceTask(p, "truth", calibration_dir=calibration, sidecar=str(sidecar_path(p)), **windows)
            for p in simulated])
    if settings.label_errors and simulated:
        ev.labels = run("labels", evaluate_groundtruth, [GroundTruthErrorTask(p, elastic, pose, calibration)
                                                          for pose in settings.label_poses
                                                          for elastic in ("layer", "halfspace") for p in simulated])
    if settings.sweep:
        chosen = paths if settings.sweep_recordings is None else _spread(paths, settings.sweep_recordings)
        ev.sweep = run_sweep(chosen, model, settings.models_dir, run, calibration, **windows)
    if settings.stress:
        axes = stress_axes_measured(settings.stress_axes, settings.stress_metrics)
        ev.stress = stress_suite.run_stress(run, grid=settings.stress_grid, axes=axes, model=str(model),
                                            calibration_dir=calibration)
    ev.summary = headline(ev)
    return ev


def _spread(items: list[str], n: int) -> list[str]:
    """``n`` items spread evenly over ``items`` (campaigns list indenters in groups)."""
    if n >= len(items):
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, n).round().astype(int)]


def _runner(settings: EvaluationSettings, ev: Evaluation, progress: Progress | None) -> Run:
    def run(kind: str, fn: Callable[[Any], Any], tasks: list[Any]) -> list[Any]:
        results = run_tasks(fn, tasks, workers=settings.workers, scheduler=settings.scheduler,
                            cache_dir=settings.cache_dir, use_cache=settings.use_cache,
                            progress=(lambda done, total: progress(kind, done, total)) if progress else None)
        ev.cache[kind] = results.summary()
        return list(results)

    return run


def _scan_recordings(paths: list[str], tolerance_s: float = 0.1) -> tuple[list[str], dict[str, float]]:
    """One look at each recording: those with the sim's truth (virtual rig), and those whose camera
    stream stops more than ``tolerance_s`` before the protocol ends (name -> seconds missing)."""
    simulated, short = [], {}
    for path in paths:
        with Recording(path) as rec:
            if "truth/depth" in rec.streams and rec.rows("truth/depth") > 0:
                simulated.append(path)
            missing_s = camera_shortfall_s(rec)
        if missing_s > tolerance_s:
            short[Path(path).name] = round(missing_s, 2)
    return simulated, short


def stress_axes_measured(keys: Sequence[str] | None, metrics: Sequence[str] | None) -> list[StressAxis] | None:
    """The stress axes named by ``keys`` (None: every axis), each measuring only ``metrics`` of its own (None:
    all); an axis left with none is dropped. None: every axis as it is."""
    if keys is None and metrics is None:
        return None
    axes = [axis_named(key) for key in keys] if keys else list(STRESS_AXES)
    if metrics is None:
        return axes
    kept = [replace(a, metrics=tuple(m for m in a.metrics if m in metrics)) for a in axes]
    chosen = [a for a in kept if a.metrics]
    if not chosen:
        raise LabrigError(f"no stress axis measures {', '.join(metrics)}; leave out --stress-metrics or choose other axes")
    return chosen


# -- headline numbers --------------------------------------------------------------------------


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def _median(values: Sequence[float]) -> float | None:
    """The median of the finite values (None: none)."""
    finite = [v for v in values if np.isfinite(v)]
    return _finite(float(np.median(finite))) if finite else None


def headline(ev: Evaluation) -> dict[str, Any]:
    """The summary ``labrig evaluate --json`` prints: stable keys, units in the names."""
    t3 = {row["axis"]: row for row in tables.table3(ev.forces)}
    depth = tables.depth_row(ev.depth[str(ev.model)])
    runtime = tables.runtime_row(ev.forces, ("read", "sae", "track", "depth", "displacement", "forces"))
    out: dict[str, Any] = {
        "data": str(ev.settings.data), "split": ev.settings.split, "recordings": len(ev.recordings),
        "model": str(ev.model), "window_events": ev.settings.window_events, "window_ms": ev.settings.window_ms,
        "force_windows": int(sum(int(np.sum(r.probing)) for r in ev.forces)),
        "force_x_mae_n": t3["x"]["force_mae_n"], "force_y_mae_n": t3["y"]["force_mae_n"],
        "force_z_mae_n": t3["z"]["force_mae_n"], "force_total_mae_n": t3["total"]["force_mae_n"],
        "position_total_mae_px": t3["total"]["position_mae_px"],
        "depth_total_mm": depth["total_mm"], "depth_contact_mm": depth["contact_mm"],
        "depth_noncontact_mm": depth["noncontact_mm"],
        "pipeline_ms": runtime["total_ms"], "pipeline_rate_hz": runtime["rate_hz"],
        "pipeline_window_ms_median": runtime["window_ms_median"], "pipeline_window_ms_p95": runtime["window_ms_p95"],
        "runtime_cores": runtime["cores"], "runtime_load_1min": runtime["load_1min_median"],
        "paper": PAPER, "cache": ev.cache, "camera_stream_short_s": ev.camera_short_s,
        "force_by_indenter": tables.force_by_indenter(ev.forces),
    }
    held = hold_summary(ev.forces)
    out.update({"hold_presses": len(held.presses), "hold_fz_error_first_5s_n": _finite(held.fz_error_first_n),
                "hold_fz_error_last_5s_n": _finite(held.fz_error_last_n),
                "hold_error_ratio_last_to_first": _finite(held.error_ratio_last_to_first),
                "hold_fz_after_release_n": _finite(held.after_release_fz_n)})
    if ev.control:
        runs = ev.control
        out.update({"control_recordings": len(runs),
                    "control_step_overshoot_pct": _median([r.step_overshoot_pct for r in runs]),
                    "control_step_settling_s": _median([r.step_settling_s for r in runs]),
                    "control_hold_rms_n_ft": _median([r.hold_rms_n_ft for r in runs]),
                    "control_hold_rms_n_estimate": _median([r.hold_rms_n_estimate for r in runs]),
                    "control_reading_scatter_n": _median([r.reading_scatter_n for r in runs]),
                    "control_slip_onset_error_ms": _median([r.slip_onset_error_ms for r in runs])})
    if ev.forces_truth:
        truth = {row["axis"]: row for row in tables.table3(ev.forces_truth)}
        out.update({f"force_{a}_mae_true_depth_n": truth[a]["force_mae_n"] for a in ("x", "y", "z", "total")})
        out["position_total_mae_true_depth_px"] = truth["total"]["position_mae_px"]
    if ev.tracking:
        best = [r for r in table_lost_tracks(ev.tracking)
                if r["tracker"] == "paper" and r["refine"] and r["patch_scale"] == 3.0]
        out["lost_tracks_per_sequence"] = best[0]["lost_mean"] if best else None
    if ev.sweep is not None:
        out["sweep_recommended"] = {metric: {"setting": p.label, "latency_ms": p.latency_ms, "error": p.error}
                                    for metric, p in ev.sweep.recommendations.items()}
        out["sweep_knee"] = {metric: (p.label if p else None) for metric, p in ev.sweep.knees.items()}
    if ev.labels:
        out["labels"] = label_summary(ev.labels)
    if ev.stress is not None:
        out["stress_breakdown"] = stress_suite.stress_summary(ev.stress)
    return out


def label_summary(results: Sequence[GroundTruthErrorResult | None]) -> dict[str, dict[str, float | int | None]]:
    """Per elastic model and gel pose ("layer/lab", ...): the labels' mean errors over the recordings, mm, and the
    mean IoU of their contact masks."""
    out: dict[str, dict[str, float | int | None]] = {}
    for r in results:
        if r is not None:
            out.setdefault(f"{r.elastic}/{r.pose}", {})
    for key in out:
        group = [r for r in results if r is not None and f"{r.elastic}/{r.pose}" == key]
        out[key] = {"recordings": len(group),
                    "mae_contact_mm": _finite(float(np.mean([r.mae_contact_mm for r in group]))),
                    "mae_noncontact_mm": _finite(float(np.mean([r.mae_noncontact_mm for r in group]))),
                    "p95_noncontact_mm": _finite(float(np.mean([r.p95_noncontact_mm for r in group]))),
                    "mask_iou": _finite(float(np.mean([r.mask_iou for r in group])))}
    return out
