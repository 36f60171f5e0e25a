"""The front stage: what each window of events gives before depth and forces.

Per window ``[t0_us, t1_us)``: the SAE of the depth source's span ending at ``t1_us`` (when the source
needs one: :func:`labrig.pipeline.sae.sae_grid`), the signed event counts per grid cell (when it
integrates the brightness change: :func:`labrig.pipeline.brightness.signed_counts`, every event counted
once and in order) and the markers (:class:`~labrig.pipeline.marker_stage.MarkerStage`: the tracker and
the rest refinement). Its output is a :class:`TrackedWindow`, which the back stage
(:class:`~labrig.pipeline.runtime.Pipeline`) turns into depth and forces.

A window whose forces are skipped (a live run that falls behind) still passes through the stage
(:meth:`FrontStage.skip`): its events move the markers, stay in the depth source's span and are
counted into the next window's signed counts, so that a state integrated from the counts loses none
of them.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.pipeline import brightness, sae
from labrig.pipeline.marker_stage import MarkerStage
from labrig.pipeline.run_setup import PipelineSetup
from labrig.pipeline.windows import Events

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class TrackedWindow:
    """A window through the front stage, waiting for the back stage (depth, displacements, forces).

    Times are in the stream's time base (us): a recording's host time, a live camera's device time.
    """

    index: int  # windows through the stage before this one, skipped ones not counted
    t0_us: int  # window start
    t1_us: int  # window end (exclusive)
    n_events: int
    positions_px: Array  # (M, 2) tracked marker centres, this window's own copy
    updated: npt.NDArray[np.bool_]  # (M,) markers the window's events moved
    depth_t0_us: int  # start of the depth source's span, which ends at t1_us
    depth_n_events: int  # events in that span
    # (2, 90, 112) SAE of the depth source's span (None unless it needs one or keep_sae). Each window
    # has its own array: the front runs ahead of the back stage, which must still see this one.
    sae: npt.NDArray[np.float32] | None
    seconds: Mapping[str, float]  # the front stage's processing time: read, sae, track
    rest_px: Array | None = None  # (M, 2) the rest this window's displacements are measured from (None: the setup's)
    # (90, 112) ON minus OFF events per grid cell (reference events) since the last window the back stage saw:
    # this window's and those of the skipped windows before it (None unless the source ``needs_counts``).
    counts: npt.NDArray[np.float32] | None = None
    depth_due: bool = True  # the depth source runs on this window (False: the back stage keeps the last map)


class FrontStage:
    """SAE, signed counts and markers, window by window, for one depth source's needs.

    ``depth_window_us``: the span the SAE covers, ending at each window's end (None: the window itself);
    ``needs_sae`` / ``needs_counts``: what the depth source takes; ``keep_sae``: the SAE on every window
    regardless (a viewer); ``depth_every_us``: the depth source runs only on the first window ending at
    least this long after the last one it ran on (None: every window); ``counter``: the depth source's own count of
    a window's events (:meth:`~labrig.pipeline.depth_sources.DepthSource.count_events`; None, or a None from it:
    :func:`~labrig.pipeline.brightness.signed_counts` with the setup's thresholds)."""

    def __init__(self, setup: PipelineSetup, markers: MarkerStage, *, depth_window_us: float | None,
                 needs_sae: bool, needs_counts: bool, keep_sae: bool = False,
                 depth_every_us: int | None = None,
                 counter: Callable[[Events], npt.NDArray[np.float32] | None] | None = None) -> None:
        if depth_every_us is not None and depth_every_us <= 0:
            raise ValueError(f"depth_every_us must be positive or None, not {depth_every_us}")
        self.setup = setup
        self.markers = markers
        self.depth_window_us = depth_window_us
        self.needs_sae = needs_sae
        self.needs_counts = needs_counts
        self.keep_sae = keep_sae
        self.depth_every_us = depth_every_us
        self.counter = counter
        self._index = 0
        self._recent: deque[Events] = deque()  # events of the depth source's span, a view per window
        self._depth_ran_us: int | None = None  # the end of the last window the depth source ran on
        self._skipped_counts: npt.NDArray[np.float32] | None = None  # the skipped windows' counts, not yet handed on

    def window(self, t0_us: int, t1_us: int, events: Events, read_s: float = 0.0) -> TrackedWindow:
        """The window ``[t0_us, t1_us)`` through the stage; ``read_s``: the time its events took to read."""
        seconds = {"read": read_s}
        grid = None
        start = time.perf_counter()
        d0_us, d_count = self._depth_span(t0_us, t1_us, events)
        due = (self.depth_every_us is None or self._depth_ran_us is None
               or t1_us - self._depth_ran_us >= self.depth_every_us)
        if due:
            self._depth_ran_us = t1_us
        if (self.needs_sae and due) or self.keep_sae:
            grid = sae.sae_grid(self._span_events(), d0_us, t1_us, self.setup.rig.roi)
        counts = self._counts(events)
        if counts is not None and self._skipped_counts is not None:
            counts += self._skipped_counts
            self._skipped_counts = None
        seconds["sae"] = time.perf_counter() - start
        start = time.perf_counter()
        positions, updated = self.markers.update(events, t0_us, t1_us)
        seconds["track"] = time.perf_counter() - start
        tracked = TrackedWindow(self._index, t0_us, t1_us, len(events), positions.copy(), updated.copy(),
                                d0_us, d_count, grid, seconds, self.markers.rest_px, counts, due)
        self._index += 1
        return tracked

    def skip(self, t0_us: int, t1_us: int, events: Events) -> None:
        """A window whose forces are skipped: its events move the markers, stay in the depth source's span
        and are counted into the next :meth:`window`'s counts."""
        self._depth_span(t0_us, t1_us, events)
        counts = self._counts(events)
        if counts is not None:
            self._skipped_counts = counts if self._skipped_counts is None else self._skipped_counts + counts
        self.markers.update(events, t0_us, t1_us)

    def _counts(self, events: Events) -> npt.NDArray[np.float32] | None:
        if not self.needs_counts:
            return None
        counts = self.counter(events) if self.counter is not None else None
        if counts is not None:
            return counts
        return brightness.signed_counts(events, self.setup.rig.roi, thresholds=self.setup.thresholds)

    def _depth_span(self, t0_us: int, t1_us: int, events: Events) -> tuple[int, int]:
        """(start, number of events) of the depth source's span ending at ``t1_us``, its events kept.

        Windows shorter than the span (count windows in a fast press, 1 ms windows) reach back into the
        events of earlier windows, kept here as views and joined only when the span is read
        (:meth:`_span_events`); longer ones (count windows at rest) are cut."""
        span = self.depth_window_us
        if span is None:
            self._recent = deque([events])
            return t0_us, len(events)
        d0 = round(t1_us - span)
        recent = self._recent
        recent.append(events)
        while len(recent) > 1 and (len(recent[0]) == 0 or int(recent[0]["t"][-1]) < d0):
            recent.popleft()
        first = int(np.searchsorted(recent[0]["t"], d0))
        if first:
            recent[0] = recent[0][first:]
        return d0, sum(len(e) for e in recent)

    def _span_events(self) -> Events:
        """The events of the last :meth:`_depth_span`, joined."""
        if len(self._recent) > 1:
            self._recent = deque([np.concatenate(self._recent)])
        return self._recent[0]
