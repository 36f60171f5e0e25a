"""The streaming runtime: windows of events through SAE, tracker, depth, displacements and forces.

Windows (:mod:`labrig.pipeline.windows`) are fixed in time (``window_us``, 10 ms by default) or
in event count (``window_events``, 20,000 in the paper's evaluation). Per window:

1. front stage (:meth:`Pipeline.front`, :class:`~labrig.pipeline.front_stage.FrontStage`): the SAE on the
   network grid (only when the depth source needs it), the signed event counts (when it needs them) and
   the markers' stage (the tracker and the rest refinement); its output is a
   :class:`~labrig.pipeline.front_stage.TrackedWindow`. A window whose forces are skipped still passes
   through it (:meth:`Pipeline.skip`);
2. back stage (:meth:`Pipeline.back`): the depth map from a
   :class:`~labrig.pipeline.depth_sources.DepthSource` (the recording's ``/truth/depth``
   nearest in time, or the ONNX network of :mod:`labrig.pipeline.depthnet`), the markers'
   3D displacements, per-marker forces (the dense surface operator of
   :func:`labrig.pipeline.ifem.build_surface_operator`), net force and contact location.

With ``concurrent=True`` the two stages run in two threads (:class:`~labrig.pipeline.front_thread.FrontThread`,
window k's forces while window k+1 is tracked), as in the paper. ``concurrent=False`` runs them in turn.
The run's camera, rest pixels and gel law are a :class:`~labrig.pipeline.run_setup.PipelineSetup`.
Tracking starts from the calibration's measured rest pixels, refined by the stream's first quiet
windows (:class:`~labrig.pipeline.rest.RestRefiner`; each tracked window carries the rest it is
measured from); missing markers are not tracked and their in-plane displacements are condensed by
the inverse FEM (:mod:`labrig.pipeline.unobserved`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline import displacement, forces, ifem, tracking
from labrig.pipeline.anchor import AnchorFilter, anchor_px
from labrig.pipeline.depth_lane import DepthLane, DepthSteps, SteppedLane, Steps
from labrig.pipeline.depth_sources import DepthSource
from labrig.pipeline.forces import ContactLocation
from labrig.pipeline.front_stage import FrontStage, TrackedWindow
from labrig.pipeline.front_thread import FrontThread, Handoff
from labrig.pipeline.map_forces import MapForces
from labrig.pipeline.marker_stage import MarkerStage
from labrig.pipeline.rest import RestParams
from labrig.pipeline.run_setup import PipelineSetup
from labrig.pipeline.warm_up import dent_map, press_windows
from labrig.pipeline.windows import DEFAULT_WINDOW_US, Events, WindowSpec, recording_windows
from labrig.recording import Recording

Array = npt.NDArray[np.float64]

STAGES = ("read", "sae", "track", "depth", "displacement", "forces")
#: Tracked windows that may wait for the back stage when the stages run in two threads.
QUEUED_WINDOWS = 2


@dataclass(frozen=True)
class MapWork:
    """What one depth map gives every window until the depth source runs again: its forces
    (:mod:`labrig.pipeline.map_forces`), the large-strain factor, the contact's core and the deepest point
    (mm), and the markers' normal displacements (M,) mm read at ``rest_px`` (the rest they were read at)."""

    depth: npt.NDArray[np.float32]
    forces: MapForces
    stiffening: float
    contact: ContactLocation | None
    peak_mm: float
    rest_px: Array
    marker_depths_mm: Array


@dataclass
class WindowResult:
    """One window's output. Forces are on the gel (pressing: Fz < 0), gel frame, N."""

    index: int
    t0_us: int
    t1_us: int
    n_events: int
    positions_px: Array  # (M, 2) tracked marker centres
    updated: npt.NDArray[np.bool_]  # (M,)
    displacement_mm: Array  # (M, 3)
    forces_n: Array  # (M, 3)
    net_force_n: Array  # (3,)
    contact_px: Array  # (2,), nan without contact
    contact_mm: Array  # (2,), nan without contact
    depth_mm: npt.NDArray[np.float32]  # (90, 112)
    sae: npt.NDArray[np.float32] | None = None  # (2, 90, 112) when computed
    seconds: dict[str, float] = field(default_factory=dict)  # per-stage processing time


class Pipeline:
    """The stages for one sensor; :meth:`process` runs one window, :meth:`run` streams a recording."""

    def __init__(self, setup: PipelineSetup, depth: DepthSource, *,
                 tracker_params: tracking.TrackerParams | None = None,
                 surface_params: ifem.SurfaceParams | None = None, normal_mode: str = "contact",
                 threshold_mm: float = 0.01, keep_sae: bool = False, cache_dir: str | Path | None = None,
                 rest_params: RestParams | None = None, depth_every_us: int | None = None,
                 reference: bool = False, depth_lane: bool = False, depth_parts: int | None = None) -> None:
        """``depth_every_us``: run the depth source only on the first window ending at least this long after
        the last one it ran on, and keep its map in between (tracking and forces every window, e.g. 1 ms
        windows with depth every 10 ms); None: every window. ``reference``: redo every window's work that
        depends on the depth map alone (the path the default one, :class:`MapWork`, is tested against).
        ``depth_lane``: run the depth source's jobs in a thread of their own (:mod:`labrig.pipeline.depth_lane`;
        each window takes the newest finished map); :meth:`close` stops it. ``depth_parts``: run the depth source's
        jobs in steps in the windows' own thread instead (:class:`~labrig.pipeline.depth_lane.SteppedLane`, for one
        core): the network cut into this many parts, one per window, then the map's work in the next window."""
        if depth_lane and depth_parts is not None:
            raise ValueError("depth_lane (a thread) and depth_parts (steps in the windows' thread) exclude each other")
        if depth_parts is not None and depth_parts < 1:
            raise ValueError(f"depth_parts must be at least 1, not {depth_parts}")
        self.setup = setup
        self.depth = depth
        rig = setup.rig
        self.front_stage = FrontStage(setup, MarkerStage.for_setup(setup, tracker_params, rest_params),
                                      depth_window_us=depth.window_us, needs_sae=depth.needs_sae,
                                      needs_counts=depth.needs_counts, keep_sae=keep_sae, depth_every_us=depth_every_us,
                                      counter=depth.count_events)
        self._rest_px, self._rest_mm = self.front_stage.markers.rest_px, setup.rest_mm()
        base = surface_params or ifem.SurfaceParams()
        self.surface_params = replace(base, youngs_modulus_mpa=setup.youngs_modulus_mpa,
                                      poisson_ratio=setup.poisson_ratio)
        self.operator = ifem.build_surface_operator(rig, self.surface_params, cache_dir=cache_dir).precompute()
        self.surface = forces.SurfaceForces(self.operator, setup.camera, rig.roi, GRID_SHAPE, observed=setup.observed)
        self.normal_mode = normal_mode
        self.threshold_mm = threshold_mm
        self.keep_sae = keep_sae
        self.anchor = AnchorFilter(depth.anchor) if depth.anchor is not None else None
        self.reference = reference
        self._last_t1_us: int | None = None
        self._depth_map: npt.NDArray[np.float32] | None = None  # its map (back stage)
        self._map_work: MapWork | None = None
        self._flat_map = np.zeros(GRID_SHAPE, np.float32)
        self.lane: DepthLane[MapWork] | None = DepthLane() if depth_lane else None
        self.stepped: SteppedLane[MapWork] | None = None
        if depth_parts is not None:
            depth.split_network(depth_parts)
            self.stepped = SteppedLane()
        self._tracker_params, self._rest_params = tracker_params, rest_params

    def warm_up(self) -> float:
        """Take every stage through its first-window costs (compiled kernels loaded, the depth source's first run)
        on throwaway state: a fresh front stage on synthetic windows (:mod:`labrig.pipeline.warm_up`), the depth
        source's :meth:`~labrig.pipeline.depth_sources.DepthSource.warm_up`, and the forces of a flat map and a dent.
        This pipeline's own state (tracks, rest, the depth source's state, the last map) is untouched. Returns the
        seconds it took."""
        start = time.perf_counter()
        setup, depth = self.setup, self.depth
        front = FrontStage(setup, MarkerStage.for_setup(setup, self._tracker_params, self._rest_params),
                           depth_window_us=depth.window_us, needs_sae=True, needs_counts=True)
        for t0, t1, events in press_windows(setup.rest_px, setup.observed, DEFAULT_WINDOW_US):
            tracked = front.window(t0, t1, events)
        depth.warm_up()
        rest_px = setup.rest_px
        rest_mm = setup.rest_mm(rest_px)
        for depth_map in (self._flat_map, dent_map()):
            work = self._new_work(depth_map, rest_px)
            u = setup.camera.backproject_to_planes(tracked.positions_px, -work.marker_depths_mm) - rest_mm
            work.forces(u)
            if self.reference:
                u = displacement.displacements_mm(tracked.positions_px, depth_map, setup.camera, rest_mm, setup.rig.roi,
                                                  sample_px=rest_px)
                self.surface(depth_map, u, self.normal_mode, self.threshold_mm)
        return time.perf_counter() - start

    # The two stages.

    @property
    def markers(self) -> MarkerStage:
        """The markers' stage (tracker and rest refinement) of the front stage."""
        return self.front_stage.markers

    def front(self, t0_us: int, t1_us: int, events: Events, read_s: float = 0.0) -> TrackedWindow:
        """SAE (if needed), signed counts (if needed) and tracking of the window ``[t0_us, t1_us)``;
        ``read_s``: the time its events took to read."""
        return self.front_stage.window(t0_us, t1_us, events, read_s)

    def skip(self, t0_us: int, t1_us: int, events: Events) -> None:
        """A window whose back stage is skipped (a live run behind): tracked, its events kept for the next
        window's SAE span and counts (:meth:`FrontStage.skip`)."""
        self.front_stage.skip(t0_us, t1_us, events)

    def observe(self, tracked: TrackedWindow) -> None:
        """A tracked window whose depth and forces are skipped (a live run catching up): the depth source still
        observes it (its markers, its signed counts), so a state integrated from them misses nothing."""
        self.depth.observe(tracked.positions_px, self._rest_of(tracked), tracked.counts, tracked.t1_us)

    def _rest_of(self, tracked: TrackedWindow) -> Array:
        """(M, 2) px: the rest ``tracked``'s positions are measured from."""
        return self.setup.rest_px if tracked.rest_px is None else tracked.rest_px

    def back(self, tracked: TrackedWindow) -> WindowResult:
        """Depth, displacements, forces, net force and contact location."""
        seconds = dict(tracked.seconds)
        start = time.perf_counter()
        rest_px = self._rest_of(tracked)
        self.observe(tracked)
        if self.lane is not None or self.stepped is not None:
            depth = self._lane_depth(tracked, rest_px)
        elif tracked.sae is None and self.depth.needs_sae and self._depth_map is None:
            # no map yet and no SAE to make one (a live run that skipped the window its depth was due on): the gel
            # is taken as flat until the next window with an SAE
            depth = self._flat_map
        elif tracked.depth_due or self._depth_map is None:
            depth = self.depth.depth_mm(tracked.sae, tracked.depth_t0_us, tracked.t1_us, tracked.depth_n_events)
            self._depth_map, self._map_work = depth, None
        else:
            depth = self._depth_map
        seconds["depth"] = time.perf_counter() - start
        start = time.perf_counter()
        work = None if self.reference else self._work_for(depth, rest_px)
        prepare_s = time.perf_counter() - start  # the map's forces: counted with them
        start = time.perf_counter()
        rest_mm = self._rest_points(rest_px)
        if work is None:
            u = displacement.displacements_mm(tracked.positions_px, depth, self.setup.camera, rest_mm,
                                              self.setup.rig.roi, sample_px=rest_px)
        else:
            u = self.setup.camera.backproject_to_planes(tracked.positions_px, -work.marker_depths_mm) - rest_mm
        seconds["displacement"] = time.perf_counter() - start
        start = time.perf_counter()
        if work is None:
            f = self.surface(depth, u, self.normal_mode, self.threshold_mm)
            f *= forces.stiffening_factor(depth, self.setup.rig.gel.thickness_mm, self.setup.stiffening)
            where = forces.contact_location(depth, self.setup.rig.roi, self.setup.camera, self.threshold_mm)
        else:
            f = work.forces(u)
            f *= work.stiffening
            where = work.contact
        contact_px, contact_mm = self._contact(where, float(np.max(depth)) if work is None else work.peak_mm,
                                               tracked.t0_us, tracked.t1_us)
        seconds["forces"] = time.perf_counter() - start + prepare_s
        return WindowResult(tracked.index, tracked.t0_us, tracked.t1_us, tracked.n_events, tracked.positions_px,
                            tracked.updated, u, f, forces.net_force_n(f), contact_px, contact_mm, depth,
                            tracked.sae if self.keep_sae else None, seconds)

    def _lane_depth(self, tracked: TrackedWindow, rest_px: Array) -> npt.NDArray[np.float32]:
        """The newest map the depth lane (a thread, or steps run here) has finished (flat before its first), after
        handing it this window's job when depth is due."""
        due = tracked.depth_due and (tracked.sae is not None or not self.depth.needs_sae)
        if self.stepped is not None:
            if due:
                steps = self.depth.depth_steps(tracked.sae, tracked.depth_t0_us, tracked.t1_us, tracked.depth_n_events)
                self.stepped.submit(self._then_work(steps, rest_px), tracked.t1_us)
            self.stepped.step()
            done = self.stepped.poll()
        else:
            assert self.lane is not None
            if due:
                job = self.depth.depth_job(tracked.sae, tracked.depth_t0_us, tracked.t1_us, tracked.depth_n_events)
                self.lane.submit(lambda: self._new_work(job(), rest_px), tracked.t1_us)  # the map's work in the lane too
            done = self.lane.poll()
        if done is not None:
            self._map_work = done[0]
            self._depth_map = self._map_work.depth
        return self._depth_map if self._depth_map is not None else self._flat_map

    def _then_work(self, steps: DepthSteps, rest_px: Array) -> Steps[MapWork]:
        """The depth source's steps, then the map's work as one step more."""
        depth = yield from steps
        yield
        return self._new_work(depth, rest_px)

    def close(self) -> None:
        """Stop the depth lane (if any); the pipeline can no longer run."""
        if self.lane is not None:
            self.lane.close()
        if self.stepped is not None:
            self.stepped.close()

    def _work_for(self, depth: npt.NDArray[np.float32], rest_px: Array) -> MapWork:
        """The work of ``depth`` that every window until the next map reuses (redone when the rest changes)."""
        work = self._map_work
        if work is None or work.depth is not depth:
            work = self._new_work(depth, rest_px)
        elif work.rest_px is not rest_px:
            work = replace(work, rest_px=rest_px,
                           marker_depths_mm=displacement.marker_depths_mm(depth, rest_px, self.setup.rig.roi))
        self._map_work = work
        return work

    def _new_work(self, depth: npt.NDArray[np.float32], rest_px: Array) -> MapWork:
        """Everything of ``depth`` the windows reuse (it reads only the map, the setup and the operator: the depth
        lane may run it)."""
        return MapWork(depth, self.surface.prepare(depth, self.normal_mode, self.threshold_mm),
                       forces.stiffening_factor(depth, self.setup.rig.gel.thickness_mm, self.setup.stiffening),
                       forces.contact_location(depth, self.setup.rig.roi, self.setup.camera, self.threshold_mm),
                       float(np.max(depth)), rest_px, displacement.marker_depths_mm(depth, rest_px, self.setup.rig.roi))

    def _contact(self, where: ContactLocation | None, peak_mm: float, t0_us: int,
                 t1_us: int) -> tuple[Array, Array]:
        """The contact's location (px, mm; nan without a dent): the dent's core, through the anchor filter."""
        dt_s = (t1_us - (t0_us if self._last_t1_us is None else self._last_t1_us)) / 1e6
        self._last_t1_us = t1_us
        if self.anchor is not None:
            anchor_mm = self.anchor.update(where.position_mm if where else None, peak_mm, dt_s)
            if anchor_mm is not None:
                return anchor_px(anchor_mm, self.setup.camera), anchor_mm
        elif where is not None:
            return where.position_px, where.position_mm
        return np.full(2, np.nan), np.full(2, np.nan)

    def _rest_points(self, rest_px: Array) -> Array:
        """(M, 3) gel-frame rest points of ``rest_px``, recomputed only when the rest changed."""
        if rest_px is not self._rest_px:
            self._rest_px, self._rest_mm = rest_px, self.setup.rest_mm(rest_px)
        return self._rest_mm

    def process(self, t0_us: int, t1_us: int, events: Events) -> WindowResult:
        return self.back(self.front(t0_us, t1_us, events))

    def run(self, recording: Recording, *, window_us: int | None = DEFAULT_WINDOW_US, window_events: int | None = None,
            start_us: int = 0, end_us: int | None = None, concurrent: bool = True,
            on_result: Callable[[WindowResult], None] | None = None) -> Iterator[WindowResult]:
        """Stream ``recording`` through the pipeline, yielding each window's result in order.

        ``window_events`` (if given) replaces the default time windows."""
        spec = WindowSpec.events_first(window_us, window_events)
        source = _timed(recording_windows(recording, window_us=spec.window_us, window_events=spec.window_events,
                                          start_us=start_us, end_us=end_us))
        if not concurrent:
            for t0, t1, events, read_s in source:
                result = self.back(self.front(t0, t1, events, read_s))
                if on_result is not None:
                    on_result(result)
                yield result
            return

        def track(handoff: Handoff[TrackedWindow]) -> None:
            for t0, t1, events, read_s in source:
                if handoff.halted:
                    break
                handoff.put(self.front(t0, t1, events, read_s))

        with FrontThread(track, max_queued=QUEUED_WINDOWS, name="labrig-pipeline-front") as tracked_windows:
            for tracked in tracked_windows:
                result = self.back(tracked)
                if on_result is not None:
                    on_result(result)
                yield result


def _timed(windows: Iterator[tuple[int, int, Events]]) -> Iterator[tuple[int, int, Events, float]]:
    """Each window with the seconds its events took to read."""
    while True:
        start = time.perf_counter()
        try:
            t0, t1, events = next(windows)
        except StopIteration:
            return
        yield t0, t1, events, time.perf_counter() - start
