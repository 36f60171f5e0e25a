"""The local computation grid: square cells centred on the indenter tip.

Cell (i, j) is centred at x = x_mm[j], y = y_mm[i] (mm) relative to the tip, in
the gel frame's x, y directions. Sizes are odd so the tip sits on a cell centre
and a 180 degree rotation of a field is an array reversal. The gel is treated
as laterally infinite: the grid is only where fields are computed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True)
class Grid:
    """ny x nx cells of ``spacing_mm``; the tip is at the centre cell."""

    spacing_mm: float
    ny: int
    nx: int

    def __post_init__(self) -> None:
        if self.spacing_mm <= 0 or self.ny < 1 or self.nx < 1:
            raise ValueError(f"bad grid: spacing {self.spacing_mm} mm, {self.ny} x {self.nx} cells")

    @classmethod
    def centred(cls, size_mm: float | tuple[float, float], spacing_mm: float) -> Grid:
        """The odd-sized grid that covers at least ``size_mm`` (one value, or (y, x))."""
        size_y, size_x = size_mm if isinstance(size_mm, tuple) else (size_mm, size_mm)
        half_y = int(np.ceil(float(size_y) / (2 * spacing_mm) - 1e-9))
        half_x = int(np.ceil(float(size_x) / (2 * spacing_mm) - 1e-9))
        return cls(float(spacing_mm), 2 * half_y + 1, 2 * half_x + 1)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.ny, self.nx)

    @property
    def cell_area_mm2(self) -> float:
        return self.spacing_mm**2

    @property
    def x_mm(self) -> npt.NDArray[np.float64]:
        """Cell-centre x coordinates relative to the tip, mm."""
        return np.asarray((np.arange(self.nx) - self.nx // 2) * self.spacing_mm, dtype=np.float64)

    @property
    def y_mm(self) -> npt.NDArray[np.float64]:
        """Cell-centre y coordinates relative to the tip, mm."""
        return np.asarray((np.arange(self.ny) - self.ny // 2) * self.spacing_mm, dtype=np.float64)

    def mesh_mm(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(x, y) of every cell centre, each (ny, nx)."""
        return np.meshgrid(self.x_mm, self.y_mm)
