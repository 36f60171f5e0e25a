"""Adaptive time steps: how far the rig may advance before markers move too far in the image."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from labrig.physics.camera import CameraModel


def image_velocity_px_s(camera: CameraModel, xyz_mm: npt.ArrayLike, velocity_mm_s: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Image velocities (N, 2), px/s, of gel-frame points (N, 3) mm moving at (N, 3) mm/s (first order)."""
    jac = camera.jacobian_px_per_mm(xyz_mm)
    return np.einsum("nij,nj->ni", jac, np.asarray(velocity_mm_s, dtype=np.float64))


def step_us(image_velocity: npt.ArrayLike, max_step_px: float, *, min_us: int = 1, max_us: int = 10_000) -> int:
    """The longest step (whole us, within [min_us, max_us]) over which no point moves more than ``max_step_px``.

    ``image_velocity`` is (N, 2) px/s (or (N,) speeds); the rig's default
    ``max_step_px`` is ``sim_config(rig).events.max_step_px``.
    """
    v = np.asarray(image_velocity, dtype=np.float64)
    speed = float(np.max(np.linalg.norm(v, axis=-1) if v.ndim > 1 else np.abs(v), initial=0.0))
    if speed <= 0:
        return max_us
    return int(np.clip(np.floor(max_step_px / speed * 1e6), min_us, max_us))
