"""The markers' front stage: each window of events through a marker tracker, then the rest refinement.

One seam for every consumer of marker positions: the streaming runtime
(:class:`labrig.pipeline.runtime.Pipeline`, and the live runner's skipped windows), the tracks the
training's displacement channels are cut from (:func:`labrig.training.state_data.track_recording`)
and the tracker evaluation (:mod:`labrig.evaluation.tracking`, which compares trackers with the rest
held). A tracker is anything with the :class:`MarkerTracker` protocol: the pipeline's
(:class:`~labrig.pipeline.tracking.Tracker`), the circle fit and Evetac's.

While the rest refinement (:class:`~labrig.pipeline.rest.RestRefiner`) still averages the first
quiet windows, each window's positions go to it and the tracker's rest (its neighbour prior's
offsets) follows the refined one; once frozen, the stage is the tracker alone.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import numpy.typing as npt

from labrig.pipeline import tracking
from labrig.pipeline.rest import RestParams, RestRefiner
from labrig.pipeline.run_setup import PipelineSetup

Array = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


class MarkerTracker(Protocol):
    """Marker positions (M, 2) px on the sensor, window by window."""

    rest_px: Array
    positions_px: Array
    observed: BoolArray

    def update(self, events: npt.NDArray, t_end_us: float | None = None) -> tuple[Array, BoolArray]:
        """Advance by one window of events (EVENT_DTYPE) ending at ``t_end_us`` (host us; None: its last
        event); copies of the positions (M, 2) px and of the mask (M,) of markers it moved."""
        ...


class MarkerStage:
    """A tracker and (optionally) the rest refinement it feeds, advanced one window at a time."""

    def __init__(self, tracker: MarkerTracker, rest: RestRefiner | None = None) -> None:
        self.tracker = tracker
        self.rest = rest

    @classmethod
    def for_setup(cls, setup: PipelineSetup, tracker_params: tracking.TrackerParams | None = None,
                  rest_params: RestParams | None = None) -> MarkerStage:
        """The pipeline's tracker on ``setup``'s rest pixels and observed markers (the marker diameter
        through its camera unless ``tracker_params`` say otherwise), with the rest refinement."""
        params = tracker_params or tracking.TrackerParams(
            marker_diameter_px=tracking.marker_diameter_px(setup.rig, setup.camera))
        tracker = tracking.Tracker(setup.rest_px, params, observed=setup.observed)
        return cls(tracker, RestRefiner(setup.rest_px, setup.observed, rest_params or RestParams()))

    @property
    def rest_px(self) -> Array:
        """(M, 2) px the rest the positions are measured from: the refined one, else the tracker's."""
        return self.rest.rest_px if self.rest is not None else self.tracker.rest_px

    def update(self, events: npt.NDArray, t0_us: float, t1_us: float) -> tuple[Array, BoolArray]:
        """The window ``[t0_us, t1_us)``'s events through the tracker, then the rest refinement:
        positions (M, 2) px at ``t1_us`` and the mask (M,) of markers the tracker moved."""
        positions, updated = self.tracker.update(events, t1_us)
        if self.rest is not None and not self.rest.frozen:
            self.rest.add(positions, len(events), t1_us - t0_us)
            self.tracker.rest_px = self.rest.rest_px  # the neighbour prior's offsets
        return positions, updated
