"""The motion envelope of the hand tools (``labrig cnc move|jog|send|stream``): where the tool may go.

Built from the rig file and the mounted indenter. Positions are of the tool reference point in
machine coordinates (GRBL's MPos, mm); the indenter's tip is the reference point plus its
``tool_offset_mm``. The gel frame has its origin at the nominal gel surface centre (``[rig]
gel_origin_machine_mm``, where the tip touches), x and y along the gel's sides (yawed by
``gel_yaw_deg`` about the machine z axis), z up. Rules:

* every commanded point lies inside the ``[safety]`` workspace (``workspace_min_mm`` ..
  ``workspace_max_mm``);
* over the *press area*, the gel (``[gel] size_x_mm`` x ``size_y_mm``) grown by the indenter's
  ``footprint_radius_mm``, the tip stays at most the indenter's ``max_depth_mm`` (and never more
  than the gel's ``thickness_mm``) below the gel surface;
* out to ``[safety] body_margin_mm`` beyond the press area the tip stays above the gel surface:
  the sensor body that carries the gel is solid there, all the way down;
* a straight move is checked along its whole length (segment against the region), so a move
  from beside the gel to beside it below the surface does not cut through the gel.

A move that starts inside that region (reached with the override) may only go straight up.
Each problem is one line naming the value and what to do. Pure: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from labrig.config import RigConfig
from labrig.indenters import Indenter
from labrig.physics.geometry import gel_frame
from labrig.protocol.rigfile import safety_limits
from labrig.protocol.safety import SafetyError

Point = tuple[float, float, float]

#: Distances (mm) this close to the region's faces count as outside it (a tip exactly at the deepest
#: allowed press, a move along the surface).
TOLERANCE_MM = 1e-6


class EnvelopeError(SafetyError):
    """A hand-tool motion outside the envelope, refused before anything is sent."""


def most_conservative_indenter(indenters: Mapping[str, Indenter]) -> Indenter:
    """The indenter whose tip reaches lowest (the most negative ``tool_offset_mm`` z); ties go to the
    smallest ``max_depth_mm``, then the widest footprint, then the first in the file."""
    if not indenters:
        raise EnvelopeError("the indenters file defines no indenter; give the mounted one with --indenter")
    order = {name: i for i, name in enumerate(indenters)}
    return min(indenters.values(), key=lambda ind: (ind.tool_offset_mm[2], ind.max_depth_mm,
                                                     -ind.footprint_radius_mm, order[ind.name]))


@dataclass(frozen=True)
class MotionEnvelope:
    """Where the tool reference point may go (machine mm; see the module docstring for the rules).

    ``gel_origin_machine_mm``: the gel surface centre (machine mm, the tip's frame);
    ``gel_yaw_deg``: the gel's turn about the machine z axis; ``gel_size_mm``: its x and y sides;
    ``press_depth_mm``: how far the tip may go below the surface over the press area (the
    indenter's ``max_depth_mm``, at most the gel's thickness); ``tool_offset_mm``: the tip
    relative to the reference point (machine axes).
    """

    workspace_min_mm: Point
    workspace_max_mm: Point
    gel_origin_machine_mm: Point
    gel_yaw_deg: float
    gel_size_mm: tuple[float, float]
    body_margin_mm: float
    indenter_name: str
    tool_offset_mm: Point
    press_depth_mm: float
    footprint_radius_mm: float

    @classmethod
    def of(cls, rig: RigConfig, indenter: Indenter) -> MotionEnvelope:
        """The envelope of ``indenter`` mounted on the rig of ``rig`` (its ``[safety]``, ``[rig]`` and ``[gel]``)."""
        limits = safety_limits(rig)
        return cls(
            workspace_min_mm=limits.workspace_min_mm,
            workspace_max_mm=limits.workspace_max_mm,
            gel_origin_machine_mm=rig.rig.gel_origin_machine_mm,
            gel_yaw_deg=rig.rig.gel_yaw_deg,
            gel_size_mm=(rig.gel.size_x_mm, rig.gel.size_y_mm),
            body_margin_mm=limits.body_margin_mm,
            indenter_name=indenter.name,
            tool_offset_mm=indenter.tool_offset_mm,
            press_depth_mm=min(indenter.max_depth_mm, rig.gel.thickness_mm),
            footprint_radius_mm=indenter.footprint_radius_mm,
        )

    @property
    def surface_reference_z_mm(self) -> float:
        """Machine Z of the reference point with the tip in the gel surface's plane."""
        return self.gel_origin_machine_mm[2] - self.tool_offset_mm[2]

    def point_problem(self, point_mm: Point) -> str | None:
        """What is wrong with the reference point at ``point_mm`` (machine mm), or None."""
        problem = self._workspace_problem(point_mm)
        if problem is None and self._forbidden_part(self._in_gel(point_mm), self._in_gel(point_mm)) is not None:
            problem = self._inside_text(point_mm, self._in_gel(point_mm))
        return problem

    def segment_problem(self, start_mm: Point, end_mm: Point) -> str | None:
        """What is wrong with a straight move of the reference point from ``start_mm`` to ``end_mm``
        (machine mm), or None. The start is where the machine is: it may lie outside the envelope
        (reached with the override), and then only the way out, straight up, is allowed."""
        problem = self._workspace_problem(end_mm)
        if problem is not None:
            return problem
        start, end = self._in_gel(start_mm), self._in_gel(end_mm)
        if self._forbidden_part(start, start) is not None:
            if math.dist(start_mm[:2], end_mm[:2]) <= TOLERANCE_MM and end_mm[2] >= start_mm[2]:
                return None  # straight up (or staying): the way out
            return (f"the {self.indenter_name}'s tip is already {-start[2]:.3f} mm below the gel surface at "
                    f"{_machine(start_mm)}: move straight up first (Z only, to machine Z >= "
                    f"{self.surface_reference_z_mm:.3f})")
        if self._forbidden_part(end, end) is not None:
            return self._inside_text(end_mm, end)
        at = self._forbidden_part(start, end)
        if at is not None:
            through = np.asarray(start_mm) + at * (np.asarray(end_mm) - np.asarray(start_mm))
            depth = -(start[2] + at * (end[2] - start[2]))
            return (f"the straight move from {_machine(start_mm)} to {_machine(end_mm)} passes through the gel or "
                    f"the sensor body (the {self.indenter_name}'s tip {depth:.3f} mm below the gel surface at "
                    f"{_machine(tuple(through.tolist()))}): move up to machine Z >= "
                    f"{self.surface_reference_z_mm:.3f} first, then across")
        return None

    # -- geometry ------------------------------------------------------------------------

    def _workspace_problem(self, point_mm: Point) -> str | None:
        for axis, value, low, high in zip("XYZ", point_mm, self.workspace_min_mm, self.workspace_max_mm, strict=True):
            if not low - TOLERANCE_MM <= value <= high + TOLERANCE_MM:
                return (f"machine {axis} {value:.3f} mm is outside the workspace [{low:g}, {high:g}] mm "
                        f"([safety] workspace_min_mm, workspace_max_mm); keep {axis} within it")
        return None

    def _in_gel(self, point_mm: Point) -> Point:
        """The tip of the reference point at ``point_mm`` (machine mm) in the gel frame (mm)."""
        tip = np.asarray(point_mm, dtype=np.float64) + np.asarray(self.tool_offset_mm)
        x, y, z = gel_frame(self.gel_origin_machine_mm, self.gel_yaw_deg).inverse().apply(tip).tolist()
        return (x, y, z)

    @property
    def _press_half_mm(self) -> tuple[float, float]:
        return (self.gel_size_mm[0] / 2 + self.footprint_radius_mm, self.gel_size_mm[1] / 2 + self.footprint_radius_mm)

    def _forbidden_part(self, start: Point, end: Point) -> float | None:
        """A parameter t in [0, 1] where the tip's straight path (gel frame) is inside the forbidden
        region (below the surface within the body, less the press slab), or None if it never is."""
        px, py = self._press_half_mm
        bx, by = px + self.body_margin_mm, py + self.body_margin_mm
        t = TOLERANCE_MM
        body = _interval(start, end, ((-bx + t, bx - t), (-by + t, by - t), (-math.inf, -t)))
        if body is None:
            return None
        press = _interval(start, end, ((-px - t, px + t), (-py - t, py + t), (-self.press_depth_mm - t, t)))
        a, b = body
        if press is None:
            return (a + b) / 2
        c, e = press
        if a < c:
            return (a + min(b, c)) / 2
        if b > e:
            return (max(a, e) + b) / 2
        return None

    def _inside_text(self, point_mm: Point, tip: Point) -> str:
        px, py = self._press_half_mm
        depth = -tip[2]
        if abs(tip[0]) <= px and abs(tip[1]) <= py:
            deepest = self.surface_reference_z_mm - self.press_depth_mm
            return (f"machine Z {point_mm[2]:.3f} mm at X {point_mm[0]:.3f} Y {point_mm[1]:.3f} puts the "
                    f"{self.indenter_name}'s tip {depth:.3f} mm below the gel surface over the gel, deeper than the "
                    f"{self.press_depth_mm:g} mm it may press (its max_depth_mm, at most the gel's thickness): keep "
                    f"machine Z >= {deepest:.3f} there")
        return (f"machine Z {point_mm[2]:.3f} mm at X {point_mm[0]:.3f} Y {point_mm[1]:.3f} puts the "
                f"{self.indenter_name}'s tip {depth:.3f} mm below the gel surface beside the gel, where the sensor "
                f"body is (within [safety] body_margin_mm {self.body_margin_mm:g} mm): keep machine Z >= "
                f"{self.surface_reference_z_mm:.3f} there")


def _interval(start: Point, end: Point, box: tuple[tuple[float, float], ...]) -> tuple[float, float] | None:
    """The parameters t in [0, 1] of ``start + t (end - start)`` inside the closed ``box`` (per axis
    (low, high), infinite allowed), as (first, last), or None if none are."""
    first, last = 0.0, 1.0
    for p0, p1, (low, high) in zip(start, end, box, strict=True):
        step = p1 - p0
        if step == 0.0:
            if not low <= p0 <= high:
                return None
            continue
        t_low, t_high = (low - p0) / step, (high - p0) / step
        if t_low > t_high:
            t_low, t_high = t_high, t_low
        first, last = max(first, t_low), min(last, t_high)
        if first > last:
            return None
    return first, last


def _machine(point_mm: Point | tuple[float, ...]) -> str:
    """A machine position as text (mm)."""
    return f"X {point_mm[0]:.3f} Y {point_mm[1]:.3f} Z {point_mm[2]:.3f}"
