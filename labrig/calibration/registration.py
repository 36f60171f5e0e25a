"""Rig registration: where the gel is for the CNC, and how the F/T sensor's axes sit in the gel frame.

The touch-offs that feed it move the rig (:func:`labrig.protocol.touchoff.press`,
run by :func:`labrig.protocol.calibration_runs.register_rig`): with the sphere,
at a few known locations, travel above the location (nominal gel pose, every
target checked like a probing run), tare, approach until the mean |Fz| of 16
F/T samples exceeds the contact force (the runner's detection), then press in
quasi-static steps (move, settle, average F/T samples) and record the camera's
events from the approach to the deepest step. Each gives a :class:`Press`.
:func:`solve_registration` does the rest:

1. **Surface** (:func:`depth_offsets`): the depth at which contact was detected
   (a few 0.1 mm: the detection force needs some depth) is fitted on the
   force-depth steps with the bonded-layer contact table
   (:mod:`labrig.calibration.gel`); the surface point under each press is the
   contact point raised by it.
2. **In-plane** (:func:`labrig.calibration.contact_location.locate_contact`):
   the contact's centre on the gel plane from the press's events.
3. **Transform**: machine surface points and gel contact points give the
   machine-from-gel pose (Kabsch: position, yaw, tilt; the surface height is the
   origin's z).
4. **F/T axes**: the normal force of each press (gel +z on the indenter) and
   the force change of a small shear in a known machine direction (the gel
   pushes back, opposite the shear) give the sensor's axes in the gel frame
   (Wahba/SVD); the nearest signed permutation is the axis map, the remainder a
   small rotation.

Output: :class:`~labrig.calibration.registration_file.RigRegistration`, written
to ``calibration/rig-registration.toml``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from labrig.cache import sha256_of
from labrig.calibration.contact_location import PixelMap, locate_contact
from labrig.calibration.fits import axis_map, fit_ft_axes, kabsch, reject_outliers
from labrig.calibration.gel import ForceDepthCurve, GelModel, gel_model, model_contact_table
from labrig.calibration.registration_file import PointResult, RigRegistration
from labrig.config import RigConfig
from labrig.errors import CalibrationError
from labrig.frames import matrix_to_rotvec
from labrig.indenters import Indenter
from labrig.physics.camera import CameraModel
from labrig.physics.mechanics import ContactTable
from labrig.recording import Recording

F64 = npt.NDArray[np.float64]

#: Fewest touch-offs a registration accepts (a plane and an in-plane rotation).
MIN_POINTS = 3
#: Steps up to this depth fit the depth at which contact was detected.
SURFACE_FIT_DEPTH_MM = 0.4
#: A shear's force change under this (N) gives no direction for the F/T axes.
MIN_SHEAR_FORCE_N = 0.05
#: A touch-off is dropped from the pose when its distance from the pose fitted to the others exceeds
#: this (mm) and OUTLIER_RATIO times the others' rms residual (a good touch-off is within ~0.02 mm).
OUTLIER_MIN_RESIDUAL_MM = 0.05
OUTLIER_RATIO = 5.0


@dataclass(frozen=True)
class Press:
    """One touch-off and quasi-static indentation (machine mm, tared F/T N in sensor axes).

    ``contact_tool_mm``: the tool position where contact was detected; ``down``: the unit pressing
    direction (machine); ``depth_mm`` and ``force_n``: per step, the depth below the contact and the
    mean force. ``shear_dir_machine``: the sheared tool position minus the contact point (machine mm),
    ``shear_force_n`` the force change it made.
    """

    indenter: str
    location_mm: tuple[float, float]
    contact_tool_mm: F64
    tool_offset_mm: F64
    down: F64
    depth_mm: F64
    force_n: F64
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
        if self.recording is None:
            raise CalibrationError("this press was not recorded: no events to locate the contact with")
        with Recording(self.recording) as rec:
            if rec.rows("events") == 0:
                raise CalibrationError(f"{self.recording}: no camera events; is the camera streaming and the LED on?")
            x = rec.column("events", "x").astype(np.float64)
            y = rec.column("events", "y").astype(np.float64)
            p = np.where(rec.column("events", "p") > 0, 1.0, -1.0)
        return x, y, p


def depth_offsets(presses: Sequence[Press], table: ContactTable, gel: GelModel,
                  max_depth_mm: float = SURFACE_FIT_DEPTH_MM) -> tuple[F64, float]:
    """Per press, the depth (mm) at which the approach detected contact, from its force-depth steps up to
    ``max_depth_mm``: the model ``s F_table(d + d0) (1 + b (d + d0) / h)`` of the gel touched (``table``
    built for ``gel``; b, h: ``gel``'s stiffening and thickness), one force scale s shared by the presses
    (same indenter), one offset d0 each (the curve's shape fixes the zero). Returns (offsets, rms residual N)."""
    data = []
    for p in presses:
        keep = p.depth_mm <= max_depth_mm + 1e-9
        if int(keep.sum()) < 3:
            raise CalibrationError(f"the touch-off at {p.location_mm} has {int(keep.sum())} steps up to "
                                   f"{max_depth_mm} mm; at least 3 are needed to find the surface")
        data.append((p.depth_mm[keep], p.force_n[keep, 2]))

    def model_n(delta: F64) -> F64:
        d = np.clip(delta, 0, None)
        return np.interp(d, table.depths_mm, table.normal_force_n) * (1.0 + gel.stiffening * d / gel.thickness_mm)

    def residuals(x: F64) -> F64:
        return np.concatenate([x[0] * model_n(d + d0) - f for (d, f), d0 in zip(data, x[1:], strict=True)])

    n = len(presses)
    result = least_squares(residuals, np.r_[1.0, [0.05] * n], bounds=(np.r_[1e-3, [-0.5] * n], np.r_[1e3, [1.0] * n]),
                           x_scale="jac")
    return result.x[1:].copy(), float(np.sqrt(np.mean(result.fun ** 2)))


def solve_registration(presses: Sequence[Press], rig: RigConfig, indenter: Indenter, camera: CameraModel,
                       camera_source: str = "", *, gel: GelModel | None = None, table: ContactTable | None = None,
                       virtual_rig: bool = True) -> RigRegistration:
    """Everything after the touch-offs: surface offsets, contact locations, the pose (touch-offs the
    others disagree with dropped, see :func:`~labrig.calibration.fits.reject_outliers`) and the F/T axes.
    ``gel``: the gel touched (default :func:`~labrig.calibration.gel.gel_model`: the gel calibration
    next to the rig file, else its ``[gel]``); ``table``: its contact table for ``indenter``."""
    if len(presses) < MIN_POINTS:
        raise CalibrationError(f"{len(presses)} touch-off(s); the registration needs at least {MIN_POINTS} "
                               "at locations not on one line (a plane and an in-plane rotation)")
    gel = gel if gel is not None else gel_model(rig)
    table = table if table is not None else model_contact_table(indenter, rig, gel)
    offsets, surface_rms = depth_offsets(presses, table, gel)
    pixels = PixelMap.build(rig, camera)
    contacts, surfaces = [], []
    for p, d0 in zip(presses, offsets, strict=True):
        x, y, pol = p.events()
        contacts.append(locate_contact(x, y, pol, pixels, table, float(p.depth_mm[-1] + d0), p.location_mm))
        surfaces.append(p.contact_tip_mm - d0 * p.down)
    gel_pts = np.array([[*c.xy_mm, 0.0] for c in contacts])
    machine_pts = np.array(surfaces)
    _require_spread(gel_pts)
    kept, dropped = reject_outliers(gel_pts, machine_pts, min_residual_mm=OUTLIER_MIN_RESIDUAL_MM, ratio=OUTLIER_RATIO,
                                    min_points=MIN_POINTS)
    _require_spread(gel_pts[kept])
    pose = kabsch(gel_pts[kept], machine_pts[kept])
    dropped_mm = {d.index: d.residual_mm for d in dropped}
    points = [PointResult(p.location_mm, c.xy_mm, m, float(d0), c.rms, residual_mm=pose.apply(g) - m,
                          recording=str(p.recording) if p.recording else "",
                          sha256=sha256_of(p.recording) if p.recording else "",
                          rejected=i in dropped_mm, rejected_residual_mm=dropped_mm.get(i, 0.0))
              for i, (p, d0, c, g, m) in enumerate(zip(presses, offsets, contacts, gel_pts, machine_pts, strict=True))]
    presses = [p for p, k in zip(presses, kept, strict=True) if k]
    # F/T axes: the normal force (gel +z on the indenter) and the shear force changes (against the shear).
    gel_dirs: list[F64] = []
    ft_dirs: list[F64] = []
    weights: list[float] = []
    for p in presses:
        fn = p.force_n[-1]
        gel_dirs.append(np.array([0.0, 0.0, 1.0]))
        ft_dirs.append(fn / np.linalg.norm(fn))
        weights.append(1.0)
        if p.shear_force_n is not None and p.shear_dir_machine is not None:
            shear_gel = pose.rotation.T @ p.shear_dir_machine
            shear_gel[2] = 0.0
            shear_gel /= np.linalg.norm(shear_gel)
            size = float(np.linalg.norm(p.shear_force_n))
            if size > MIN_SHEAR_FORCE_N:
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
                           str(rig.path), virtual_rig, surface_gel=gel)


def _require_spread(gel_points: F64) -> None:
    """Refuse touch-offs (nearly) on one line: they fix no in-plane rotation."""
    spread = np.linalg.svd(gel_points[:, :2] - gel_points[:, :2].mean(axis=0), compute_uv=False)
    if spread[-1] < 1.0:
        raise CalibrationError("the touch-off locations used are (nearly) on one line: spread them over the gel "
                               "(e.g. the four corners of a 14 x 12 mm rectangle)")
