"""Depth error of a network on one recording: per evaluation window, against the ground-truth sidecar.

At each window's end the network sees the SAE of its own trained window (model card
``window_ms``) ending there, and is compared with the sidecar's map nearest to the last
event of that window, as in training (``labrig.training.data``): depth clipped to
[0, scale], mean absolute error in mm over all cells, the contact cells and the rest.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from labrig.config import DEFAULT_CALIBRATION_DIR, Roi
from labrig.dataset import sidecar_path
from labrig.groundtruth import load_groundtruth
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline import depth_sources, run_setup, runtime
from labrig.pipeline.depthnet import DepthModel
from labrig.pipeline.sae import sae_grid
from labrig.pipeline.windows import PAPER_WINDOW_EVENTS, window_ends_us
from labrig.recording import Recording

BATCH = 32
F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class DepthTask:
    """One recording, one model. Windows: ``window_events`` events each, or ``window_us`` long."""

    recording: str
    model: str  # .onnx with its card
    window_events: int | None = PAPER_WINDOW_EVENTS
    window_us: int | None = None
    max_windows: int | None = None  # evenly thinned when there are more
    sidecar: str = ""  # the ground truth (default NAME.gt.h5 beside the recording); named so caches see it change
    calibration_dir: str | None = DEFAULT_CALIBRATION_DIR  # a stateful network's camera and markers (its pipeline run)


@dataclass(frozen=True)
class DepthResult:
    """Depth errors of one network on one recording, per evaluation window (W windows), against its sidecar.

    Errors are mean absolute errors over the map's cells, depth clipped to [0, scale], mm.
    """

    t_us: npt.NDArray[np.int64]  # (W,) evaluation times (window ends), host us
    total_mm: F64  # (W,) over all cells
    contact_mm: F64  # (W,) over the contact cells, nan without contact
    noncontact_mm: F64  # (W,) over the other cells, nan when all touch
    true_max_mm: npt.NDArray[np.floating]  # (W,) the ground-truth map's deepest cell
    contact_cells: npt.NDArray[np.int64]  # (W,) cells in contact
    gt_offset_us: npt.NDArray[np.int64]  # (W,) the map's time - the window's last event, us
    window_ms: float  # the network's trained window
    model: str  # the network's name
    infer_ms: float  # median inference time per window (batched), ms


def evaluate_depth(task: DepthTask) -> DepthResult:
    """Per-window depth errors (mm) of ``task.model`` on ``task.recording``."""
    import time

    model = DepthModel(task.model, threads=1)
    gt = load_groundtruth(Path(task.sidecar) if task.sidecar else sidecar_path(task.recording))
    roi = Roi(*(int(v) for v in gt.attrs["roi_px"]))
    scale = np.float32(gt.scale_mm)
    window_us = model.window_ms * 1000.0
    with Recording(task.recording) as rec:
        _, t1 = window_ends_us(rec, window_events=task.window_events, window_us=task.window_us)
        if task.max_windows is not None and t1.size > task.max_windows:
            t1 = t1[np.linspace(0, t1.size - 1, task.max_windows).round().astype(int)]
        saes = np.zeros((t1.size, 2, *GRID_SHAPE), np.float32)
        t_last = np.empty(t1.size)
        for k, end in enumerate(t1):
            events = rec.events_between(end - window_us, end)
            sae_grid(events, end - window_us, end, roi, GRID_SHAPE, out=saes[k])
            t_last[k] = float(events["t"].max()) if len(events) else float(end)
    pred = np.zeros((t1.size, *GRID_SHAPE), np.float32)
    seconds: list[float] = []
    if model.inputs.stateful:  # the state comes from the windows before: the whole pipeline, every window, in order
        pred, seconds = _pipeline_depth(task, t1)
    for start in range(0, t1.size if not model.inputs.stateful else 0, BATCH):
        tic = time.perf_counter()
        pred[start:start + BATCH] = model.depth_mm(saes[start:start + BATCH])
        seconds.append((time.perf_counter() - tic) / max(1, min(BATCH, t1.size - start)))
    index = np.atleast_1d(gt.nearest_index(t_last))
    true = np.clip(gt.depth_mm[index], 0.0, scale)
    contact = gt.contact_mask[index] > 0
    errors = per_map_errors_mm(pred, true, contact)
    return DepthResult(
        t_us=t1, total_mm=errors["total_mm"], contact_mm=errors["contact_mm"], noncontact_mm=errors["noncontact_mm"],
        true_max_mm=true.reshape(len(true), -1).max(1) if len(true) else np.zeros(0),
        contact_cells=contact.reshape(len(contact), -1).sum(1), gt_offset_us=gt.t_us[index] - t_last,
        window_ms=model.window_ms, model=model.name, infer_ms=float(np.median(seconds) * 1e3) if seconds else float("nan"))


evaluate_depth.cache_version = "9"  # type: ignore[attr-defined]  # 9: the release settles whatever the step length; 8: the marker diameter through the run's camera; 7: the contrast thresholds weigh the brightness events; 6: neighbours' moves; 5: the tracker (rest gate, displacement inputs); 2: stateful networks through the pipeline; 3: brightness networks (no hold, no gate); 4: the force evaluation's windows


def _pipeline_depth(task: DepthTask, t1_us: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.float32], list[float]]:
    """A stateful network's maps (W, 90, 112) at the window ends ``t1_us`` (a subset of the recording's windows):
    the pipeline (tracker, the depth source from the one builder) over every window of :func:`window_ends_us`
    (the windows of the force evaluation, from the first event, which precedes host time 0 in a recording made
    through the drivers), and its depth seconds."""
    with Recording(task.recording) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=task.calibration_dir)
        pipe = runtime.Pipeline(setup, depth_sources.depth_source("model", setup, rec, task.model))
        maps = {}
        for a, b in zip(*window_ends_us(rec, window_events=task.window_events, window_us=task.window_us)):
            r = pipe.process(int(a), int(b), rec.events_between(a, b))
            maps[int(b)] = (r.depth_mm, r.seconds.get("depth", 0.0))
    pred = np.stack([maps[int(t)][0] for t in t1_us]) if len(t1_us) else np.zeros((0, *GRID_SHAPE), np.float32)
    return pred.astype(np.float32), [maps[int(t)][1] for t in t1_us]


def per_map_errors_mm(pred_mm: npt.NDArray[np.floating], true_mm: npt.NDArray[np.floating],
                      contact: npt.NDArray[np.bool_]) -> dict[str, npt.NDArray[np.float64]]:
    """Per map: MAE over all cells, over the contact cells (nan if none), over the rest (nan if none), mm."""
    n = len(pred_mm)
    err = np.abs(np.asarray(pred_mm, np.float64) - np.asarray(true_mm, np.float64)).reshape(n, -1)
    c = np.asarray(contact, bool).reshape(n, -1)
    n_c, n_nc = c.sum(1), (~c).sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        contact_mm = np.where(n_c > 0, (err * c).sum(1) / n_c, np.nan)
        noncontact_mm = np.where(n_nc > 0, (err * ~c).sum(1) / n_nc, np.nan)
    return {"total_mm": err.mean(1) if n else np.zeros(0), "contact_mm": contact_mm, "noncontact_mm": noncontact_mm}
