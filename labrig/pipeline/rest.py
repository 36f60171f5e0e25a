"""Each recording's rest positions: the calibration's measured ones, refined by the first quiet windows.

The extrinsic calibration measures where every marker rests (px; ``extrinsics.toml``'s
marker map). Between that calibration and a recording the gel may have settled (a
previous press relaxing, the sensor handled): before anything touches it, the tracker
follows that and its estimates while nothing else moves are the markers' rest now.
:class:`RestRefiner` watches the recording's first windows: while they are quiet (the
event rate near the noise floor the first window sets, :class:`~labrig.pipeline.quiet.NoiseFloor`)
it averages the tracker's positions of the observed markers; at the first window with
motion (contact) or after ``windows`` quiet windows the rest is frozen. A marker whose
average left its calibrated rest by more than ``max_shift_px`` keeps the calibrated one
(a tracker that slipped onto noise is not a rest). Missing markers keep theirs.

Displacements are measured from :attr:`RestRefiner.rest_px` (the running average while
refining), so a quiet start shows no displacement and no force.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.pipeline.quiet import NoiseFloor, QuietParams

Array = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class RestParams:
    """How a recording's first quiet windows refine the rest positions; ``windows`` 0 turns it off."""

    windows: int = 50  # quiet windows averaged at most (0.5 s of 10 ms windows)
    max_shift_px: float = 2.0  # farther from the calibrated rest: keep the calibrated one
    quiet_ratio: float = 1.6  # a window is quiet below this times the noise floor

    def __post_init__(self) -> None:
        if self.windows < 0 or self.max_shift_px <= 0 or self.quiet_ratio <= 0:
            raise ValueError("windows must be >= 0, max_shift_px and quiet_ratio positive")


@dataclass(frozen=True)
class RestRefinement:
    """What the refinement did: quiet windows averaged, markers moved (and how far), markers kept."""

    windows: int
    frozen: bool
    shifted_markers: int  # observed markers whose rest moved by more than 0.01 px
    shift_median_px: float
    shift_max_px: float
    rejected_markers: int  # moved beyond max_shift_px: calibrated rest kept


class RestRefiner:
    """Rest positions (M, 2) px for one recording, from ``calibrated_px`` and its first quiet windows."""

    def __init__(self, calibrated_px: npt.ArrayLike, observed: npt.ArrayLike | None = None,
                 params: RestParams = RestParams()) -> None:
        self.calibrated_px = np.array(calibrated_px, np.float64).reshape(-1, 2)
        m = len(self.calibrated_px)
        self.observed = np.ones(m, bool) if observed is None else np.array(observed, bool).reshape(-1)
        if self.observed.shape != (m,):
            raise ValueError(f"observed mask of {self.observed.size} for {m} markers")
        self.params = params
        self._floor = NoiseFloor(QuietParams(quiet_ratio=params.quiet_ratio))
        self._sum = np.zeros((m, 2))
        self._windows = 0
        self.frozen = params.windows == 0
        self.rest_px = self.calibrated_px.copy()
        self._rejected = np.zeros(m, bool)

    def add(self, positions_px: npt.ArrayLike, n_events: int, duration_us: float) -> bool:
        """One window's tracked positions; True while the rest is still being refined."""
        if self.frozen:
            return False
        if not self._floor.is_quiet(n_events, duration_us):
            self.frozen = True
            return False
        self._sum += np.asarray(positions_px, np.float64)
        self._windows += 1
        mean = self._sum / self._windows
        shift = np.linalg.norm(mean - self.calibrated_px, axis=1)
        self._rejected = self.observed & ~(shift <= self.params.max_shift_px)
        use = self.observed & ~self._rejected
        rest = self.calibrated_px.copy()
        rest[use] = mean[use]
        self.rest_px = rest
        self.frozen = self._windows >= self.params.windows
        return not self.frozen

    def summary(self) -> RestRefinement:
        shift = np.linalg.norm(self.rest_px - self.calibrated_px, axis=1)[self.observed]
        return RestRefinement(self._windows, self.frozen, int((shift > 0.01).sum()),
                              float(np.median(shift)) if shift.size else 0.0,
                              float(shift.max()) if shift.size else 0.0, int(self._rejected.sum()))
