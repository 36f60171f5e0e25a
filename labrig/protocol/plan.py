"""Where a probing run goes: its targets in machine coordinates, before any move (pure geometry).

Locations are in the gel frame (mm from the gel centre along the marker
grid, z out of the gel); the gel pose in machine coordinates comes from the
rig registration (the nominal pose in ``rig.toml`` until calibration exists).
Machine coordinates are those of the CNC's tool reference point: a target for
the indenter tip is shifted by the indenter's tool offset.

The surface height under the location is only nominal here: the approach
searches for contact, and the runner re-anchors Normal Down, Shear and Normal
Up at the contact it finds (:meth:`ProbePlan.from_contact`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.frames import Pose
from labrig.indenters import Indenter
from labrig.protocol.spec import ProbeSpec

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ProbePlan:
    """Tool-reference targets (machine mm) of one probing run, and the gel directions in machine axes."""

    spec: ProbeSpec
    gel_in_machine: Pose
    tool_offset_mm: F64
    #: Above the location at the travel clearance, at the approach start, at the retract height.
    clearance_mm: F64
    approach_start_mm: F64
    approach_limit_mm: F64
    retract_mm: F64
    #: The gel's inward normal and the shear direction, machine axes (unit vectors).
    down: F64
    shear_dir: F64
    #: The rig's indenter-gel Coulomb coefficient (the slip reflex's, unless the protocol gives its own).
    friction: float = 1.0
    #: The most a slip reflex may press (N): under the normal force limit.
    press_limit_n: float = float("inf")

    @classmethod
    def build(cls, spec: ProbeSpec, gel_in_machine: Pose, indenter: Indenter, clearance_mm: float, *,
              friction: float = 1.0, press_limit_n: float = float("inf")) -> ProbePlan:
        offset = np.asarray(indenter.tool_offset_mm, dtype=np.float64)
        x, y = spec.location_mm

        def tool_at(z_gel_mm: float) -> F64:
            return gel_in_machine.apply(np.array([x, y, z_gel_mm])) - offset

        a = np.radians(spec.shear_direction_deg)
        rotation = gel_in_machine.rotation
        start = spec.approach.start_height_mm
        return cls(
            spec=spec,
            gel_in_machine=gel_in_machine,
            tool_offset_mm=offset,
            clearance_mm=tool_at(max(clearance_mm, start, spec.retract_height_mm)),
            approach_start_mm=tool_at(start),
            approach_limit_mm=tool_at(start - spec.approach.max_travel_mm),
            retract_mm=tool_at(spec.retract_height_mm),
            down=rotation @ np.array([0.0, 0.0, -1.0]),
            shear_dir=rotation @ np.array([np.cos(a), np.sin(a), 0.0]),
            friction=friction,
            press_limit_n=press_limit_n,
        )

    def bottom_mm(self, contact_mm: npt.ArrayLike) -> F64:
        """Tool target at the normal depth below the contact point (depth targets)."""
        assert self.spec.depth_mm is not None
        return np.asarray(contact_mm, dtype=np.float64) + self.spec.depth_mm * self.down

    def max_bottom_mm(self, contact_mm: npt.ArrayLike, max_depth_mm: float) -> F64:
        """The deepest the tool may go below the contact point (force targets search down to it)."""
        return np.asarray(contact_mm, dtype=np.float64) + max_depth_mm * self.down

    def sheared_mm(self, bottom_mm: npt.ArrayLike) -> F64:
        return np.asarray(bottom_mm, dtype=np.float64) + self.spec.shear_mm * self.shear_dir

    def nominal_targets(self, max_depth_mm: float) -> list[tuple[str, F64]]:
        """Every target the run may command, with the nominal surface as contact, for the workspace check."""
        surface = self.approach_start_mm + self.spec.approach.start_height_mm * self.down
        depth = self.spec.depth_mm if self.spec.depth_mm is not None else max_depth_mm
        bottom = surface + depth * self.down
        return [
            ("travel height", self.clearance_mm),
            ("approach start", self.approach_start_mm),
            ("approach limit", self.approach_limit_mm),
            ("normal down", bottom),
            ("shear", self.sheared_mm(bottom)),
            ("retract", self.retract_mm),
        ]
