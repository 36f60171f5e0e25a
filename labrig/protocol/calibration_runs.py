"""The rig calibrations that move the rig: the registration's touch-offs and the gel's force-depth presses.

:func:`register_rig` touches off with the sphere at a few locations (nominal gel
pose) and solves the registration
(:func:`labrig.calibration.registration.solve_registration`);
:func:`measure_curves` presses each indenter of a plan in quasi-static steps at
the registered gel pose, for the modulus fit
(:func:`labrig.calibration.gel.fit_modulus`). Each opens its rig session with
:meth:`~labrig.protocol.session.RigSession.for_rig` (the virtual rig when the rig
file names no devices).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

from labrig.calibration.files import camera_model
from labrig.calibration.gel import ForceDepthCurve, gel_model
from labrig.calibration.registration import MIN_POINTS, Press, solve_registration
from labrig.calibration.registration_file import RigRegistration, gel_pose
from labrig.config import RigConfig
from labrig.errors import CalibrationError
from labrig.indenters import Indenter
from labrig.physics.geometry import nominal_gel_in_machine
from labrig.protocol.rigfile import safety_limits
from labrig.protocol.session import RigSession
from labrig.protocol.touchoff import lift, press

#: Touch-off locations in the order a registration uses them (gel mm, nominal frame; the sphere's
#: footprint inside the gel): the corners of a 14 x 12 mm rectangle, its centre, its edges' midpoints.
TOUCHOFF_LOCATIONS: tuple[tuple[float, float], ...] = ((-7.0, -6.0), (7.0, -6.0), (7.0, 6.0), (-7.0, 6.0), (0.0, 0.0),
                                                       (0.0, -6.0), (7.0, 0.0), (0.0, 6.0), (-7.0, 0.0))
#: Touch-offs by default: one more than the four corners, so that a touch-off the others disagree
#: with can be dropped and the rest still checked against each other.
DEFAULT_TOUCHOFFS = 5
#: Default touch-off locations (gel mm, nominal frame).
DEFAULT_LOCATIONS: tuple[tuple[float, float], ...] = TOUCHOFF_LOCATIONS[:DEFAULT_TOUCHOFFS]
#: Depths below the detected contact for the touch-offs' quasi-static steps, mm.
SPHERE_DEPTHS_MM: tuple[float, ...] = (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0)
#: Default indentations for the modulus: indenter -> (locations in gel mm, depths below contact in mm).
DEFAULT_PLAN: dict[str, tuple[tuple[tuple[float, float], ...], tuple[float, ...]]] = {
    "sphere": (((0.0, 0.0),), (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0)),
    "cylinder": (((0.0, 0.0),), (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8)),
}

Progress = Callable[[str], None]


def touchoff_locations(count: int) -> tuple[tuple[float, float], ...]:
    """The first ``count`` of :data:`TOUCHOFF_LOCATIONS` (gel mm, nominal frame); 3 to 9."""
    if not MIN_POINTS <= count <= len(TOUCHOFF_LOCATIONS):
        raise CalibrationError(f"{count} touch-offs asked; the registration takes {MIN_POINTS} to "
                               f"{len(TOUCHOFF_LOCATIONS)} (default {DEFAULT_TOUCHOFFS})")
    return TOUCHOFF_LOCATIONS[:count]


def register_rig(
    rig: RigConfig,
    indenters: dict[str, Indenter],
    *,
    data_dir: str | Path,
    locations: Sequence[tuple[float, float]] = DEFAULT_LOCATIONS,
    depths_mm: Sequence[float] = SPHERE_DEPTHS_MM,
    indenter_name: str = "sphere",
    shear_mm: float = 0.3,
    extrinsics_path: str | Path | None = None,
    gel_path: str | Path | None = None,
    session: RigSession | None = None,
    seed: int = 0,
    indenters_path: Path | None = None,
    progress: Progress | None = None,
) -> RigRegistration:
    """Touch off at ``locations`` (nominal gel frame), recording each to ``data_dir``, and solve the
    registration for the gel of :func:`~labrig.calibration.gel.gel_model` (``gel_path``, default the gel
    calibration next to the rig file, else its ``[gel]``). Opens a :class:`RigSession` from the rig
    file's devices (the virtual rig when none) unless ``session`` (open, with the indenter mounted) is
    given. Raises CalibrationError when the fit is refused (:func:`require_usable_fit`)."""
    if len(locations) < MIN_POINTS:
        raise CalibrationError(f"{len(locations)} touch-off location(s) given; the registration needs at least {MIN_POINTS}")
    indenter = indenters[indenter_name]
    camera, source = camera_model(rig, extrinsics_path)
    gel = gel_model(rig, gel_path)
    nominal = nominal_gel_in_machine(rig)
    data_dir = Path(data_dir)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    shear_directions_deg = [90.0 * (i % 4) for i in range(len(locations))]
    presses: list[Press] = []
    own = session is None
    if session is None:
        session = RigSession.for_rig(rig, indenter, seed=seed, indenters_path=indenters_path,
                                     shear_directions_deg=shear_directions_deg).open()
    try:
        for i, (loc, direction) in enumerate(zip(locations, shear_directions_deg, strict=True)):
            if progress:
                progress(f"touch-off {i + 1}/{len(locations)} at {loc} mm")
            presses.append(press(session, rig, indenter, nominal, loc, depths_mm, shear_mm=shear_mm,
                                 shear_direction_deg=direction, record_to=data_dir / f"rig-{stamp}-{i}.h5"))
        lift(session, nominal, indenter, _clearance_mm(rig))
        virtual = bool(session.virtual)
    finally:
        if own:
            session.close()
    if progress:
        progress("solving")
    registration = solve_registration(presses, rig, indenter, camera, source, gel=gel, virtual_rig=virtual)
    require_usable_fit(registration, data_dir)
    return registration


def require_usable_fit(registration: RigRegistration, data_dir: str | Path) -> None:
    """Raise CalibrationError (one line: the figures and what to do) when the registration's residuals
    pass a REFUSE threshold (:func:`~labrig.calibration.registration_file.assess_fit`)."""
    quality = registration.quality
    if quality.verdict == "refused":
        raise CalibrationError(
            f"{quality.message()}. Not written: check that intrinsics.toml and extrinsics.toml next to the rig file "
            f"were calibrated on this gel, and the touch-off recordings in {data_dir}; then rerun with more --points")


def measure_curves(
    rig: RigConfig,
    indenters: dict[str, Indenter],
    plan: dict[str, tuple[tuple[tuple[float, float], ...], tuple[float, ...]]] | None = None,
    *,
    seed: int = 0,
    indenters_path: Path | None = None,
    registration_path: str | Path | None = None,
    progress: Progress | None = None,
) -> list[ForceDepthCurve]:
    """Stepped normal indentations per indenter of ``plan`` (default :data:`DEFAULT_PLAN`; one rig
    session each; on hardware the operator mounts each indenter when asked), at the registered gel
    pose (or the nominal one), with :func:`~labrig.protocol.touchoff.press`'s default approach and steps."""
    plan = plan if plan is not None else DEFAULT_PLAN
    pose = gel_pose(rig, registration_path)
    curves = []
    for name, (locations, depths) in plan.items():
        if name not in indenters:
            raise CalibrationError(f"unknown indenter {name!r}; known: {', '.join(sorted(indenters))}")
        indenter = indenters[name]
        if progress:
            progress(f"{name}: opening the rig")
        with RigSession.for_rig(rig, indenter, seed=seed, indenters_path=indenters_path) as session:
            for loc in locations:
                if progress:
                    progress(f"{name}: pressing at {loc} mm")
                result = press(session, rig, indenter, pose, loc, depths)
                curves.append(ForceDepthCurve(name, result.depth_mm, result.force_n[:, 2], f"{name}@{loc[0]:g},{loc[1]:g}",
                                              (float(loc[0]), float(loc[1]))))
            lift(session, pose, indenter, _clearance_mm(rig))
    return curves


def _clearance_mm(rig: RigConfig) -> float:
    """The rig file's safe height above the gel for travel ([safety] clearance_mm)."""
    return float(safety_limits(rig).clearance_mm)
