"""Events per cell of the network grid, weighed by the camera's contrast thresholds: log-intensity change.

An event fires each time a pixel's log intensity moves by its contrast threshold, so ``C_on`` times
a pixel's ON events less ``C_off`` times its OFF events is its log-intensity change. Counted per cell
of the network grid (:mod:`labrig.physics.grid`, the cells of :func:`labrig.pipeline.sae.sae_grid`)
in **reference events** (the change over
:data:`~labrig.calibration.event_thresholds_file.NOMINAL_THRESHOLD_LN`), it is the unit of the depth
network's brightness channel (:mod:`labrig.pipeline.brightness`) and of the light's slope fit
(:mod:`labrig.calibration.slope_response`).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from labrig.calibration.event_thresholds_file import ContrastThresholds
from labrig.config import Roi
from labrig.errors import LabrigError
from labrig.physics.grid import GRID_SHAPE, grid_cells_of_pixels

F32 = npt.NDArray[np.float32]


def signed_counts(events: npt.NDArray, roi: Roi, grid_shape: tuple[int, int] = GRID_SHAPE,
                  thresholds: ContrastThresholds | None = None) -> F32:
    """(rows, cols) float32: the log-intensity change per grid cell (the cells of ``sae_grid``) in reference
    events, summed over its pixels: ON minus OFF events, each weighted by its cell's threshold over
    :data:`~labrig.calibration.event_thresholds_file.NOMINAL_THRESHOLD_LN` when ``thresholds`` are given
    (else 1); events outside the ROI are dropped."""
    rows, cols = grid_shape
    if len(events) == 0:
        return np.zeros(grid_shape, np.float32)
    cell, inside = grid_cells_of_pixels(events["x"], events["y"], roi.x0_px, roi.y0_px, roi.width_px, roi.height_px,
                                        grid_shape)
    cell, on = cell[inside], events["p"][inside] > 0
    if thresholds is None:
        weight = np.where(on, 1.0, -1.0)
    else:
        if thresholds.on_ln.shape != grid_shape:
            raise LabrigError(f"{thresholds.source}: thresholds on a {thresholds.on_ln.shape} grid, the channel's is "
                              f"{grid_shape}")
        on_weight, off_weight = thresholds.reference_weights
        weight = np.where(on, on_weight[cell], off_weight[cell])
    counts = np.bincount(cell, weights=weight, minlength=rows * cols)
    return counts.reshape(grid_shape).astype(np.float32)
