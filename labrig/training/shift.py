"""Translation augmentation: a training window moved across the grid, its input and its ground truth together.

A campaign presses at a few locations, and the depth at a location is then part of what a network can
learn: trained on deep presses at the centre and shallow ones at the sides, a U-Net (whose padding lets it
tell where it is) answers a deep press at the side with a shallow dent. Moving each window by a random
whole number of grid cells, the network's input and the depth map alike, shows every press at many
locations, so that the answer follows the image and not the place. A window moves by at most
``max_cells`` cells per axis; cells that come from outside the grid are zero (no event, no change, no
depth), and what leaves the grid is dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.sae import crop_from_unet, pad_for_unet


def shifted(a: npt.NDArray[Any], dr: int, dc: int) -> npt.NDArray[Any]:
    """``a`` (..., rows, cols) moved by ``dr`` rows and ``dc`` columns, zeros where it came from outside."""
    out = np.zeros_like(a)
    rows, cols = a.shape[-2:]
    if abs(dr) >= rows or abs(dc) >= cols:
        return out
    out[..., max(dr, 0):rows + min(dr, 0), max(dc, 0):cols + min(dc, 0)] = \
        a[..., max(-dr, 0):rows + min(-dr, 0), max(-dc, 0):cols + min(-dc, 0)]
    return out


@dataclass(frozen=True)
class ShiftAugment:
    """Moves a training window by up to ``max_cells`` grid cells per axis, drawn uniformly."""

    max_cells: int

    def draw(self, rng: np.random.Generator) -> tuple[int, int]:
        """(rows, cols) to move by, each uniform in [-max_cells, max_cells]."""
        dr, dc = rng.integers(-self.max_cells, self.max_cells + 1, 2)
        return int(dr), int(dc)

    def apply(self, sample: Any, dr: int, dc: int) -> Any:
        """``sample`` (:class:`labrig.training.data.Sample`: input (C, 96, 112) padded, target and contact
        (90, 112)) moved by (dr, dc) cells: the input within the grid, before its padding, so that it stays
        aligned with the target."""
        network_input = pad_for_unet(shifted(crop_from_unet(sample.sae, GRID_SHAPE), dr, dc))
        return replace(sample, sae=network_input.astype(np.float32), target=shifted(sample.target, dr, dc),
                       contact=shifted(sample.contact, dr, dc))

    def describe(self) -> dict[str, Any]:
        return {"max_cells": self.max_cells, "fill": "zero (no event, no change, no depth)",
                "draw": "uniform whole cells per axis, input and ground truth together"}
