"""Sets of ROI pixels: flat index lists and dense rectangular blocks.

A render step changes two kinds of pixel sets: a few thousand scattered
pixels (the rims of moving markers), best kept as flat row-major indices,
and, when the membrane's shading changes, most of a large rectangle, best
kept as a dense block (a boolean mask of the changed pixels and their new
values over the rectangle) so that per-pixel work runs on contiguous slices
instead of gathers and scatters. :class:`PixelBlock` is that dense form.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Index = npt.NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class PixelBlock:
    """Changed pixels of the rectangle rows y0..y0+h, columns x0..x0+w of a pixel window.

    ``changed`` (h, w) marks the pixels that changed; ``values`` (h, w) holds the
    window's values over the whole rectangle after the change: the new value
    where ``changed``, elsewhere exactly the value the pixel already had (a
    consumer may then process the rectangle without masking the values).
    """

    y0: int
    x0: int
    changed: npt.NDArray[np.bool_]
    values: npt.NDArray[np.float64]

    @property
    def shape(self) -> tuple[int, int]:
        return self.changed.shape  # type: ignore[return-value]

    def flat_indices(self, width: int) -> Index:
        """Row-major indices, in a window ``width`` pixels wide, of the changed pixels."""
        rows, cols = np.divmod(np.flatnonzero(self.changed), self.changed.shape[1])
        return (rows + self.y0) * width + (cols + self.x0)

    def changed_values(self) -> npt.NDArray[np.float64]:
        """New values of the changed pixels, in :meth:`flat_indices` order."""
        return self.values[self.changed]
