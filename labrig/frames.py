"""Rigid transforms between the rig's frames: machine, gel, F/T sensor, camera.

A :class:`Pose` maps points from a child frame into a parent frame:
``p_parent = R @ p_child + t`` (mm). Rotations come from Rodrigues vectors
(rad) or from the small yaw/tilt angles a rig config uses (deg).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


def rotvec_to_matrix(rotvec: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Rodrigues: rotation vector (axis * angle, rad) to a 3x3 matrix."""
    r = np.asarray(rotvec, dtype=np.float64)
    angle = float(np.linalg.norm(r))
    if angle < 1e-12:
        return np.eye(3)
    k = r / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def matrix_to_rotvec(matrix: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Inverse of :func:`rotvec_to_matrix` (angle in [0, pi])."""
    m = np.asarray(matrix, dtype=np.float64)
    cos = np.clip((np.trace(m) - 1) / 2, -1.0, 1.0)
    angle = float(np.arccos(cos))
    if angle < 1e-12:
        return np.zeros(3)
    if np.pi - angle < 1e-6:
        # Near pi the antisymmetric part vanishes; take the axis from R + I.
        col = np.argmax(np.diag(m))
        axis = (m[:, col] + np.eye(3)[:, col]) / np.sqrt(2 * (1 + m[col, col]))
        return axis * angle
    axis = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) / (2 * np.sin(angle))
    return axis * angle


def yaw_tilt_matrix(yaw_deg: float, tilt_deg: tuple[float, float] = (0.0, 0.0)) -> npt.NDArray[np.float64]:
    """Rotation of a frame yawed about parent z, then tilted about its own x, then y."""
    yaw, tx, ty = np.radians([yaw_deg, tilt_deg[0], tilt_deg[1]])
    return rotvec_to_matrix([0, 0, yaw]) @ rotvec_to_matrix([tx, 0, 0]) @ rotvec_to_matrix([0, ty, 0])


@dataclass(frozen=True)
class Pose:
    """Child frame in a parent frame: ``p_parent = rotation @ p_child + translation_mm``."""

    rotation: npt.NDArray[np.float64]
    translation_mm: npt.NDArray[np.float64]

    @classmethod
    def identity(cls) -> Pose:
        return cls(np.eye(3), np.zeros(3))

    def apply(self, points_mm: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Map (..., 3) points from the child frame to the parent frame."""
        p = np.asarray(points_mm, dtype=np.float64)
        return p @ self.rotation.T + self.translation_mm

    def rotate(self, vectors: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Map (..., 3) free vectors (forces, directions) from child to parent axes."""
        return np.asarray(vectors, dtype=np.float64) @ self.rotation.T

    def inverse(self) -> Pose:
        r_t = self.rotation.T
        return Pose(r_t, -r_t @ self.translation_mm)

    def compose(self, child: Pose) -> Pose:
        """``self`` (B in A) composed with ``child`` (C in B) gives C in A."""
        return Pose(self.rotation @ child.rotation, self.rotation @ child.translation_mm + self.translation_mm)


def wrench_about(force_n: npt.ArrayLike, point_mm: npt.ArrayLike, origin_mm: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Torque (N m) about ``origin_mm`` of a force applied at ``point_mm`` (same frame)."""
    lever_m = (np.asarray(point_mm, dtype=np.float64) - np.asarray(origin_mm, dtype=np.float64)) * 1e-3
    return np.cross(lever_m, np.asarray(force_n, dtype=np.float64))
