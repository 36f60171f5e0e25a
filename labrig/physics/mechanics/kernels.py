"""Surface kernels of one gel on one grid: the entry point to the convolutions.

``SurfaceKernels(grid, gel, mode)`` bundles the influence coefficients
(:mod:`influence`, computed once and cached per grid, gel and mode) and hands
out cached DC-FFT convolvers (:mod:`convolution`) between rectangles of the
grid. Modes: ``"halfspace"`` (Boussinesq/Cerruti) and ``"layer"`` (the gel as a
layer of ``gel.thickness_mm`` bonded to a rigid window, frictionless top for
the normal kernel). The gel is laterally infinite in both modes.

Rectangles are :class:`Box` objects in cell indices of the grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.config import GelConfig
from labrig.physics.mechanics.convolution import SurfaceConvolver, coefficient_window, convolver
from labrig.physics.mechanics.grid import Grid
from labrig.physics.mechanics.influence import check_mode, normal_coefficients, tangential_coefficients


@dataclass(frozen=True)
class Box:
    """Rows y0:y1 and columns x0:x1 of a grid (end exclusive)."""

    y0: int
    y1: int
    x0: int
    x1: int

    @classmethod
    def around(cls, mask: npt.NDArray[np.bool_], margin: int = 0) -> Box:
        """Bounding box of ``mask`` grown by ``margin`` cells, clipped to the array; whole array if empty."""
        ny, nx = mask.shape
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        if rows.size == 0:
            return cls(0, ny, 0, nx)
        return cls(
            max(int(rows[0]) - margin, 0),
            min(int(rows[-1]) + 1 + margin, ny),
            max(int(cols[0]) - margin, 0),
            min(int(cols[-1]) + 1 + margin, nx),
        )

    @classmethod
    def full(cls, shape: tuple[int, int]) -> Box:
        return cls(0, shape[0], 0, shape[1])

    @property
    def shape(self) -> tuple[int, int]:
        return (self.y1 - self.y0, self.x1 - self.x0)

    @property
    def slices(self) -> tuple[slice, slice]:
        return (slice(self.y0, self.y1), slice(self.x0, self.x1))

    def union(self, other: Box) -> Box:
        return Box(min(self.y0, other.y0), max(self.y1, other.y1), min(self.x0, other.x0), max(self.x1, other.x1))

    def contains(self, other: Box) -> bool:
        return self.y0 <= other.y0 and self.x0 <= other.x0 and self.y1 >= other.y1 and self.x1 >= other.x1


@dataclass(frozen=True)
class SurfaceKernels:
    """Normal and tangential surface responses of ``gel`` on ``grid`` in ``mode``."""

    grid: Grid
    gel: GelConfig
    mode: str = "layer"

    def __post_init__(self) -> None:
        check_mode(self.mode)

    @property
    def normal_coefficients(self) -> npt.NDArray[np.float64]:
        """(1, 2ny-1, 2nx-1) uz per unit pressure on a cell, mm/MPa."""
        return normal_coefficients(self.grid, self.gel, self.mode)

    @property
    def tangential_coefficients(self) -> npt.NDArray[np.float64]:
        """(3, 2ny-1, 2nx-1) [xx, xy, yy] in-plane displacement per unit traction on a cell, mm/MPa."""
        return tangential_coefficients(self.grid, self.gel, self.mode)

    def normal(self, source: Box, target: Box | None = None) -> SurfaceConvolver:
        """Convolver: pressure (1, *source.shape) -> uz (1, *target.shape)."""
        return self._convolver(self.normal_coefficients, source, target)

    def tangential(self, source: Box, target: Box | None = None) -> SurfaceConvolver:
        """Convolver: traction (2, *source.shape) -> (ux, uy) (2, *target.shape)."""
        return self._convolver(self.tangential_coefficients, source, target)

    def tangential_window(self, source: Box, target: Box) -> npt.NDArray[np.float64]:
        """The tangential coefficients a source -> target convolver needs (to store with a table)."""
        return coefficient_window(self.tangential_coefficients, source.shape, target.shape, _offset(source, target))

    def _convolver(self, coefficients: npt.NDArray[np.float64], source: Box, target: Box | None) -> SurfaceConvolver:
        target = source if target is None else target
        return convolver(coefficients, source.shape, target.shape, _offset(source, target))


def _offset(source: Box, target: Box) -> tuple[int, int]:
    return (target.y0 - source.y0, target.x0 - source.x0)
