"""Quiet windows: when a window's events are only the sensor's background noise, nothing moved.

An event camera reports change. While the indenter rests (before contact, and in the
protocol's waits) a window holds only noise events, spread evenly over the array, and the
depth network answers that nearly empty SAE with a thin false dimple: summed over the gel
by the inverse FEM, tens of newtons of normal force at rest. The gel has not moved, so the
depth map of the last window that saw motion still holds; :class:`QuietHold` keeps it
(zeros before any motion).

The noise floor is a low percentile of recent event rates (events/s in the network's
window): the sensor's noise differs with the sensor, the light and the bias settings, so it
is measured, not configured. A window is quiet when its rate is below ``quiet_ratio`` times
the floor. A stream starts at rest: its first window defines the floor and is quiet. The
floor forgets after ``history_windows``; a motion that never pauses for ``floor_percentile``
percent of that history would raise the floor to its own rate (the protocol pauses between
every phase).

A noisy sensor hides motion in the total rate: at 1-2 Hz of noise per pixel the ROI's
background is 5,000-10,000 events per 10 ms, more than a slow press adds. Motion is local,
noise is spread evenly, so :class:`TileActivity` also counts the SAE's active cells per
tile against each tile's own floor (a low percentile, so a hot pixel raises only its own
tile's); a tile far above its floor (``tile_z`` standard deviations of the binomial count
whose low percentile the floor is) makes the window active whatever the total rate says.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True)
class QuietParams:
    """How quiet windows are found. ``history_windows`` at 10 ms windows is about 20 s."""

    history_windows: int = 2048
    floor_percentile: float = 5.0
    quiet_ratio: float = 1.6
    tiles: tuple[int, int] | None = None  # rows x columns of tiles over the SAE grid; None: the rate alone
    tile_z: float = 6.0
    refresh_windows: int = 32  # the tile floors are recomputed every this many windows

    def __post_init__(self) -> None:
        if self.history_windows < 1:
            raise ValueError("history_windows must be at least 1")
        if not 0.0 <= self.floor_percentile <= 100.0:
            raise ValueError("floor_percentile must be in [0, 100]")
        if self.quiet_ratio <= 0.0:
            raise ValueError("quiet_ratio must be positive")
        if self.tiles is not None and min(self.tiles) < 1:
            raise ValueError("tiles must be at least 1 x 1")
        if self.tile_z <= 0.0 or self.refresh_windows < 1:
            raise ValueError("tile_z and refresh_windows must be positive")


class NoiseFloor:
    """Running noise-floor estimate over the last windows' event rates (events/s)."""

    def __init__(self, params: QuietParams = QuietParams()) -> None:
        self.params = params
        self._rates_hz: deque[float] = deque(maxlen=params.history_windows)
        self.floor_hz = float("nan")

    def is_quiet(self, n_events: int, duration_us: float) -> bool:
        """Add one window (``n_events`` over ``duration_us``) and say whether it is quiet."""
        rate_hz = n_events / max(float(duration_us), 1.0) * 1e6
        self._rates_hz.append(rate_hz)
        self.floor_hz = float(np.percentile(self._rates_hz, self.params.floor_percentile))
        return rate_hz < self.params.quiet_ratio * self.floor_hz or n_events == 0


def active_cells_per_tile(sae_grid: npt.NDArray[np.float32], tiles: tuple[int, int]) -> npt.NDArray[np.int64]:
    """Cells with an event of either polarity, summed per tile: (tile rows, tile columns)."""
    active = (sae_grid > 0).any(axis=0) if sae_grid.ndim == 3 else sae_grid > 0
    rows, cols = active.shape
    r_edges = (np.arange(tiles[0]) * rows) // tiles[0]
    c_edges = (np.arange(tiles[1]) * cols) // tiles[1]
    per_row = np.add.reduceat(active.astype(np.int64), r_edges, axis=0)
    return np.add.reduceat(per_row, c_edges, axis=1)


class TileActivity:
    """Per-tile floors of the SAE's active cells; says when one tile rises far above its own."""

    def __init__(self, params: QuietParams = QuietParams()) -> None:
        assert params.tiles is not None
        self.params = params
        self._counts: deque[npt.NDArray[np.int64]] = deque(maxlen=params.history_windows)
        self.floor: npt.NDArray[np.float64] | None = None
        self._cells: npt.NDArray[np.float64] | None = None  # cells per tile
        self._since_refresh = 0

    def is_active(self, sae_grid: npt.NDArray[np.float32]) -> bool:
        """Add one window's SAE and say whether a tile is far above its floor."""
        assert self.params.tiles is not None
        counts = active_cells_per_tile(sae_grid, self.params.tiles)
        if self._cells is None:
            self._cells = active_cells_per_tile(np.ones(sae_grid.shape[-2:], bool), self.params.tiles).astype(float)
        self._counts.append(counts)
        self._since_refresh += 1
        refresh = self._since_refresh >= self.params.refresh_windows or len(self._counts) < self.params.refresh_windows
        if self.floor is None or refresh:
            self.floor = np.percentile(np.stack(self._counts), self.params.floor_percentile, axis=0)
            self._since_refresh = 0
        return bool(np.any(counts > self.threshold()))

    def threshold(self) -> npt.NDArray[np.float64]:
        """Active cells per tile above which a tile moves.

        Noise makes each of a tile's ``n`` cells active with some probability, so its count is
        binomial (it saturates as the noise fills the cells). The mean ``mu`` is the one whose
        low percentile is the floor, ``mu - z_p sigma(mu) = floor`` with ``sigma^2 = mu (1 - mu / n)``
        (a quadratic in ``mu``); the threshold is ``tile_z`` sigmas above it.
        """
        assert self.floor is not None and self._cells is not None
        p = self.params.floor_percentile
        z_p = NormalDist().inv_cdf(1.0 - p / 100.0) if 0.0 < p < 50.0 else 0.0
        n, f = self._cells, np.clip(self.floor, 0.0, self._cells)
        a = 1.0 + z_p**2 / n
        b = 2.0 * f + z_p**2
        mu = (b + np.sqrt(np.maximum(b**2 - 4.0 * a * f**2, 0.0))) / (2.0 * a)
        return mu + self.params.tile_z * np.sqrt(np.maximum(mu * (1.0 - mu / n), 1.0))


class QuietHold:
    """Keeps the last active window's depth map through quiet windows (zeros before any motion)."""

    def __init__(self, shape: tuple[int, ...], params: QuietParams = QuietParams()) -> None:
        self.floor = NoiseFloor(params)
        self.tiles = TileActivity(params) if params.tiles is not None else None
        self.held_mm = np.zeros(shape, np.float32)
        self.quiet = False

    def __call__(self, n_events: int, duration_us: float, sae_grid: npt.NDArray[np.float32] | None = None) -> bool:
        """True when the window is quiet (use :attr:`held_mm`); else call :meth:`update` with its map.

        Quiet: the total rate is near the noise floor and (given the window's SAE) no tile rises
        far above its own floor.
        """
        quiet = self.floor.is_quiet(n_events, duration_us)
        if self.tiles is not None and sae_grid is not None:
            quiet = not self.tiles.is_active(sae_grid) and quiet  # both floors see every window
        self.quiet = quiet
        return quiet

    def update(self, depth_mm: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        self.held_mm = depth_mm
        return depth_mm
