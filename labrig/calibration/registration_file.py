"""The rig registration's file, ``rig-registration.toml``: the result, writing it, reading it back.

:class:`RigRegistration` is what :func:`labrig.calibration.registration.solve_registration`
finds; :meth:`RigRegistration.to_toml` writes it (keys in docs/calibration.md).
:func:`gel_pose` is the gel frame in machine coordinates every procedure moves
by: the registered pose when the file exists, else the nominal pose of
``rig.toml``.
"""

from __future__ import annotations

import datetime as _dt
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.calibration.files import save_text_atomic
from labrig.calibration.fits import yaw_tilt_of
from labrig.calibration.gel import GelModel
from labrig.config import RigConfig
from labrig.errors import CalibrationError
from labrig.frames import Pose, matrix_to_rotvec, rotvec_to_matrix, yaw_tilt_matrix
from labrig.physics.geometry import nominal_gel_in_machine

F64 = npt.NDArray[np.float64]

REGISTRATION_FILE = "rig-registration.toml"

#: The touch-offs' rms residual under the registered pose (mm) above which the registration warns
#: (a good one is a few um: the contact locator's and the surface fit's noise) ...
WARN_RESIDUAL_RMS_MM = 0.025
#: ... and above which it refuses (a camera calibration of another gel, a touch-off that slipped).
REFUSE_RESIDUAL_RMS_MM = 0.1
#: The worst kept touch-off's residual (mm) above which the registration warns, and refuses.
WARN_WORST_RESIDUAL_MM = 0.05
REFUSE_WORST_RESIDUAL_MM = 0.2


@dataclass(frozen=True)
class PointResult:
    """One touch-off in the registration: where it was aimed (gel mm, nominal frame), the contact found
    in the image (gel mm), the surface point under it (machine mm), the depth at which contact was
    detected (mm), the template's rms (events per pixel), the pose's residual there (machine mm) and
    the recording it came from with its SHA-256."""

    location_mm: tuple[float, float]
    contact_gel_mm: F64
    surface_machine_mm: F64
    depth_offset_mm: float
    template_rms: float
    residual_mm: F64 = field(default_factory=lambda: np.zeros(3))
    recording: str = ""
    sha256: str = ""
    #: Left out of the pose: the other touch-offs disagree with it (its distance from their pose, mm).
    rejected: bool = False
    rejected_residual_mm: float = 0.0


@dataclass(frozen=True)
class FitQuality:
    """How well the touch-offs kept agree with the registered pose (machine mm) and what follows:
    ``verdict`` "good", "poor" (warn) or "refused"; ``problems``: one line per threshold exceeded or
    touch-off dropped, with the figures."""

    residual_rms_mm: float
    worst_index: int
    worst_location_mm: tuple[float, float]
    worst_residual_mm: float
    yaw_deg: float
    points_used: int
    points_rejected: int
    verdict: str
    problems: tuple[str, ...]

    def message(self) -> str:
        """One line: the figures and the problems."""
        return (f"rig registration {self.verdict}: {self.residual_rms_mm * 1e3:.0f} um rms over {self.points_used} "
                f"touch-offs, worst {self.worst_residual_mm * 1e3:.0f} um at touch-off {self.worst_index} "
                f"{self.worst_location_mm} mm, yaw {self.yaw_deg:+.3f} deg; " + "; ".join(self.problems))


@dataclass(frozen=True)
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
    #: The gel the surface fit and the contact locator modelled (None: not recorded).
    surface_gel: GelModel | None = None
    date: str = field(default_factory=lambda: _dt.datetime.now().astimezone().isoformat(timespec="seconds"))

    @property
    def yaw_tilt_deg(self) -> tuple[float, tuple[float, float]]:
        return yaw_tilt_of(self.gel_in_machine.rotation)

    @property
    def kept_points(self) -> list[PointResult]:
        """The touch-offs the pose was fitted to."""
        return [p for p in self.points if not p.rejected]

    @property
    def residual_rms_mm(self) -> float:
        """The kept touch-offs' rms distance from the registered pose (mm)."""
        return float(np.sqrt(np.mean([np.sum(p.residual_mm ** 2) for p in self.kept_points])))

    @property
    def worst_point_index(self) -> int:
        """The index (into ``points``) of the kept touch-off farthest from the registered pose."""
        return max((i for i, p in enumerate(self.points) if not p.rejected),
                   key=lambda i: float(np.linalg.norm(self.points[i].residual_mm)))

    @property
    def quality(self) -> FitQuality:
        """The residual figures against the named thresholds (see :class:`FitQuality`)."""
        return assess_fit(self)

    def summary(self) -> dict[str, Any]:
        """The registration as JSON-ready values (units in the keys)."""
        yaw, tilt = self.yaw_tilt_deg
        quality = self.quality
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
            "residual_max_mm": round(quality.worst_residual_mm, 5),
            "worst_point": {"index": quality.worst_index, "location_mm": list(quality.worst_location_mm),
                            "residual_mm": round(quality.worst_residual_mm, 5)},
            "points_used": quality.points_used, "points_rejected": quality.points_rejected,
            "fit_quality": quality.verdict, "problems": list(quality.problems),
            "thresholds_mm": {"warn_residual_rms_mm": WARN_RESIDUAL_RMS_MM, "refuse_residual_rms_mm": REFUSE_RESIDUAL_RMS_MM,
                              "warn_worst_residual_mm": WARN_WORST_RESIDUAL_MM,
                              "refuse_worst_residual_mm": REFUSE_WORST_RESIDUAL_MM},
            "surface_fit_rms_n": round(self.surface_fit_rms_n, 5),
            "surface_gel": None if self.surface_gel is None else self.surface_gel.summary(),
            "camera": self.camera_source, "virtual_rig": self.virtual_rig, "indenter": self.indenter,
            "points": [{"location_mm": list(p.location_mm), "contact_gel_mm": [round(float(v), 4) for v in p.contact_gel_mm],
                        "surface_machine_mm": [round(float(v), 4) for v in p.surface_machine_mm],
                        "depth_offset_mm": round(p.depth_offset_mm, 4),
                        "residual_mm": [round(float(v), 5) for v in p.residual_mm],
                        "rejected": p.rejected, "rejected_residual_mm": round(p.rejected_residual_mm, 5),
                        "recording": p.recording}
                       for p in self.points],
        }

    def to_toml(self) -> str:
        yaw, tilt = self.yaw_tilt_deg
        quality = self.quality
        t = self.gel_in_machine.translation_mm
        rv = matrix_to_rotvec(self.gel_in_machine.rotation)
        ft_rv = matrix_to_rotvec(self.ft_axes_in_gel)

        def vec(v: npt.ArrayLike, fmt: str = ".6f") -> str:
            return "[" + ", ".join(format(float(x), fmt) for x in np.ravel(v)) + "]"

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
            "[residuals]                   # over the touch-offs kept (a dropped one: rejected = true in its points entry)",
            f"registration_rms_mm = {self.residual_rms_mm:.6f}",
            f"registration_max_mm = {quality.worst_residual_mm:.6f}",
            f"worst_point_index = {quality.worst_index}",
            f"worst_point_location_mm = {vec(quality.worst_location_mm, '.4f')}",
            f"points_used = {quality.points_used}",
            f"points_rejected = {quality.points_rejected}",
            f"fit_quality = {json.dumps(quality.verdict)}",
            f"problems = [{', '.join(json.dumps(s) for s in quality.problems)}]",
            f"ft_angle_rms_deg = {self.ft_angle_rms_deg:.5f}",
            f"surface_fit_rms_n = {self.surface_fit_rms_n:.6f}",
        ]
        if self.surface_gel is not None:
            g = self.surface_gel
            lines += ["", "[surface_gel]                 # the gel the surface fit and the contact locator modelled",
                      f"thickness_mm = {g.thickness_mm:.6g}", f"youngs_modulus_mpa = {g.youngs_modulus_mpa:.6g}",
                      f"poisson_ratio = {g.poisson_ratio:.6g}", f"stiffening = {g.stiffening:.6g}",
                      f"source = {json.dumps(g.source)}"]
        for p in self.points:
            lines += ["", "[[points]]", f"location_mm = {vec(p.location_mm, '.4f')}",
                      f"contact_gel_mm = {vec(p.contact_gel_mm, '.5f')}",
                      f"surface_machine_mm = {vec(p.surface_machine_mm, '.5f')}",
                      f"depth_offset_mm = {p.depth_offset_mm:.5f}", f"template_rms = {p.template_rms:.5f}",
                      f"residual_mm = {vec(p.residual_mm, '.5f')}", f"rejected = {str(p.rejected).lower()}",
                      f"rejected_residual_mm = {p.rejected_residual_mm:.5f}", f"recording = {json.dumps(p.recording)}",
                      f"sha256 = {json.dumps(p.sha256)}"]
        return "\n".join(lines) + "\n"

    def save(self, path: str | Path) -> Path:
        return save_text_atomic(path, self.to_toml())


def assess_fit(reg: RigRegistration) -> FitQuality:
    """The registration's residual figures against WARN_* and REFUSE_* (mm): "refused" past a REFUSE
    threshold, "poor" past a WARN threshold or with touch-offs dropped as outliers, else "good"."""
    worst = reg.worst_point_index
    worst_mm = float(np.linalg.norm(reg.points[worst].residual_mm))
    rms = reg.residual_rms_mm
    refuse, warn = [], []
    if rms > REFUSE_RESIDUAL_RMS_MM:
        refuse.append(f"rms above {REFUSE_RESIDUAL_RMS_MM * 1e3:.0f} um")
    elif rms > WARN_RESIDUAL_RMS_MM:
        warn.append(f"rms above {WARN_RESIDUAL_RMS_MM * 1e3:.0f} um")
    if worst_mm > REFUSE_WORST_RESIDUAL_MM:
        refuse.append(f"worst above {REFUSE_WORST_RESIDUAL_MM * 1e3:.0f} um")
    elif worst_mm > WARN_WORST_RESIDUAL_MM:
        warn.append(f"worst above {WARN_WORST_RESIDUAL_MM * 1e3:.0f} um")
    for i, p in enumerate(reg.points):
        if p.rejected:
            warn.append(f"touch-off {i} at {p.location_mm} mm dropped: {p.rejected_residual_mm * 1e3:.0f} um from "
                        "the others' pose")
    verdict = "refused" if refuse else "poor" if warn else "good"
    return FitQuality(rms, worst, reg.points[worst].location_mm, worst_mm, reg.yaw_tilt_deg[0], len(reg.kept_points),
                      len(reg.points) - len(reg.kept_points), verdict, tuple(refuse + warn))


def default_registration_path(rig: RigConfig) -> Path:
    """Where the rig's registration lives: next to its rig file."""
    return rig.path.parent / REGISTRATION_FILE


def load_registration(path: str | Path) -> dict[str, Any]:
    """The registration file's TOML tables as read (see docs/calibration.md for the keys)."""
    try:
        return tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CalibrationError(f"{path}: no rig registration; run `labrig calibrate rig`") from None
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(f"{path}: not valid TOML ({exc})") from None


def gel_pose(rig: RigConfig, registration_path: str | Path | None = None) -> Pose:
    """The gel frame in machine coordinates (mm): the registered pose when the registration file exists
    (``registration_path``, default ``rig-registration.toml`` next to the rig file), else the nominal one."""
    path = Path(registration_path) if registration_path is not None else default_registration_path(rig)
    if not path.exists():
        return nominal_gel_in_machine(rig)
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
