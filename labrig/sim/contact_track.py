"""The indenter's contact state over time: cheap kinematics, shared by every consumer.

Turning a tool position into a contact state (depth, contact anchor, shear
memory, net force, centre of pressure) costs microseconds; turning that state
into contact fields (for markers, shading and truth) costs milliseconds. The
virtual rig's consumers need the state at different times: the F/T twin at
the host's "now" (800 Hz, timing-critical), the renderer behind it (its
events carry their own timestamps, so it may lag). :class:`ContactTrack`
samples the state in strictly increasing time, stores it, and serves both:
a query at or after the last sample takes a new sample; an earlier one is
answered from the stored samples.

Contact kinematics (:class:`ContactKinematics`)
-----------------------------------------------
The indenter tip is mapped into the gel frame through the rig's true gel pose.
Depth = -z of the tip. At first contact the tip's (x, y) becomes the contact
anchor: the contact fields are centred there (small-displacement description
in reference coordinates), and the tip's in-plane motion since then is the
tangential shift, fed through a Masing :class:`ShearHistory` along one shear
axis. In gross slip the anchor is dragged so the shift never exceeds the
table's slip shift. Lifting off clears the anchor and the history (the
residual traction after Shear and Shear Opposite stays until then). Each such
fresh start (contact made, lifted off, the shear memory dropped for a new axis
or table) begins an epoch (:attr:`ContactState.epoch`): the fields change
continuously within an epoch and may jump between two, so the virtual rig
solves on both sides of an epoch's edge rather than interpolating across it.

Beyond the gel model (deeper than the table's ``max_depth_mm``) the state is held at the
table's deepest depth and the excursion is counted in :attr:`ContactKinematics.faults`: the
twins keep answering (a request must never kill the rig), the owner reports the fault and the
run that pressed too deep aborts and retracts.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.frames import Pose
from labrig.physics.mechanics import ContactTable, ShearHistory
from labrig.physics.mechanics.history import Term
from labrig.physics.mechanics.tables import table_direction_deg
from labrig.sim.faults import RigFault

F64 = npt.NDArray[np.float64]
ToolPath = Callable[[npt.ArrayLike], F64]
#: The tool (machine mm) at one world time (us), as Python floats.
ToolPoint = Callable[[int], tuple[float, float, float]]

#: A shear axis is fixed once the tip has moved this far in-plane from the anchor, mm.
SHEAR_AXIS_MM = 1e-3
#: A non-axisymmetric indenter's table direction is chosen once the shift is this long, mm.
DIRECTION_FIX_MM = 0.02


@dataclass(frozen=True)
class ContactState:
    """The contact at one world time (gel frame, mm, N)."""

    t_us: int
    tip_gel_mm: F64
    depth_mm: float
    anchor_mm: F64 | None
    terms: tuple[Term, ...]
    angle_rad: float
    #: Net force on the gel (pressing is -z).
    force_on_gel_n: F64
    centre_of_pressure_mm: F64
    #: The table the state was computed with (non-axisymmetric indenters: one per shear direction).
    table: ContactTable | None = None
    #: Counts the kinematics' fresh starts (contact made, lifted off, shear memory dropped for a new axis or
    #: table): the contact fields may jump between two states of different epochs, never within one.
    epoch: int = 0
    #: The whole contact slides (gross slip): the shift is at the table's slip shift and the anchor is dragged.
    sliding: bool = False

    @property
    def in_contact(self) -> bool:
        return self.anchor_mm is not None


class ContactKinematics:
    """Tool positions (machine mm) -> :class:`ContactState`; feed them in time order."""

    def __init__(self, table: ContactTable, tool_offset_mm: npt.ArrayLike, machine_to_gel: Pose,
                 table_for_direction: Callable[[float], ContactTable] | None = None) -> None:
        """``table_for_direction(deg)``: the table of a non-axisymmetric indenter for another shear
        direction (see :func:`~labrig.physics.mechanics.tables.table_direction_deg`), loaded on first use."""
        self.table = table
        self.tool_offset_mm = np.asarray(tool_offset_mm, dtype=np.float64).reshape(3)
        self.machine_to_gel = machine_to_gel
        self._table_for_direction = table_for_direction
        self._tables = {float(table.meta["direction_deg"]) % 180.0: table}
        self._active = table
        self._history = ShearHistory()
        # The state in Python floats (a step runs at the F/T rate: no small arrays on its way).
        self._anchor: tuple[float, float] | None = None
        self._shear_axis: tuple[float, float] | None = None
        self._rotation = machine_to_gel.rotation.tolist()
        self._origin = (machine_to_gel.rotation @ self.tool_offset_mm + machine_to_gel.translation_mm).tolist()
        self._deepest_mm = float(table.depths_mm[-1])
        #: One per excursion beyond the gel model's depth (appended when it starts; world us).
        self.faults: list[RigFault] = []
        self._beyond = False
        self._epoch = 0

    def step(self, t_us: int, tool_machine_mm: npt.ArrayLike) -> ContactState:
        if isinstance(tool_machine_mm, tuple):
            x, y, z = tool_machine_mm
        else:
            x, y, z = np.asarray(tool_machine_mm, dtype=np.float64).reshape(3).tolist()
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self._rotation
        o0, o1, o2 = self._origin
        tx, ty, tz = r00 * x + r01 * y + r02 * z + o0, r10 * x + r11 * y + r12 * z + o1, r20 * x + r21 * y + r22 * z + o2
        tip = np.array([tx, ty, tz])
        depth = max(0.0, -tz)
        if depth <= 0.0:
            if self._anchor is not None:
                self._epoch += 1
            self._anchor = None
            self._shear_axis = None
            self._active = self.table
            self._history.reset()
            return ContactState(int(t_us), tip, 0.0, None, (), 0.0, np.zeros(3), np.array([tx, ty, 0.0]),
                                epoch=self._epoch)
        deepest = self._deepest_mm
        if depth > deepest:
            if not self._beyond:
                self.faults.append(RigFault(int(t_us), (
                    f"the indenter went {depth:.3f} mm deep, beyond the gel model's {deepest:.2f} mm "
                    "(the indenter's max_depth_mm): its forces and fields are held at that depth")))
            self._beyond = True
            depth = deepest
        else:
            self._beyond = False
        if self._anchor is None:
            self._anchor = (tx, ty)
            self._epoch += 1
        ax, ay = self._anchor
        sx, sy = self._shear_shift(tx - ax, ty - ay)
        if not self.table.axisymmetric and self._shear_axis is not None:
            sx, sy = self._along_table(sx, sy)
        limit = self._active.slip_shift_at(depth)
        size = math.hypot(sx, sy)
        sliding = limit > 0 and size > limit
        if sliding:  # gross slip: the contact is dragged along
            ax, ay = tx - sx * (limit / size), ty - sy * (limit / size)
            self._anchor = (ax, ay)
            sx, sy = tx - ax, ty - ay
        table = self._active
        terms, angle = table.shear_terms((sx, sy), self._history)
        fx, fy, fz = table.force_xyz_for_terms(depth, terms, angle)
        cx, cy = table.pressure_centre_xy(depth)
        return ContactState(int(t_us), tip, depth, np.array([ax, ay]), terms, angle,
                            np.array([fx, fy, -fz]), np.array([ax + cx, ay + cy, 0.0]), table, self._epoch, sliding)

    def _along_table(self, sx: float, sy: float) -> tuple[float, float]:
        """A non-axisymmetric indenter's shift, along the direction of the table that serves it.

        The table is chosen once the shift is DIRECTION_FIX_MM long (a few micrometres of drift,
        e.g. from the gel's tilt while pressing, do not pick one) and kept from the first reversal
        on; the shift is projected on its direction (at most DIRECTION_STEP_DEG / 2 away)."""
        size = math.hypot(sx, sy)
        if size >= DIRECTION_FIX_MM and not self._history.reversals_mm and self._shear_axis is not None:
            table = self._table_for(self._shear_axis)
            if table is not self._active:
                self._active = table
                self._history.reset()
                self._epoch += 1
        dx, dy = (float(v) for v in self._active.direction)
        self._history.axis = (dx, dy)
        along = sx * dx + sy * dy
        return along * dx, along * dy

    def _table_for(self, axis: tuple[float, float]) -> ContactTable:
        if self.table.axisymmetric or self._table_for_direction is None:
            return self.table
        direction = table_direction_deg(math.degrees(math.atan2(axis[1], axis[0])))
        if direction not in self._tables:
            self._tables[direction] = self._table_for_direction(direction)
        return self._tables[direction]

    def _shear_shift(self, sx: float, sy: float) -> tuple[float, float]:
        """The in-plane shift (x, y mm) along the current shear axis (Masing needs one axis).

        While the loading is virgin (no reversal yet) the axis is the shift's own
        direction; from the first reversal on it stays, and the component across
        it is dropped (tilt, CNC jitter). The tangential state
        (including the residual traction after Shear, Shear Opposite) lasts
        until lift-off; a shift clearly across the axis starts a new axis and a
        fresh history (the old residual is then forgotten: an approximation).
        """
        size = math.hypot(sx, sy)
        axis = self._shear_axis
        if axis is not None and not self._history.reversals_mm and size >= SHEAR_AXIS_MM and sx * axis[0] + sy * axis[1] > 0:
            # Virgin loading has no memory to keep: the axis follows the shift's direction (a slow
            # drift before the shear, e.g. from the gel's tilt, does not fix a wrong axis).
            self._shear_axis = (sx / size, sy / size)
            self._history.axis = self._shear_axis
            return sx, sy
        if axis is not None:
            along = sx * axis[0] + sy * axis[1]
            across = math.hypot(sx - along * axis[0], sy - along * axis[1])
            if across <= SHEAR_AXIS_MM or across <= 0.1 * abs(along):
                return along * axis[0], along * axis[1]
        if size < SHEAR_AXIS_MM:
            return 0.0, 0.0
        if axis is not None:  # a new axis drops the old one's memory (the residual traction)
            self._epoch += 1
        self._shear_axis = (sx / size, sy / size)
        self._history.reset()
        self._history.axis = self._shear_axis
        return sx, sy

    def _slip_shift_mm(self, depth: float) -> float:
        return self._active.slip_shift_at(depth)


class ContactTrack:
    """Contact states sampled in increasing world time from a tool path; thread-safe.

    ``keep_us``: how much history to keep behind the newest sample (older
    samples are dropped unless :meth:`hold` pins them for a lagging reader).
    """

    def __init__(self, kinematics: ContactKinematics, tool_path: ToolPath, *, keep_us: int = 30_000_000,
                 tool_at: ToolPoint | None = None) -> None:
        """``tool_at``: ``tool_path`` at one time as Python floats, for the samples (optional)."""
        self.kinematics = kinematics
        self.tool_path = tool_path
        self.tool_at = tool_at
        self.keep_us = int(keep_us)
        self._times: list[int] = []
        self._states: list[ContactState] = []
        self._held_us: int | None = None
        self._lock = threading.RLock()

    @property
    def last_us(self) -> int | None:
        with self._lock:
            return self._times[-1] if self._times else None

    def sample(self, t_us: int) -> ContactState:
        """The state at ``t_us`` if it is at or after the last sample (sampled now),
        else the latest stored state at or before it (the earliest one if none)."""
        t = int(t_us)
        with self._lock:
            if not self._times or t > self._times[-1]:
                state = self.kinematics.step(t, self.tool_at(t) if self.tool_at is not None else self.tool_path(t)[0])
                self._times.append(t)
                self._states.append(state)
                self._prune()
                return state
            i = bisect.bisect_right(self._times, t) - 1
            return self._states[max(i, 0)]

    def first_after(self, t_us: int, not_after_us: int) -> ContactState:
        """A state later than ``t_us`` and as late as possible up to ``not_after_us``:
        sampled at ``not_after_us`` when that is new, else the latest stored one in
        (t_us, not_after_us], else the first stored one after ``t_us``."""
        with self._lock:
            if not self._times or not_after_us > self._times[-1]:
                return self.sample(not_after_us)
            i = bisect.bisect_right(self._times, int(not_after_us)) - 1
            if i >= 0 and self._times[i] > t_us:
                return self._states[i]
            j = bisect.bisect_right(self._times, int(t_us))
            return self._states[j] if j < len(self._states) else self.sample(max(int(t_us) + 1, self._times[-1] + 1))

    def epoch_edge(self, t0_us: int, t1_us: int) -> tuple[ContactState, ContactState] | None:
        """The first fresh start of the kinematics (:attr:`ContactState.epoch`) after ``t0_us``, up to ``t1_us``,
        among the stored samples: (the last sample of the epoch at ``t0_us``, the first of the next), or None."""
        with self._lock:
            i = bisect.bisect_right(self._times, int(t0_us)) - 1
            if i < 0:
                return None
            epoch = self._states[i].epoch
            for j in range(i + 1, bisect.bisect_right(self._times, int(t1_us))):
                if self._states[j].epoch != epoch:
                    return self._states[j - 1], self._states[j]
            return None

    def wrench_state(self, t_us: float) -> tuple[F64, F64, F64]:
        """(force on the gel N, centre of pressure mm, tip mm) at ``t_us``, gel frame:
        sampled when ``t_us`` is new, else interpolated linearly between stored samples."""
        t = round(t_us)
        with self._lock:
            if not self._times or t >= self._times[-1]:
                s = self.sample(t)
                return s.force_on_gel_n, s.centre_of_pressure_mm, s.tip_gel_mm
            j = bisect.bisect_right(self._times, t)
            if j == 0:
                s = self._states[0]
                return s.force_on_gel_n, s.centre_of_pressure_mm, s.tip_gel_mm
            a, b = self._states[j - 1], self._states[j]
            w = (t - a.t_us) / (b.t_us - a.t_us)
            return (
                a.force_on_gel_n + w * (b.force_on_gel_n - a.force_on_gel_n),
                a.centre_of_pressure_mm + w * (b.centre_of_pressure_mm - a.centre_of_pressure_mm),
                a.tip_gel_mm + w * (b.tip_gel_mm - a.tip_gel_mm),
            )

    def hold(self, t_us: int | None) -> None:
        """Keep every sample from ``t_us`` on (a lagging reader's position); None releases."""
        with self._lock:
            self._held_us = None if t_us is None else int(t_us)

    def _prune(self) -> None:
        cut = self._times[-1] - self.keep_us
        if self._held_us is not None:
            cut = min(cut, self._held_us)
        i = bisect.bisect_left(self._times, cut) - 1  # keep one sample at or before the cut
        if i > 1024:
            del self._times[:i]
            del self._states[:i]
