"""The nominal rig geometry: where the gel sits in the machine frame by design.

Machine frame: the CNC's work coordinates (mm) of the tool-tip reference.
Gel frame: origin at the centre of the undeformed gel surface, x along the
marker columns, y along the rows, z out of the gel (mm). A pose maps gel
points into machine coordinates, ``p_machine = R @ p_gel + t``.

The nominal pose is the rig file's ``[rig]`` section (yaw only); the rig
registration (:mod:`labrig.calibration.registration`) measures the real one,
and the virtual rig's true pose (with tilt) is the simulator's business.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig
from labrig.frames import Pose, yaw_tilt_matrix


def gel_frame(origin_machine_mm: npt.ArrayLike, yaw_deg: float, tilt_deg: tuple[float, float] = (0.0, 0.0)) -> Pose:
    """The gel frame in machine coordinates from its origin (machine mm), yaw about z and tilts about x, y (deg)."""
    return Pose(yaw_tilt_matrix(yaw_deg, tilt_deg), np.asarray(origin_machine_mm, float))


def nominal_gel_in_machine(rig: RigConfig) -> Pose:
    """The gel frame in machine coordinates as designed: ``[rig] gel_origin_machine_mm`` and ``gel_yaw_deg``."""
    return gel_frame(rig.rig.gel_origin_machine_mm, rig.rig.gel_yaw_deg)
