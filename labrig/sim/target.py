"""The intrinsic-calibration scene: a planar dot-grid target seen by the camera on the whole sensor.

The target and its frame are :mod:`labrig.physics.target`; a pose
``target_to_camera`` places it in front of the camera. Each dot is drawn like
a marker (:mod:`labrig.sim.discs`): an anti-aliased ellipse centred on the projection of the dot's centre through
the same camera model (with distortion), so the dot's intensity centroid is
the projected point. (A real dot's image centroid is off the projected centre
by a small perspective bias; the sim leaves it out so that calibration has an
exact truth.) Intensity is linear in [0, 1], on the full sensor.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from labrig.frames import Pose
from labrig.physics.camera import CameraModel
from labrig.physics.target import DotGridTarget
from labrig.sim.discs import ellipse_coverage, patch_half_px, patch_origins

Array = npt.NDArray[np.float64]


def render_target(camera: CameraModel, target: DotGridTarget, target_to_camera: Pose, *, edge_px: float = 1.0) -> Array:
    """Intensity image (height_px, width_px) of the target at this pose; dots behind the camera are left out."""
    points = target.points_mm()
    in_front = target_to_camera.apply(points)[:, 2] > 1e-6
    points = points[in_front]
    height, width = camera.height_px, camera.width_px
    image = np.full((height, width), target.plate_level)
    if points.shape[0] == 0:
        return image
    centres = camera.project(points, target_to_camera)
    axes = camera.jacobian_px_per_mm(points, target_to_camera)[..., :2] * (target.dot_diameter_mm / 2)
    half = patch_half_px(axes, edge_px, margin=1.0)
    origins = patch_origins(centres, half)
    side = 2 * half
    onscreen = (origins[:, 0] > -side) & (origins[:, 0] < width) & (origins[:, 1] > -side) & (origins[:, 1] < height)
    centres, axes, origins = centres[onscreen], axes[onscreen], origins[onscreen]
    coverage = ellipse_coverage(centres, axes, origins, half, edge_px)
    # Accumulate on a canvas grown by one patch side so no patch needs clipping.
    canvas = np.zeros((height + 2 * side, width + 2 * side))
    rows = (origins[:, 1] + side)[:, None, None] + np.arange(side)[None, :, None]
    cols = (origins[:, 0] + side)[:, None, None] + np.arange(side)[None, None, :]
    np.add.at(canvas, (np.broadcast_to(rows, coverage.shape), np.broadcast_to(cols, coverage.shape)), coverage)
    alpha = np.clip(canvas[side : side + height, side : side + width], 0.0, 1.0)
    return image + alpha * (target.dot_level - target.plate_level)
