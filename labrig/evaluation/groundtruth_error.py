"""How wrong the labels are: ground-truth maps of each elastic model against the sim's true normal displacement.

Beyond the paper (which could not measure it): for a simulated recording, the maps
``labrig groundtruth`` makes from what a lab has (CNC pose, registration, calibration,
fitted modulus) are compared with ``/truth/depth`` on the same grid at the frames where
the indenter touches the gel, the truth between two solves blended linearly in time
(:func:`~labrig.pipeline.depth_sources.truth_between`). The truth is read here only; the
generator never reads it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labrig.config import DEFAULT_CALIBRATION_DIR
from labrig.errors import LabrigError
from labrig.groundtruth import generate, lab_inputs
from labrig.groundtruth.inputs import recording_rig
from labrig.pipeline.depth_sources import truth_between
from labrig.recording import Recording
from labrig.sim.motion import true_gel_in_machine

#: The gel poses labels can be made with (:class:`GroundTruthErrorTask`).
LABEL_POSES = ("lab", "true")


@dataclass(frozen=True)
class GroundTruthErrorTask:
    """One simulated recording, one elastic model ("layer" or "halfspace"), one gel pose.

    ``pose``: "lab" (the registration in ``calibration_dir``, else the nominal pose) or "true"
    (the sim's own pose: a perfect registration)."""

    recording: str
    elastic: str = "layer"
    pose: str = "lab"
    calibration_dir: str | None = DEFAULT_CALIBRATION_DIR


@dataclass(frozen=True)
class GroundTruthErrorResult:
    """One elastic model's labels against the sim's truth on one recording, over the frames in contact (mm)."""

    indenter: str
    elastic: str  # "layer" or "halfspace"
    method: str  # the contact solution the generator chose
    pose: str  # "lab" or "true"
    frames: int  # frames in contact
    mae_contact_mm: float  # inside the true contact
    mae_noncontact_mm: float  # outside it
    p95_noncontact_mm: float
    mae_total_mm: float
    mask_iou: float  # the labels' contact mask against the true one
    indentation_error_max_mm: float
    maps_per_s: float  # the generator's rate


def evaluate_groundtruth(task: GroundTruthErrorTask) -> GroundTruthErrorResult:
    """MAE (mm) in and out of the true contact, p95 out of contact, total, the masks' IoU, the
    indentation error and the generation rate (maps per second), over frames in contact."""
    with Recording(task.recording) as rec:
        if "truth/depth" not in rec.streams or rec.rows("truth/depth") == 0:
            raise LabrigError(f"{task.recording}: no /truth/depth; label errors need a virtual-rig recording")
        truth = rec.stream("truth/depth")
        contact = rec.stream("truth/contact")
        rig, _ = recording_rig(str(rec.attrs.get("rig", "")))
        indenter = str(rec.attrs.get("indenter", ""))
    lab = None
    if task.pose == "true":
        lab = lab_inputs(rig, task.calibration_dir, gel_pose=true_gel_in_machine(rig))
    elif task.pose != "lab":
        raise LabrigError(f"pose must be 'lab' or 'true', not {task.pose!r}")
    gt = generate(task.recording, elastic=task.elastic, lab=lab, calibration_dir=task.calibration_dir)
    before, after, w = truth_between(truth["t_host_us"], gt.t_us)  # the sim's truth between its solves
    maps = truth["depth_mm"].astype(np.float32)
    true_depth = maps[before] * (1.0 - w[:, None, None]).astype(np.float32) + maps[after] * w[:, None, None].astype(np.float32)
    true_mask = truth["contact_mask"][np.where(w < 0.5, before, after)].astype(bool)
    true_indentation = np.interp(gt.t_us, contact["t_host_us"], contact["indentation_mm"])
    frames = true_indentation > 0
    if not frames.any():
        raise LabrigError(f"{task.recording}: the indenter never touches the gel")
    err = np.abs(gt.depth_mm[frames] - true_depth[frames])
    inside, outside = true_mask[frames], ~true_mask[frames]
    ours = gt.contact_mask[frames].astype(bool)
    return GroundTruthErrorResult(
        indenter=indenter, elastic=task.elastic, method=str(gt.attrs["contact_model"]), pose=task.pose,
        frames=int(frames.sum()), mae_contact_mm=float(err[inside].mean()), mae_noncontact_mm=float(err[outside].mean()),
        p95_noncontact_mm=float(np.percentile(err[outside], 95)), mae_total_mm=float(err.mean()),
        mask_iou=float((ours & inside).sum() / max(int((ours | inside).sum()), 1)),
        indentation_error_max_mm=float(np.abs(gt.indentation_mm[frames] - true_indentation[frames]).max()),
        maps_per_s=float(gt.t_us.size / gt.seconds))


evaluate_groundtruth.cache_version = "2"  # type: ignore[attr-defined]  # 2: the truth between solves (was the last)
