"""``labrig evaluate --sweep``: accuracy against latency over the knobs that trade them.

Each knob setting is a set of per-recording tasks (the same task functions as the tables,
so the cache shares their results); pooled, a setting becomes one point (latency per
window in ms, error) on the chart of its error metric:

* tracking error (px, p95 against the sim's markers) over patch size 1-5 x, refinement
  on/off, the tracker with gates or as published; latency: the tracker's time per window;
* depth error in contact (mm) over network width (models of one window and loss) and window
  length (Table II's models); latency: window length + inference (a window must fill
  before the network sees it);
* force error (N, norm of the error vector) over FEM mesh refinement and event-count vs
  fixed-time windows; latency: median window duration + the pipeline's time.

One Pareto chart per metric marks the front's knee and the recommendation: the fastest
setting within 5 % of the best error (model no more than a scene needs).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from labrig.config import DEFAULT_CALIBRATION_DIR
from labrig.dataset import sidecar_path
from labrig.evaluation import charts, tables
from labrig.evaluation.depth import DepthTask, evaluate_depth
from labrig.evaluation.forces import ForceTask, evaluate_forces
from labrig.evaluation.report import Report
from labrig.evaluation.tracking import TrackingTask, track_recording
from labrig.executor import Run
from labrig.pipeline.depthnet import benchmark_ms
from labrig.pipeline.model_card import ModelCard, card_path, find_models
from labrig.pipeline.windows import PAPER_WINDOW_EVENTS, WindowArgs

TOLERANCE = 0.05
PATCH_SCALES = (1.0, 2.0, 3.0, 4.0, 5.0)
MESH_REFINEMENTS = (1, 2, 3)
FORCE_WINDOWS: tuple[tuple[str, dict[str, int | None]], ...] = (
    ("10 ms", {"window_us": 10_000, "window_events": None}), ("30 ms", {"window_us": 30_000, "window_events": None}),
    ("5k events", {"window_us": None, "window_events": 5_000}),
    ("20k events", {"window_us": None, "window_events": 20_000}))
METRICS = {"tracking": ("p95 tracking error", "px"), "depth": ("depth error in contact", "mm"),
           "forces": ("force error", "N")}


@dataclass(frozen=True)
class SweepPoint:
    """One knob setting pooled over the recordings: latency per window (ms) and error (the metric's unit)."""

    metric: str  # a key of METRICS
    knob: str
    label: str
    latency_ms: float
    error: float
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SweepResult:
    """Every setting's point, and per metric the recommended setting and the Pareto front's knee."""

    points: list[SweepPoint]
    recommendations: dict[str, SweepPoint]
    knees: dict[str, SweepPoint | None]


def sweep_models(models_dir: Path | None, main_model: Path) -> tuple[list[str], list[str]]:
    """(width models: same window and loss as ``main_model``, different widths; window models: Table II's
    contact-aware ones at the main model's width)."""
    main = ModelCard.load(card_path(main_model))
    cards = find_models(models_dir) if models_dir is not None else []
    width, loss, window = main.width, main.loss, main.window_ms
    widths = {c.width: str(c.onnx) for c in cards if c.loss == loss and abs(c.window_ms - window) < 1e-6}
    widths.setdefault(width, str(main_model))
    windows = {c.window_ms: str(c.onnx) for c in cards if c.loss == "contact" and c.width == width}
    windows.setdefault(window, str(main_model))
    return [widths[w] for w in sorted(widths, key=lambda w: w or 0)], [windows[w] for w in sorted(windows)]


def run_sweep(recordings: list[str], main_model: Path, models_dir: Path | None, run: Run,
              calibration_dir: str | None = DEFAULT_CALIBRATION_DIR, window_events: int | None = PAPER_WINDOW_EVENTS,
              window_us: int | None = None, mesh_refinements: tuple[int, ...] = MESH_REFINEMENTS,
              patch_scales: tuple[float, ...] = PATCH_SCALES) -> SweepResult:
    """Every knob setting on ``recordings``; ``run(kind, fn, tasks) -> results`` runs tasks (parallel, cached)."""
    points: list[SweepPoint] = []
    # tracking: patch size x refinement x tracker
    settings = [(tracker, refine, scale) for tracker in ("paper", "paper-published") for refine in (True, False)
                for scale in patch_scales]
    tracking_tasks = [TrackingTask(p, tracker=t, patch_scale=s, refine=r, calibration_dir=calibration_dir)
                      for t, r, s in settings for p in recordings]
    results = run("sweep tracking", track_recording, tracking_tasks)
    for i, (tracker, refine, scale) in enumerate(settings):
        group = [r for r in results[i * len(recordings):(i + 1) * len(recordings)] if r is not None]
        errors = [r.error_p95_px for r in group if r.error_p95_px is not None]
        if errors:
            label = f"{'gated' if tracker == 'paper' else 'published'} {scale:g}x{' +ref' if refine else ''}"
            points.append(SweepPoint("tracking", "tracker", label, float(np.median([r.track_ms_median for r in group])),
                                     float(np.mean(errors)), {"lost_tracks": float(np.mean([r.lost_tracks for r in group]))}))
    # depth: widths and windows
    width_models, window_models = sweep_models(models_dir, main_model)
    models = sorted(set(width_models) | set(window_models))
    windows: WindowArgs = {"window_events": window_events, "window_us": window_us}
    depth_tasks = [DepthTask(p, m, sidecar=str(sidecar_path(p)), **windows) for m in models for p in recordings]
    results = run("sweep depth", evaluate_depth, depth_tasks)
    for k, model in enumerate(models):
        group = results[k * len(recordings):(k + 1) * len(recordings)]
        card = ModelCard.load(card_path(model))
        infer_ms = benchmark_ms(model, threads=1, repeats=30, warmup=3)
        row = tables.depth_row(group)
        if row["contact_mm"] is None:
            continue
        width, window = card.width, card.window_ms
        if model in width_models:
            points.append(SweepPoint("depth", "width", f"width {width}", infer_ms + window, row["contact_mm"],
                                     {"infer_ms": infer_ms, "total_mm": row["total_mm"], "model": model}))
        if model in window_models:
            points.append(SweepPoint("depth", "window", f"{window:g} ms (w{width})", infer_ms + window, row["contact_mm"],
                                     {"infer_ms": infer_ms, "total_mm": row["total_mm"], "model": model}))
    # forces: mesh refinement, window kind
    force_settings: list[tuple[str, dict[str, Any]]] = [(f"mesh {m}", {"surface_refinement": m, **windows})
                                                       for m in mesh_refinements]
    force_settings += [(name, {"surface_refinement": 2, **w}) for name, w in FORCE_WINDOWS]
    force_tasks = [ForceTask(p, str(main_model), calibration_dir=calibration_dir, sidecar=str(sidecar_path(p)), **options)
                   for _, options in force_settings for p in recordings]
    results = run("sweep forces", evaluate_forces, force_tasks)
    for k, (name, _) in enumerate(force_settings):
        group = results[k * len(recordings):(k + 1) * len(recordings)]
        total = next(r for r in tables.table3(group) if r["axis"] == "total")["force_mae_n"]
        if total is None:
            continue
        duration_ms = float(np.median(np.concatenate([(r.t1_us - r.t0_us) / 1e3 for r in group])))
        pipeline_ms = float(np.median([r.total_ms for r in group]))
        knob = "mesh" if name.startswith("mesh") else "windows"
        points.append(SweepPoint("forces", knob, name, duration_ms + pipeline_ms, total,
                                 {"window_ms": duration_ms, "pipeline_ms": pipeline_ms,
                                  "forces_ms": float(np.median([r.stage_ms["forces"] for r in group]))}))
    recommendations: dict[str, SweepPoint] = {}
    knees: dict[str, SweepPoint | None] = {}
    for metric in METRICS:
        mine = [p for p in points if p.metric == metric]
        if not mine:
            continue
        best = charts.recommend([charts.Candidate(p.label, p.latency_ms, p.error) for p in mine], TOLERANCE)
        recommendations[metric] = next(p for p in mine if p.label == best.label)
        knee = charts.knee_index([p.latency_ms for p in mine], [p.error for p in mine])
        knees[metric] = mine[knee] if knee is not None else None
    return SweepResult(points, recommendations, knees)


def add_sweep_to_report(report: Report, sweep: SweepResult) -> None:
    """One Pareto chart and one table per error metric, with the knee and the recommendation."""
    report.section("Speed against accuracy", "sweep")
    report.add_text("sweep_note", (
        "Each point is one setting pooled over the recordings. Latency is per window: for depth the window length "
        "plus inference (a window must fill before the network sees it), for forces the median window duration plus "
        "the pipeline's time, for tracking the tracker's time. Recommended: the fastest setting within 5 % of the "
        "best error; the knee: the front point farthest below the chord of the Pareto front."))
    for metric, (name, unit) in METRICS.items():
        mine = [p for p in sweep.points if p.metric == metric]
        if not mine:
            continue
        report.add_figure(f"pareto_{metric}", f"{name.capitalize()} against latency",
                          charts.pareto([charts.Candidate(p.label, p.latency_ms, p.error) for p in mine],
                                        error_name=name, error_unit=unit, tolerance=TOLERANCE,
                                        budget_ms=None if metric == "forces" else 10.0))
        chosen, knee = sweep.recommendations.get(metric), sweep.knees.get(metric)
        report.add_table(f"sweep_{metric}", f"{name.capitalize()}: settings", ["knob", "setting", "latency", "error",
                                                                               "mark"],
                         [[p.knob, p.label, p.latency_ms, p.error,
                           ", ".join(m for m, q in (("recommended", chosen), ("knee", knee)) if q is p)] for p in mine],
                         units={"latency": "ms", "error": unit})
