"""The report of ``labrig evaluate``: its sections (Tables I-III, ranges, runtime, labels, sweep, stress) from an
:class:`labrig.evaluation.evaluate.Evaluation`."""

from __future__ import annotations

import platform
from pathlib import Path

import numpy as np

from labrig.evaluation import charts, tables
from labrig.evaluation.evaluate import PAPER, TABLE1_TRACKERS, Evaluation
from labrig.evaluation.hold import AFTER_RELEASE_S, EDGE_S, force_after_release_n, hold_summary
from labrig.evaluation.report import MeanStd, Report
from labrig.evaluation.stress import add_stress_to_report
from labrig.evaluation.sweep import add_sweep_to_report
from labrig.evaluation.tracking import table_lost_tracks


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
    _headline(report, ev)
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
        add_sweep_to_report(report, ev.sweep)
    if ev.stress is not None:
        add_stress_to_report(report, ev.stress)
    report.add_json("summary", ev.summary)
    return report


def _headline(report: Report, ev: Evaluation) -> None:
    """The answer first: each headline figure beside the paper's, and which is better."""
    h = ev.summary
    runtime = (f"on {h['runtime_cores']} cores, 1-min load {h['runtime_load_1min']:.1f} while timed"
               if h.get("runtime_load_1min") is not None else "")
    rows: list[list[object]] = []
    for label, key, paper_key, unit in (
            ("force x on the gel", "force_x_mae_n", "force_x_mae_n", "N"),
            ("force y on the gel", "force_y_mae_n", "force_y_mae_n", "N"),
            ("force z on the gel", "force_z_mae_n", "force_z_mae_n", "N"),
            ("depth, all cells", "depth_total_mm", "depth_total_mm", "mm"),
            ("depth, contact cells", "depth_contact_mm", "depth_contact_mm", "mm"),
            ("contact position", "position_total_mae_px", "position_total_mae_px", "px"),
            ("lost tracks per recording", "lost_tracks_per_sequence", "lost_tracks", ""),
            ("pipeline per window, median", "pipeline_window_ms_median", None, "ms"),
            ("pipeline per window, 95th percentile", "pipeline_window_ms_p95", None, "ms")):
        value = h.get(key)
        if value is None:
            continue
        paper = PAPER.get(paper_key) if paper_key else None
        verdict = "" if paper is None else ("better" if value < paper else "same" if value == paper else "worse")
        rows.append([label, value, paper, verdict, unit])
    report.add_table("headline", "The answer", ["figure", "labrig", "paper", "labrig is", "unit"], rows,
                     caption="Mean absolute errors over the evaluation windows (forces: the force on the gel, gel frame, "
                             "against the F/T sensor); the paper's values from its Tables I-III. The pipeline's time per "
                             f"window counts every stage in turn {runtime}; the paper's ~100 Hz is on a GPU.")


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
                             "over windows in the probing phases; position: the contact's anchor (each window's dent core, "
                             "the centre of mass of the depth above a fifth of the map's peak, filtered over the contact "
                             "with the network's noise: labrig.pipeline.anchor; the true depth's unfiltered) against the "
                             "contact centre where the indenter touched (CNC pose; the maps are indexed by the surface "
                             "at rest, so shear does not move it). Total: norm of the error vector. 'True depth' "
                             "(virtual-rig recordings): the same pipeline fed the sim's depth maps instead of the "
                             "network's, so what is left is tracking, the inverse FEM and the gel law.",
                     units={"force": "N", "position": "px", "paper force": "N",
                            **({"force, true depth": "N", "position, true depth": "px"} if truth else {})})
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
                      for r in tables.force_by_range(ev.forces) if r["windows"]],
                     caption="Under-prediction: mean of |measured| - |predicted| along the axis (positive: too small).",
                     units={"range": "N", "mae": "N", "under-prediction": "N"})
    report.add_table("force_by_indenter", "Force error per indenter",
                     ["indenter", "recordings", "x", "y", "z", "total", "position"],
                     [[r["indenter"], r["recordings"], r["force_x_mae_n"], r["force_y_mae_n"], r["force_z_mae_n"],
                       r["force_total_mae_n"], r["position_total_mae_px"]] for r in tables.force_by_indenter(ev.forces)],
                     caption="Table III's errors per indenter (the recording's own indenter name): shapes the network "
                             "never saw against the ones it trained on.",
                     units={"x": "N", "y": "N", "z": "N", "total": "N", "position": "px"})
    held = hold_summary(ev.forces)
    if held.presses:
        after = {r.recording: force_after_release_n(r) for r in ev.forces}
        report.add_table("hold", "Presses held",
                         ["recording", "wait", "held", "measured Fz", f"error first {EDGE_S:g} s",
                          f"error last {EDGE_S:g} s", "last / first", "Fz after release"],
                         [[p.recording, p.wait_index + 1, p.duration_s, p.measured_fz_n, p.fz_error_first_n,
                           p.fz_error_last_n, p.error_ratio_last_to_first, after.get(p.recording)]
                          for p in held.presses],
                         caption=f"Every wait of 10 s or more: the mean |predicted - measured| Fz over the windows "
                                 f"ending in its first and in its last {EDGE_S:g} s (a ratio above 1: the estimate "
                                 f"forgets the dent), and the mean |predicted Fz| {AFTER_RELEASE_S[0]:g}-"
                                 f"{AFTER_RELEASE_S[1]:g} s after Normal Up ends, when the gel is at rest. Pooled: "
                                 f"{held.fz_error_first_n:.3f} N first, {held.fz_error_last_n:.3f} N last "
                                 f"(ratio {held.error_ratio_last_to_first:.2f}), {held.after_release_fz_n:.3f} N "
                                 f"after the release.",
                         units={"held": "s", "measured Fz": "N", f"error first {EDGE_S:g} s": "N",
                                f"error last {EDGE_S:g} s": "N", "Fz after release": "N"})
        longest = max(held.presses, key=lambda p: p.duration_s)
        holder = next(r for r in ev.forces if r.recording == longest.recording)
        report.add_figure("hold_series", "Force over the longest held press",
                          charts.time_series(holder.t1_us / 1e6, holder.measured_n, holder.predicted_n, unit="N",
                                             phases=[(n, a / 1e6, b / 1e6) for n, a, b in holder.phases]),
                          caption=f"{longest.recording}: measured (F/T sensor) and predicted force on the gel; "
                                  f"its wait {longest.wait_index + 1} lasts {longest.duration_s:.0f} s.")
    if ev.control:
        _control_section(report, ev)
    example = max(ev.forces, key=lambda r: float(np.max(np.abs(r.measured_n[:, 2]))) if len(r.measured_n) else 0)
    t_s = example.t1_us / 1e6
    report.add_figure("force_series", "Net force over a recording (largest normal force)",
                      charts.time_series(t_s, example.measured_n, example.predicted_n, unit="N"),
                      caption="Measured (F/T sensor) and predicted (summed per-marker forces) force on the gel.")
    if any(np.isfinite(r.marker_mae_n).any() for r in ev.forces):
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
    missing: list[str] = []
    for (loss, window), model in ev.table2_models.items():
        if model is None:
            if loss == "contact" and window == 10.0 and str(ev.model) in ev.depth:
                model = str(ev.model)
            else:
                missing.append(f"{loss} {window:g} ms")
                continue
        row = tables.depth_row(ev.depth[model])
        rows.append([loss, window, Path(model).stem, _ms(row["total_mm"], row["total_std_mm"]),
                     _ms(row["contact_mm"], row["contact_std_mm"]), _ms(row["noncontact_mm"], row["noncontact_std_mm"])])
    report.add_table("table2", "Depth error per window and loss", ["loss", "window", "model", "total", "contact",
                                                                     "non-contact"], rows,
                     caption="Mean ± std over evaluation windows; each network sees its own trained window ending at the "
                             "evaluation time." + (f" Not shown, no network for them in --models: {', '.join(missing)}."
                                                   if missing else ""),
                     units={"window": "ms", "total": "mm", "contact": "mm", "non-contact": "mm"})
    main = ev.depth[str(ev.model)]
    report.add_table("depth_by_range", f"Depth error per ground-truth depth range ({ev.model.stem})",
                     ["range", "windows", "total", "contact", "non-contact"],
                     [[r["range_mm"], r["windows"], _ms(r["total_mm"], r["total_std_mm"]), _ms(r["contact_mm"],
                       r["contact_std_mm"]), _ms(r["noncontact_mm"], r["noncontact_std_mm"])]
                      for r in tables.depth_by_range(main) if r["windows"]],
                     units={"range": "mm", "total": "mm", "contact": "mm", "non-contact": "mm"})
    true = tables.pooled(r.true_max_mm for r in main)
    contact = tables.pooled(r.contact_mm for r in main)
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
            for tracker in ev.settings.trackers for name in [TABLE1_TRACKERS[tracker]]
            for refine, label in ((True, "yes"), (False, "no"))]
    report.add_table("table1", "Lost tracks per sequence per patch size", cols, body,
                     caption="Start-end drift above 15 px (the paper's metric), mean ± std over recordings; patch size "
                             "as a multiple of the marker diameter. The paper: 4.4, 3.1, 2.8, 3.0, 5.0 with refinement; "
                             "8.7, 3.8, 3.2, 3.9, 5.2 without." + (
                                 " Evetac's published tracker has a fixed ring band: one setting, under the first "
                                 "patch size." if "evetac" in ev.settings.trackers else ""))
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
                      charts.runtime_bars({s: [r.stage_ms[s] for r in ev.forces] for s in stages}))


POSE_LABELS = {"lab": "registered", "true": "true (the sim's)"}


def _labels_section(report: Report, ev: Evaluation) -> None:
    report.section("Ground-truth labels against the sim's truth", "labels")
    rows = []
    poses = [p for p in ("lab", "true") if any(r and r.pose == p for r in ev.labels)]
    for pose in poses:
        for elastic in ("layer", "halfspace"):
            group = [r for r in ev.labels if r and r.elastic == elastic and r.pose == pose]
            if group:
                rows.append([elastic, POSE_LABELS[pose], MeanStd.of([r.mae_contact_mm for r in group]),
                             MeanStd.of([r.mae_noncontact_mm for r in group]),
                             MeanStd.of([r.p95_noncontact_mm for r in group]), MeanStd.of([r.mask_iou for r in group])])
    report.add_table("label_errors", "Label error per elastic model and gel pose",
                     ["model", "gel pose", "in contact", "out of contact", "p95 out", "mask IoU"], rows,
                     units={"in contact": "mm", "out of contact": "mm", "p95 out": "mm"},
                     caption="Maps made from what a lab has (CNC pose, registration, calibration, fitted modulus) against "
                             "the sim's true normal displacement, frames in contact, mean ± std over recordings. "
                             "Gel pose: the registration's, or the sim's own (a perfect registration: "
                             "`--label-poses lab,true`).")


def _control_section(report: Report, ev: Evaluation) -> None:
    """The recordings whose normal force a force loop held: the step and the hold, the F/T as the reference."""
    report.add_table("control", "Forces held by the loop",
                     ["recording", "feedback", "target", "rise", "overshoot", "settling", "hold RMS (F/T)",
                      "hold RMS (estimate)", "reading scatter", "loop rate", "slip told - onset", "slip cue"],
                     [[r.recording, r.feedback, r.target_n, r.step_rise_s, r.step_overshoot_pct, r.step_settling_s,
                       r.hold_rms_n_ft, r.hold_rms_n_estimate, r.reading_scatter_n, r.loop_hz, r.slip_onset_error_ms,
                       r.slip_cue]
                      for r in ev.control],
                     caption="Runs with a held press or shear: the held Normal Down as a step from contact to the "
                             "target (10-90 % rise, overshoot, settling into 5 %, of the F/T's |Fz|), and the RMS "
                             "from the target over the held waits and shears of the F/T's |Fz| and of the "
                             "pipeline's estimate (what the event sensor would have fed the loop); the scatter of "
                             "the loop's readings less the F/T about their mean in each held wait and shear (1 sigma: "
                             "what [control] reading_noise_n stands for); with a slip "
                             "reflex, when it told slip in Shear less when the whole contact truly began to slide "
                             "(the virtual rig's truth; negative: told before), and the cue that told it.",
                     units={"target": "N", "rise": "s", "overshoot": "%", "settling": "s", "hold RMS (F/T)": "N",
                            "hold RMS (estimate)": "N", "reading scatter": "N", "loop rate": "Hz",
                            "slip told - onset": "ms"})
    run = ev.control[0]
    forces = next((r for r in ev.forces if r.recording == run.recording), None)
    has_estimate = forces is not None and len(forces.t1_us) > 0
    t_estimate_s = (forces.t1_us - run.origin_us) / 1e6 if forces is not None and has_estimate else None
    estimate_n = np.abs(forces.predicted_n[:, 2]) if forces is not None and has_estimate else None
    report.add_figure("control_series", "A force held by the loop",
                      charts.held_force(run.t_s, run.ft_fz_n, run.target_series_n, t_estimate_s=t_estimate_s,
                                        estimate_n=estimate_n, phases=run.phases_s),
                      caption=f"{run.recording}: the F/T's |Fz| (the reference), the target the loop held "
                              f"({run.feedback} feedback) and the pipeline's estimate; time from the first held "
                              "phase's start.")
