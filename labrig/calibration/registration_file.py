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
from labrig.config import RigConfig
from labrig.errors import CalibrationError
from labrig.frames import Pose, matrix_to_rotvec, rotvec_to_matrix, yaw_tilt_matrix
from labrig.physics.geometry import nominal_gel_in_machine

F64 = npt.NDArray[np.float64]

REGISTRATION_FILE = "rig-registration.toml"


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
    date: str = field(default_factory=lambda: _dt.datetime.now().astimezone().isoformat(timespec="seconds"))

    @property
    def yaw_tilt_deg(self) -> tuple[float, tuple[float, float]]:
        return yaw_tilt_of(self.gel_in_machine.rotation)

    @property
    def residual_rms_mm(self) -> float:
        return float(np.sqrt(np.mean([np.sum(p.residual_mm ** 2) for p in self.points])))

    def summary(self) -> dict[str, Any]:
        """The registration as JSON-ready values (units in the keys)."""
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
        return save_text_atomic(path, self.to_toml())


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
