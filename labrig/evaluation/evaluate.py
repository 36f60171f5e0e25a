"""``labrig evaluate``: a campaign's recordings through the pipeline, measured as the paper did and beyond.

:func:`evaluate_campaign` plans every per-recording task (tracking for Table I, depth for
Table II and the per-range analysis, forces for Table III, label errors on the virtual
rig), runs them through :func:`labrig.evaluation.executor.run_tasks` (parallel, cached),
pools the results into tables (:mod:`labrig.evaluation.tables`) and writes the report
(:mod:`labrig.evaluation.report`, :mod:`labrig.evaluation.charts`).
"""

from __future__ import annotations

import platform
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from labrig.dataset import ALL_SPLITS, DatasetRecording, open_data, require_groundtruth, require_present, sidecar_path
from labrig.dataset import SPLITS as DATASET_SPLITS
from labrig.errors import LabrigError
from labrig.evaluation import charts, tables
from labrig.evaluation.depth import DepthTask, evaluate_depth
from labrig.evaluation.executor import run_tasks
from labrig.evaluation.forces import ForceTask, evaluate_forces
from labrig.evaluation.groundtruth_error import GroundTruthErrorTask, evaluate_groundtruth
from labrig.evaluation.report import MeanStd, Report
from labrig.evaluation.tracking import TABLE_PATCH_SCALES, table_lost_tracks, table_tasks, track_recording
from labrig.evaluation.windows import PAPER_WINDOW_EVENTS
from labrig.models import BUNDLED, bundled_model_path, model_path

SPLITS = (*DATASET_SPLITS, ALL_SPLITS)
PAPER = {"force_x_mae_n": 0.14, "force_y_mae_n": 0.10, "force_z_mae_n": 0.93, "force_total_mae_n": 0.94,
         "position_total_mae_px": 2.47, "depth_total_mm": 0.091, "depth_contact_mm": 0.265, "lost_tracks": 2.8}
Progress = Callable[[str, int, int], None]
TABLE1_TRACKERS = {"paper-published": "as published", "paper": "bundled (event gates)"}


@dataclass
class EvaluationSettings:
    """What ``labrig evaluate`` measures and how; paths as given on the command line."""

    data: Path
    split: str = "test"
    model: Path | None = None  # default: the bundled network
    models_dir: Path | None = None  # Table II's models (cards give window and loss)
    window_events: int | None = PAPER_WINDOW_EVENTS
    window_ms: float | None = None
    calibration_dir: Path | None = Path("calibration")
    workers: int | None = None
    scheduler: str | None = None
    cache_dir: Path | None = None
    use_cache: bool = True
    patch_scales: tuple[float, ...] = TABLE_PATCH_SCALES
    table1: bool = True
    label_errors: bool = True
    sweep: bool = False
    sweep_recordings: int | None = 4  # the sweep's recordings: the first N of the split (None: all)
    stress: bool = False  # the stress suite on the virtual rig (labrig.evaluation.stress)
    stress_grid: str = "full"  # or "reduced"

    def check(self) -> None:
        if self.split not in SPLITS:
            raise LabrigError(f"--split must be one of {', '.join(SPLITS)}, not {self.split!r}")
        if (self.window_events is None) == (self.window_ms is None):
            raise LabrigError("give --window-events or --window-ms, not both")
        if (self.window_events is not None and self.window_events <= 0) or (self.window_ms is not None
                                                                           and self.window_ms <= 0):
            raise LabrigError("--window-events and --window-ms must be positive")
        if self.models_dir is not None and not Path(self.models_dir).is_dir():
            raise LabrigError(f"--models {self.models_dir}: not a folder (give the folder tools/depth_sweep.py wrote)")
        if self.stress_grid not in ("full", "reduced"):
            raise LabrigError(f"--stress-grid must be full or reduced, not {self.stress_grid!r}")
        if self.model is not None and not model_path(self.model).exists():
            raise LabrigError(f"--model {self.model}: no such file (give a depth network .onnx with its .json card, "
                              f"or a bundled one: {', '.join(BUNDLED)})")

    @property
    def window_us(self) -> int | None:
        return None if self.window_ms is None else round(self.window_ms * 1000)


@dataclass
class Evaluation:
    """Everything measured: per-recording results by kind, the pooled tables, the report once written."""

    settings: EvaluationSettings
    recordings: list[Path]
    model: Path
    tracking: list[dict[str, Any] | None] = field(default_factory=list)
    depth: dict[str, list[dict[str, Any]]] = field(default_factory=dict)  # model path -> per recording
    forces: list[dict[str, Any]] = field(default_factory=list)
    forces_truth: list[dict[str, Any]] = field(default_factory=list)  # the sim's depth maps instead of the network's
    labels: list[dict[str, Any]] = field(default_factory=list)
    table2_models: dict[tuple[str, float], str | None] = field(default_factory=dict)
    cache: dict[str, str] = field(default_factory=dict)  # kind -> "hits/misses" summary
    sweep: Any = None  # labrig.evaluation.sweep.SweepResult with --sweep
    stress: Any = None  # labrig.evaluation.stress.StressResult with --stress
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
    from labrig.pipeline.depthnet import find_models

    cards = find_models(models_dir)
    for loss, window in tables.TABLE2_ROWS:
        matching = [c for c in cards if c.get("loss", {}).get("name") == loss
                    and abs(float(c.get("window_ms", -1)) - window) < 1e-6]
        matching.sort(key=lambda c: (c.get("architecture", {}).get("width") != width, c["onnx"]))
        found[(loss, window)] = matching[0]["onnx"] if matching else None
    return found


def evaluate_campaign(settings: EvaluationSettings, progress: Progress | None = None) -> Evaluation:
    """Run every task of the evaluation (parallel, cached) and pool the results."""
    from labrig.pipeline.depthnet import read_card

    settings.check()
    chosen = campaign_recordings(settings.data, settings.split)
    recordings = [r.path for r in chosen]
    model = model_path(settings.model) if settings.model is not None else default_model()
    width = read_card(model.with_suffix(".json")).get("architecture", {}).get("width")
    ev = Evaluation(settings, recordings, model, table2_models=table2_models(settings.models_dir, width))
    run = _runner(settings, ev, progress)
    calibration = str(settings.calibration_dir) if settings.calibration_dir is not None else None
    windows = {"window_events": settings.window_events, "window_us": settings.window_us}
    paths = [str(p) for p in recordings]

    ev.forces = run("forces", evaluate_forces, [ForceTask(p, str(model), calibration_dir=calibration,
                                                          sidecar=str(sidecar_path(p)), **windows) for p in paths])
    depth_models = [str(model), *sorted({m for m in ev.table2_models.values() if m and m != str(model)})]
    depth_tasks = [DepthTask(p, m, sidecar=str(sidecar_path(p)), **windows) for m in depth_models for p in paths]
    results = run("depth", evaluate_depth, depth_tasks)
    for m in depth_models:
        ev.depth[m] = [r for t, r in zip(depth_tasks, results) if t.model == m]
    if settings.table1:
        ev.tracking = run("tracking", track_recording,
                          [t for tracker in TABLE1_TRACKERS for t in table_tasks(
                              paths, patch_scales=settings.patch_scales, calibration_dir=calibration, tracker=tracker)])
    simulated, ev.camera_short_s = _scan_recordings(paths)
    if simulated:
        ev.forces_truth = run("forces-truth", evaluate_forces, [
            ForceTask(p, "truth", calibration_dir=calibration, sidecar=str(sidecar_path(p)), **windows)
            for p in simulated])
    if settings.label_errors and simulated:
        ev.labels = run("labels", evaluate_groundtruth, [GroundTruthErrorTask(p, elastic, "lab", calibration)
                                                          for elastic in ("layer", "halfspace") for p in simulated])
    if settings.sweep:
        from labrig.evaluation.sweep import run_sweep

        chosen = paths if settings.sweep_recordings is None else _spread(paths, settings.sweep_recordings)
        ev.sweep = run_sweep(chosen, model, settings.models_dir, run, calibration, **windows)
    if settings.stress:
        from labrig.evaluation.stress import run_stress

        ev.stress = run_stress(run, grid=settings.stress_grid, model=str(model), calibration_dir=calibration)
    ev.summary = headline(ev)
    return ev


def _spread(items: list[str], n: int) -> list[str]:
    """``n`` items spread evenly over ``items`` (campaigns list indenters in groups)."""
    if n >= len(items):
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, n).round().astype(int)]


def _runner(settings: EvaluationSettings, ev: Evaluation, progress: Progress | None) -> Callable[..., list[Any]]:
    def run(kind: str, fn: Callable[[Any], dict[str, Any]], tasks: list[Any]) -> list[Any]:
        results = run_tasks(fn, tasks, workers=settings.workers, scheduler=settings.scheduler,
                            cache_dir=settings.cache_dir, use_cache=settings.use_cache,
                            progress=(lambda done, total: progress(kind, done, total)) if progress else None)
        ev.cache[kind] = results.summary()
        return list(results)

    return run


def _scan_recordings(paths: list[str], tolerance_s: float = 0.1) -> tuple[list[str], dict[str, float]]:
    """One look at each recording: those with the sim's truth (virtual rig), and those whose camera
    stream stops more than ``tolerance_s`` before the protocol ends (name -> seconds missing)."""
    from labrig.evaluation.windows import camera_shortfall_s
    from labrig.recording import Recording

    simulated, short = [], {}
    for path in paths:
        with Recording(path) as rec:
            if "truth/depth" in rec.streams and rec.rows("truth/depth") > 0:
                simulated.append(path)
            missing_s = camera_shortfall_s(rec)
        if missing_s > tolerance_s:
            short[Path(path).name] = round(missing_s, 2)
    return simulated, short


# -- headline numbers --------------------------------------------------------------------------


def headline(ev: Evaluation) -> dict[str, Any]:
    """The summary ``labrig evaluate --json`` prints: stable keys, units in the names."""
    t3 = {row["axis"]: row for row in tables.table3(ev.forces)}
    depth = tables.depth_row(ev.depth[str(ev.model)])
    runtime = tables.runtime_row(ev.forces, ("read", "sae", "track", "depth", "displacement", "forces"))
    out: dict[str, Any] = {
        "data": str(ev.settings.data), "split": ev.settings.split, "recordings": len(ev.recordings),
        "model": str(ev.model), "window_events": ev.settings.window_events, "window_ms": ev.settings.window_ms,
        "force_windows": int(sum(int(np.sum(r["probing"])) for r in ev.forces)),
        "force_x_mae_n": t3["x"]["force_mae_n"], "force_y_mae_n": t3["y"]["force_mae_n"],
        "force_z_mae_n": t3["z"]["force_mae_n"], "force_total_mae_n": t3["total"]["force_mae_n"],
        "position_total_mae_px": t3["total"]["position_mae_px"],
        "depth_total_mm": depth["total_mm"], "depth_contact_mm": depth["contact_mm"],
        "depth_noncontact_mm": depth["noncontact_mm"],
        "pipeline_ms": runtime["total_ms"], "pipeline_rate_hz": runtime["rate_hz"],
        "paper": PAPER, "cache": ev.cache, "camera_stream_short_s": ev.camera_short_s,
    }
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
    if ev.stress is not None:
        from labrig.evaluation.stress import stress_summary

        out["stress_breakdown"] = stress_summary(ev.stress)
    return out


# -- the report --------------------------------------------------------------------------------


def build_report(ev: Evaluation) -> Report:
    """Tables and charts of an evaluation, ready to :meth:`Report.write`."""
    s = ev.settings
    windows = f"{s.window_events:,} events" if s.window_events else f"{s.window_ms:g} ms"
    report = Report("labrig evaluation", meta={
        "data": str(s.data), "split": s.split, "recordings": len(ev.recordings), "model": ev.model.name,
        "evaluation windows": windows, "machine": f"{platform.machine()}, {platform.python_version()}"})
    report.add_text("overview", (
        f"{len(ev.recordings)} recordings of the **{s.split}** split of `{s.data}`, evaluated on sequential windows "
        f"of {windows}; depth network `{ev.model.name}`. The paper's figures are its floor: force MAE (0.14, 0.10, "
        "0.93) N, depth MAE 0.091 mm (0.265 mm in contact), 2.8 lost tracks per sequence, 2.47 px contact position."))
    if ev.camera_short_s:
        listed = ", ".join(f"{name} ({short:g} s)" for name, short in sorted(ev.camera_short_s.items()))
        report.add_text("data_warnings", (
            f"**Data warning.** In {len(ev.camera_short_s)} of {len(ev.recordings)} recordings the camera's events "
            f"stop before the protocol ends: {listed}. Windows there have no events and are not scored (count "
            "windows end at the last event); the pipeline's figures cover less of those runs. Record them again."))
    _forces_section(report, ev)
    _depth_section(report, ev)
    if ev.tracking:
        _tracking_section(report, ev)
    _runtime_section(report, ev)
    if ev.labels:
        _labels_section(report, ev)
    if ev.sweep is not None:
        from labrig.evaluation.sweep import add_sweep_to_report

        add_sweep_to_report(report, ev.sweep)
    if ev.stress is not None:
        from labrig.evaluation.stress import add_stress_to_report

        add_stress_to_report(report, ev.stress)
    report.add_json("summary", ev.summary)
    return report


def _ms(mean: float | None, std: float | None) -> MeanStd | None:
    return None if mean is None else MeanStd(mean, std if std is not None else float("nan"))


def _forces_section(report: Report, ev: Evaluation) -> None:
    report.section("Forces (Table III)", "forces")
    rows = tables.table3(ev.forces)
    truth = {r["axis"]: r for r in tables.table3(ev.forces_truth)} if ev.forces_truth else {}
    columns = ["axis", "force", "position", *(["force, true depth", "position, true depth"] if truth else []),
               "paper force"]
    report.add_table("table3", "Force and contact position errors", columns,
                     [[r["axis"], _ms(r["force_mae_n"], r["force_std_n"]), _ms(r["position_mae_px"], r["position_std_px"]),
                       *([_ms(truth[r["axis"]]["force_mae_n"], truth[r["axis"]]["force_std_n"]),
                          _ms(truth[r["axis"]]["position_mae_px"], truth[r["axis"]]["position_std_px"])] if truth else []),
                       PAPER[f"force_{r['axis']}_mae_n"]] for r in rows],
                     caption="Summed per-marker forces against the F/T sensor (force on the gel, gel frame), mean ± std "
                             "over windows in the probing phases; position: the depth map's centre of mass against the "
                             "contact centre where the indenter touched (CNC pose; the maps are indexed by the surface "
                             "at rest, so shear does not move it). Total: norm of the error vector. 'True depth' "
                             "(virtual-rig recordings): the same pipeline fed the sim's depth maps instead of the "
                             "network's, so what is left is tracking, the inverse FEM and the gel law.",
                     units={"force": "N", "position": "px", "force, true depth": "N", "position, true depth": "px",
                            "paper force": "N"})
    error, measured, _ = tables.force_errors(ev.forces)
    panels = {axis: np.abs(measured[:, i]) for i, axis in enumerate("xyz")}
    errs = {axis: np.abs(error[:, i]) for i, axis in enumerate("xyz")}
    report.add_figure("force_by_range_plot", "Force error per measured force range",
                      charts.error_by_range(panels, errs, {a: tables.FORCE_RANGES_N[a] for a in "xyz"},
                                            value_name="|F| measured", value_unit="N", error_name="|error|",
                                            error_unit="N"),
                      caption="The paper's Fig. 3: absolute error per axis, grouped by the measured force on that axis.")
    report.add_table("force_by_range", "Force error per range", ["axis", "range", "windows", "mae", "under-prediction"],
                     [[r["axis"], r["range_n"], r["windows"], _ms(r["mae_n"], r["std_n"]), r["under_prediction_n"]]
                      for r in tables.force_by_range(ev.forces)],
                     caption="Under-prediction: mean of |measured| - |predicted| along the axis (positive: too small).",
                     units={"range": "N", "mae": "N", "under-prediction": "N"})
    example = max(ev.forces, key=lambda r: float(np.max(np.abs(r["measured_n"][:, 2]))) if len(r["measured_n"]) else 0)
    t_s = example["t1_us"] / 1e6
    report.add_figure("force_series", "Net force over a recording (largest normal force)",
                      charts.time_series(t_s, example["measured_n"], example["predicted_n"], unit="N"),
                      caption="Measured (F/T sensor) and predicted (summed per-marker forces) force on the gel.")
    if any(np.isfinite(r["marker_mae_n"]).any() for r in ev.forces):
        dense = tables.dense_errors(ev.forces)
        report.add_table("dense_forces", "Beyond the paper: per-marker forces against the sim's field",
                         ["axis", "per-marker mae", "net vs sim", "sim vs F/T"],
                         [[a, _ms(dense[f"marker_{a}_mae_n"], dense[f"marker_{a}_std_n"]), dense[f"net_vs_sim_{a}_mae_n"],
                           dense[f"sim_vs_ft_{a}_mae_n"]] for a in "xyz"],
                         caption="Virtual-rig recordings only: the dense field the paper could not measure; 'sim vs F/T' "
                                 "is the measurement's own error (noise, tare, registration).",
                         units={"per-marker mae": "N", "net vs sim": "N", "sim vs F/T": "N"})


def _depth_section(report: Report, ev: Evaluation) -> None:
    report.section("Depth (Table II)", "depth")
    rows = []
    for (loss, window), model in ev.table2_models.items():
        if model is None:
            if loss == "contact" and window == 10.0 and str(ev.model) in ev.depth:
                model = str(ev.model)
            else:
                rows.append([loss, window, "missing", None, None, None])
                continue
        row = tables.depth_row(ev.depth[model])
        rows.append([loss, window, Path(model).stem, _ms(row["total_mm"], row["total_std_mm"]),
                     _ms(row["contact_mm"], row["contact_std_mm"]), _ms(row["noncontact_mm"], row["noncontact_std_mm"])])
    report.add_table("table2", "Depth error per window and loss", ["loss", "window", "model", "total", "contact",
                                                                     "non-contact"], rows,
                     caption="Mean ± std over evaluation windows; each network sees its own trained window ending at the "
                             "evaluation time. Rows without a model in --models are missing, not faked.",
                     units={"window": "ms", "total": "mm", "contact": "mm", "non-contact": "mm"})
    main = ev.depth[str(ev.model)]
    report.add_table("depth_by_range", f"Depth error per ground-truth depth range ({ev.model.stem})",
                     ["range", "windows", "total", "contact", "non-contact"],
                     [[r["range_mm"], r["windows"], _ms(r["total_mm"], r["total_std_mm"]), _ms(r["contact_mm"],
                       r["contact_std_mm"]), _ms(r["noncontact_mm"], r["noncontact_std_mm"])]
                      for r in tables.depth_by_range(main)],
                     units={"range": "mm", "total": "mm", "contact": "mm", "non-contact": "mm"})
    true = tables.pooled(main, "true_max_mm")
    contact = tables.pooled(main, "contact_mm")
    keep = np.isfinite(contact)
    report.add_figure("depth_by_range_plot", "Depth error in contact per ground-truth depth",
                      charts.error_by_range(true[keep], contact[keep], tables.DEPTH_RANGES_MM,
                                            value_name="deepest cell", value_unit="mm", error_name="MAE in contact",
                                            error_unit="mm"))


def _tracking_section(report: Report, ev: Evaluation) -> None:
    report.section("Marker tracking (Table I)", "tracking")
    rows = table_lost_tracks(ev.tracking)
    scales = sorted({r["patch_scale"] for r in rows})
    by = {(r["tracker"], r["refine"], r["patch_scale"]): r for r in rows}
    cols = ["tracker", "refinement"] + [f"{s:g}x" for s in scales]
    body = [[name, label] + [_ms(by[key]["lost_mean"], by[key]["lost_std"]) if (key := (tracker, refine, s)) in by
                             else None for s in scales]
            for tracker, name in TABLE1_TRACKERS.items() for refine, label in ((True, "yes"), (False, "no"))]
    report.add_table("table1", "Lost tracks per sequence per patch size", cols, body,
                     caption="Start-end drift above 15 px (the paper's metric), mean ± std over recordings; patch size "
                             "as a multiple of the marker diameter. The paper: 4.4, 3.1, 2.8, 3.0, 5.0 with refinement; "
                             "8.7, 3.8, 3.2, 3.9, 5.2 without.")
    if any(r["error_p95_px_mean"] is not None for r in rows):
        report.add_table("tracking_truth", "Beyond the paper: true tracking error (virtual rig)",
                         ["tracker", "refinement", "patch", "p95 error", "lost by truth", "tracker time"],
                         [[TABLE1_TRACKERS.get(r["tracker"], r["tracker"]), r["refine"], r["patch_scale"],
                           r["error_p95_px_mean"], r["lost_by_truth_mean"], r["track_ms_median"]] for r in rows],
                         units={"patch": "x diameter", "p95 error": "px", "tracker time": "ms"},
                         caption="Against the sim's marker truth at each window's end; 'lost by truth': markers ever "
                                 "more than 15 px off.")


def _runtime_section(report: Report, ev: Evaluation) -> None:
    report.section("Runtime", "runtime")
    stages = ("read", "sae", "track", "depth", "displacement", "forces")
    row = tables.runtime_row(ev.forces, stages)
    report.add_table("runtime", "Per-stage latency per window (median over recordings)",
                     [*stages, "total", "rate"], [[row[f"{s}_ms"] for s in stages] + [row["total_ms"], row["rate_hz"]]],
                     units={**{s: "ms" for s in stages}, "total": "ms", "rate": "Hz"},
                     caption="Stages run in turn here; `labrig run` overlaps tracking with depth and forces.")
    report.add_figure("runtime_plot", "Per-stage latency",
                      charts.runtime_bars({s: [r["stage_ms"][s] for r in ev.forces] for s in stages}))


def _labels_section(report: Report, ev: Evaluation) -> None:
    report.section("Ground-truth labels against the sim's truth", "labels")
    rows = []
    for elastic in ("layer", "halfspace"):
        group = [r for r in ev.labels if r and r["elastic"] == elastic]
        if group:
            rows.append([elastic, MeanStd.of([r["mae_contact_mm"] for r in group]),
                         MeanStd.of([r["mae_noncontact_mm"] for r in group]),
                         MeanStd.of([r["p95_noncontact_mm"] for r in group]), MeanStd.of([r["mask_iou"] for r in group])])
    report.add_table("label_errors", "Label error per elastic model", ["model", "in contact", "out of contact",
                                                                        "p95 out", "mask IoU"], rows,
                     units={"in contact": "mm", "out of contact": "mm", "p95 out": "mm"},
                     caption="Maps made from what a lab has (CNC pose, registration, calibration, fitted modulus) against "
                             "the sim's true normal displacement, frames in contact, mean ± std over recordings.")
