"""The animated view of a pipeline run (``labrig run --view``): a GIF like the paper's figure 1.

Each frame: the window's SAE, the marker tracks, the depth map, then the x, y and normal force
per marker (N, on the gel, gel frame). matplotlib (Agg) is imported when a view is written.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from labrig.errors import LabrigError
from labrig.pipeline.run_setup import PipelineSetup
from labrig.pipeline.runtime import WindowResult


def _marker_grid(values: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Per-marker values (M,) as the marker grid (rows, cols), row-major as the rig numbers them."""
    return values.reshape(rows, cols)


def write_view(frames: Sequence[WindowResult], setup: PipelineSetup, path: Path, fps: int = 10) -> Path:
    """A GIF like the paper's figure 1: SAE, marker tracks, depth, then x, y and normal force per marker."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

    if not frames:
        raise LabrigError("nothing to animate")
    rig = setup.rig
    rows, cols = rig.markers.rows, rig.markers.cols
    roi = rig.roi
    extent_px = (roi.x0_px, roi.x1_px, roi.y1_px, roi.y0_px)
    fmax = max(float(np.abs(f.forces_n).max()) for f in frames) or 1.0
    shear_max = max(float(np.abs(f.forces_n[:, :2]).max()) for f in frames) or 1.0
    dmax = max(float(f.depth_mm.max()) for f in frames) or 1.0
    fig, axes = plt.subplots(2, 3, figsize=(11, 6.2), constrained_layout=True)
    (ax_sae, ax_track, ax_depth), (ax_fx, ax_fy, ax_fz) = axes
    first = frames[0]

    def sae_rgb(f: WindowResult) -> np.ndarray:
        s = np.zeros((*f.depth_mm.shape, 3), np.float32)
        if f.sae is not None:
            s[..., 0], s[..., 2] = f.sae[1], f.sae[0]  # ON red, OFF blue
        return s

    im_sae = ax_sae.imshow(sae_rgb(first), extent=extent_px, interpolation="nearest")
    ax_sae.set_title("SAE (ON red, OFF blue)")
    rest = setup.rest_px
    ax_track.scatter(rest[:, 0], rest[:, 1], s=4, c="0.7")
    tracks = ax_track.scatter(first.positions_px[:, 0], first.positions_px[:, 1], s=6, c="k")
    quiver = ax_track.quiver(rest[:, 0], rest[:, 1], *(first.positions_px - rest).T * 5, angles="xy",
                             scale_units="xy", scale=1, color="tab:red", width=0.004)
    ax_track.set_xlim(roi.x0_px, roi.x1_px)
    ax_track.set_ylim(roi.y1_px, roi.y0_px)
    ax_track.set_aspect("equal")
    ax_track.set_title("marker tracks (shift x5)")
    im_depth = ax_depth.imshow(first.depth_mm, extent=extent_px, cmap="viridis", vmin=0, vmax=dmax)
    ax_depth.set_title("depth, mm")
    fig.colorbar(im_depth, ax=ax_depth, shrink=0.8)
    maps = []
    for ax, comp, label, vmax, cmap in ((ax_fx, 0, "Fx, N", shear_max, "RdBu_r"), (ax_fy, 1, "Fy, N", shear_max, "RdBu_r"),
                                        (ax_fz, 2, "normal force -Fz, N", fmax, "magma")):
        values = -first.forces_n[:, 2] if comp == 2 else first.forces_n[:, comp]
        im = ax.imshow(_marker_grid(values, rows, cols), cmap=cmap, vmin=0 if comp == 2 else -vmax, vmax=vmax,
                       origin="upper", interpolation="nearest")
        ax.set_title(label)
        fig.colorbar(im, ax=ax, shrink=0.8)
        maps.append((im, comp))
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    title = fig.suptitle("")

    def update(i: int) -> list[Any]:
        f = frames[i]
        im_sae.set_data(sae_rgb(f))
        tracks.set_offsets(f.positions_px)
        quiver.set_UVC(*(f.positions_px - rest).T * 5)
        im_depth.set_data(f.depth_mm)
        for im, comp in maps:
            values = -f.forces_n[:, 2] if comp == 2 else f.forces_n[:, comp]
            im.set_data(_marker_grid(values, rows, cols))
        n = f.net_force_n
        title.set_text(f"t = {f.t1_us / 1e6:.3f} s   net force ({n[0]:+.2f}, {n[1]:+.2f}, {n[2]:+.2f}) N")
        return [im_sae, tracks, quiver, im_depth, title, *(m for m, _ in maps)]

    anim = FuncAnimation(fig, update, frames=len(frames), blit=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    anim.save(str(path), writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path
