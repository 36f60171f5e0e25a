"""Indenter motion for the virtual rig: tool paths and the standard probing sequence.

A path gives the CNC tool reference point in machine coordinates (mm) at any
world time (us). The CNC twin provides its own path from planned moves; these
are for tests, benchmarks and scripted scenes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig
from labrig.frames import Pose
from labrig.indenters import Indenter
from labrig.physics.geometry import gel_frame, nominal_gel_in_machine
from labrig.sim.truth_config import sim_config


def true_gel_in_machine(rig: RigConfig) -> Pose:
    """The gel frame in machine coordinates as the virtual rig builds it: ``[sim.rig_pose]``, tilt included.

    The nominal pose a real runner starts from is :func:`labrig.physics.geometry.nominal_gel_in_machine`.
    """
    p = sim_config(rig).rig_pose
    return gel_frame(p.gel_origin_machine_mm, p.gel_yaw_deg, p.gel_tilt_deg)


@dataclass(frozen=True)
class PiecewiseLinearPath:
    """Tool position (machine mm) interpolated linearly between knots; held at the ends."""

    t_us: npt.NDArray[np.float64]
    position_mm: npt.NDArray[np.float64]
    phases: tuple[tuple[str, float, float], ...] = ()

    def __call__(self, t_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        t = np.atleast_1d(np.asarray(t_us, dtype=np.float64))
        return np.stack([np.interp(t, self.t_us, self.position_mm[:, i]) for i in range(3)], axis=-1)

    @property
    def duration_us(self) -> float:
        return float(self.t_us[-1])


def probing_path(
    rig: RigConfig,
    indenter: Indenter,
    *,
    location_mm: tuple[float, float] = (0.0, 0.0),
    depth_mm: float = 1.5,
    shear_mm: float = 1.0,
    shear_direction_deg: float = 0.0,
    normal_speed_mm_s: float = 1.5,
    shear_speed_mm_s: float = 1.5,
    wait_s: float = 0.3,
    approach_mm: float = 0.5,
    nominal: bool = False,
) -> PiecewiseLinearPath:
    """The paper's sequence as straight moves, planned in the gel frame.

    Approach, Normal Down, Wait, Shear, Wait, Shear Opposite, Wait, Normal Up,
    retract. Locations are gel-frame mm; the path is returned in machine mm
    using the true gel pose (or the nominal one, as a real runner would).

    A scripted scene's path, timed on paper: the tip meets the gel's surface where the
    pose puts it, every move runs at its speed from end to end, and a run without shear
    keeps its (still) shear phases and waits. A probing run's own sequence (contact
    search, force targets, recovery) is :mod:`labrig.protocol.procedure`, played on
    the virtual rig's device twins.
    """
    x, y = location_mm
    u = np.array([np.cos(np.radians(shear_direction_deg)), np.sin(np.radians(shear_direction_deg)), 0.0])
    above = np.array([x, y, approach_mm])
    surface = np.array([x, y, 0.0])
    bottom = np.array([x, y, -depth_mm])
    sheared = bottom + shear_mm * u
    # Each move: (phase, target in gel mm, speed mm/s or None for a wait).
    moves: list[tuple[str, np.ndarray, float | None]] = [
        ("approach", surface, normal_speed_mm_s),
        ("normal_down", bottom, normal_speed_mm_s),
        ("wait", bottom, None),
        ("shear", sheared, shear_speed_mm_s),
        ("wait", sheared, None),
        ("shear_opposite", bottom, shear_speed_mm_s),
        ("wait", bottom, None),
        ("normal_up", surface, normal_speed_mm_s),
        ("retract", above, normal_speed_mm_s),
    ]
    times = [0.0]
    tips = [above]
    phases = []
    for name, target, speed in moves:
        duration_s = wait_s if speed is None else float(np.linalg.norm(target - tips[-1])) / speed
        phases.append((name, times[-1], times[-1] + duration_s * 1e6))
        times.append(times[-1] + duration_s * 1e6)
        tips.append(target)
    gel = nominal_gel_in_machine(rig) if nominal else true_gel_in_machine(rig)
    tip_machine = gel.apply(np.array(tips))
    tool_machine = tip_machine - np.asarray(indenter.tool_offset_mm)
    return PiecewiseLinearPath(np.array(times), tool_machine, tuple(phases))
