"""Synthetic windows that take a pipeline through its first-window costs before a stream starts.

A pipeline's first window loads its compiled kernels (the tracker's, the SAE's, the camera's: tens of
milliseconds from numba's cache) and the depth network's first run allocates its buffers. On a live
stream that window's delay carries over to the windows queued behind it, so a live run takes the
pipeline through :func:`press_windows` on throwaway state first
(:meth:`labrig.pipeline.runtime.Pipeline.warm_up`).

The windows are events at the markers' rest pixels (both polarities, as a marker's edge gives) and a
shallow dent on the network grid, so that the tracker, the signed counts, the SAE and the force
solvers all run their usual paths. One window holds a single event: numba types a one-element field
view as contiguous, which loads another specialisation of every kernel that takes event columns.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import numpy.typing as npt

from labrig.eventtypes import EVENT_DTYPE
from labrig.physics.grid import GRID_SHAPE

#: Events per marker per synthetic window.
EVENTS_PER_MARKER = 12
#: The synthetic dent's depth (mm) and radius (grid cells).
DENT_DEPTH_MM = 0.3
DENT_RADIUS_CELLS = 8.0


def press_windows(rest_px: npt.ArrayLike, observed: npt.ArrayLike | None, window_us: int,
                  seed: int = 0) -> Iterator[tuple[int, int, npt.NDArray]]:
    """Windows (t0_us, t1_us, events) of ``window_us`` each from t = 0: EVENT_DTYPE events around the observed
    markers' rest pixels (M, 2) px, within a pixel, times spread over the window; :data:`EVENTS_PER_MARKER` per
    marker, then one event, none, and as many again."""
    rng = np.random.default_rng(seed)
    rest = np.asarray(rest_px, np.float64)
    if observed is not None:
        rest = rest[np.asarray(observed, bool)]
    full = len(rest) * EVENTS_PER_MARKER
    for k, n in enumerate((full, 1, 0, full)):
        events = np.zeros(n, EVENT_DTYPE)
        where = np.repeat(rest, EVENTS_PER_MARKER, axis=0)[:n] + rng.uniform(-1.0, 1.0, (n, 2))
        events["x"] = np.clip(np.rint(where[:, 0]), 0, np.iinfo(np.uint16).max)
        events["y"] = np.clip(np.rint(where[:, 1]), 0, np.iinfo(np.uint16).max)
        events["p"] = rng.integers(0, 2, n)
        events["t"] = np.sort(rng.integers(k * window_us, (k + 1) * window_us, n))
        yield k * window_us, (k + 1) * window_us, events


def dent_map(depth_mm: float = DENT_DEPTH_MM, radius_cells: float = DENT_RADIUS_CELLS) -> npt.NDArray[np.float32]:
    """(90, 112) float32: a spherical-cap dent ``depth_mm`` deep at the grid's centre (mm into the gel)."""
    rows, cols = GRID_SHAPE
    r, c = np.mgrid[0:rows, 0:cols]
    rho2 = ((r - rows / 2) ** 2 + (c - cols / 2) ** 2) / radius_cells**2
    return (depth_mm * np.clip(1.0 - rho2, 0.0, None)).astype(np.float32)
