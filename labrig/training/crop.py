"""Patch training: each training window cut to a square of the grid that holds its contact.

A U-Net is fully convolutional, so it can learn from patches of the grid and still run on the whole
grid. Most of the 90 x 112 grid of a window is undeformed gel, and a step's cost grows with the
cells it sees: a 64 x 64 patch costs about 0.4 of the whole grid. A patch holds the centre of the
window's contact (the mean of its contact cells), placed uniformly among the patches that hold it;
a window without contact gets a patch anywhere. Its side must be a multiple of 2**pools so that the
network's poolings divide it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.sae import crop_from_unet


@dataclass(frozen=True)
class CropAugment:
    """Cuts a training window to a ``cells`` x ``cells`` patch of the grid that holds its contact's centre."""

    cells: int

    def draw(self, rng: np.random.Generator, contact: np.ndarray) -> tuple[int, int]:
        """(first row, first column) of the patch in the (90, 112) grid, for the window's contact mask."""
        rows, cols = GRID_SHAPE
        side = self.cells
        if contact.any():
            r, c = (float(np.mean(axis)) for axis in np.nonzero(contact))
            r_lo, r_hi = max(0, int(np.ceil(r)) - side + 1), min(rows - side, int(r))
            c_lo, c_hi = max(0, int(np.ceil(c)) - side + 1), min(cols - side, int(c))
        else:
            r_lo, r_hi, c_lo, c_hi = 0, rows - side, 0, cols - side
        return int(rng.integers(r_lo, r_hi + 1)), int(rng.integers(c_lo, c_hi + 1))

    def apply(self, sample: Any, r0: int, c0: int) -> Any:
        """``sample`` (:class:`labrig.training.data.Sample`: input (C, 96, 112) padded, target and contact
        (90, 112)) cut to the patch at (r0, c0): input (C, cells, cells), target and contact (cells, cells)."""
        side = (slice(r0, r0 + self.cells), slice(c0, c0 + self.cells))
        grid_input = crop_from_unet(sample.sae, GRID_SHAPE)
        return replace(sample, sae=np.ascontiguousarray(grid_input[(..., *side)], np.float32),
                       target=np.ascontiguousarray(sample.target[side]),
                       contact=np.ascontiguousarray(sample.contact[side]))

    def describe(self) -> dict[str, Any]:
        return {"cells": self.cells, "place": "uniform among the patches that hold the contact's centre "
                                                 "(anywhere without contact)"}
