"""Before any move: a probing run's plan, built and checked against the rig, the indenter and the limits.

The same checks whichever executor plays the run (the drivers' or the virtual-time one); the
speeds are checked apart, against the CNC whose max rates apply (:class:`~labrig.protocol.safety.SpeedLimits`).
"""

from __future__ import annotations

from labrig.config import RigConfig
from labrig.frames import Pose
from labrig.indenters import Indenter
from labrig.protocol.plan import ProbePlan
from labrig.protocol.safety import SafetyError, SafetyLimits, check_location, check_targets, depth_problem
from labrig.protocol.spec import ProbeSpec

#: A slip reflex presses to at most this share of the normal force limit (the monitor trips at the limit itself).
PRESS_LIMIT_SHARE = 0.8


def checked_plan(spec: ProbeSpec, rig: RigConfig, indenter: Indenter, gel_in_machine: Pose,
                 limits: SafetyLimits) -> ProbePlan:
    """The plan of ``spec`` for the mounted ``indenter`` at the gel pose ``gel_in_machine``, every
    target inside ``limits`` (already capped by the indenter's forces); raises
    :class:`~labrig.protocol.safety.SafetyError` with the problems otherwise."""
    if spec.indenter != indenter.name:
        raise SafetyError(f"the run needs the {spec.indenter} indenter but {indenter.name} is mounted")
    check_location(spec.location_mm, (rig.gel.size_x_mm, rig.gel.size_y_mm), indenter.footprint_radius_mm,
                   limits.gel_margin_mm)
    for value in (spec.depth_mm, spec.max_depth_mm):
        problem = None if value is None else depth_problem(value, indenter.name, indenter.max_depth_mm)
        if problem is not None:
            raise SafetyError(f"depth {problem}")
    if spec.force_n is not None and spec.force_n > limits.max_normal_force_n:
        raise SafetyError(f"force target {spec.force_n} N is over the normal force limit {limits.max_normal_force_n} N")
    plan = ProbePlan.build(spec, gel_in_machine, indenter, limits.clearance_mm, friction=rig.gel.friction,
                           press_limit_n=PRESS_LIMIT_SHARE * limits.max_normal_force_n)
    check_targets(plan.nominal_targets(indenter.max_depth_mm), limits)
    return plan
