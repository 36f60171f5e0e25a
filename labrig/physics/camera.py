"""The pinhole camera with OpenCV distortion: projection and back-projection.

Frames and units: points in the gel frame (mm) are mapped into the OpenCV
camera frame (x right, y down, z along the optical axis; mm) by the
gel->camera pose ``p_cam = R @ p_gel + t`` (R from a Rodrigues vector, rad).
Normalised coordinates are ``(x/z, y/z)`` in the camera frame; the OpenCV
model (k1 k2 p1 p2 k3) distorts them, and ``u = fx x_d + cx``,
``v = fy y_d + cy`` gives pixels with the origin at the top-left pixel's
centre. Undistortion inverts the distortion by fixed-point iteration
(OpenCV's scheme, iterated to convergence), which converges for the mild
distortion of a real lens inside the image.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt
from numba import njit

from labrig.config import RigConfig
from labrig.errors import ConfigError
from labrig.frames import Pose, rotvec_to_matrix

__all__ = ["CameraModel", "distort_normalized", "undistort_normalized"]

Array = npt.NDArray[np.float64]


def distort_normalized(xy: npt.ArrayLike, distortion: tuple[float, ...]) -> Array:
    """Apply OpenCV (k1, k2, p1, p2, k3) distortion to (N, 2) normalised coordinates."""
    xy = np.asarray(xy, dtype=np.float64)
    k1, k2, p1, p2, k3 = distortion
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


@njit(cache=True, nogil=True)
def _camera_points_to_pixels(points, fx, fy, cx, cy, k1, k2, p1, p2, k3, out):  # type: ignore[no-untyped-def]
    """Camera-frame points (N, 3) -> pixels (N, 2) in ``out``: :func:`distort_normalized` and the intrinsics,
    operation for operation (no fastmath), in one compiled pass instead of some twenty small array passes."""
    for n in range(points.shape[0]):
        z = points[n, 2]
        x = points[n, 0] / z
        y = points[n, 1] / z
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        out[n, 0] = fx * xd + cx
        out[n, 1] = fy * yd + cy
    return out


@njit(cache=True, nogil=True)
def _pixels_to_planes(xy_px, z_mm, fx, fy, cx, cy, k1, k2, p1, p2, k3, rotation, origin, tol, max_iter, out):  # type: ignore[no-untyped-def]
    """Pixels (N, 2) -> points (N, 3) on the planes z = ``z_mm`` (N,) of the frame whose ``rotation`` (camera
    axes to the frame's) and camera centre ``origin`` are given: :func:`undistort_normalized` per pixel, the
    unit ray, rotated and met with its plane, as :meth:`CameraModel.backproject_to_plane` does, in one
    compiled pass."""
    for n in range(xy_px.shape[0]):
        xd = (xy_px[n, 0] - cx) / fx
        yd = (xy_px[n, 1] - cy) / fy
        x, y = xd, yd
        for _ in range(max_iter):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            nx = (xd - dx) / radial
            ny = (yd - dy) / radial
            change = max(abs(nx - x), abs(ny - y))
            x, y = nx, ny
            if change < tol:
                break
        norm = np.sqrt(x * x + y * y + 1.0)
        rx, ry, rz = x / norm, y / norm, 1.0 / norm
        g0 = rx * rotation[0, 0] + ry * rotation[0, 1] + rz * rotation[0, 2]
        g1 = rx * rotation[1, 0] + ry * rotation[1, 1] + rz * rotation[1, 2]
        g2 = rx * rotation[2, 0] + ry * rotation[2, 1] + rz * rotation[2, 2]
        s = (z_mm[n] - origin[2]) / g2
        out[n, 0] = origin[0] + s * g0
        out[n, 1] = origin[1] + s * g1
        out[n, 2] = origin[2] + s * g2
    return out


def undistort_normalized(
    xy_distorted: npt.ArrayLike, distortion: tuple[float, ...], *, tol: float = 1e-14, max_iter: int = 100
) -> Array:
    """Invert :func:`distort_normalized` by fixed-point iteration (to ``tol`` in normalised units)."""
    xyd = np.asarray(xy_distorted, dtype=np.float64)
    k1, k2, p1, p2, k3 = distortion
    xy = xyd.copy()
    for _ in range(max_iter):
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        new = np.stack([(xyd[..., 0] - dx) / radial, (xyd[..., 1] - dy) / radial], axis=-1)
        change = float(np.max(np.abs(new - xy), initial=0.0))
        xy = new
        if change < tol:
            break
    return xy


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics (px), distortion (k1 k2 p1 p2 k3) and the gel->camera pose (rad, mm)."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, float, float, float, float]
    gel_to_camera_rotvec_rad: tuple[float, float, float]
    gel_to_camera_translation_mm: tuple[float, float, float]
    width_px: int = 1280
    height_px: int = 720

    @classmethod
    def nominal(cls, rig: RigConfig) -> CameraModel:
        """The camera as the rig file states it, before calibration: fx = fy = ``focal_length_mm`` /
        ``pixel_um``, the principal point at the sensor's centre, no distortion, and the gel
        ``gel_distance_mm`` along the optical axis, turned by ``nominal_rotvec_rad`` (``[camera]``)."""
        cam = rig.camera
        if cam.focal_length_mm is None or cam.gel_distance_mm is None:
            raise ConfigError(f"{rig.path}: [camera] needs focal_length_mm and gel_distance_mm for the nominal camera "
                              "(or calibrate it: `labrig calibrate intrinsics`, `labrig calibrate extrinsics`)")
        focal_px = float(cam.focal_length_mm) * 1000.0 / float(cam.pixel_um)
        return cls(
            fx_px=focal_px,
            fy_px=focal_px,
            cx_px=(cam.width_px - 1) / 2.0,
            cy_px=(cam.height_px - 1) / 2.0,
            distortion=(0.0, 0.0, 0.0, 0.0, 0.0),
            gel_to_camera_rotvec_rad=tuple(float(r) for r in cam.nominal_rotvec_rad),  # type: ignore[arg-type]
            gel_to_camera_translation_mm=(0.0, 0.0, float(cam.gel_distance_mm)),
            width_px=cam.width_px,
            height_px=cam.height_px,
        )

    @cached_property
    def gel_to_camera(self) -> Pose:
        """The gel frame in the camera frame: ``p_cam = R @ p_gel + t`` (mm)."""
        return Pose(rotvec_to_matrix(self.gel_to_camera_rotvec_rad), np.asarray(self.gel_to_camera_translation_mm, float))

    @property
    def matrix(self) -> Array:
        """The 3x3 intrinsic matrix K (px)."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    # -- forward ---------------------------------------------------------------------------------

    def normalized_to_pixels(self, xy_norm: npt.ArrayLike) -> Array:
        """Undistorted normalised coordinates (N, 2) -> distorted pixel coordinates (N, 2)."""
        xyd = distort_normalized(xy_norm, self.distortion)
        return np.stack([self.fx_px * xyd[..., 0] + self.cx_px, self.fy_px * xyd[..., 1] + self.cy_px], axis=-1)

    def project_camera(self, points_cam_mm: npt.ArrayLike) -> Array:
        """Camera-frame points (N, 3) mm -> pixels (N, 2); points must have z > 0.

        The same numbers as ``normalized_to_pixels(p[..., :2] / p[..., 2:3])``, compiled: the virtual rig
        projects its markers at every render step."""
        p = np.asarray(points_cam_mm, dtype=np.float64)
        flat = np.ascontiguousarray(p.reshape(-1, 3))
        out = np.empty((flat.shape[0], 2))
        _camera_points_to_pixels(flat, self.fx_px, self.fy_px, self.cx_px, self.cy_px, *self.distortion, out)
        return out.reshape(*p.shape[:-1], 2)

    def project(self, points_mm: npt.ArrayLike, pose: Pose | None = None) -> Array:
        """Points (N, 3) mm in the gel frame (or in the frame ``pose`` maps into the camera) -> pixels (N, 2)."""
        return self.project_camera((pose or self.gel_to_camera).apply(points_mm))

    # -- backward --------------------------------------------------------------------------------

    def pixels_to_normalized(self, xy_px: npt.ArrayLike) -> Array:
        """Pixels (N, 2) -> undistorted normalised coordinates (N, 2), by iterative undistortion."""
        xy = np.asarray(xy_px, dtype=np.float64)
        xyd = np.stack([(xy[..., 0] - self.cx_px) / self.fx_px, (xy[..., 1] - self.cy_px) / self.fy_px], axis=-1)
        return undistort_normalized(xyd, self.distortion)

    def pixel_rays(self, xy_px: npt.ArrayLike) -> Array:
        """Unit viewing rays (N, 3) in the camera frame through the pixels (N, 2)."""
        xy = self.pixels_to_normalized(xy_px)
        rays = np.concatenate([xy, np.ones((*xy.shape[:-1], 1))], axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def backproject_to_plane(self, xy_px: npt.ArrayLike, z_mm: float = 0.0, pose: Pose | None = None) -> Array:
        """Points (N, 3) on the plane z = ``z_mm`` of the gel frame (or of ``pose``'s frame) seen by the pixels.

        The ray from the camera centre through each pixel is intersected with
        the plane; the result is in that frame's coordinates (mm).
        """
        frame = pose or self.gel_to_camera
        rays_cam = self.pixel_rays(xy_px)
        inv = frame.inverse()
        origin = inv.translation_mm  # camera centre in the frame
        rays = inv.rotate(rays_cam)
        s = (z_mm - origin[2]) / rays[..., 2]
        return origin + s[..., None] * rays

    def backproject_to_planes(self, xy_px: npt.ArrayLike, z_mm: npt.ArrayLike) -> Array:
        """Points (N, 3) of the gel frame seen by the pixels (N, 2), each on its own plane z = ``z_mm`` (N,):
        :meth:`backproject_to_plane` per pixel, compiled (the runtime back-projects every marker every window)."""
        xy = np.ascontiguousarray(np.asarray(xy_px, dtype=np.float64).reshape(-1, 2))
        z = np.ascontiguousarray(np.broadcast_to(np.asarray(z_mm, dtype=np.float64), (len(xy),)))
        rotation, origin = self._camera_in_gel
        out = np.empty((len(xy), 3))
        _pixels_to_planes(xy, z, self.fx_px, self.fy_px, self.cx_px, self.cy_px, *self.distortion, rotation, origin,
                          1e-14, 100, out)
        return out

    @cached_property
    def _camera_in_gel(self) -> tuple[Array, Array]:
        """The camera's axes in the gel frame (3, 3) and its centre (3,) mm, contiguous for the compiled kernels."""
        inv = self.gel_to_camera.inverse()
        return np.ascontiguousarray(inv.rotation), np.ascontiguousarray(inv.translation_mm)

    def jacobian_px_per_mm(self, points_mm: npt.ArrayLike, pose: Pose | None = None) -> Array:
        """d(pixel)/d(point) at points (N, 3) of the gel frame (or ``pose``'s frame): (N, 2, 3), px per mm.

        Central differences (step 1e-4 mm); columns 0 and 1 give the image of a
        small patch of the frame's x-y plane, e.g. a marker disc.
        """
        p = np.asarray(points_mm, dtype=np.float64)
        h = 1e-4
        cols = []
        for axis in range(3):
            step = np.zeros(3)
            step[axis] = h
            cols.append((self.project(p + step, pose) - self.project(p - step, pose)) / (2 * h))
        return np.stack(cols, axis=-1)
