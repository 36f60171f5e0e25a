"""Rig registration: where the gel is for the CNC, and how the F/T sensor's axes sit in the gel frame.

Procedure (:func:`register_rig`), with one indenter (the sphere) on an open
:class:`~labrig.protocol.session.RigSession`, at a few known locations:

1. **Touch off** (:func:`press`): travel above the location (nominal gel pose,
   every target checked like a probing run), tare, approach until the mean
   |Fz| of 16 F/T samples exceeds the contact force (the runner's detection),
   then press in quasi-static steps (move, settle, average F/T samples) and
   record the camera's events from the approach to the deepest step.
2. **Surface**: the depth at which contact was detected (a few 0.1 mm: the
   detection force needs some depth) is fitted on the force-depth steps with
   the bonded-layer contact table (:mod:`labrig.calibration.gel`); the surface
   point under each press is the contact point raised by it.
3. **In-plane** (:func:`locate_contact`): the press's events are accumulated per
   pixel, back-projected to the gel plane through the camera model, and fitted
   with a template centred on the contact: the membrane's brightness change
   under the LED ring follows the surface slope, which is axisymmetric about the
   contact, so the density of events (markers masked out) is
   ``a * log(1 + g * slope(|x - c|)) - b`` with the slope profile of the
   tabulated contact at the press depth and a, g, b, c fitted.
4. **Transform**: machine surface points and gel contact points give the
   machine-from-gel pose (Kabsch: position, yaw, tilt; the surface height is the
   origin's z).
5. **F/T axes**: the normal force of each press (gel +z on the indenter) and
   the force change of a small shear in a known machine direction (the gel
   pushes back, opposite the shear) give the sensor's axes in the gel frame
   (Wahba/SVD); the nearest signed permutation is the axis map, the remainder a
   small rotation.

Output: ``calibration/rig-registration.toml`` (:meth:`RigRegistration.to_toml`);
:func:`gel_pose` returns the registered pose when that file exists, else the
nominal pose of ``rig.toml``. The camera model comes from :func:`camera_model`:
the extrinsics calibration when it exists, else (virtual rig) the sim's true
camera.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.cache import sha256_of
from labrig.calibration.gel import CalibrationError, ForceDepthCurve, contact_table
from labrig.config import RigConfig
from labrig.frames import Pose, matrix_to_rotvec, rotvec_to_matrix, yaw_tilt_matrix
from labrig.indenters import Indenter

F64 = npt.NDArray[np.float64]

REGISTRATION_FILE = "rig-registration.toml"
#: Default touch-off locations (gel mm, nominal frame): the sphere's footprint inside the gel.
DEFAULT_LOCATIONS: tuple[tuple[float, float], ...] = ((-7.0, -6.0), (7.0, -6.0), (7.0, 6.0), (-7.0, 6.0))
#: Depths below the detected contact for the quasi-static steps, mm.
SPHERE_DEPTHS_MM: tuple[float, ...] = (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0)
#: Fewest touch-offs a registration accepts (a plane and an in-plane rotation).
MIN_POINTS = 3
#: Steps up to this depth fit the depth at which contact was detected.
SURFACE_FIT_DEPTH_MM = 0.4
#: Pixels whose gel point is this close to a marker's rest centre are left out of the slope template.
MARKER_MASK_MM = 0.6
#: The template is fitted over this radius around the contact, mm.
TEMPLATE_RADIUS_MM = 8.0
MOVE_MARGIN_S = 5.0


# ---------------------------------------------------------------------------------------------
# camera model switch


def camera_model(rig: RigConfig, extrinsics_path: str | Path | None = None,
                 intrinsics_path: str | Path | None = None) -> tuple[Any, str]:
    """(camera model, where it came from): the camera calibration (``intrinsics.toml`` and
    ``extrinsics.toml`` next to the rig file, or the paths given) when both exist, else the
    virtual rig's true camera (only meaningful on the virtual rig)."""
    from labrig.sim.camera import CameraModel

    extrinsics = Path(extrinsics_path) if extrinsics_path is not None else rig.path.parent / "extrinsics.toml"
    intrinsics = Path(intrinsics_path) if intrinsics_path is not None else rig.path.parent / "intrinsics.toml"
    if extrinsics.exists() and intrinsics.exists():
        from labrig.calibration.files import load_camera

        return load_camera(intrinsics, extrinsics), f"{intrinsics} + {extrinsics}"
    if extrinsics_path is not None or intrinsics_path is not None:
        raise CalibrationError(f"the camera calibration needs both {intrinsics} and {extrinsics}; "
                               "run `labrig calibrate intrinsics` and `labrig calibrate extrinsics`")
    return CameraModel.from_rig(rig), "sim truth (rig.toml [sim.camera]; no intrinsics/extrinsics calibration yet)"


# ---------------------------------------------------------------------------------------------
# touch-offs


@dataclass
class Press:
    """One touch-off and quasi-static indentation (machine mm, tared F/T N in sensor axes)."""

    indenter: str
    location_mm: tuple[float, float]
    contact_tool_mm: F64
    tool_offset_mm: F64
    down: F64
    depth_mm: F64
    force_n: F64
    #: The sheared tool position minus the contact point (machine mm) and the force change it made.
    shear_dir_machine: F64 | None = None
    shear_force_n: F64 | None = None
    recording: Path | None = None

    @property
    def contact_tip_mm(self) -> F64:
        return self.contact_tool_mm + self.tool_offset_mm

    def curve(self) -> ForceDepthCurve:
        return ForceDepthCurve(self.indenter, self.depth_mm, self.force_n[:, 2],
                               str(self.recording.name) if self.recording else "", self.location_mm)

    def events(self) -> tuple[F64, F64, F64]:
        """(x, y, polarity +-1) of every event recorded from the approach to the deepest step."""
        from labrig.recording import Recording

        if self.recording is None:
            raise CalibrationError("this press was not recorded: no events to locate the contact with")
        with Recording(self.recording) as rec:
            if rec.rows("events") == 0:
                raise CalibrationError(f"{self.recording}: no camera events; is the camera streaming and the LED on?")
            x = rec.column("events", "x").astype(np.float64)
            y = rec.column("events", "y").astype(np.float64)
            p = np.where(rec.column("events", "p") > 0, 1.0, -1.0)
        return x, y, p


def _wait(grbl: Any, session: Any, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    from labrig.devices.grbl import GrblTimeout

    while True:
        if session.monitor.trip is not None:
            raise CalibrationError(f"force limit during calibration: {session.monitor.trip.reason}")
        try:
            grbl.wait_idle(timeout_s=0.2)
            return
        except GrblTimeout:
            if time.monotonic() > deadline:
                raise CalibrationError(f"a move did not finish within {timeout_s:.1f} s (GRBL {grbl.state})") from None


def _move(session: Any, target: F64, speed_mm_s: float) -> None:
    grbl = session.grbl
    here = np.asarray(grbl.status().position_mm, dtype=np.float64)
    grbl.move_to(*np.asarray(target, dtype=np.float64).tolist(), feed_mm_min=speed_mm_s * 60, machine=True)
    _wait(grbl, session, 1.5 * float(np.linalg.norm(target - here)) / speed_mm_s + MOVE_MARGIN_S)


def _mean_force(session: Any, samples: int) -> F64:
    got = session.ft.wait_samples(samples)
    return np.mean([s.force_n for s in got], axis=0).astype(np.float64)


def press(
    session: Any,
    rig: RigConfig,
    indenter: Indenter,
    gel_pose: Pose,
    location_mm: tuple[float, float],
    depths_mm: Sequence[float],
    *,
    shear_mm: float = 0.0,
    shear_direction_deg: float = 0.0,
    record_to: str | Path | None = None,
    approach_start_mm: float = 0.8,
    approach_speed_mm_s: float = 0.5,
    contact_force_n: float = 0.1,
    max_travel_mm: float = 2.0,
    speed_mm_s: float = 1.0,
    settle_s: float = 0.05,
    samples: int = 40,
) -> Press:
    """Touch off at ``location_mm`` (gel frame of ``gel_pose``), press in steps to each depth below the
    detected contact, optionally shear, and go back up. Events are recorded to ``record_to`` from the
    approach to the deepest step. Raises CalibrationError when no contact is found."""
    from labrig.protocol.runner import DETECT_SAMPLES, ProbeRunner
    from labrig.protocol.spec import ApproachSpec, ProbeSpec
    from labrig.recording import RecordingMetadata, RecordingWriter

    if not depths_mm:
        raise CalibrationError("no indentation depths given")
    spec = ProbeSpec(indenter.name, location_mm=(float(location_mm[0]), float(location_mm[1])),
                     depth_mm=float(max(depths_mm)), normal_speed_mm_s=speed_mm_s, shear_mm=shear_mm,
                     shear_direction_deg=shear_direction_deg, shear_speed_mm_s=speed_mm_s,
                     approach=ApproachSpec(start_height_mm=approach_start_mm, speed_mm_s=approach_speed_mm_s,
                                           contact_force_n=contact_force_n, max_travel_mm=max_travel_mm),
                     retract_height_mm=1.0)
    plan = ProbeRunner(session, rig, indenter, gel_in_machine=gel_pose).check(spec)  # refuses unsafe targets
    grbl = session.grbl
    if grbl.status().state.startswith("Alarm"):
        raise CalibrationError("GRBL is in Alarm: home it (labrig cnc home) first")
    session.monitor.trip = None
    fast = 5.0
    here = np.asarray(grbl.status().position_mm, dtype=np.float64)
    up = here.copy()
    up[2] = max(here[2], plan.clearance_mm[2])
    for target in (up, plan.clearance_mm, plan.approach_start_mm):
        _move(session, target, fast)
    session.tare()
    writer = None
    if record_to is not None:
        record_to = Path(record_to)
        record_to.parent.mkdir(parents=True, exist_ok=True)
        if record_to.exists():
            record_to.unlink()
        meta = RecordingMetadata(indenter=indenter.name, rig_toml=rig.text, extra={
            "purpose": "calibration touch-off", "virtual_rig": bool(session.virtual), "seed": int(session.seed),
            "location_mm": json.dumps(list(spec.location_mm)), "depths_mm": json.dumps([float(d) for d in depths_mm])})
        writer = RecordingWriter(record_to, meta, clock=session.clock).open()
        session.begin(writer)
        writer.phase_begin("approach")
    contact: F64 | None = None
    depth_rows: list[float] = []
    forces: list[F64] = []
    shear_force = None
    shear_dir = None
    status = "complete"
    reason = ""
    try:
        reached = session.monitor.arm("contact", contact_force_n, grbl.jog_cancel, average_samples=DETECT_SAMPLES)
        grbl.jog(*plan.approach_limit_mm.tolist(), feed_mm_min=approach_speed_mm_s * 60, relative=False, machine=True)
        _wait(grbl, session, max_travel_mm / approach_speed_mm_s * 1.5 + MOVE_MARGIN_S)
        session.monitor.disarm()
        if not reached.is_set():
            raise CalibrationError(
                f"no contact found at {spec.location_mm} mm within {max_travel_mm} mm of the approach start "
                f"({approach_start_mm} mm above the gel surface of the pose used): |Fz| stayed under "
                f"{contact_force_n} N. Check the gel height (rig.toml [rig] gel_origin_machine_mm) or raise max_travel_mm")
        contact = np.asarray(grbl.status().position_mm, dtype=np.float64)
        if writer is not None:
            writer.phase_begin("normal_down")
        for depth in sorted(float(d) for d in depths_mm):
            _move(session, contact + depth * plan.down, speed_mm_s)
            time.sleep(settle_s)
            forces.append(_mean_force(session, samples))
            position = np.asarray(grbl.status().position_mm, dtype=np.float64)
            depth_rows.append(float((position - contact) @ plan.down))
        if writer is not None:
            end_ns = session.clock.now_ns()
            writer.phase_end((end_ns - writer.t0_host_ns) // 1000)
            session.end(end_ns)
        bottom = contact + depth_rows[-1] * plan.down
        if shear_mm > 0:
            # The tip's whole in-plane motion since contact is the shear (pressing along the nominal
            # normal drifts it a little across a tilted gel): keep it from the contact point.
            shear_dir = bottom + shear_mm * plan.shear_dir - contact
            _move(session, bottom + shear_mm * plan.shear_dir, speed_mm_s)
            time.sleep(settle_s)
            shear_force = _mean_force(session, samples) - forces[-1]
            _move(session, bottom, speed_mm_s)
    except BaseException as exc:
        status, reason = "aborted", str(exc) or type(exc).__name__
        raise
    finally:
        session.monitor.disarm()
        if writer is not None:
            with contextlib.suppress(Exception):
                session.end(session.clock.now_ns(), timeout_s=1.0)
            writer.close(status, reason, raise_on_fault=False)
        with contextlib.suppress(Exception):
            if session.monitor.trip is not None or grbl.status().state.startswith(("Hold", "Alarm")):
                grbl.soft_reset()
                if grbl.status().state.startswith("Alarm"):
                    grbl.unlock()
            here = np.asarray(grbl.status().position_mm, dtype=np.float64)
            anchor = contact if contact is not None else here
            above = anchor - 1.0 * plan.down
            rise = float((here - above) @ plan.down)
            if rise > 0:
                _move(session, here - rise * plan.down, speed_mm_s)
    return Press(indenter.name, spec.location_mm, contact, np.asarray(indenter.tool_offset_mm, dtype=np.float64),
                 plan.down.copy(), np.asarray(depth_rows), np.asarray(forces), shear_dir, shear_force,
                 Path(record_to) if record_to is not None else None)


def lift(session: Any, gel_pose: Pose, indenter: Indenter, height_mm: float, speed_mm_s: float = 5.0) -> None:
    """The indenter tip up to ``height_mm`` above the gel origin (machine z), e.g. after the last press."""
    grbl = session.grbl
    here = np.asarray(grbl.status().position_mm, dtype=np.float64)
    target = here.copy()
    target[2] = max(here[2], float(gel_pose.translation_mm[2]) + height_mm - float(indenter.tool_offset_mm[2]))
    _move(session, target, speed_mm_s)


# ---------------------------------------------------------------------------------------------
# contact depth offsets


def depth_offsets(presses: Sequence[Press], rig: RigConfig, indenter: Indenter, table: Any | None = None,
                  max_depth_mm: float = SURFACE_FIT_DEPTH_MM) -> tuple[F64, float]:
    """Per press, the depth (mm) at which the approach detected contact, from its force-depth steps up to
    ``max_depth_mm``: one force scale shared by the presses (same indenter), one offset each (the
    table's curve shape fixes the zero). Returns (offsets, rms residual N)."""
    from scipy.optimize import least_squares

    table = table if table is not None else contact_table(indenter, rig)
    data = []
    for p in presses:
        keep = p.depth_mm <= max_depth_mm + 1e-9
        if int(keep.sum()) < 3:
            raise CalibrationError(f"the touch-off at {p.location_mm} has {int(keep.sum())} steps up to "
                                   f"{max_depth_mm} mm; at least 3 are needed to find the surface")
        data.append((p.depth_mm[keep], p.force_n[keep, 2]))

    def residuals(x: F64) -> F64:
        return np.concatenate([x[0] * np.interp(np.clip(d + d0, 0, None), table.depths_mm, table.normal_force_n) - f
                               for (d, f), d0 in zip(data, x[1:], strict=True)])

    n = len(presses)
    result = least_squares(residuals, np.r_[1.0, [0.05] * n], bounds=(np.r_[1e-3, [-0.5] * n], np.r_[1e3, [1.0] * n]),
                           x_scale="jac")
    return result.x[1:].copy(), float(np.sqrt(np.mean(result.fun ** 2)))


# ---------------------------------------------------------------------------------------------
# locating a contact in the image


@dataclass
class PixelMap:
    """ROI pixels, their rest points on the gel plane and whether they are clear of the markers."""

    index_of: Callable[[F64, F64], npt.NDArray[np.int64]]
    gel_xy: F64
    clear: npt.NDArray[np.bool_]

    @classmethod
    def build(cls, rig: RigConfig, camera: Any, step: int = 1) -> PixelMap:
        roi = rig.roi
        ys, xs = np.mgrid[roi.y0_px:roi.y1_px:step, roi.x0_px:roi.x1_px:step]
        gel = camera.backproject_to_plane(np.c_[xs.ravel(), ys.ravel()].astype(np.float64))[:, :2]
        m = rig.markers
        fc = gel[:, 0] / m.pitch_mm + (m.cols - 1) / 2
        fr = gel[:, 1] / m.pitch_mm + (m.rows - 1) / 2
        near = np.hypot((fc - np.clip(np.rint(fc), 0, m.cols - 1)) * m.pitch_mm,
                        (fr - np.clip(np.rint(fr), 0, m.rows - 1)) * m.pitch_mm)
        width = xs.shape[1]

        def index_of(x: F64, y: F64) -> npt.NDArray[np.int64]:
            xi, yi = x.astype(np.int64), y.astype(np.int64)
            inside = (xi >= roi.x0_px) & (xi < roi.x1_px) & (yi >= roi.y0_px) & (yi < roi.y1_px)
            inside &= ((xi - roi.x0_px) % step == 0) & ((yi - roi.y0_px) % step == 0)
            out = ((yi - roi.y0_px) // step) * width + (xi - roi.x0_px) // step
            return np.where(inside, out, -1)

        return cls(index_of, gel, near > MARKER_MASK_MM)


@dataclass(frozen=True)
class Located:
    """A contact located in the image: gel-plane centre (mm), template residual (events per pixel), pixels used."""

    xy_mm: F64
    rms: float
    pixels: int
    params: F64


def locate_contact(x: F64, y: F64, polarity: F64, pixels: PixelMap, table: Any, depth_mm: float,
                   guess_mm: npt.ArrayLike) -> Located:
    """The contact centre on the gel plane from the signed event counts of one press (see the module doc)."""
    from scipy.interpolate import RegularGridInterpolator
    from scipy.optimize import least_squares

    index = pixels.index_of(x, y)
    ok = index >= 0
    counts = np.bincount(index[ok], polarity[ok], minlength=len(pixels.gel_xy))
    if float(np.abs(counts).sum()) < 1000:
        raise CalibrationError(f"only {int(np.abs(counts).sum())} events in the gel region during the press; "
                               "at least 1000 are needed to locate the contact: press deeper or check the camera")
    fields = table.fields(min(max(depth_mm, float(table.depths_mm[1])), float(table.depths_mm[-1])))
    depth = np.asarray(fields.depth_mm, dtype=np.float64)
    gy, gx = np.gradient(depth, fields.y_mm, fields.x_mm)
    slope = RegularGridInterpolator((fields.y_mm, fields.x_mm), np.hypot(gx, gy), bounds_error=False, fill_value=0.0)
    centre = np.asarray(guess_mm, dtype=np.float64).copy()
    # Mean shift on the positive counts first: robust to a guess a few mm off.
    pos = np.clip(counts, 0, None) * pixels.clear
    for _ in range(10):
        near = np.hypot(*(pixels.gel_xy - centre).T) < TEMPLATE_RADIUS_MM * 0.75
        weight = pos[near]
        if weight.sum() <= 0:
            break
        step = (pixels.gel_xy[near] * weight[:, None]).sum(axis=0) / weight.sum() - centre
        centre += step
        if float(np.hypot(*step)) < 0.05:
            break
    use = pixels.clear & (np.hypot(*(pixels.gel_xy - centre).T) < TEMPLATE_RADIUS_MM)
    gel, obs = pixels.gel_xy[use], counts[use]

    def residuals(p: F64) -> F64:
        s = slope((gel[:, 1] - p[1], gel[:, 0] - p[0]))
        return p[2] * np.log1p(p[3] * s) - p[4] - obs

    start = np.r_[centre, max(float(obs.max()), 1.0), 2.0, 0.0]
    result = least_squares(residuals, start, x_scale=np.r_[0.1, 0.1, 1.0, 1.0, 0.1],
                           bounds=(np.r_[-np.inf, -np.inf, 0.0, 0.01, -np.inf], np.r_[np.inf, np.inf, np.inf, 100, np.inf]))
    return Located(result.x[:2].copy(), float(np.sqrt(np.mean(result.fun ** 2))), int(use.sum()), result.x.copy())


# ---------------------------------------------------------------------------------------------
# fits


def kabsch(gel_points: F64, machine_points: F64) -> Pose:
    """The rigid pose with ``machine ~= R @ gel + t`` (least squares, proper rotation)."""
    a, b = np.asarray(gel_points, float), np.asarray(machine_points, float)
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return Pose(r, cb - r @ ca)


def yaw_tilt_of(rotation: F64) -> tuple[float, tuple[float, float]]:
    """(yaw, (tilt about x, tilt about y)) in degrees with ``yaw_tilt_matrix(yaw, tilt) == rotation``."""
    r = np.asarray(rotation, float)
    tx = np.arctan2(r[2, 1], np.hypot(r[2, 0], r[2, 2]))
    ty = np.arctan2(-r[2, 0], r[2, 2])
    rz = r @ (rotvec_to_matrix([tx, 0, 0]) @ rotvec_to_matrix([0, ty, 0])).T
    yaw = np.arctan2(rz[1, 0], rz[0, 0])
    return float(np.degrees(yaw)), (float(np.degrees(tx)), float(np.degrees(ty)))


def fit_ft_axes(gel_dirs: F64, ft_dirs: F64, weights: F64 | None = None) -> F64:
    """The F/T sensor's axes in the gel frame (columns: sensor x, y, z in gel axes) from unit directions
    known in the gel frame and measured in sensor axes: ``ft = A.T @ gel`` (Wahba, SVD)."""
    g, f = np.asarray(gel_dirs, float), np.asarray(ft_dirs, float)
    w = np.ones(len(g)) if weights is None else np.asarray(weights, float)
    u, _, vt = np.linalg.svd((f * w[:, None]).T @ g)
    d = np.sign(np.linalg.det(u @ vt))
    at = u @ np.diag([1.0, 1.0, d]) @ vt  # maps gel -> sensor
    return at.T


def axis_map(axes_in_gel: F64) -> tuple[F64, list[str]]:
    """The signed permutation nearest to the sensor axes (e.g. ["+x", "-y", "-z"]: sensor x along gel +x ...)."""
    a = np.asarray(axes_in_gel, float)
    perm = np.zeros((3, 3))
    names = []
    for col in range(3):
        row = int(np.argmax(np.abs(a[:, col])))
        sign = 1.0 if a[row, col] > 0 else -1.0
        perm[row, col] = sign
        names.append(("+" if sign > 0 else "-") + "xyz"[row])
    if sorted(n[1] for n in names) != ["x", "y", "z"]:
        raise CalibrationError(f"the F/T axes do not map onto the gel axes one to one ({names}): "
                               "check the sensor's mounting and the shear data")
    return perm, names


# ---------------------------------------------------------------------------------------------
# the registration


@dataclass
class PointResult:
    location_mm: tuple[float, float]
    contact_gel_mm: F64
    surface_machine_mm: F64
    depth_offset_mm: float
    template_rms: float
    residual_mm: F64 = field(default_factory=lambda: np.zeros(3))
    recording: str = ""
    sha256: str = ""


@dataclass
class RigRegistration:
    """The registered machine-from-gel pose, the F/T axes in the gel frame, residuals and provenance."""

    gel_in_machine: Pose
    ft_axes_in_gel: F64
    ft_axis_map: list[str]
    ft_residual_rotvec_rad: F64
    points: list[PointResult]
    ft_angle_rms_deg: float
    surface_fit_rms_n: float
    indenter: str
    camera_source: str
    rig_path: str
    virtual_rig: bool
    date: str = field(default_factory=lambda: _dt.datetime.now().astimezone().isoformat(timespec="seconds"))

    @property
    def yaw_tilt_deg(self) -> tuple[float, tuple[float, float]]:
        return yaw_tilt_of(self.gel_in_machine.rotation)

    @property
    def residual_rms_mm(self) -> float:
        return float(np.sqrt(np.mean([np.sum(p.residual_mm ** 2) for p in self.points])))

    def summary(self) -> dict[str, Any]:
        yaw, tilt = self.yaw_tilt_deg
        return {
            "gel_origin_machine_mm": [round(float(v), 4) for v in self.gel_in_machine.translation_mm],
            "surface_height_mm": round(float(self.gel_in_machine.translation_mm[2]), 4),
            "gel_yaw_deg": round(yaw, 4), "gel_tilt_deg": [round(tilt[0], 4), round(tilt[1], 4)],
            "gel_rotvec_rad": [round(float(v), 6) for v in matrix_to_rotvec(self.gel_in_machine.rotation)],
            "ft_axis_map": self.ft_axis_map,
            "ft_axes_in_gel_rotvec_rad": [round(float(v), 6) for v in matrix_to_rotvec(self.ft_axes_in_gel)],
            "ft_residual_rotvec_rad": [round(float(v), 6) for v in self.ft_residual_rotvec_rad],
            "ft_angle_rms_deg": round(self.ft_angle_rms_deg, 4),
            "residual_rms_mm": round(self.residual_rms_mm, 5),
            "surface_fit_rms_n": round(self.surface_fit_rms_n, 5),
            "camera": self.camera_source, "virtual_rig": self.virtual_rig, "indenter": self.indenter,
            "points": [{"location_mm": list(p.location_mm), "contact_gel_mm": [round(float(v), 4) for v in p.contact_gel_mm],
                        "surface_machine_mm": [round(float(v), 4) for v in p.surface_machine_mm],
                        "depth_offset_mm": round(p.depth_offset_mm, 4),
                        "residual_mm": [round(float(v), 5) for v in p.residual_mm], "recording": p.recording}
                       for p in self.points],
        }

    def to_toml(self) -> str:
        yaw, tilt = self.yaw_tilt_deg
        t = self.gel_in_machine.translation_mm
        rv = matrix_to_rotvec(self.gel_in_machine.rotation)
        ft_rv = matrix_to_rotvec(self.ft_axes_in_gel)

        def vec(v: Any, fmt: str = ".6f") -> str:
            return "[" + ", ".join(format(float(x), fmt) for x in v) + "]"

        lines = [
            "# Rig registration by `labrig calibrate rig` (labrig.calibration.registration).",
            "# p_machine = R p_gel + origin (tool tip, machine mm); gel frame: origin at the surface centre,",
            "# x along the marker columns, z out of the gel. R = yaw about machine z, then tilt about gel x, then y.",
            f"date = {json.dumps(self.date)}",
            f"rig = {json.dumps(self.rig_path)}",
            f"indenter = {json.dumps(self.indenter)}",
            f"virtual_rig = {str(self.virtual_rig).lower()}",
            f"camera = {json.dumps(self.camera_source)}",
            "",
            "[gel_in_machine]",
            f"origin_mm = {vec(t, '.5f')}",
            f"surface_height_mm = {float(t[2]):.5f}",
            f"yaw_deg = {yaw:.5f}",
            f"tilt_deg = {vec(tilt, '.5f')}",
            f"rotvec_rad = {vec(rv, '.8f')}",
            "",
            "[ft_axes]                     # the F/T sensor's axes in the gel frame (it reads the force on the indenter)",
            f"axis_map = [{', '.join(json.dumps(n) for n in self.ft_axis_map)}]   # sensor x, y, z along these gel axes",
            f"rotvec_rad = {vec(ft_rv, '.8f')}          # full rotation (axis map and the small rotation)",
            f"residual_rotvec_rad = {vec(self.ft_residual_rotvec_rad, '.8f')}  # after the axis map",
            "",
            "[residuals]",
            f"registration_rms_mm = {self.residual_rms_mm:.6f}",
            f"registration_max_mm = {max(float(np.linalg.norm(p.residual_mm)) for p in self.points):.6f}",
            f"ft_angle_rms_deg = {self.ft_angle_rms_deg:.5f}",
            f"surface_fit_rms_n = {self.surface_fit_rms_n:.6f}",
        ]
        for p in self.points:
            lines += ["", "[[points]]", f"location_mm = {vec(p.location_mm, '.4f')}",
                      f"contact_gel_mm = {vec(p.contact_gel_mm, '.5f')}",
                      f"surface_machine_mm = {vec(p.surface_machine_mm, '.5f')}",
                      f"depth_offset_mm = {p.depth_offset_mm:.5f}", f"template_rms = {p.template_rms:.5f}",
                      f"residual_mm = {vec(p.residual_mm, '.5f')}", f"recording = {json.dumps(p.recording)}",
                      f"sha256 = {json.dumps(p.sha256)}"]
        return "\n".join(lines) + "\n"

    def save(self, path: str | Path) -> Path:
        from labrig.calibration.files import save_text_atomic

        return save_text_atomic(path, self.to_toml())


def solve_registration(presses: Sequence[Press], rig: RigConfig, indenter: Indenter, camera: Any,
                       camera_source: str = "", *, table: Any | None = None, virtual_rig: bool = True) -> RigRegistration:
    """Everything after the touch-offs: surface offsets, contact locations, the pose and the F/T axes."""
    if len(presses) < MIN_POINTS:
        raise CalibrationError(f"{len(presses)} touch-off(s); the registration needs at least {MIN_POINTS} "
                               "at locations not on one line (a plane and an in-plane rotation)")
    table = table if table is not None else contact_table(indenter, rig)
    offsets, surface_rms = depth_offsets(presses, rig, indenter, table)
    pixels = PixelMap.build(rig, camera)
    points = []
    for p, d0 in zip(presses, offsets, strict=True):
        x, y, pol = p.events()
        located = locate_contact(x, y, pol, pixels, table, float(p.depth_mm[-1] + d0), p.location_mm)
        surface = p.contact_tip_mm - d0 * p.down
        rec = p.recording
        points.append(PointResult(p.location_mm, located.xy_mm, surface, float(d0), located.rms,
                                  recording=str(rec) if rec else "", sha256=sha256_of(rec) if rec else ""))
    gel_pts = np.array([[*q.contact_gel_mm, 0.0] for q in points])
    machine_pts = np.array([q.surface_machine_mm for q in points])
    spread = np.linalg.svd(gel_pts[:, :2] - gel_pts[:, :2].mean(axis=0), compute_uv=False)
    if spread[-1] < 1.0:
        raise CalibrationError("the touch-off locations are (nearly) on one line: spread them over the gel "
                               "(e.g. the four corners of a 14 x 12 mm rectangle)")
    pose = kabsch(gel_pts, machine_pts)
    for q, g, m in zip(points, gel_pts, machine_pts, strict=True):
        q.residual_mm = pose.apply(g) - m
    # F/T axes: the normal force (gel +z on the indenter) and the shear force changes (against the shear).
    gel_dirs, ft_dirs, weights = [], [], []
    for p in presses:
        fn = p.force_n[-1]
        gel_dirs.append([0.0, 0.0, 1.0])
        ft_dirs.append(fn / np.linalg.norm(fn))
        weights.append(1.0)
        if p.shear_force_n is not None and p.shear_dir_machine is not None:
            shear_gel = pose.rotation.T @ p.shear_dir_machine
            shear_gel[2] = 0.0
            shear_gel /= np.linalg.norm(shear_gel)
            size = float(np.linalg.norm(p.shear_force_n))
            if size > 0.05:
                gel_dirs.append(-shear_gel)
                ft_dirs.append(p.shear_force_n / size)
                weights.append(1.0)
    gel_dirs_a, ft_dirs_a = np.array(gel_dirs), np.array(ft_dirs)
    if np.linalg.matrix_rank(gel_dirs_a, tol=0.1) < 2:
        raise CalibrationError("the F/T axes need the normal force and at least one shear in a known direction: "
                               "give shear_mm > 0")
    axes = fit_ft_axes(gel_dirs_a, ft_dirs_a, np.array(weights))
    perm, names = axis_map(axes)
    residual = matrix_to_rotvec(perm.T @ axes)
    predicted = gel_dirs_a @ axes  # rows: each direction in sensor axes
    cos = np.clip(np.sum(predicted * ft_dirs_a, axis=1), -1, 1)
    angle_rms = float(np.degrees(np.sqrt(np.mean(np.arccos(cos) ** 2))))
    return RigRegistration(pose, axes, names, residual, points, angle_rms, surface_rms, indenter.name, camera_source,
                           str(rig.path), virtual_rig)


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
    session: Any = None,
    seed: int = 0,
    indenters_path: Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> RigRegistration:
    """Touch off at ``locations`` (nominal gel frame) and solve the registration. Opens a
    :class:`RigSession` from the rig file's devices (the virtual rig when none) unless ``session`` is given."""
    from labrig.protocol.rigfile import device_config, safety_limits
    from labrig.protocol.session import RigSession
    from labrig.sim.motion import gel_in_machine

    if len(locations) < MIN_POINTS:
        raise CalibrationError(f"{len(locations)} touch-off location(s) given; the registration needs at least {MIN_POINTS}")
    indenter = indenters[indenter_name]
    camera, source = camera_model(rig, extrinsics_path)
    nominal = gel_in_machine(rig, truth=False)
    data_dir = Path(data_dir)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    presses = []
    own = session is None
    if own:
        session = RigSession(rig, device_config(rig), safety_limits(rig), seed=seed, indenter=indenter,
                             indenters_path=indenters_path).open()
    try:
        for i, loc in enumerate(locations):
            if progress:
                progress(f"touch-off {i + 1}/{len(locations)} at {loc} mm")
            presses.append(press(session, rig, indenter, nominal, loc, depths_mm, shear_mm=shear_mm,
                                 shear_direction_deg=90.0 * i, record_to=data_dir / f"rig-{stamp}-{i}.h5"))
        lift(session, nominal, indenter, rig_clearance(rig))
        virtual = bool(session.virtual)
    finally:
        if own:
            session.close()
    if progress:
        progress("solving")
    return solve_registration(presses, rig, indenter, camera, source, virtual_rig=virtual)


def rig_clearance(rig: RigConfig) -> float:
    from labrig.protocol.rigfile import safety_limits

    return float(safety_limits(rig).clearance_mm)


# ---------------------------------------------------------------------------------------------
# reading it back


def default_registration_path(rig: RigConfig) -> Path:
    """Where the rig's registration lives: next to its rig file."""
    return rig.path.parent / REGISTRATION_FILE


def load_registration(path: str | Path) -> dict[str, Any]:
    import tomllib

    try:
        return tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CalibrationError(f"{path}: no rig registration; run `labrig calibrate rig`") from None
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(f"{path}: not valid TOML ({exc})") from None


def gel_pose(rig: RigConfig, registration_path: str | Path | None = None) -> Pose:
    """The gel frame in machine coordinates: the registered pose when the registration file exists
    (``registration_path``, default ``rig-registration.toml`` next to the rig file), else the nominal one."""
    from labrig.sim.motion import gel_in_machine

    path = Path(registration_path) if registration_path is not None else default_registration_path(rig)
    if not path.exists():
        return gel_in_machine(rig, truth=False)
    data = load_registration(path)
    try:
        section = data["gel_in_machine"]
        origin = np.asarray(section["origin_mm"], dtype=np.float64).reshape(3)
        if "rotvec_rad" in section:
            rotation = rotvec_to_matrix(np.asarray(section["rotvec_rad"], dtype=np.float64).reshape(3))
        else:
            rotation = yaw_tilt_matrix(float(section["yaw_deg"]), tuple(section.get("tilt_deg", (0.0, 0.0))))
    except (KeyError, ValueError, TypeError) as exc:
        raise CalibrationError(f"{path}: [gel_in_machine] needs origin_mm and rotvec_rad (or yaw_deg): {exc}") from None
    return Pose(rotation, origin)


def plot_registration(reg: RigRegistration, path: str | Path) -> Path:
    """Touch-off points on the gel and their residual arrows (in-plane, and height)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4.5))
    gel = np.array([p.contact_gel_mm for p in reg.points])
    res = np.array([reg.gel_in_machine.inverse().rotate(p.residual_mm) for p in reg.points]) * 1e3
    left.plot(gel[:, 0], gel[:, 1], "o")
    left.quiver(gel[:, 0], gel[:, 1], res[:, 0], res[:, 1], angles="xy", scale_units="xy", scale=1 / 0.2, color="r")
    for p, g in zip(reg.points, gel, strict=True):
        left.annotate(f"{p.location_mm}", g, fontsize=7, xytext=(4, 4), textcoords="offset points")
    left.set_aspect("equal")
    left.set_xlabel("gel x (mm)")
    left.set_ylabel("gel y (mm)")
    left.set_title("contacts; residual arrows: 1 um = 0.2 mm")
    right.bar(range(len(res)), res[:, 2])
    right.set_xlabel("touch-off")
    right.set_ylabel("height residual (um)")
    yaw, tilt = reg.yaw_tilt_deg
    right.set_title(f"yaw {yaw:.3f} deg, tilt {tilt[0]:.3f}/{tilt[1]:.3f} deg, rms {reg.residual_rms_mm * 1e3:.1f} um")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
