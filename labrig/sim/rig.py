"""The virtual rig: indenter pose -> contact -> markers -> camera image -> events.

:class:`VirtualRig` advances a simulated sensor through world time (integer
microseconds from the rig's start) while a tool path (machine mm) drives the
indenter. It produces what the devices would see (camera events, trigger
edges, the wrench on the F/T sensor) and what only a simulation knows (marker
positions, the depth field, per-marker forces).

Time stepping
-------------
* Mechanics are quasi-static and solved as often as the motion needs: the next
  solve comes when the tool has moved ``solve_step_mm`` (0.02 mm), within 2 to
  50 ms. Contact fields come from the precomputed
  :class:`~labrig.physics.mechanics.ContactTable` (one lookup per solve).
* Marker 3D positions are interpolated linearly between the two solves that
  bracket a render time. Where the kinematics start afresh between two solves
  (contact made or lost, shear memory dropped for a new axis), the rig solves
  at the contact track's samples on both sides of that edge instead (lifting
  off lets go of the residual shear at once: the markers jump).
* Renders (and event sensor steps) are adaptive: a step is as long as keeps
  every marker's image motion under ``max_step_px`` (0.2 px), estimated from the
  bracketing solves (once per solve pair). The slope shading of the membrane
  changes at solve times.
* Cost (single core, see tools/bench/bench_rig.py): per render, only the
  markers' rims and the pixels they change; per solve, one table lookup and,
  in contact, a re-shade of the slope box (a sparse product over the ROI
  and dense passes over the box, renderer and pixels alike). What depends
  only on the contact anchor (pixel weights on the grid, marker weights and
  cells) is kept while the anchor stays put.

Contact kinematics
------------------
See :mod:`labrig.sim.contact_track`: tool positions become contact states
(depth, anchor, shear memory, net force) on a :class:`ContactTrack` that the
F/T twin shares when the rig is served live; the rig turns the states it
solves at into contact fields. A non-axisymmetric footprint is turned by the
indenter's yaw relative to the true gel (the tables of
:func:`~labrig.sim.truth_config.true_contact_table`); the gel's tilt is
ignored in the contact shape (below a degree).

The markers are the printed ones (:mod:`labrig.sim.printed`); hot pixels
(:class:`~labrig.sim.delivery.HotPixels`) add their events to the sensor's.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig, Roi
from labrig.frames import Pose, rotvec_to_matrix
from labrig.indenters import Indenter
from labrig.physics.mechanics import ContactFields, ContactTable
from labrig.sim.contact_track import ContactKinematics, ContactState, ContactTrack, ToolPoint
from labrig.sim.delivery import HotPixels, merge_events
from labrig.sim.events import EVENT_DTYPE, EventSensor
from labrig.sim.motion import true_gel_in_machine
from labrig.sim.optics import Renderer
from labrig.sim.printed import PrintedLayout
from labrig.sim.shading import DepthField
from labrig.sim.truth_config import sim_config, true_camera, true_contact_table

ToolPath = Callable[[npt.ArrayLike], npt.NDArray[np.float64]]

#: How long the LED ring takes to switch on or off, us.
LED_SWITCH_US = 20

#: Interval of the true-marker samples, us (>= 1 kHz).
TRUTH_MARKER_INTERVAL_US = 1000

_NO_PIXELS = np.zeros(0, np.int64)
_NO_VALUES = np.zeros(0, np.float64)


@dataclass(frozen=True)
class Solve:
    """The quasi-static contact state at one world time."""

    t_us: int
    tip_gel_mm: npt.NDArray[np.float64]
    depth_mm: float
    markers_mm: npt.NDArray[np.float64]
    force_on_gel_n: npt.NDArray[np.float64]
    centre_of_pressure_mm: npt.NDArray[np.float64]
    marker_forces_n: npt.NDArray[np.float64]
    fields: ContactFields | None
    anchor_mm: npt.NDArray[np.float64] | None
    sliding: bool = False  # the whole contact slides (gross slip)


@dataclass
class RigOutput:
    """What one :meth:`VirtualRig.advance` produced (world times, us)."""

    events: npt.NDArray[np.void]
    triggers: list[tuple[int, int]] = field(default_factory=list)
    solves: list[Solve] = field(default_factory=list)
    truth_t_us: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    truth_markers_mm: npt.NDArray[np.float32] = field(default_factory=lambda: np.zeros((0, 0, 3), np.float32))
    truth_markers_px: npt.NDArray[np.float32] = field(default_factory=lambda: np.zeros((0, 0, 2), np.float32))
    #: Renderer calls (a step over an image at rest needs none; the event sensor still steps).
    renders: int = 0


class VirtualRig:
    """A simulated sensor under a CNC-driven indenter. Deterministic under ``seed``."""

    def __init__(
        self,
        rig: RigConfig,
        indenter: Indenter,
        *,
        seed: int = 0,
        table: ContactTable | None = None,
        solve_step_mm: float = 0.02,
        min_solve_interval_us: int = 2_000,
        max_solve_interval_us: int = 50_000,
        max_render_interval_us: int = 10_000,
        track: ContactTrack | None = None,
        dead_pixels: Roi | None = None,
    ) -> None:
        """``dead_pixels``: a rectangle of sensor pixels that emit no events (a dead region), or None."""
        self.rig = rig
        #: The virtual rig's truth (the rig file's ``sim.*`` sections).
        self.truth = sim_config(rig)
        self.indenter = indenter
        self.camera = true_camera(rig)
        self.table = table if table is not None else true_contact_table(indenter, rig)
        self.gel_in_machine: Pose = true_gel_in_machine(rig)
        self.machine_to_gel = self.gel_in_machine.inverse()
        pose = self.truth.rig_pose
        #: F/T sensor axes in the gel frame; its origin rides with the tool.
        self.ft_axes_in_gel = rotvec_to_matrix(pose.ft_axes_in_gel_rotvec_rad)
        self.ft_origin_from_tip_mm = np.asarray(pose.ft_origin_in_gel_mm, dtype=np.float64)
        self._ft_axes_list, self._ft_origin_list = self.ft_axes_in_gel.tolist(), self.ft_origin_from_tip_mm.tolist()
        #: The markers as printed ([sim.markers]); ``rest_mm``: their rest centres (N = rows * cols, gel mm).
        self.printed = PrintedLayout(rig)
        self.rest_mm = self.printed.rest_mm
        self.cells = _marker_cells(rig)
        self.renderer = Renderer(rig, self.camera, **self.printed.renderer_options())
        self.renderer.prepare_shading()
        self.sensor = EventSensor.from_rig(rig, self.renderer.image, t_us=0, seed=seed, dead=_dead_mask(rig.roi, dead_pixels))
        self.hot_pixels = HotPixels(rig, seed)
        self.solve_step_mm = solve_step_mm
        self.min_solve_interval_us = min_solve_interval_us
        self.max_solve_interval_us = max_solve_interval_us
        self.max_render_interval_us = max_render_interval_us
        self.max_step_px = self.truth.events.max_step_px
        self.t_us = 0
        self.kinematics = ContactKinematics(
            self.table, indenter.tool_offset_mm, self.machine_to_gel,
            table_for_direction=None if indenter.axisymmetric or table is not None
            else lambda deg: true_contact_table(indenter, rig, direction_deg=deg),
        )
        #: The contact states the rig solves at; shared with the F/T twin when served live.
        self.track = track
        self._own_track = track is None
        self._depth_field: DepthField | None = None
        self._prev: Solve | None = None
        self._next: Solve | None = None
        self._pending_triggers: list[tuple[int, int]] = []
        self._trigger_lock = threading.Lock()
        self._led_switches: list[tuple[int, float]] = []
        self._next_truth_us = 0
        # The solve intervals _next_solve_time tries (us), for these min and max intervals.
        self._solve_offsets = np.zeros(0, np.int64)
        self._solve_offsets_key: tuple[int, int] | None = None
        # The last contact solved: (table, (depth, terms, angle, anchor), (fields, markers, marker forces)).
        self._solved: tuple[ContactTable, tuple[object, ...], tuple[ContactFields, npt.NDArray[np.float64],
                                                                    npt.NDArray[np.float64]]] | None = None
        # The markers and depth field of the last render (None: unknown, render again).
        self._rendered: tuple[npt.NDArray[np.float64], DepthField | None] | None = None
        # Per solve pair: the markers' image positions at both solves and the render step they allow.
        self._prev_px: npt.NDArray[np.float64] | None = None
        self._next_px: npt.NDArray[np.float64] | None = None
        self._step: int = max_render_interval_us
        # Per contact anchor: marker cells of the grid nodes and the markers' bilinear weights.
        self._cells_key: tuple[float, ...] | None = None
        self._cells_of_nodes: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None = None
        self._marker_weights_key: tuple[float, ...] | None = None
        self._marker_weights: _Weights | None = None

    def bind(self, tool_path: ToolPath, tool_at: ToolPoint | None = None) -> ContactTrack:
        """Drive the rig from ``tool_path`` (machine mm at world us) through a shared contact
        track, which other consumers (the F/T twin) may sample too; returns it. ``tool_at``:
        the same path at one time as Python floats (the track's samples), if the caller has it."""
        self.track = ContactTrack(self.kinematics, tool_path, tool_at=tool_at)
        self._own_track = False
        return self.track

    # -- clocks and triggers ---------------------------------------------------

    def camera_time_us(self, t_world_us: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """The camera's own timestamps for world times (offset and drift)."""
        clock = self.truth.camera_clock
        t = np.asarray(t_world_us, dtype=np.float64)
        return (clock.origin_us + np.floor(t * (1 + clock.drift_ppm * 1e-6))).astype(np.int64)

    def set_led(self, level: float, t_world_us: int | None = None) -> None:
        """Set the LED ring's level at ``t_world_us`` (default: now): 1 (or True) full, 0 (or False)
        off, which darkens the membrane and markers (the extrinsic-calibration blink scene); a level
        between them scales every pixel's light (the event-response scene's dimming ramps)."""
        t = self.t_us if t_world_us is None else int(t_world_us)
        if t < self.t_us:
            raise ValueError("the LED cannot be switched in the past")
        if not 0.0 <= float(level) <= 1.0:
            raise ValueError(f"the LED ring's level must be in [0, 1], not {level}")
        self._led_switches.append((t, float(level)))
        self._led_switches.sort(key=lambda item: item[0])

    def trigger(self, t_world_us: int, polarity: int) -> None:
        """An edge on the camera's trigger input (the CNC output toggled); any thread may call it.

        An edge later than the rig's time comes out of the :meth:`advance` that reaches it."""
        with self._trigger_lock:
            self._pending_triggers.append((int(t_world_us), int(polarity)))

    # -- mechanics ---------------------------------------------------------------

    def solve(self, state: ContactState) -> Solve:
        """Contact fields, displaced markers and per-marker forces for a contact state."""
        if not state.in_contact:
            return Solve(state.t_us, state.tip_gel_mm, 0.0, self.rest_mm.copy(), np.zeros(3),
                         state.centre_of_pressure_mm, self.printed.mask_truth(np.zeros((len(self.rest_mm), 3))), None, None)
        assert state.anchor_mm is not None
        table = state.table or self.table
        key = (state.depth_mm, state.terms, state.angle_rad, float(state.anchor_mm[0]), float(state.anchor_mm[1]))
        if self._solved is not None and self._solved[0] is table and self._solved[1] == key:
            # The same contact as the last solve (a wait, a stop): the same fields, markers and forces.
            fields, markers, forces = self._solved[2]
        else:
            fields = table.fields_for_terms(state.depth_mm, state.terms, state.angle_rad)
            markers = self._displaced_markers(fields, state.anchor_mm)
            forces = self._marker_forces(fields, state.anchor_mm)
            self._solved = (table, key, (fields, markers, forces))
        return Solve(state.t_us, state.tip_gel_mm, state.depth_mm, markers, state.force_on_gel_n,
                     state.centre_of_pressure_mm, forces, fields, state.anchor_mm.copy(), state.sliding)

    def _displaced_markers(self, fields: ContactFields, anchor: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        key = (float(anchor[0]), float(anchor[1]), float(fields.x_mm[0]), float(fields.y_mm[0]),
               len(fields.x_mm), len(fields.y_mm))
        if self._marker_weights is None or self._marker_weights_key != key:
            self._marker_weights = _Weights.build(fields.x_mm, fields.y_mm, self.rest_mm[:, :2] - anchor)
            self._marker_weights_key = key
        weights = self._marker_weights
        ux = weights.sample(fields.ux_mm)
        uy = weights.sample(fields.uy_mm)
        uz = -weights.sample(fields.depth_mm)
        return self.rest_mm + np.stack([ux, uy, uz], axis=1)

    def _marker_forces(self, fields: ContactFields, anchor: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """Traction integrated over each marker's cell (N, gel frame, on the gel).

        Only the box of nodes under pressure is summed (the traction vanishes
        with the pressure, under the Coulomb bound), which leaves the sums as
        they are; the nodes' cells are kept per contact anchor.
        """
        n = self.cells.rows * self.cells.cols
        out = np.zeros((n, 3))
        loaded = fields.pressure_mpa > 0
        rows = np.flatnonzero(loaded.any(axis=1))
        if rows.size == 0:
            return self.printed.mask_truth(out)
        cols = np.flatnonzero(loaded[rows[0] : rows[-1] + 1].any(axis=0))
        box = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
        flat, index = self._node_cells(fields, anchor, box)
        area = (fields.x_mm[1] - fields.x_mm[0]) * (fields.y_mm[1] - fields.y_mm[0])
        out[:, 0] = np.bincount(index, fields.traction_mpa[0][box].ravel()[flat], minlength=n) * area
        out[:, 1] = np.bincount(index, fields.traction_mpa[1][box].ravel()[flat], minlength=n) * area
        out[:, 2] = -np.bincount(index, fields.pressure_mpa[box].ravel()[flat], minlength=n) * area
        return self.printed.mask_truth(out)

    def _node_cells(
        self, fields: ContactFields, anchor: npt.NDArray[np.float64], box: tuple[slice, slice]
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """(flat positions in the node box of the nodes inside a marker cell, their cell indices), cached."""
        key = (float(anchor[0]), float(anchor[1]), float(fields.x_mm[0]), float(fields.y_mm[0]),
               box[0].start, box[0].stop, box[1].start, box[1].stop)
        if self._cells_of_nodes is None or self._cells_key != key:
            x_mm, y_mm = fields.x_mm[box[1]], fields.y_mm[box[0]]
            col = np.floor((x_mm + anchor[0] - self.cells.x0_mm) / self.cells.pitch_mm).astype(int)
            row = np.floor((y_mm + anchor[1] - self.cells.y0_mm) / self.cells.pitch_mm).astype(int)
            col = np.where((col >= 0) & (col < self.cells.cols), col, -1)
            row = np.where((row >= 0) & (row < self.cells.rows), row, -1)
            cell = np.where((row[:, None] >= 0) & (col[None, :] >= 0), row[:, None] * self.cells.cols + col[None, :], -1)
            cell = self.printed.cells(x_mm + anchor[0], y_mm + anchor[1], cell)
            flat = np.flatnonzero(cell >= 0)
            self._cells_of_nodes = (flat, cell.ravel()[flat])
            self._cells_key = key
        return self._cells_of_nodes

    def ft_wrench(self, solve: Solve | ContactState) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(force N, torque N m) the F/T sensor measures, in its own axes."""
        return self.ft_wrench_of(solve.force_on_gel_n, solve.centre_of_pressure_mm, solve.tip_gel_mm)

    def ft_wrench_of(
        self, force_on_gel_n: npt.ArrayLike, centre_of_pressure_mm: npt.ArrayLike, tip_gel_mm: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(force N, torque N m) in the F/T sensor's axes for a contact (gel frame inputs).

        The sensor carries the indenter, so it feels the reaction of the force
        on the gel, applied at the centre of pressure, about its own origin.
        """
        force, torque = self.ft_wrench_values(force_on_gel_n, centre_of_pressure_mm, tip_gel_mm)
        return np.array(force), np.array(torque)

    def ft_wrench_values(
        self, force_on_gel_n: npt.ArrayLike, centre_of_pressure_mm: npt.ArrayLike, tip_gel_mm: npt.ArrayLike
    ) -> tuple[list[float], list[float]]:
        """:meth:`ft_wrench_of` as Python floats (the F/T twin's 800 Hz samples: no small arrays on their way)."""
        f0, f1, f2 = (-v for v in np.asarray(force_on_gel_n, dtype=np.float64).tolist())
        o0, o1, o2 = (a + b for a, b in zip(np.asarray(tip_gel_mm, dtype=np.float64).tolist(), self._ft_origin_list))
        p0, p1, p2 = np.asarray(centre_of_pressure_mm, dtype=np.float64).tolist()
        a0, a1, a2 = (p0 - o0) * 1e-3, (p1 - o1) * 1e-3, (p2 - o2) * 1e-3  # lever (m), as frames.wrench_about
        torque = [a1 * f2 - a2 * f1, a2 * f0 - a0 * f2, a0 * f1 - a1 * f0]
        return _to_ft(self._ft_axes_list, [f0, f1, f2]), _to_ft(self._ft_axes_list, torque)

    # -- time stepping ------------------------------------------------------------

    def advance(self, t_end_us: int, tool_path: ToolPath) -> RigOutput:
        """Simulate from the current time to ``t_end_us`` with the tool on ``tool_path``."""
        t_end_us = int(t_end_us)
        if t_end_us < self.t_us:
            raise ValueError("the virtual rig cannot go back in time")
        out = RigOutput(events=np.zeros(0, EVENT_DTYPE))
        t_start_us = self.t_us
        chunks: list[npt.NDArray[np.void]] = []
        truth_t: list[int] = []
        truth_mm: list[npt.NDArray[np.float64]] = []
        if self.track is None:
            self.track = ContactTrack(self.kinematics, tool_path)
        elif self._own_track:
            self.track.tool_path = tool_path
        if self._prev is None:
            self._prev = self.solve(self.track.sample(self.t_us))
            out.solves.append(self._prev)
        while self.t_us < t_end_us:
            assert self._prev is not None
            if self._next is None or self.t_us >= self._next.t_us:
                self._next_pair(out, tool_path)
            assert self._next is not None
            t1 = min(self.t_us + self._step, self._next.t_us, t_end_us)
            # At rest (a pair of solves that leaves the image as it is), a render step need not end at the
            # solve: the pairs roll on while at rest (fewer, longer sensor steps over the same image).
            while t1 == self._next.t_us < min(self.t_us + self._step, t_end_us) and self._at_rest():
                self._truth_to(t1, truth_t, truth_mm)
                self._next_pair(out, tool_path)
                if not self._at_rest():
                    break
                t1 = min(self.t_us + self._step, self._next.t_us, t_end_us)
            if self._led_switches:
                t1 = min(t1, max(self._led_switches[0][0], self.t_us + 1))
            markers = self._markers_at(t1)
            self._truth_to(t1, truth_t, truth_mm)
            if self._unchanged_image(markers):
                chunks.append(self.sensor.step(self.t_us, t1, _NO_PIXELS, _NO_VALUES))
            else:
                update = self.renderer.render(self.printed.drawn(markers), self._depth_field)
                self._rendered = (markers, self._depth_field)
                chunks.append(self.sensor.step(self.t_us, t1, update.pixels, update.values, block=update.block))
                out.renders += 1
            self.t_us = t1
            if self._led_switches and self._led_switches[0][0] <= t1 < t_end_us:
                # The LED switches within LED_SWITCH_US; the photoreceptors' low-pass spreads the events.
                _, level = self._led_switches.pop(0)
                t1 = min(t1 + LED_SWITCH_US, t_end_us)
                update = self.renderer.render(self.printed.drawn(self._markers_at(t1)), self._depth_field, led=level)
                self._rendered = None
                chunks.append(self.sensor.step(self.t_us, t1, update.pixels, update.values, block=update.block))
                out.renders += 1
                self.t_us = t1
        if chunks:
            out.events = np.concatenate(chunks)
        if len(self.hot_pixels):
            out.events = merge_events(out.events, self.hot_pixels.events(t_start_us, t_end_us))
        with self._trigger_lock:
            edges = sorted(self._pending_triggers)
            out.triggers = [e for e in edges if e[0] <= t_end_us]
            self._pending_triggers = [e for e in edges if e[0] > t_end_us]
        if truth_t:
            out.truth_t_us = np.array(truth_t, np.int64)
            mm = np.array(truth_mm)
            out.truth_markers_mm = self.printed.mask_truth(mm.astype(np.float32), axis=1)
            out.truth_markers_px = self.printed.mask_truth(
                self.camera.project(mm.reshape(-1, 3)).reshape(len(truth_t), -1, 2).astype(np.float32), axis=1)
        return out

    def _next_pair(self, out: RigOutput, tool_path: ToolPath) -> None:
        """The next solve pair: the later solve becomes the earlier, a new solve follows it."""
        assert self._prev is not None and self.track is not None
        if self._next is not None:
            self._prev, self._prev_px = self._next, self._next_px
        t_next = self._next_solve_time(self._prev, tool_path)
        state = self.track.first_after(self._prev.t_us, t_next)
        # A fresh start of the kinematics in between (contact made or lost, shear memory dropped): solve on both
        # sides of it, not across (the fields jump there: lifting off lets go of the residual shear at once).
        edge = self.track.epoch_edge(self._prev.t_us, state.t_us)
        if edge is not None:
            state = edge[0] if edge[0].t_us > self._prev.t_us else edge[1]
        self._next = self.solve(state)
        self.track.hold(self._prev.t_us)
        out.solves.append(self._next)
        self._depth_field = self._shading_field(self._prev)
        self._step = self._step_us()

    def _at_rest(self) -> bool:
        """Whether the current solve pair leaves the image as it is (the same markers and contact fields)."""
        prev, nxt = self._prev, self._next
        assert prev is not None and nxt is not None
        if prev.fields is not nxt.fields or (prev.anchor_mm is None) != (nxt.anchor_mm is None):
            return False
        if prev.anchor_mm is not None and nxt.anchor_mm is not None and not np.array_equal(prev.anchor_mm, nxt.anchor_mm):
            return False
        return bool(np.array_equal(prev.markers_mm, nxt.markers_mm))

    def _unchanged_image(self, markers: npt.NDArray[np.float64]) -> bool:
        """Whether rendering ``markers`` on the current depth field would change no pixel (the last render's
        scene, at rest): the renderer's own test would find no moved marker and the same field."""
        if self._rendered is None or not self._at_rest():
            return False
        last_markers, last_depth = self._rendered
        depth = self._depth_field
        if depth is not last_depth and (depth is None or not depth.same_as(last_depth)):
            return False
        return bool(np.array_equal(markers, last_markers))

    def _truth_to(self, t1: int, truth_t: list[int], truth_mm: list[npt.NDArray[np.float64]]) -> None:
        """True marker samples due up to ``t1`` (us), from the current solve pair."""
        if self._next_truth_us <= t1:
            times = np.arange(self._next_truth_us, t1 + 1, TRUTH_MARKER_INTERVAL_US, dtype=np.int64)
            truth_t.extend(times.tolist())
            truth_mm.extend(self._markers_at_times(times))
            self._next_truth_us = int(times[-1]) + TRUTH_MARKER_INTERVAL_US

    def _next_solve_time(self, prev: Solve, tool_path: ToolPath) -> int:
        """The latest time, within [min, max] solve intervals, before the tool
        moves more than ``solve_step_mm`` (quasi-static solves as often as the
        motion needs)."""
        if self._solve_offsets_key != (self.min_solve_interval_us, self.max_solve_interval_us):
            self._solve_offsets = np.geomspace(self.min_solve_interval_us, self.max_solve_interval_us, 8).astype(np.int64)
            self._solve_offsets_key = (self.min_solve_interval_us, self.max_solve_interval_us)
        candidates = prev.t_us + self._solve_offsets
        tool = tool_path(np.concatenate(([prev.t_us], candidates)))  # one call: prev's position, then the candidates'
        moved = np.linalg.norm(tool[1:] - tool[0], axis=1)
        ok = candidates[moved <= self.solve_step_mm]
        return int(ok[-1]) if ok.size else int(candidates[0])

    def _markers_at(self, t_us: int) -> npt.NDArray[np.float64]:
        prev, nxt = self._prev, self._next
        assert prev is not None
        if nxt is None or nxt.t_us == prev.t_us:
            return prev.markers_mm
        w = (t_us - prev.t_us) / (nxt.t_us - prev.t_us)
        return prev.markers_mm + w * (nxt.markers_mm - prev.markers_mm)

    def _markers_at_times(self, t_us: npt.NDArray[np.int64]) -> npt.NDArray[np.float64]:
        """:meth:`_markers_at` for several times at once, (T, N, 3)."""
        prev, nxt = self._prev, self._next
        assert prev is not None
        if nxt is None or nxt.t_us == prev.t_us:
            return np.repeat(prev.markers_mm[None], len(t_us), axis=0)
        w = (t_us - prev.t_us) / (nxt.t_us - prev.t_us)
        return prev.markers_mm + w[:, None, None] * (nxt.markers_mm - prev.markers_mm)

    def _step_us(self) -> int:
        """Longest render step keeping every marker's image motion under max_step_px (once per solve pair)."""
        prev, nxt = self._prev, self._next
        assert prev is not None and nxt is not None
        if self._prev_px is None:
            self._prev_px = self.camera.project(prev.markers_mm)
        self._next_px = self.camera.project(nxt.markers_mm)
        motion = self._next_px - self._prev_px
        px = float(np.max(np.hypot(motion[:, 0], motion[:, 1])))
        if px <= 1e-9:
            return self.max_render_interval_us
        return int(np.clip(self.max_step_px / px * (nxt.t_us - prev.t_us), 1, self.max_render_interval_us))

    def _shading_field(self, solve: Solve) -> DepthField | None:
        if solve.fields is None or solve.anchor_mm is None:
            return None
        f = solve.fields
        return DepthField(f.x_mm + solve.anchor_mm[0], f.y_mm + solve.anchor_mm[1], np.asarray(f.depth_mm, np.float64))


def _to_ft(axes: list[list[float]], v: list[float]) -> list[float]:
    """``axes.T @ v`` on floats: a gel-frame vector in the F/T sensor's axes (``axes``: its axes in the gel)."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = axes
    return [a00 * v[0] + a10 * v[1] + a20 * v[2], a01 * v[0] + a11 * v[1] + a21 * v[2], a02 * v[0] + a12 * v[1] + a22 * v[2]]


def _dead_mask(roi: Roi, dead: Roi | None) -> npt.NDArray[np.bool_] | None:
    """(height, width) mask over the ROI of the sensor pixels inside ``dead`` (sensor pixels, ends exclusive)."""
    if dead is None:
        return None
    mask = np.zeros((roi.height_px, roi.width_px), dtype=bool)
    y0, y1 = max(dead.y0_px - roi.y0_px, 0), min(dead.y1_px - roi.y0_px, roi.height_px)
    x0, x1 = max(dead.x0_px - roi.x0_px, 0), min(dead.x1_px - roi.x0_px, roi.width_px)
    if y1 > y0 and x1 > x0:
        mask[y0:y1, x0:x1] = True
    return mask


@dataclass(frozen=True)
class _Cells:
    x0_mm: float
    y0_mm: float
    pitch_mm: float
    rows: int
    cols: int


def _marker_cells(rig: RigConfig) -> _Cells:
    m = rig.markers
    return _Cells(-m.cols * m.pitch_mm / 2, -m.rows * m.pitch_mm / 2, m.pitch_mm, m.rows, m.cols)


@dataclass(frozen=True)
class _Weights:
    """Bilinear sampling of fields on a regular grid at fixed points (N, 2); zero outside the grid."""

    i0: npt.NDArray[np.int64]
    j0: npt.NDArray[np.int64]
    wx: npt.NDArray[np.float64]
    wy: npt.NDArray[np.float64]
    inside: npt.NDArray[np.bool_]

    @classmethod
    def build(cls, x_mm: npt.NDArray[np.float64], y_mm: npt.NDArray[np.float64], xy: npt.NDArray[np.float64]) -> _Weights:
        dx, dy = x_mm[1] - x_mm[0], y_mm[1] - y_mm[0]
        fx = (xy[:, 0] - x_mm[0]) / dx
        fy = (xy[:, 1] - y_mm[0]) / dy
        inside = (fx >= 0) & (fx <= len(x_mm) - 1) & (fy >= 0) & (fy <= len(y_mm) - 1)
        i0 = np.clip(np.floor(fx).astype(int), 0, len(x_mm) - 2)
        j0 = np.clip(np.floor(fy).astype(int), 0, len(y_mm) - 2)
        return cls(i0, j0, np.clip(fx - i0, 0, 1), np.clip(fy - j0, 0, 1), inside)

    def sample(self, values: npt.NDArray[np.floating]) -> npt.NDArray[np.float64]:
        i0, j0, wx, wy, v = self.i0, self.j0, self.wx, self.wy, values
        out = (v[j0, i0] * (1 - wx) * (1 - wy) + v[j0, i0 + 1] * wx * (1 - wy)
               + v[j0 + 1, i0] * (1 - wx) * wy + v[j0 + 1, i0 + 1] * wx * wy)
        return np.where(self.inside, out, 0.0)

