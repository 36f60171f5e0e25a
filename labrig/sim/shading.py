"""Slope shading of the membrane under the LED ring, from a depth field on a gel-frame grid.

Model: the LED ring lights the membrane at grazing angles all round, so a
tilted patch of membrane scatters more light towards the camera whatever the
tilt's direction. The relative brightness is ``S = 1 + slope_gain * |grad d|``
with ``d`` the depth field (mm, either sign: only the slope magnitude counts)
and ``|grad d|`` the surface slope (mm/mm, dimensionless). Flat membrane has S = 1.
The gradient is taken by central differences on the grid (one-sided at its
edges), the slope magnitude at the nodes, and interpolated bilinearly between them.

Small-displacement approximation: the membrane point seen by a pixel is taken
where the pixel's ray meets the undeformed surface z = 0 (the rest
back-projection), not where it meets the deformed surface; the error is the
lateral surface displacement (below ~1 mm), small against the width of a
contact's slope field.

Sampling cost: the pixels' gel points are fixed, so the bilinear weights of
every pixel on a grid (:class:`GridLookup`) are computed once per grid
position (a contact keeps its grid while its anchor stays put); the renderer
applies them in a fused loop (:mod:`labrig.sim._render_kernels`). A grid that
moves at every render (a sliding contact) has the weights computed in that
loop instead, for the pixels it re-shades, by the same arithmetic.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt

from labrig.sim import _render_kernels as _k

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class DepthField:
    """Surface depth ``depth_mm[iy, ix]`` (mm) on the regular gel-frame grid ``x_mm`` (nx,), ``y_mm`` (ny,)."""

    x_mm: Array
    y_mm: Array
    depth_mm: Array

    def __post_init__(self) -> None:
        if self.depth_mm.shape != (len(self.y_mm), len(self.x_mm)) or len(self.x_mm) < 2 or len(self.y_mm) < 2:
            raise ValueError(f"depth_mm must be (ny, nx) = ({len(self.y_mm)}, {len(self.x_mm)}) with nx, ny >= 2")

    @cached_property
    def slope(self) -> Array:
        """Surface slope magnitude |grad depth| (dimensionless) at the grid nodes, (ny, nx) (one compiled pass:
        :func:`~labrig.sim._render_kernels.slope_magnitude`, the arithmetic of :func:`slope_of`)."""
        d = np.ascontiguousarray(self.depth_mm, dtype=np.float64)
        x0, x1, nx, y0, y1, ny = self.grid_key()
        out = np.empty_like(d)
        _k.slope_magnitude(d, (x1 - x0) / (nx - 1), (y1 - y0) / (ny - 1), out)
        return out

    def same_as(self, other: DepthField | None) -> bool:
        """Whether ``other`` holds the same grid and depth values (then both share one computed slope)."""
        if other is None or other.grid_key() != self.grid_key() or not np.array_equal(other.depth_mm, self.depth_mm):
            return False
        for a, b in ((self, other), (other, self)):
            if "slope" in a.__dict__ and "slope" not in b.__dict__:
                b.__dict__["slope"] = a.__dict__["slope"]  # the cached_property's own storage
        return True

    def slope_bbox_mm(self, tol: float) -> tuple[float, float, float, float] | None:
        """(x0, x1, y0, y1) gel-frame box (mm) holding every node with slope > tol, grown by one node; None if flat."""
        rows0, rows1, cols0, cols1 = _k.above_box(self.slope, float(tol))
        if rows0 < 0:
            return None
        return self._grown_box_mm(rows0, rows1, cols0, cols1)

    def node_box_mm(self, nodes: npt.NDArray[np.bool_]) -> tuple[float, float, float, float] | None:
        """(x0, x1, y0, y1) gel-frame box (mm) of the marked nodes (ny, nx), grown by one node; None if none."""
        rows = np.flatnonzero(nodes.any(axis=1))
        if rows.size == 0:
            return None
        cols = np.flatnonzero(nodes[rows[0] : rows[-1] + 1].any(axis=0))
        return self._grown_box_mm(int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1]))

    def _grown_box_mm(self, row0: int, row1: int, col0: int, col1: int) -> tuple[float, float, float, float]:
        """The gel-frame box (mm) of node rows and columns (inclusive), grown by one node within the grid."""
        nx, ny = len(self.x_mm), len(self.y_mm)
        i0, i1 = max(col0 - 1, 0), min(col1 + 1, nx - 1)
        j0, j1 = max(row0 - 1, 0), min(row1 + 1, ny - 1)
        return float(self.x_mm[i0]), float(self.x_mm[i1]), float(self.y_mm[j0]), float(self.y_mm[j1])

    def grid_key(self) -> tuple[float, float, int, float, float, int]:
        """The grid's geometry (x0, x1, nx, y0, y1, ny): fields with equal keys share a :class:`GridLookup`."""
        x, y = self.x_mm, self.y_mm
        return float(x[0]), float(x[-1]), len(x), float(y[0]), float(y[-1]), len(y)

    def sample_slope(self, xy_mm: npt.ArrayLike) -> Array:
        """Bilinearly interpolated slope at gel points (N, 2) mm; 0 outside the grid."""
        return GridLookup.build(self.grid_key(), xy_mm).sample(self.slope, slice(None))


def slope_of(depth_mm: Array, dx_mm: float, dy_mm: float) -> Array:
    """|grad depth| on a uniform grid by numpy passes (the model of :attr:`DepthField.slope`'s kernel)."""
    gx = _derivative(np.asarray(depth_mm, dtype=np.float64), dx_mm, axis=1)
    gy = _derivative(np.asarray(depth_mm, dtype=np.float64), dy_mm, axis=0)
    gx *= gx
    gy *= gy
    gx += gy
    return np.sqrt(gx, out=gx)


def _derivative(values: Array, spacing: float, axis: int) -> Array:
    """d values / d axis on a uniform grid: central differences, one-sided at the two edges (as np.gradient)."""
    v = np.moveaxis(values, axis, 0)
    out = np.empty_like(v)
    np.subtract(v[2:], v[:-2], out=out[1:-1])
    out[1:-1] /= 2.0 * spacing
    np.subtract(v[1], v[0], out=out[0])
    np.subtract(v[-1], v[-2], out=out[-1])
    out[0] /= spacing
    out[-1] /= spacing
    return np.moveaxis(out, 0, axis)


@dataclass(frozen=True, eq=False)
class GridLookup:
    """Bilinear interpolation weights of fixed query points on a regular grid, reusable across fields.

    ``base`` is the flat index of each point's lower-left node (-1: outside the grid);
    ``tx``, ``ty`` its fractional offsets in grid cells.
    """

    base: npt.NDArray[np.int64]
    tx: Array
    ty: Array
    nx: int
    ny: int = 0

    @classmethod
    def build(cls, grid_key: tuple[float, float, int, float, float, int], xy_mm: npt.ArrayLike) -> GridLookup:
        """Weights for points (N, 2) mm on the grid described by :meth:`DepthField.grid_key`."""
        x0, x1, nx, y0, y1, ny = grid_key
        xy = np.asarray(xy_mm, dtype=np.float64)
        fx = (xy[:, 0] - x0) / (x1 - x0) * (nx - 1)
        fy = (xy[:, 1] - y0) / (y1 - y0) * (ny - 1)
        inside = (fx >= 0) & (fx <= nx - 1) & (fy >= 0) & (fy <= ny - 1)
        ix = np.clip(np.floor(fx).astype(np.int64), 0, nx - 2)
        iy = np.clip(np.floor(fy).astype(np.int64), 0, ny - 2)
        base = np.where(inside, iy * nx + ix, -1)
        return cls(base, np.clip(fx - ix, 0.0, 1.0), np.clip(fy - iy, 0.0, 1.0), nx, ny)

    def reshape(self, *shape: int) -> GridLookup:
        """The same lookup with its points arranged in ``shape`` (e.g. an image), for slicing."""
        return GridLookup(self.base.reshape(shape), self.tx.reshape(shape), self.ty.reshape(shape), self.nx, self.ny)

    def sample(self, grid_values: Array, points: npt.NDArray[np.int64] | slice | tuple[slice, ...]) -> Array:
        """Interpolate ``grid_values`` (ny, nx) at the points selected by ``points`` (any numpy index); 0 outside."""
        base = self.base[points]
        outside = base < 0
        v = np.asarray(grid_values).ravel()
        # Points outside the grid read a block of zeros appended after the last node.
        padded = np.concatenate([v, np.zeros(self.nx + 2, dtype=v.dtype)])
        b = np.where(outside, v.size, base) if outside.any() else base
        tx, ty = self.tx[points], self.ty[points]
        low = padded.take(b)
        low += (padded.take(b + 1) - low) * tx
        high = padded.take(b + self.nx)
        high += (padded.take(b + self.nx + 1) - high) * tx
        high -= low
        high *= ty
        low += high
        return low


def slope_shading(slope: npt.ArrayLike, slope_gain: float) -> Array:
    """Relative membrane brightness ``1 + slope_gain * slope`` (dimensionless)."""
    return 1.0 + slope_gain * np.asarray(slope, dtype=np.float64)
