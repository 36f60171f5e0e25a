"""Rendering the membrane seen by the event camera: linear intensity in [0, 1] over the ROI.

Scene model (units: intensity relative to full scale, pixels of the sensor):

* The membrane is dark (``membrane_level``); each marker is a bright disc
  (``marker_level``) of ``markers.diameter_mm`` on it, drawn as an
  anti-aliased ellipse (:mod:`labrig.sim.discs`) centred on the projection of
  the marker's 3D centre (gel frame, mm) and shaped by the projection's local
  Jacobian in the gel x-y plane (the membrane's own tilt is neglected).
  Overlapping markers add coverage, clipped at 1. Printed markers may differ
  (``marker_diameter_mm``, ``marker_contrast``: :mod:`labrig.sim.imperfections`): a
  marker's coverage is weighted by its contrast c (its brightness above the
  membrane relative to the nominal), and the clip is at max(1, max c).
* Everything is scaled by the slope shading S of :mod:`labrig.sim.shading`
  (1 on flat membrane), sampled at each pixel's rest back-projection
  onto z = 0 (small-displacement approximation), and clipped to [0, 1]:
  ``I = led * clip(S * (m + min(coverage, 1) * (M - m)), 0, 1)``, ``led`` the LED ring's level
  (1 full, 0 off: the extrinsic-calibration blink scene; between them: the event-response scene's
  dimming ramps). S is 1 outside the box of the depth field's nodes with slope above ``slope_tol``.

:class:`Renderer` is incremental. It keeps the marker coverage, the
luminance ``m + min(coverage, 1) (M - m)`` and the shading of the whole ROI
and, per call:

* re-draws the markers that moved by more than ``min_move_px`` since they
  were last drawn, and keeps exactly the pixels whose coverage changed (old
  and new patch differenced in one window per marker: the rims, not the
  whole patches);
* re-shades, for a new depth field, the pixels whose shading may have
  changed: the whole slope box when it or the grid moved, else the pixels
  around the nodes whose slope moved by more than ``shade_tol`` since those
  nodes were last used. A grid translated by a few nodes (a sliding contact's
  field moves with it) counts as unmoved: its slope resampled onto the grid
  it left picks the nodes, and the pixels around them take their slope from
  the new grid (:data:`FIXED_GRID_DRIFT_NODES`). So a pixel's shading is never more than
  ``2 * slope_gain * shade_tol`` off (on a translated grid, plus the resampling's error where
  nodes were left alone: small where the slope is smooth, which is where they are left): by
  default ``min_rel_change``, the smallest change the renderer reports; ``shade_tol=0``
  re-shades on any change);
* reports the pixels whose intensity changed by more than ``min_rel_change``
  of its value: the re-shaded rectangle as a dense :class:`~labrig.sim.pixels.PixelBlock`
  (mask and values, no index lists) and the marker rims outside it as flat indices.

``min_rel_change`` (default :data:`MIN_REL_CHANGE`, 0.1 %) is a dead band: a pixel's
reported intensity follows the scene in steps of at least that much. The event sensor's
contrast threshold is about 0.22 in log intensity with a pixel-to-pixel spread of 0.03, so
the dead band (0.001 in log intensity) is 1/220 of a threshold and 1/30 of its spread: it
moves no event beyond what the sensor's own mismatch does. What it saves is the gel's
shading: while the indenter presses, every solve changes the shading of the whole contact
region by a few 1e-4, and with a 1e-4 dead band the sensor updated all those pixels at each
solve (on the paper campaign's 1.5 mm sphere press: 68 million pixel updates; 19 million at
0.1 %, with 1,166,750 events against 1,166,775).

Pixel indices are flat, row-major in the ROI: ``(y - roi.y0_px) * roi.width + (x - roi.x0_px)``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig, Roi
from labrig.physics.camera import CameraModel
from labrig.sim import _render_kernels as _k
from labrig.sim.discs import ellipse_coverage, patch_half_px, patch_origins, rim_radii
from labrig.sim.pixels import PixelBlock
from labrig.sim.shading import DepthField, GridLookup
from labrig.sim.truth_config import sim_config, true_camera

Array = npt.NDArray[np.float64]
Index = npt.NDArray[np.int64]
Rect = tuple[int, int, int, int]  # x0, x1, y0, y1: ROI pixels, exclusive ends

#: The renderer's dead band: the smallest relative intensity change it reports (see the module's notes).
MIN_REL_CHANGE = 1e-3
#: Finite-difference step of the projection Jacobian, mm (as CameraModel.jacobian_px_per_mm).
_JACOBIAN_STEP_MM = 1e-4
#: Stand-ins for the kernel when nothing is re-shaded.
_NO_NODES = np.zeros(8)
_NO_LOOKUP = (np.zeros((1, 1), dtype=np.int32), np.zeros((1, 1)), np.zeros((1, 1)))
_NO_GRID = (0.0, 1.0, 2.0, 0.0, 1.0, 2.0)
#: Gel boxes whose pixel boxes a renderer keeps (cleared when full).
_PIXEL_BOX_CACHE = 4096
#: How far (grid nodes, either axis) a translated depth grid is shown on the grid it left before it is taken as is.
FIXED_GRID_DRIFT_NODES = 10.0


class RenderUpdate:
    """The ROI pixels one render changed and their new linear intensity in [0, 1].

    ``pixels`` / ``values``: scattered pixels (flat ROI indices, distinct);
    ``block``: a dense rectangle of changed pixels (disjoint from ``pixels``), or None.
    :attr:`indices` and :attr:`intensity` give everything as flat arrays.
    """

    __slots__ = ("_flat", "block", "pixels", "values", "width")

    def __init__(self, pixels: Index, values: Array, block: PixelBlock | None = None, width: int = 0) -> None:
        self.pixels, self.values, self.block, self.width = pixels, values, block, width
        self._flat: tuple[Index, Array] | None = None

    def _merged(self) -> tuple[Index, Array]:
        if self._flat is None:
            if self.block is None:
                self._flat = (self.pixels, self.values)
            else:
                self._flat = (
                    np.concatenate([self.pixels, self.block.flat_indices(self.width)]),
                    np.concatenate([self.values, self.block.changed_values()]),
                )
        return self._flat

    @property
    def indices(self) -> Index:
        """Flat ROI indices (n,) int64 of every changed pixel (distinct)."""
        return self._merged()[0]

    @property
    def intensity(self) -> Array:
        """New linear intensity (n,) of the pixels in :attr:`indices`."""
        return self._merged()[1]

    def __iter__(self):  # type: ignore[no-untyped-def]
        """Unpacks as ``indices, intensity``."""
        return iter(self._merged())

    def __len__(self) -> int:
        return int(self.pixels.size + (0 if self.block is None else np.count_nonzero(self.block.changed)))


#: Rest back-projections of the ROI pixels per (camera, ROI), shared by renderers in a process.
_GEL_XY: dict[tuple[CameraModel, Roi], Array] = {}


class Renderer:
    """Incremental membrane renderer over the rig's ROI (see the module docstring).

    Coverage and luminance live on a canvas: the ROI grown by one patch side on
    each edge, so marker patches never need clipping. Shading and the reported
    intensity live on the ROI.
    """

    def __init__(
        self,
        rig: RigConfig,
        camera: CameraModel | None = None,
        *,
        marker_xyz_mm: npt.ArrayLike | None = None,
        marker_diameter_mm: npt.ArrayLike | None = None,
        marker_contrast: npt.ArrayLike | None = None,
        edge_px: float = 1.0,
        half_px: int | None = None,
        min_move_px: float = 0.002,
        min_rel_change: float = MIN_REL_CHANGE,
        slope_tol: float = 1e-4,
        shade_tol: float | None = None,
    ) -> None:
        """``marker_xyz_mm`` (N, 3): the markers drawn, rest centres in the gel frame (default: the nominal
        lattice); ``marker_diameter_mm`` (N,), ``marker_contrast`` (N,): per marker (default: nominal, 1).
        ``shade_tol`` (default: ``min_rel_change / (2 slope_gain)``, so that no pixel's shading is further off
        than the smallest change the renderer reports)."""
        self.camera = camera or true_camera(rig)
        self.roi = rig.roi
        self.lighting = sim_config(rig).lighting
        self.radius_mm: float | Array = (rig.markers.diameter_mm / 2 if marker_diameter_mm is None
                                         else np.asarray(marker_diameter_mm, dtype=np.float64)[:, None, None] / 2)
        #: Per-marker coverage weights (contrast), or None: all 1 (the compiled rim update then serves every move).
        self.ink: Array | None = None if marker_contrast is None else np.asarray(marker_contrast, dtype=np.float64)
        self._coverage_max = 1.0 if self.ink is None else max(1.0, float(self.ink.max()))
        self.edge_px, self.min_move_px, self.min_rel_change = edge_px, min_move_px, min_rel_change
        gain = float(self.lighting.slope_gain)
        self.slope_tol = slope_tol
        self.shade_tol = shade_tol if shade_tol is not None else (min_rel_change / (2 * gain) if gain > 0 else 0.0)
        rest = rig.markers.rest_positions_mm() if marker_xyz_mm is None else np.asarray(marker_xyz_mm, float)
        self.half_px = half_px or patch_half_px(self._axes(rest), edge_px)
        side = 2 * self.half_px
        h, w = self.roi.height_px, self.roi.width_px
        self._pad = side
        self._canvas_shape = (h + 2 * side, w + 2 * side)
        cw = self._canvas_shape[1]
        self._roi_to_canvas = ((np.arange(h)[:, None] + side) * cw + side + np.arange(w)[None, :]).ravel()
        self._canvas_to_roi = np.full(self._canvas_shape[0] * cw, -1, dtype=np.int64)
        self._canvas_to_roi[self._roi_to_canvas] = np.arange(h * w)
        self._offsets = (np.arange(side)[:, None] * cw + np.arange(side)[None, :]).ravel()
        self._scratch = np.zeros(self._canvas_to_roi.size, dtype=np.int64)
        self._led = 1.0 if self.lighting.led_on else 0.0
        # Canvas: marker coverage and luminance m + min(coverage, 1) (M - m); ROI: shading, reported intensity.
        self._cov = np.zeros(self._canvas_to_roi.size)
        self._lum = np.full(self._cov.size, float(self.lighting.membrane_level))
        self._shade = np.ones((h, w))
        self._reported = np.zeros((h, w))
        # Shading state: the slope box (ROI rect), the grid, the node slopes last used, the pixels' grid weights.
        # The field the re-shade's bookkeeping follows (the caller's, or it resampled onto the grid it moved from),
        # and the caller's last field, whose slope shades the pixels.
        self._depth: DepthField | None = None
        self._source: DepthField | None = None
        self._shade_box: Rect | None = None
        self._shade_key: tuple[float, float, int, float, float, int] | None = None
        self._shade_nodes: Array | None = None
        self._pixel_gel_xy: Array | None = None
        self._pixel_gel_planes: tuple[Array, Array] | None = None
        self._lookup_key: tuple[float, float, int, float, float, int] | None = None
        self._lookup: GridLookup | None = None
        self._kernel_base = np.zeros((1, 1), dtype=np.int32)
        self._last_shade_key: tuple[float, float, int, float, float, int] | None = None
        self._pixel_boxes: dict[tuple[float, float, float, float], Rect | None] = {}
        self._centres, self._axes_px = self._project(rest)
        self._origins = patch_origins(self._centres, self.half_px)
        self._patches = ellipse_coverage(self._centres, self._axes_px, self._origins, self.half_px, edge_px)
        np.add.at(self._cov, self._patch_index(self._origins).ravel(), self._inked(self._patches).ravel())
        self._inner_px, self._outer_px = rim_radii(self._axes_px, edge_px)

        self._lum[:] = self._luminance(self._cov)
        self._reported[:] = self._intensity(self._lum2d(), self._shade, self._led)

    # -- public ------------------------------------------------------------------------------------

    def prepare_shading(self) -> None:
        """Compute now what the first re-shade would (the pixels' rest points on the gel, the compiled pixel
        loops), e.g. before serving live."""
        self._gel_planes()
        _k.warm_up()

    @property
    def image(self) -> Array:
        """The current ROI intensity image (height, width), as last reported."""
        return self._reported.copy()

    def render(
        self, marker_xyz_mm: npt.ArrayLike, depth: DepthField | None = None, *, led: float | None = None
    ) -> RenderUpdate:
        """Move the scene to new marker centres (N, 3, gel mm) and depth field; return the changed pixels.

        ``depth`` is compared by identity: pass the same object to mean "unchanged".
        ``led``: the LED ring's level (1 full, 0 off; True and False mean those); None keeps it.
        """
        touched = self._move_markers(np.asarray(marker_xyz_mm, dtype=np.float64))
        rect, shade = None, None
        if depth is not self._source:
            previous, self._source = self._source, depth
            if depth is None or not depth.same_as(previous):  # a new object for the same field changes nothing
                rect, shade = self._reshade(self._on_shown_grid(depth))
        if led is not None and _led_level(led) != self._led:
            self._led = _led_level(led)
            rect = (0, self.roi.width_px, 0, self.roi.height_px)
        # The touched pixels' luminance first (the block reads it), then the block, then the rest of them.
        outside = np.empty(touched.size, dtype=np.int64)
        n = _k.touch_luminance(touched, self._scratch, self._cov, float(self.lighting.membrane_level),
                               float(self.lighting.marker_level), float(self._coverage_max), self._lum,
                               self._canvas_to_roi, rect or (0, 0, 0, 0), self.roi.width_px, outside)
        block = self._compose_block(rect, shade) if rect is not None else None
        pixels, values = self._compose_pixels(outside[:n])
        return RenderUpdate(pixels, values, block, self.roi.width_px)

    def render_full(self, marker_xyz_mm: npt.ArrayLike, depth: DepthField | None = None, *, led: float | None = None) -> Array:
        """Render the ROI (height, width) from scratch, without touching the incremental state."""
        centres, axes = self._project(np.asarray(marker_xyz_mm, dtype=np.float64))
        origins = patch_origins(centres, self.half_px)
        cov = np.zeros_like(self._cov)
        patches = ellipse_coverage(centres, axes, origins, self.half_px, self.edge_px)
        np.add.at(cov, self._patch_index(origins).ravel(), self._inked(patches).ravel())
        shade = np.ones((self.roi.height_px, self.roi.width_px))
        box = self._slope_box(depth)
        if box is not None and depth is not None:
            x0, x1, y0, y1 = box
            shade[y0:y1, x0:x1] = 1.0 + self.lighting.slope_gain * self._sample(depth, box)
        lum = self._luminance(cov)[self._roi_to_canvas].reshape(shade.shape)
        return self._intensity(lum, shade, self._led if led is None else _led_level(led))

    # -- markers -----------------------------------------------------------------------------------

    def _inked(self, patches: Array, markers: Index | None = None) -> Array:
        """Coverage patches (K, S, S) of ``markers`` (default: all) weighted by their contrast."""
        if self.ink is None:
            return patches
        ink = self.ink if markers is None else self.ink[markers]
        return patches * ink[:, None, None]

    def _axes(self, xyz: Array) -> Array:
        return self.camera.jacobian_px_per_mm(xyz)[..., :2] * self.radius_mm

    def _project(self, xyz: Array) -> tuple[Array, Array]:
        """Sensor-pixel centres (N, 2) and ellipse axes (N, 2, 2) of the markers (one batched projection)."""
        h = _JACOBIAN_STEP_MM
        points = np.repeat(xyz[None], 5, axis=0)
        points[1, :, 0] += h
        points[2, :, 0] -= h
        points[3, :, 1] += h
        points[4, :, 1] -= h
        px = self.camera.project(points.reshape(-1, 3)).reshape(5, len(xyz), 2)
        jac = np.stack([(px[1] - px[2]) / (2 * h), (px[3] - px[4]) / (2 * h)], axis=-1)
        return px[0], jac * self.radius_mm

    def _canvas_corner(self, origins: npt.NDArray[np.int64], side: int) -> Index:
        """Flat canvas index of the top-left pixel of side x side windows at these sensor-pixel origins (clipped)."""
        ch, cw = self._canvas_shape
        ox = np.clip(origins[:, 0] - self.roi.x0_px + self._pad, 0, cw - side)
        oy = np.clip(origins[:, 1] - self.roi.y0_px + self._pad, 0, ch - side)
        return oy * cw + ox

    def _patch_index(self, origins: npt.NDArray[np.int64]) -> Index:
        """Flat canvas indices (K, S*S) of the patches with these sensor-pixel origins (clipped to the canvas)."""
        return self._canvas_corner(origins, 2 * self.half_px)[:, None] + self._offsets[None, :]

    def _move_markers(self, xyz: Array) -> Index:
        """Re-draw the markers that moved; return the canvas pixels whose coverage changed (overlapping markers
        repeat theirs; their luminance is left to :func:`._render_kernels.touch_luminance`).

        Only the rims can change: pixels nearer the centre than the inner rim radius are fully covered and
        those beyond the outer one empty, before and after. Candidates: an annulus about the new centre
        holding both rims (the old one widened by the move). Markers whose annulus lies inside the new patch
        take the compiled rim update (:func:`._render_kernels.rim_moves`, with :func:`._render_kernels.rim_change`:
        the new coverage evaluated only at the candidates, with the arithmetic of :func:`ellipse_coverage`, so the
        stored patches stay exactly the full ones); the others (long moves, per-marker contrast) are redrawn whole
        (:meth:`_coverage_change`)."""
        centres, axes = self._project(xyz)
        moved = _k.moved_markers(centres, axes, self._centres, self._axes_px, self.min_move_px)
        if moved.size == 0:
            return moved
        c1, a1 = centres[moved], axes[moved]
        aat = a1 @ np.swapaxes(a1, -1, -2)  # numpy's product, as rim_radii and inverse_shape take it
        ch, cw = self._canvas_shape
        pixels, rim, origins, inner1, outer1 = _k.rim_moves(
            moved, c1, aat, self.half_px, float(self.edge_px), self.ink is not None, self._centres, a1, self._axes_px,
            self._origins, self._inner_px, self._outer_px, self._patches, self._pad, self.roi.x0_px, self.roi.y0_px,
            ch, cw, self._cov)
        if not rim.all():
            far = ~rim
            markers = moved[far]
            far_pixels, delta = self._coverage_change(markers, c1[far], a1[far], origins[far])
            np.add.at(self._cov, far_pixels, delta)
            pixels = np.concatenate([pixels, far_pixels])
            self._centres[markers], self._axes_px[markers], self._origins[markers] = c1[far], a1[far], origins[far]
            self._inner_px[markers], self._outer_px[markers] = inner1[far], outer1[far]
        return pixels

    def _coverage_change(self, markers: Index, c1: Array, a1: Array, new_origins: npt.NDArray[np.int64]) -> tuple[Index, Array]:
        """Canvas pixels (may repeat across markers) and the coverage change there, from old to new patches.

        The new patches are drawn in full; each marker's old and new patches are
        differenced in one window holding both, so only pixels whose coverage
        actually changed come out.
        """
        old_origins, old = self._origins[markers], self._patches[markers]
        new = ellipse_coverage(c1, a1, new_origins, self.half_px, self.edge_px)
        self._patches[markers] = new
        k, side = len(new), 2 * self.half_px
        reach = int(np.abs(new_origins - old_origins).max(initial=0))
        if reach >= side:  # a jump past the patch: old and new patches are disjoint
            index = np.concatenate([self._patch_index(old_origins).ravel(), self._patch_index(new_origins).ravel()])
            delta = np.concatenate([-self._inked(old, markers).ravel(), self._inked(new, markers).ravel()])
            keep = delta != 0
            return index[keep], delta[keep]
        win = side + reach
        corner = np.minimum(old_origins, new_origins)
        local = (np.arange(side)[:, None] * win + np.arange(side)[None, :]).ravel()
        start = np.arange(k) * (win * win)
        window = np.zeros(k * win * win)
        at_new = (start + (new_origins[:, 1] - corner[:, 1]) * win + (new_origins[:, 0] - corner[:, 0]))[:, None] + local
        at_old = (start + (old_origins[:, 1] - corner[:, 1]) * win + (old_origins[:, 0] - corner[:, 0]))[:, None] + local
        window[at_new.ravel()] = new.ravel()
        window[at_old.ravel()] -= old.ravel()
        nonzero = np.flatnonzero(window)
        marker, within = np.divmod(nonzero, win * win)
        row, col = np.divmod(within, win)
        cw = self._canvas_shape[1]
        # The window's top-left pixel on the canvas, placed as the new patch is (see _patch_index).
        lead = new_origins - corner
        top_left = self._canvas_corner(new_origins, side) - (lead[:, 1] * cw + lead[:, 0])
        delta = window[nonzero] if self.ink is None else window[nonzero] * self.ink[markers][marker]
        return top_left[marker] + row * cw + col, delta

    def _luminance(self, coverage: Array) -> Array:
        m, big_m = self.lighting.membrane_level, self.lighting.marker_level
        return m + np.clip(coverage, 0.0, self._coverage_max) * (big_m - m)

    def _lum2d(self) -> Array:
        """Canvas luminance as a 2D view."""
        return self._lum.reshape(self._canvas_shape)[self._pad : -self._pad, self._pad : -self._pad]

    # -- shading -----------------------------------------------------------------------------------

    def _gel_xy(self) -> Array:
        """Rest back-projection (H*W, 2) of every ROI pixel onto the gel surface z = 0 (mm), cached."""
        if self._pixel_gel_xy is None:
            key = (self.camera, self.roi)
            cached = _GEL_XY.get(key)
            if cached is None:  # the same for every renderer of this camera and ROI (each recording of a campaign)
                ys, xs = np.mgrid[self.roi.y0_px : self.roi.y1_px, self.roi.x0_px : self.roi.x1_px]
                xy = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
                cached = self.camera.backproject_to_plane(xy)[:, :2].copy()
                cached.flags.writeable = False
                if len(_GEL_XY) >= 4:
                    _GEL_XY.clear()
                _GEL_XY[key] = cached
            self._pixel_gel_xy = cached
        return self._pixel_gel_xy

    def _gel_planes(self) -> tuple[Array, Array]:
        """The rest gel points of :meth:`_gel_xy` as two ROI-shaped planes (x, y mm), for the compiled loop."""
        if self._pixel_gel_planes is None:
            xy = self._gel_xy().reshape(self.roi.height_px, self.roi.width_px, 2)
            self._pixel_gel_planes = (np.ascontiguousarray(xy[..., 0]), np.ascontiguousarray(xy[..., 1]))
        return self._pixel_gel_planes

    def _grid_lookup(self, depth: DepthField) -> GridLookup:
        """Bilinear weights of every ROI pixel's rest gel point on the depth field's grid, cached per grid position."""
        key = depth.grid_key()
        if self._lookup is None or self._lookup_key != key:
            self._lookup = GridLookup.build(key, self._gel_xy()).reshape(self.roi.height_px, self.roi.width_px)
            self._lookup_key = key
            # For the kernel: pixels off the grid point at the block of zeros after the last node.
            base = self._lookup.base
            self._kernel_base = np.where(base < 0, key[2] * key[5], base).astype(np.int32)
        return self._lookup

    def _sample(self, depth: DepthField, rect: Rect) -> Array:
        """The depth field's node slopes interpolated at the pixels of a ROI rect, (h, w)."""
        x0, x1, y0, y1 = rect
        return self._grid_lookup(depth).sample(depth.slope, np.s_[y0:y1, x0:x1])

    def _slope_box(self, depth: DepthField | None) -> Rect | None:
        """ROI pixel box (x0, x1, y0, y1; exclusive ends, ROI coordinates) holding the slope above tolerance."""
        if depth is None:
            return None
        return self._pixel_box(depth.slope_bbox_mm(self.slope_tol))

    def _pixel_box(self, box_mm: tuple[float, float, float, float] | None) -> Rect | None:
        """ROI pixel box holding the image of a gel-frame box (mm), with a 2-3 px margin; None if empty.

        Cached per box: the boxes lie on the depth grid's nodes, so while a contact's anchor stays
        put the same few recur at every re-shade (each a projection of 36 points otherwise)."""
        if box_mm is None:
            return None
        if box_mm in self._pixel_boxes:
            return self._pixel_boxes[box_mm]
        if len(self._pixel_boxes) >= _PIXEL_BOX_CACHE:
            self._pixel_boxes.clear()
        rect = self._project_box(box_mm)
        self._pixel_boxes[box_mm] = rect
        return rect

    def _project_box(self, box_mm: tuple[float, float, float, float]) -> Rect | None:
        """:meth:`_pixel_box` computed: the box's edges projected at 9 points each."""
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

    def _on_shown_grid(self, depth: DepthField | None) -> DepthField | None:
        """``depth``, or, when its grid is the shown field's translated by at most :data:`FIXED_GRID_DRIFT_NODES`
        nodes (a sliding contact's field moves with it), its depth and slope resampled onto the shown grid.

        On one grid the re-shade can keep to the nodes whose slope moved (:meth:`_reshade`); a grid that moves at
        every render would re-shade its whole slope box, which in a shear is most of the ROI. The resampled field
        only chooses what to re-shade; the pixels re-shaded take their slope from ``depth`` on its own grid."""
        shown = self._depth
        if depth is None or shown is None:
            return depth
        x0, x1, nx, y0, y1, ny = depth.grid_key()
        sx0, sx1, snx, sy0, sy1, sny = shown.grid_key()
        if (x0, y0) == (sx0, sy0) or (nx, ny) != (snx, sny) or not np.isclose(x1 - x0, sx1 - sx0, rtol=1e-9, atol=0.0) \
                or not np.isclose(y1 - y0, sy1 - sy0, rtol=1e-9, atol=0.0):
            return depth
        dx_nodes = (sx0 - x0) / (x1 - x0) * (nx - 1)
        dy_nodes = (sy0 - y0) / (y1 - y0) * (ny - 1)
        if max(abs(dx_nodes), abs(dy_nodes)) > FIXED_GRID_DRIFT_NODES:
            return depth
        depth_mm, slope = np.empty_like(depth.depth_mm, dtype=np.float64), np.empty_like(depth.slope)
        _k.translate_nodes(np.ascontiguousarray(depth.depth_mm, dtype=np.float64), dx_nodes, dy_nodes, depth_mm)
        _k.translate_nodes(depth.slope, dx_nodes, dy_nodes, slope)
        moved = DepthField(shown.x_mm, shown.y_mm, depth_mm)
        moved.__dict__["slope"] = slope  # the field's own slope resampled, not one of the resampled depth
        return moved

    def _reshade(self, depth: DepthField | None) -> tuple[Rect | None, Rect | None]:
        """Take a new depth field: (ROI rect to compose, rect within it to re-shade from the field; None if none).

        Pixels of the old slope box left outside the new one are reset to 1 here;
        the re-shading itself is fused with the composition (:meth:`_compose_block`).
        """
        if depth is not None and depth.same_as(self._depth):  # a new object for the same field (e.g. shear)
            self._depth = depth
            return None, None
        old_box = self._shade_box
        box = self._slope_box(depth)
        self._depth = depth
        if depth is None or box is None:
            self._shade_box, self._shade_key, self._shade_nodes = None, None, None
            if old_box is None:
                return None, None
            x0, x1, y0, y1 = old_box
            self._shade[y0:y1, x0:x1] = 1.0
            return old_box, None
        slope = depth.slope
        key = depth.grid_key()
        if box == old_box and key == self._shade_key and self._shade_nodes is not None:
            # Same box on the same grid: re-shade only around the nodes whose slope moved by more than shade_tol.
            moved = np.abs(slope - self._shade_nodes) > self.shade_tol
            rows = np.flatnonzero(moved.any(axis=1))
            if rows.size == 0:
                return None, None
            cols = np.flatnonzero(moved[rows[0] : rows[-1] + 1].any(axis=0))
            j0, j1, i0, i1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
            self._shade_nodes[j0:j1, i0:i1] = slope[j0:j1, i0:i1]  # their dependent pixels are all re-shaded
            ny, nx = slope.shape
            area = self._pixel_box((
                float(depth.x_mm[max(i0 - 1, 0)]), float(depth.x_mm[min(i1, nx - 1)]),
                float(depth.y_mm[max(j0 - 1, 0)]), float(depth.y_mm[min(j1, ny - 1)]),
            ))
            rect = _intersect(area, box)
            return rect, rect
        self._shade_box, self._shade_key, self._shade_nodes = box, key, slope.copy()
        if old_box is not None:
            x0, x1, y0, y1 = old_box
            self._shade[y0:y1, x0:x1] = 1.0
        return (box if old_box is None else _union(old_box, box)), box

    # -- composition -------------------------------------------------------------------------------

    def _intensity(self, lum: Array, shade: Array, led: float) -> Array:
        """``led * clip(shade * lum, 0, 1)`` (both factors are positive)."""
        out = np.multiply(shade, lum)
        out = np.minimum(out, 1.0, out=out)
        out *= led
        return out

    def _compose_block(self, rect: Rect, shade_rect: Rect | None) -> PixelBlock:
        """Re-shade ``shade_rect`` (inside ``rect``) from the current depth field, compose ``rect``, update the
        reported image where it changed; the changes as a dense block (one fused pass, :mod:`._render_kernels`)."""
        x0, x1, y0, y1 = rect
        changed = np.empty((y1 - y0, x1 - x0), dtype=bool)
        values = np.empty((y1 - y0, x1 - x0))
        gel_x, gel_y = self._gel_planes()
        base, tx, ty = _NO_LOOKUP
        field = self._source  # the caller's field shades the pixels; the one shown may be it on the grid it left
        if shade_rect is not None and field is not None:
            key = field.grid_key()
            x0_mm, x1_mm, nx, y0_mm, y1_mm, ny = key
            grid = (x0_mm, x1_mm, float(nx), y0_mm, y1_mm, float(ny))
            # A grid that stays put (a contact whose anchor holds) gets a table of every pixel's weights; one that
            # moves at each render (a sliding contact) has them computed in the loop, for the pixels it re-shades.
            if key == self._lookup_key or key == self._last_shade_key:
                lookup = self._grid_lookup(field)
                base, tx, ty = self._kernel_base, lookup.tx, lookup.ty
            self._last_shade_key = key
            nodes = np.zeros(field.slope.size + nx + 2)  # the zeros: pixels off the grid read them
            nodes[: field.slope.size] = field.slope.ravel()
        else:
            shade_rect, nodes, nx, grid = (0, 0, 0, 0), _NO_NODES, 2, _NO_GRID
        _k.shade_compose(rect, shade_rect, nodes, nx, base, tx, ty, grid, gel_x, gel_y, float(self.lighting.slope_gain),
                         self._shade, self._lum.reshape(self._canvas_shape), self._pad, self._reported, self._led,
                         float(self.min_rel_change), changed, values)
        return PixelBlock(y0, x0, changed, values)

    def _compose_pixels(self, pixels: Index) -> tuple[Index, Array]:
        """Compose scattered ROI pixels; update the reported image; (pixels that changed, their new intensity)
        (one compiled pass, :func:`._render_kernels.compose_list`)."""
        if pixels.size == 0:
            return pixels, np.empty(0)
        out_pix, out_val = np.empty(pixels.size, dtype=np.int64), np.empty(pixels.size)
        m = _k.compose_list(pixels, pixels.size, self._roi_to_canvas, self._lum, self._shade.ravel(),
                            self._reported.ravel(), self._led, float(self.min_rel_change), out_pix, out_val)
        return out_pix[:m], out_val[:m]


def _led_level(led: float) -> float:
    """The LED ring's level in [0, 1] (True: 1, False: 0)."""
    level = float(led)
    if not 0.0 <= level <= 1.0:
        raise ValueError(f"the LED ring's level must be in [0, 1], not {level}")
    return level


def _union(a: Rect, b: Rect) -> Rect:
    return min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3])


def _intersect(a: Rect | None, b: Rect) -> Rect | None:
    if a is None:
        return None
    x0, x1, y0, y1 = max(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), min(a[3], b[3])
    return (x0, x1, y0, y1) if x1 > x0 and y1 > y0 else None
