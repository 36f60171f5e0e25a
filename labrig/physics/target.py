"""The intrinsic-calibration target's geometry: a planar grid of dots.

Target frame: origin at the grid's centre, x along the dot columns, y along
the rows, z normal to the plate; mm. A pose ``target_to_camera`` (a
:class:`labrig.frames.Pose`, ``p_cam = R p_target + t``) places it in front
of the camera. The virtual rig draws it in its calibration scene; the
intrinsic calibration fits the camera to its dots.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.frames import Pose, rotvec_to_matrix

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class DotGridTarget:
    """A rows x cols grid of bright dots (pitch, diameter in mm) on a dark plate (levels: linear intensity in [0, 1])."""

    rows: int = 9
    cols: int = 15
    pitch_mm: float = 2.0
    dot_diameter_mm: float = 0.8
    plate_level: float = 0.05
    dot_level: float = 0.9

    def points_mm(self) -> Array:
        """(rows*cols, 3) dot centres in the target frame (z = 0), row-major from -y, -x."""
        cols, rows = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        x = (cols.ravel() - (self.cols - 1) / 2) * self.pitch_mm
        y = (rows.ravel() - (self.rows - 1) / 2) * self.pitch_mm
        return np.stack([x, y, np.zeros_like(x)], axis=1)


def target_pose(rotvec_rad: npt.ArrayLike, translation_mm: npt.ArrayLike) -> Pose:
    """The target frame in the camera frame from a Rodrigues vector (rad) and a translation (mm)."""
    return Pose(rotvec_to_matrix(rotvec_rad), np.asarray(translation_mm, dtype=np.float64))
