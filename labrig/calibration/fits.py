"""Small closed-form fits of the rig registration: a rigid pose, the F/T sensor's axes, yaw and tilt.

Frames: the gel frame (origin at the surface centre, x along the marker
columns, z out of the gel) and the machine frame (tool tip, mm); the F/T
sensor's axes are unit vectors. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

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


@dataclass(frozen=True)
class LeftOut:
    """The point whose removal fits the rest best: its index, its distance (mm) from the pose fitted to
    the others, and the others' rms residual (mm) under that pose."""

    index: int
    residual_mm: float
    others_rms_mm: float


def most_inconsistent_point(gel_points: F64, machine_points: F64) -> LeftOut:
    """Leave each point out in turn, fit the pose to the others (:func:`kabsch`) and keep the choice
    whose others fit best (smallest rms): that point is the one the others disagree with most."""
    a, b = np.asarray(gel_points, float), np.asarray(machine_points, float)
    best: LeftOut | None = None
    for i in range(len(a)):
        others = np.arange(len(a)) != i
        pose = kabsch(a[others], b[others])
        rms = float(np.sqrt(np.mean(np.sum((pose.apply(a[others]) - b[others]) ** 2, axis=1))))
        if best is None or rms < best.others_rms_mm:
            best = LeftOut(i, float(np.linalg.norm(pose.apply(a[i]) - b[i])), rms)
    assert best is not None
    return best


def reject_outliers(gel_points: F64, machine_points: F64, *, min_residual_mm: float, ratio: float,
                    min_points: int) -> tuple[npt.NDArray[np.bool_], list[LeftOut]]:
    """Drop, one at a time, the point the others disagree with most (:func:`most_inconsistent_point`)
    while its distance from the others' pose exceeds both ``min_residual_mm`` and ``ratio`` times the
    others' rms, and more than ``min_points`` remain. Returns (kept mask, the points dropped, indices
    into the inputs)."""
    a, b = np.asarray(gel_points, float), np.asarray(machine_points, float)
    kept = np.ones(len(a), dtype=bool)
    dropped: list[LeftOut] = []
    while int(kept.sum()) > min_points:
        index = np.flatnonzero(kept)
        worst = most_inconsistent_point(a[kept], b[kept])
        if worst.residual_mm <= max(min_residual_mm, ratio * worst.others_rms_mm):
            break
        kept[index[worst.index]] = False
        dropped.append(LeftOut(int(index[worst.index]), worst.residual_mm, worst.others_rms_mm))
    return kept, dropped


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
