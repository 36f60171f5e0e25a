"""Rendering the membrane seen by the event camera: linear intensity in [0, 1] over the ROI.

Scene model (units: intensity relative to full scale, pixels of the sensor):

* The membrane is dark (``membrane_level``); each marker is a bright disc
  (``marker_level``) of ``markers.diameter_mm`` on it, drawn as an
  anti-aliased ellipse (:mod:`labrig.sim.discs`) centred on the projection of
  the marker's 3D centre (gel frame, mm) and shaped by the projection's local
  Jacobian in the gel x-y plane (the membrane's own tilt is neglected).
  Overlapping markers add coverage, clipped at 1.
* Everything is scaled by the slope shading S of :mod:`labrig.sim.shading`
  (1 on flat membrane), sampled at each pixel's rest back-projection
  onto z = 0 (small-displacement approximation), and clipped to [0, 1]:
  ``I = led * clip(S * (m + min(coverage, 1) * (M - m)), 0, 1)``.
* LED ring off: I = 0 everywhere (the extrinsic-calibration blink scene).

:class:`Renderer` is incremental: it keeps the marker coverage and the shading
of the whole ROI and, per call, re-draws only markers that moved by more than
``min_move_px`` since they were last drawn (their old and new patches) and the
old and new bounding boxes of the slope field, then reports only the pixels
whose intensity changed (by more than ``min_rel_change`` of its value).
Pixel indices are flat, row-major in the ROI: ``(y - roi.y0_px) * roi.width + (x - roi.x0_px)``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig
from labrig.sim.camera import CameraModel
from labrig.sim.discs import ellipse_coverage, patch_half_px, patch_origins
from labrig.sim.pixels import unique_indices
from labrig.sim.shading import DepthField, GridLookup, slope_shading

Array = npt.NDArray[np.float64]
Index = npt.NDArray[np.int64]


class RenderUpdate(NamedTuple):
    """Changed ROI pixels: flat ROI indices (n,) int64 and their new linear intensity (n,) in [0, 1]."""

    indices: Index
    intensity: Array


class Renderer:
    """Incremental membrane renderer over the rig's ROI (see the module docstring).

    Internally every per-pixel buffer lives on a canvas: the ROI grown by one
    patch side on each edge, so marker patches never need clipping.
    """

    def __init__(
        self,
        rig: RigConfig,
        camera: CameraModel | None = None,
        *,
        marker_xyz_mm: npt.ArrayLike | None = None,
        edge_px: float = 1.0,
        half_px: int | None = None,
        min_move_px: float = 0.002,
        min_rel_change: float = 1e-4,
        slope_tol: float = 1e-4,
    ) -> None:
        self.camera = camera or CameraModel.from_rig(rig)
        self.roi = rig.roi
        self.lighting = rig.sim.lighting
        self.radius_mm = rig.markers.diameter_mm / 2
        self.edge_px, self.min_move_px, self.min_rel_change, self.slope_tol = edge_px, min_move_px, min_rel_change, slope_tol
        rest = rig.markers.rest_positions_mm() if marker_xyz_mm is None else np.asarray(marker_xyz_mm, float)
        self.half_px = half_px or patch_half_px(self._axes(rest), edge_px)
        side = 2 * self.half_px
        h, w = self.roi.height_px, self.roi.width_px
        self._pad = side
        self._canvas_shape = (h + 2 * side, w + 2 * side)
        canvas = np.arange(self._canvas_shape[0] * self._canvas_shape[1]).reshape(self._canvas_shape)
        self._roi_to_canvas = canvas[side : side + h, side : side + w].ravel().copy()
        self._canvas_to_roi = np.full(canvas.size, -1, dtype=np.int64)
        self._canvas_to_roi[self._roi_to_canvas] = np.arange(h * w)
        self._offsets = (np.arange(side)[:, None] * self._canvas_shape[1] + np.arange(side)[None, :]).ravel()
        self._cov = np.zeros(canvas.size)
        self._shade = np.ones(canvas.size)
        self._shade_box: tuple[int, int, int, int] | None = None
        self._depth: DepthField | None = None
        self._led_on = bool(self.lighting.led_on)
        self._scratch = np.zeros(canvas.size, dtype=np.int64)
        self._pixel_gel_xy: Array | None = None
        self._grid_lookup: tuple[tuple[float, float, int, float, float, int], GridLookup] | None = None
        self._centres, self._axes_px = self._project(rest)
        self._origins = patch_origins(self._centres, self.half_px)
        self._patches = ellipse_coverage(self._centres, self._axes_px, self._origins, self.half_px, edge_px)
        np.add.at(self._cov, self._patch_index(self._origins).ravel(), self._patches.ravel())
        self._reported = np.zeros(canvas.size)
        self._reported[self._roi_to_canvas] = self._compose(self._roi_to_canvas)

    # -- public ------------------------------------------------------------------------------------

    @property
    def image(self) -> Array:
        """The current ROI intensity image (height, width), as last reported."""
        return self._reported[self._roi_to_canvas].reshape(self.roi.height_px, self.roi.width_px)

    def render(
        self, marker_xyz_mm: npt.ArrayLike, depth: DepthField | None = None, *, led_on: bool | None = None
    ) -> RenderUpdate:
        """Move the scene to new marker centres (N, 3, gel mm) and depth field; return the changed pixels.

        ``depth`` is compared by identity: pass the same object to mean "unchanged".
        ``led_on`` None keeps the current LED state.
        """
        candidates = [self._move_markers(np.asarray(marker_xyz_mm, dtype=np.float64))]
        if depth is not self._depth:
            candidates.append(self._reshade(depth))
        if led_on is not None and bool(led_on) != self._led_on:
            self._led_on = bool(led_on)
            candidates.append(self._roi_to_canvas)
        pixels = unique_indices(np.concatenate(candidates), self._scratch)
        pixels = pixels[self._canvas_to_roi[pixels] >= 0]
        new = self._compose(pixels)
        old = self._reported[pixels]
        changed = np.abs(new - old) > self.min_rel_change * (old + new + 1e-3)
        pixels, new = pixels[changed], new[changed]
        self._reported[pixels] = new
        return RenderUpdate(self._canvas_to_roi[pixels], new)

    def render_full(self, marker_xyz_mm: npt.ArrayLike, depth: DepthField | None = None, *, led_on: bool | None = None) -> Array:
        """Render the ROI (height, width) from scratch, without touching the incremental state."""
        centres, axes = self._project(np.asarray(marker_xyz_mm, dtype=np.float64))
        origins = patch_origins(centres, self.half_px)
        cov = np.zeros_like(self._cov)
        patches = ellipse_coverage(centres, axes, origins, self.half_px, self.edge_px)
        np.add.at(cov, self._patch_index(origins).ravel(), patches.ravel())
        shade = np.ones(self.roi.height_px * self.roi.width_px)
        box = self._slope_box(depth)
        if box is not None and depth is not None:
            shade[self._box_pixels(box)] = self._box_shading(depth, box)
        led = self._led_on if led_on is None else bool(led_on)
        image = self._intensity(cov[self._roi_to_canvas], shade, led)
        return image.reshape(self.roi.height_px, self.roi.width_px)

    # -- markers -----------------------------------------------------------------------------------

    def _axes(self, xyz: Array) -> Array:
        return self.camera.jacobian_px_per_mm(xyz)[..., :2] * self.radius_mm

    def _project(self, xyz: Array) -> tuple[Array, Array]:
        """Sensor-pixel centres (N, 2) and ellipse axes (N, 2, 2) of the markers."""
        return self.camera.project(xyz), self._axes(xyz)

    def _patch_index(self, origins: npt.NDArray[np.int64]) -> Index:
        """Flat canvas indices (K, S*S) of the patches with these sensor-pixel origins (clipped to the canvas)."""
        side = 2 * self.half_px
        ch, cw = self._canvas_shape
        ox = np.clip(origins[:, 0] - self.roi.x0_px + self._pad, 0, cw - side)
        oy = np.clip(origins[:, 1] - self.roi.y0_px + self._pad, 0, ch - side)
        return (oy * cw + ox)[:, None] + self._offsets[None, :]

    def _move_markers(self, xyz: Array) -> Index:
        """Re-draw the markers that moved; return the canvas pixels whose coverage may have changed."""
        centres, axes = self._project(xyz)
        shift = np.maximum(np.abs(centres - self._centres).max(axis=1), np.abs(axes - self._axes_px).max(axis=(1, 2)))
        moved = np.flatnonzero(shift > self.min_move_px)
        if moved.size == 0:
            return np.empty(0, dtype=np.int64)
        old_index = self._patch_index(self._origins[moved])
        np.add.at(self._cov, old_index.ravel(), -self._patches[moved].ravel())
        origins = patch_origins(centres[moved], self.half_px)
        patches = ellipse_coverage(centres[moved], axes[moved], origins, self.half_px, self.edge_px)
        new_index = self._patch_index(origins)
        np.add.at(self._cov, new_index.ravel(), patches.ravel())
        relocated = np.any(origins != self._origins[moved], axis=1)
        self._centres[moved], self._axes_px[moved] = centres[moved], axes[moved]
        self._origins[moved], self._patches[moved] = origins, patches
        return np.concatenate([old_index[relocated].ravel(), new_index.ravel()])

    # -- shading -----------------------------------------------------------------------------------

    def _gel_xy(self) -> Array:
        """Rest back-projection (H*W, 2) of every ROI pixel onto the gel surface z = 0 (mm), cached."""
        if self._pixel_gel_xy is None:
            ys, xs = np.mgrid[self.roi.y0_px : self.roi.y1_px, self.roi.x0_px : self.roi.x1_px]
            xy = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
            self._pixel_gel_xy = self.camera.backproject_to_plane(xy)[:, :2].copy()
        return self._pixel_gel_xy

    def _lookup(self, depth: DepthField) -> GridLookup:
        """Bilinear weights of every ROI pixel's rest gel point on the depth field's grid, cached per grid."""
        key = depth.grid_key()
        if self._grid_lookup is None or self._grid_lookup[0] != key:
            lookup = GridLookup.build(key, self._gel_xy()).reshape(self.roi.height_px, self.roi.width_px)
            self._grid_lookup = (key, lookup)
        return self._grid_lookup[1]

    def _box_shading(self, depth: DepthField, box: tuple[int, int, int, int]) -> Array:
        """Slope shading S of the ROI pixel box, flattened row-major like :meth:`_box_pixels`."""
        x0, x1, y0, y1 = box
        slope = self._lookup(depth).sample(depth.slope, np.s_[y0:y1, x0:x1])
        return slope_shading(slope, self.lighting.slope_gain).ravel()

    def _slope_box(self, depth: DepthField | None) -> tuple[int, int, int, int] | None:
        """ROI pixel box (x0, x1, y0, y1; exclusive ends, ROI coordinates) holding the slope above tolerance."""
        if depth is None:
            return None
        box_mm = depth.slope_bbox_mm(self.slope_tol)
        if box_mm is None:
            return None
        x0, x1, y0, y1 = box_mm
        t = np.linspace(0.0, 1.0, 9)
        edge_x = np.concatenate([x0 + (x1 - x0) * t, np.full(9, x1), x1 - (x1 - x0) * t, np.full(9, x0)])
        edge_y = np.concatenate([np.full(9, y0), y0 + (y1 - y0) * t, np.full(9, y1), y1 - (y1 - y0) * t])
        px = self.camera.project(np.stack([edge_x, edge_y, np.zeros_like(edge_x)], axis=1))
        bx0 = int(np.clip(np.floor(px[:, 0].min()) - 2 - self.roi.x0_px, 0, self.roi.width_px))
        bx1 = int(np.clip(np.ceil(px[:, 0].max()) + 3 - self.roi.x0_px, 0, self.roi.width_px))
        by0 = int(np.clip(np.floor(px[:, 1].min()) - 2 - self.roi.y0_px, 0, self.roi.height_px))
        by1 = int(np.clip(np.ceil(px[:, 1].max()) + 3 - self.roi.y0_px, 0, self.roi.height_px))
        if bx1 <= bx0 or by1 <= by0:
            return None
        return bx0, bx1, by0, by1

    def _box_pixels(self, box: tuple[int, int, int, int]) -> Index:
        """Flat ROI indices of a ROI pixel box."""
        x0, x1, y0, y1 = box
        return (np.arange(y0, y1)[:, None] * self.roi.width_px + np.arange(x0, x1)[None, :]).ravel()

    def _reshade(self, depth: DepthField | None) -> Index:
        """Re-shade the old and new slope boxes; return their canvas pixels."""
        touched = [np.empty(0, dtype=np.int64)]
        box = self._slope_box(depth)
        if self._shade_box is not None:
            old = self._box_pixels(self._shade_box)
            if box is not None:  # keep only old pixels the new box will not rewrite
                y, x = np.divmod(old, self.roi.width_px)
                old = old[(x < box[0]) | (x >= box[1]) | (y < box[2]) | (y >= box[3])]
            old = self._roi_to_canvas[old]
            self._shade[old] = 1.0
            touched.append(old)
        if box is not None and depth is not None:
            new = self._box_pixels(box)
            shade = self._box_shading(depth, box)
            new = self._roi_to_canvas[new]
            self._shade[new] = shade
            touched.append(new)
        self._shade_box, self._depth = box, depth
        return np.concatenate(touched)

    # -- composition -------------------------------------------------------------------------------

    def _compose(self, pixels: Index) -> Array:
        """Current intensity at flat canvas pixels."""
        return self._intensity(self._cov[pixels], self._shade[pixels], self._led_on)

    def _intensity(self, coverage: Array, shade: Array, led_on: bool) -> Array:
        if not led_on:
            return np.zeros_like(coverage)
        m, big_m = self.lighting.membrane_level, self.lighting.marker_level
        return np.clip(shade * (m + np.clip(coverage, 0.0, 1.0) * (big_m - m)), 0.0, 1.0)
