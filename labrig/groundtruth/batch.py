"""Ground truth for the recordings of a campaign folder: whether a sidecar is current, one sidecar as an
executor task (:func:`labrig.executor.run_tasks`), a plot of a few maps."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from labrig.cache import sha256_of
from labrig.dataset import DatasetRecording
from labrig.errors import LabrigError
from labrig.groundtruth.generate import generate
from labrig.groundtruth.inputs import GroundTruthError
from labrig.groundtruth.sidecar import FORMAT, load_groundtruth, write_sidecar
from labrig.indenters import DEFAULT_INDENTERS
from labrig.recording import Recording


def is_current(recording: DatasetRecording, settings: dict[str, Any]) -> bool:
    """The sidecar exists, belongs to this exact recording and was made with the same settings."""
    side = recording.sidecar
    if not side.exists():
        return False
    try:
        with h5py.File(side, "r") as f:
            attrs = dict(f.attrs)
    except OSError:
        return False
    if attrs.get("format") != FORMAT:
        return False
    sha = recording.sha256 or sha256_of(recording.path)
    if attrs.get("source_sha256") != sha:
        return False
    return all(_same(attrs.get(k), v) for k, v in settings.items())


def _same(a: Any, b: Any) -> bool:
    if isinstance(b, float):
        return a is not None and abs(float(a) - b) < 1e-9
    return bool(a == b)


def plot_groundtruth(recording: str | Path, gt_path: str | Path, out: str | Path, frames: int = 3) -> Path:
    """PNG: depth map, contact mask and the events of +-5 ms around a few frames (deepest, shear, release)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gt = load_groundtruth(gt_path)
    if not len(gt):
        raise GroundTruthError(f"{gt_path} holds no maps to plot")
    ind = gt.indentation_mm
    deepest = int(np.argmax(ind))
    half = np.flatnonzero(ind >= 0.5 * ind[deepest]) if ind[deepest] > 0 else np.array([deepest])
    picks = sorted({int(half[0]), deepest, int(half[-1])})[:frames]  # pressing, deepest, releasing
    x0, y0, x1, y1 = (int(v) for v in gt.attrs["roi_px"])
    rows, cols = gt.depth_mm.shape[1:]
    vmax = max(float(gt.depth_mm[picks].max()), 1e-3)
    fig, axes = plt.subplots(len(picks), 3, figsize=(11, 3.2 * len(picks)), squeeze=False)
    with Recording(recording) as rec:
        for r, i in enumerate(picks):
            t = float(gt.t_us[i])
            ev = rec.events_between(t - 5000, t + 5000)
            img = np.zeros((rows, cols))
            col = ((ev["x"].astype(np.float64) - x0 + 0.5) * cols / (x1 - x0)).astype(int)
            row = ((ev["y"].astype(np.float64) - y0 + 0.5) * rows / (y1 - y0)).astype(int)
            ok = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
            np.add.at(img, (row[ok], col[ok]), np.where(ev["p"][ok] > 0, 1.0, -1.0))
            a = axes[r]
            im = a[0].imshow(gt.depth_mm[i], cmap="viridis", vmin=min(0.0, float(gt.depth_mm[i].min())), vmax=vmax)
            fig.colorbar(im, ax=a[0], label="depth mm")
            a[0].set_title(f"t {t / 1e6:.2f} s, indentation {ind[i]:.2f} mm")
            a[1].imshow(gt.contact_mask[i], cmap="gray", vmin=0, vmax=1)
            a[1].set_title(f"contact ({int(gt.contact_mask[i].sum())} cells)")
            lim = max(float(np.abs(img).max()), 1.0)
            a[2].imshow(img, cmap="coolwarm", vmin=-lim, vmax=lim)
            a[2].set_title(f"events +-5 ms ({len(ev):,}; ON red, OFF blue)")
            for ax in a:
                ax.set_xticks([])
                ax.set_yticks([])
    fig.suptitle(f"{Path(recording).name}: {gt.attrs['elastic_model']} / {gt.attrs['contact_model']}, "
                 f"scale {gt.scale_mm} mm per unit (network grid {rows} x {cols} over the ROI)")
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


@dataclass(frozen=True)
class SidecarTask:
    """One recording's ground truth to write (plain values, so it travels to a worker process or a Dask worker)."""

    recording: str
    sidecar: str
    split: str
    elastic: str
    method: str
    rate_hz: float
    scale_mm: float
    calibration_dir: str | None
    rig_path: str | None
    indenters_path: str | None = None  # for recordings that do not carry their indenter's definition


def write_sidecar_task(task: SidecarTask) -> dict[str, Any]:
    """Generate and write one sidecar; returns its summary entry (``status`` ``written``, or
    ``failed`` with the reason for a recording that cannot be labelled)."""
    entry: dict[str, Any] = {"recording": task.recording, "split": task.split}
    try:
        gt = generate(task.recording, elastic=task.elastic, method=task.method, rate_hz=task.rate_hz,
                      scale_mm=task.scale_mm, calibration_dir=task.calibration_dir, rig_path=task.rig_path,
                      indenters_path=task.indenters_path or DEFAULT_INDENTERS)
        side = write_sidecar(gt, task.sidecar)
    except LabrigError as exc:
        entry.update(status="failed", reason=str(exc))
        return entry
    n = int(gt.t_us.size)
    duration_s = float(gt.t_us[-1] - gt.t_us[0]) / 1e6 if n > 1 else 0.0
    entry.update(status="written", sidecar=str(side), maps=n, seconds=round(gt.seconds, 3),
                 maps_per_s=round(n / gt.seconds, 1) if gt.seconds > 0 else None,
                 recording_s=round(duration_s, 3), elastic_model=gt.attrs["elastic_model"],
                 contact_model=gt.attrs["contact_model"],
                 max_indentation_mm=round(float(gt.indentation_mm.max(initial=0.0)), 4),
                 max_depth_mm=round(float(gt.depth_mm.max(initial=0.0)), 4),
                 camera_source=gt.attrs["camera_source"], gel_pose_source=gt.attrs["gel_pose_source"],
                 gel_source=gt.attrs["gel_source"], bytes=Path(side).stat().st_size)
    return entry
