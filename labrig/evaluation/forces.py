"""Force error of the whole pipeline on one recording: summed per-marker forces against the F/T sensor.

Per evaluation window (sequential 20,000-event windows by default) the pipeline tracks the
markers on the window's events, the depth network sees its own trained window ending at the
window's end, and the inverse FEM gives the per-marker forces. Their sum is compared with
the F/T sensor's force over the depth window (tared, rotated into the gel frame by the rig
registration, as the force on the gel), the depth map's dent core with the true contact
centre (where the indenter touched, from the CNC pose), and, on the virtual rig, each marker's force with
the sim's ``/truth/marker_forces``.

Missing markers (never printed) have NaN rows in the sim's field: the net truth sums the
printed markers' cells (which tile the marker area, so it is still the whole force) and
the per-marker error is the mean over the markers with truth; the missing ones are counted
(``markers_missing``), as are the markers the pipeline did not observe (``markers_unobserved``,
the calibration's missing markers, whose forces the inverse FEM condenses out).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from labrig.config import DEFAULT_CALIBRATION_DIR
from labrig.dataset import sidecar_path
from labrig.evaluation.measured import contact_centre_px, ft_axes_in_gel, measured_force_on_gel_n
from labrig.groundtruth import load_groundtruth
from labrig.pipeline import depth_sources, ifem, run_setup, runtime, tracking
from labrig.pipeline.windows import PAPER_WINDOW_EVENTS, window_ends_us
from labrig.recording import Recording

PROBING_PHASES = ("normal_down", "wait", "shear", "shear_opposite", "normal_up")
F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ForceTask:
    """One recording through the pipeline. ``depth``: "truth" (the sim's map) or an .onnx network."""

    recording: str
    depth: str
    window_events: int | None = PAPER_WINDOW_EVENTS
    window_us: int | None = None
    calibration_dir: str | None = DEFAULT_CALIBRATION_DIR
    youngs_modulus_mpa: float | None = None
    stiffening: float | None = None  # None: the calibrated gel's (gel.toml); 0: a linear gel, the paper's
    patch_scale: float = 3.0
    refine_lambda: float = 0.2
    surface_refinement: int = 2
    depth_window_ms: float = 10.0  # for depth="truth": the F/T averaging window
    sidecar: str = ""  # the ground truth for the indenter's position (default NAME.gt.h5 beside the recording)
    quiet_hold: bool = True  # the network's quiet-window hold (labrig.pipeline.quiet); False feeds it every window
    rest_gate: bool = True  # the rest gate as the network's card asks (labrig.pipeline.depth_sources.rest_params_for); False: off


@dataclass(frozen=True)
class ForceResult:
    """The pipeline's forces on one recording and their errors, per evaluation window (W windows, M markers).

    Forces are the force on the gel in the gel frame, N.
    """

    t0_us: npt.NDArray[np.int64]  # (W,) window starts, host us
    t1_us: npt.NDArray[np.int64]  # (W,) window ends, host us
    predicted_n: F64  # (W, 3) summed per-marker forces
    measured_n: F64  # (W, 3) the F/T sensor over the depth window
    truth_n: F64  # (W, 3) the sim's net force; nan on hardware
    contact_error_px: F64  # (W, 2) predicted - true contact position; nan where either is missing
    marker_mae_n: F64  # (W, 3) per-marker MAE against the sim's field; nan on hardware
    probing: npt.NDArray[np.bool_]  # (W,) window ends inside the probing phases
    stage_ms: dict[str, float]  # stage -> median time per window, ms
    total_ms: float  # median time of all stages per window, ms
    drift_px: F64  # (M,) start-end drift of each marker, px
    ft_axes: str  # where the F/T axes in the gel frame came from
    depth_source: str  # "truth" or the network's name
    youngs_modulus_mpa: float  # the gel modulus the inverse FEM used
    markers_missing: int = 0  # markers without truth (NaN in the sim's field), left out of ``marker_mae_n``
    markers_unobserved: int = 0  # markers the pipeline skipped (missing in the calibration)
    # The pipeline's own depth maps (its state carried window to window) against the ground truth nearest
    # in time: mean |error| over the grid and over the true contact cells, mm; nan without a sidecar or contact.
    depth_mae_mm: F64 = field(default_factory=lambda: np.zeros(0))  # (W,)
    depth_contact_mae_mm: F64 = field(default_factory=lambda: np.zeros(0))  # (W,)
    indenter: str = ""  # the recording's indenter (its name in the indenters file)
    window_ms: F64 = field(default_factory=lambda: np.zeros(0))  # (W,) processing time of each window, all stages
    #: The machine while the windows were timed: its cores and its 1-minute load average at the end.
    cores: int = 0
    load_1min: float = float("nan")
    recording: str = ""  # the recording's file name
    #: The recording's phases: (name, start, end), host us, in the order they ran.
    phases: tuple[tuple[str, int, int], ...] = ()


def evaluate_forces(task: ForceTask) -> ForceResult:
    """Per-window forces and errors of the pipeline on ``task.recording``."""
    from dataclasses import replace

    path = Path(task.recording)
    with Recording(path) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=task.calibration_dir,
                                              youngs_modulus_mpa=task.youngs_modulus_mpa, stiffening=task.stiffening)
        source = depth_sources.depth_source("truth" if task.depth == "truth" else "model", setup, rec,
                                            None if task.depth == "truth" else task.depth,
                                            quiet="auto" if task.quiet_hold else None,
                                            rest="auto" if task.rest_gate else None)
        params = replace(tracking.TrackerParams(marker_diameter_px=tracking.marker_diameter_px(setup.rig, setup.camera)),
                         patch_scale=task.patch_scale, refine_lambda=task.refine_lambda)
        pipe = runtime.Pipeline(setup, source, tracker_params=params,
                                surface_params=ifem.SurfaceParams(refinement=task.surface_refinement))
        t0, t1 = window_ends_us(rec, window_events=task.window_events, window_us=task.window_us)
        rows = [pipe.process(int(a), int(b), rec.events_between(a, b)) for a, b in zip(t0, t1)]
        depth_window_us = source.window_us or task.depth_window_ms * 1000.0
        rotation, ft_source = ft_axes_in_gel(rec, task.calibration_dir)
        measured = measured_force_on_gel_n(rec, t1 - depth_window_us, t1, rotation)
        truth_n, marker_mae, missing = _truth(rec, t1, np.array([r.forces_n for r in rows]))
        probing = _in_phases(rec, t1)
        indenter = str(rec.attrs.get("indenter", ""))
        has_phases = "phases" in rec.streams and rec.rows("phases")
        phases = tuple((p.name, p.t_start_us, p.t_end_us) for p in rec.phases()) if has_phases else ()
    predicted = np.array([r.net_force_n for r in rows]).reshape(-1, 3)
    contact_px = np.array([r.contact_px for r in rows]).reshape(-1, 2)
    side = Path(task.sidecar) if task.sidecar else sidecar_path(path)
    depth_mae, depth_contact = np.full(len(t1), np.nan), np.full(len(t1), np.nan)
    if side.exists():
        gt = load_groundtruth(side)
        true_px = contact_centre_px(gt, t1, setup.camera)
        nearest = np.atleast_1d(gt.nearest_index(t1))
        touching = np.atleast_1d(gt.contact_mask[nearest].reshape(len(t1), -1).any(1))
        true_px[~touching] = np.nan
        for k, (r, i) in enumerate(zip(rows, nearest)):
            error = np.abs(r.depth_mm - gt.depth_mm[i])
            mask = gt.contact_mask[i].astype(bool)
            depth_mae[k] = float(error.mean())
            depth_contact[k] = float(error[mask].mean()) if mask.any() else np.nan
    else:
        true_px = np.full((len(t1), 2), np.nan)
    stage_ms = {stage: float(np.median([r.seconds.get(stage, 0.0) for r in rows]) * 1e3) if rows else float("nan")
                for stage in runtime.STAGES}
    final = rows[-1].positions_px if rows else setup.rest_px
    return ForceResult(
        t0_us=t0, t1_us=t1, predicted_n=predicted, measured_n=measured, truth_n=truth_n,
        contact_error_px=contact_px - true_px, marker_mae_n=marker_mae, probing=probing, stage_ms=stage_ms,
        total_ms=float(np.median([sum(r.seconds.values()) for r in rows]) * 1e3) if rows else 0.0,
        drift_px=np.linalg.norm(final - setup.rest_px, axis=1), ft_axes=ft_source, depth_source=source.name,
        youngs_modulus_mpa=setup.youngs_modulus_mpa, markers_missing=missing,
        markers_unobserved=int((~setup.observed).sum()), depth_mae_mm=depth_mae, depth_contact_mae_mm=depth_contact,
        indenter=indenter, window_ms=np.array([sum(r.seconds.values()) * 1e3 for r in rows]),
        cores=os.cpu_count() or 0, load_1min=os.getloadavg()[0], recording=path.name, phases=phases)


evaluate_forces.cache_version = "23"  # type: ignore[attr-defined]  # 23: the release settles whatever the step length; 22: the marker diameter through the run's camera (was the sim's); 21: the recording's name and phases; 20: per-window times, the machine's load; 19: the recording's indenter; 18: the contrast thresholds weigh the brightness events; 17: the true depth between solves; 16: a surer core starts a new contact; 15: lopsided gates make their neighbours' moves (14: their displacement); 14: the tracker follows neighbours through lopsided gates, reports dots at the window end; 13: the contact anchor filter; 12: the tracker's polarity guard; 11: the contact is the dent's core; 3: quiet windows hold the map; 5: tile activity for noise-trained networks; 6: tracker background subtraction; 8: missing markers; 9: the rest gate, depth errors; 10: brightness networks (no hold, no gate)


def _truth(rec: Recording, t_us: npt.NDArray[np.int64], forces_n: npt.NDArray[np.float64]
           ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], int]:
    """The sim's net force and per-marker MAE (W, 3) at the solves nearest ``t_us``, nan without truth, and the
    count of markers without truth (missing: NaN columns), which both leave out."""
    nan = np.full((len(t_us), 3), np.nan)
    if "truth/marker_forces" not in rec.streams or rec.rows("truth/marker_forces") == 0:
        return nan, nan.copy(), 0
    t_truth = rec.column("truth/marker_forces", "t_host_us")
    index = np.clip(np.searchsorted(t_truth, t_us), 0, len(t_truth) - 1)
    before = np.clip(index - 1, 0, len(t_truth) - 1)
    index = np.where(np.abs(t_truth[before] - t_us) <= np.abs(t_truth[index] - t_us), before, index)
    field = rec.column("truth/marker_forces", "force_n")[index].astype(np.float64)  # (W, M, 3)
    present = np.isfinite(field).all(axis=(0, 2))
    if forces_n.size == 0 or not present.any():
        return nan, nan.copy(), int((~present).sum())
    return (field[:, present].sum(1), np.abs(forces_n[:, present] - field[:, present]).mean(1),
            int((~present).sum()))


def _in_phases(rec: Recording, t_us: npt.NDArray[np.int64]) -> npt.NDArray[np.bool_]:
    inside = np.zeros(len(t_us), bool)
    if "phases" not in rec.streams or rec.rows("phases") == 0:
        return ~inside
    for phase in rec.phases():
        if phase.name in PROBING_PHASES:
            inside |= (t_us >= phase.t_start_us) & (t_us < phase.t_end_us)
    return inside
