"""Small closed-form fits of the rig registration: a rigid pose, the F/T sensor's axes, yaw and tilt.

Frames: the gel frame (origin at the surface centre, x along the marker
columns, z out of the gel) and the machine frame (tool tip, mm); the F/T
sensor's axes are unit vectors. Pure numpy.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from labrig.errors import CalibrationError
from labrig.frames import Pose, rotvec_to_matrix

F64 = npt.NDArray[np.float64]


def kabsch(gel_points: F64, machine_points: F64) -> Pose:
    """The rigid pose with ``machine ~= R @ gel + t`` (least squares, proper rotation; points in mm)."""
    a, b = np.asarray(gel_points, float), np.asarray(machine_points, float)
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return Pose(r, cb - r @ ca)


def yaw_tilt_of(rotation: F64) -> tuple[float, tuple[float, float]]:
    """(yaw, (tilt about x, tilt about y)) in degrees with ``yaw_tilt_matrix(yaw, tilt) == rotation``."""
    r = np.asarray(rotation, float)
    tx = np.arctan2(r[2, 1], np.hypot(r[2, 0], r[2, 2]))
    ty = np.arctan2(-r[2, 0], r[2, 2])
    rz = r @ (rotvec_to_matrix([tx, 0, 0]) @ rotvec_to_matrix([0, ty, 0])).T
    yaw = np.arctan2(rz[1, 0], rz[0, 0])
    return float(np.degrees(yaw)), (float(np.degrees(tx)), float(np.degrees(ty)))


def fit_ft_axes(gel_dirs: F64, ft_dirs: F64, weights: F64 | None = None) -> F64:
    """The F/T sensor's axes in the gel frame (columns: sensor x, y, z in gel axes) from unit directions
    known in the gel frame and measured in sensor axes: ``ft = A.T @ gel`` (Wahba, SVD)."""
    g, f = np.asarray(gel_dirs, float), np.asarray(ft_dirs, float)
    w = np.ones(len(g)) if weights is None else np.asarray(weights, float)
    u, _, vt = np.linalg.svd((f * w[:, None]).T @ g)
    d = np.sign(np.linalg.det(u @ vt))
    at = u @ np.diag([1.0, 1.0, d]) @ vt  # maps gel -> sensor
    return at.T


def axis_map(axes_in_gel: F64) -> tuple[F64, list[str]]:
    """The signed permutation nearest to the sensor axes (e.g. ["+x", "-y", "-z"]: sensor x along gel +x ...)."""
    a = np.asarray(axes_in_gel, float)
    perm = np.zeros((3, 3))
    names = []
    for col in range(3):
        row = int(np.argmax(np.abs(a[:, col])))
        sign = 1.0 if a[row, col] > 0 else -1.0
        perm[row, col] = sign
        names.append(("+" if sign > 0 else "-") + "xyz"[row])
    if sorted(n[1] for n in names) != ["x", "y", "z"]:
        raise CalibrationError(f"the F/T axes do not map onto the gel axes one to one ({names}): "
                               "check the sensor's mounting and the shear data")
    return perm, names
