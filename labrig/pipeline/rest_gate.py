"""The rest state: when every tracked marker is back at its rest, the gel is flat and the depth is zero.

A depth network that sees events answers a quiet window with whatever it last said (the
quiet hold of :mod:`labrig.pipeline.quiet`) or with a dimple drawn from noise; neither knows
whether the indenter has left. The tracker does: it integrates every marker's motion since
rest. :class:`RestGate` says the gel is at rest once the observed markers' displacement from
the rest they are measured from (px) has stayed at or below ``threshold_px`` for ``windows``
windows in a row; a depth source then answers exactly zero and forgets its held map and its
previous estimate, so no stale dent outlives the press.

``statistic`` picks what must stay below the threshold: ``"max"`` (every marker, the
default) or a percentile of the observed markers (``"p90"``) for a tracker that leaves a few
markers off their rest after a press. A normal press without shear moves the markers in the
image only by parallax (about 1 px at the centre for a 0.75 mm sphere press on the default
rig, docs/depthnet.md), so the threshold must stay below that: 0.3 px by default.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.errors import LabrigError


@dataclass(frozen=True)
class RestGateParams:
    """When the markers are at rest: ``statistic`` of their displacement (px) at or below
    ``threshold_px`` for ``windows`` windows in a row."""

    threshold_px: float = 0.3
    windows: int = 3
    statistic: str = "max"  # "max" or "pNN" (a percentile of the observed markers)

    def __post_init__(self) -> None:
        if self.threshold_px <= 0 or self.windows < 1:
            raise LabrigError("the rest gate needs a positive threshold (px) and at least one window")
        if self.statistic != "max" and not (self.statistic.startswith("p") and self.statistic[1:].isdigit()
                                            and 0 < int(self.statistic[1:]) <= 100):
            raise LabrigError(f"the rest gate's statistic must be max or pNN (a percentile), not {self.statistic!r}")


class RestGate:
    """Counts windows in a row with the markers at rest; :meth:`__call__` says whether the gel is at rest."""

    def __init__(self, observed: npt.ArrayLike | None = None, params: RestGateParams = RestGateParams()) -> None:
        self.observed = None if observed is None else np.asarray(observed, bool).reshape(-1)
        self.params = params
        self.still_windows = 0
        self.displacement_px = 0.0  # the statistic of the last window

    def __call__(self, positions_px: npt.ArrayLike, rest_px: npt.ArrayLike) -> bool:
        """Add one window's tracked positions (M, 2) and the rest they are measured from (M, 2)."""
        d = np.linalg.norm(np.asarray(positions_px, np.float64) - np.asarray(rest_px, np.float64), axis=-1)
        if self.observed is not None:
            d = d[self.observed]
        d = d[np.isfinite(d)]
        if d.size == 0:
            self.still_windows = 0
            return False
        stat = self.params.statistic
        self.displacement_px = float(d.max() if stat == "max" else np.percentile(d, int(stat[1:])))
        self.still_windows = self.still_windows + 1 if self.displacement_px <= self.params.threshold_px else 0
        return self.still_windows >= self.params.windows
