"""What a real lab knows, each behind one switchable function: rig, gel, camera, gel pose.

Nothing here reads a recording's ``/truth`` streams or the rig file's ``sim.*``
sections. Without camera calibration files (``intrinsics.toml`` and
``extrinsics.toml`` in the calibration folder) :func:`lab_camera` uses the rig
file's nominal camera, warns once and says so in its source string (and the
sidecar records it). Every function returns (value, source).
"""

from __future__ import annotations

import json
import tempfile
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from labrig.calibration.files import load_camera, uncalibrated_camera
from labrig.calibration.gel import load_gel
from labrig.calibration.registration_file import REGISTRATION_FILE, gel_pose
from labrig.config import DEFAULT_CALIBRATION_DIR as _DEFAULT_CALIBRATION_DIR
from labrig.config import DEFAULT_RIG, ConfigError, GelConfig, RigConfig, load_rig
from labrig.errors import LabrigError
from labrig.frames import Pose
from labrig.physics.camera import CameraModel

#: Where calibration files are looked for by default (the default rig's folder, labrig.config's).
DEFAULT_CALIBRATION_DIR = Path(_DEFAULT_CALIBRATION_DIR)


class GroundTruthError(LabrigError):
    """Ground truth cannot be made for a recording (a clear, one-line reason)."""


def rig_from_text(text: str, where: str = "recording") -> RigConfig:
    """A rig configuration from the TOML text a recording stores (its ``rig`` attribute)."""
    if not text.strip():
        raise GroundTruthError(f"{where} stores no rig configuration (empty 'rig' attribute); pass --rig")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "rig.toml"
        path.write_text(text)
        return load_rig(path)


def recording_rig(text: str, rig_path: str | Path | None = None, where: str = "recording") -> tuple[RigConfig, str]:
    """(rig, source): ``rig_path`` when given, else the recording's own rig text.

    A rig text written by an older labrig may lack keys added since; those are
    filled in from the default rig file (every value the recording has wins).
    """
    if rig_path is not None:
        return load_rig(rig_path), str(rig_path)
    try:
        return rig_from_text(text, where), "recording"
    except ConfigError as first:
        try:
            merged = _merge(tomllib.loads(DEFAULT_RIG.read_text()), tomllib.loads(text))
            return rig_from_text(_dump(merged), where), f"recording, missing keys from {DEFAULT_RIG}"
        except (ConfigError, tomllib.TOMLDecodeError, OSError, TypeError):
            raise GroundTruthError(f"{where}: its rig configuration does not load ({first}); pass --rig") from None


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def _dump(data: dict[str, Any], prefix: str = "") -> str:
    """Minimal TOML writer for a rig file (tables of scalars, strings and flat lists)."""
    scalars = {k: v for k, v in data.items() if not isinstance(v, dict)}
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    lines = [f"[{prefix}]"] if prefix and scalars else []
    lines += [f"{k} = {json.dumps(v)}" for k, v in scalars.items()]
    for key, value in tables.items():
        lines.append(_dump(value, f"{prefix}.{key}" if prefix else key))
    return "\n".join(lines) + "\n"


def lab_gel(rig: RigConfig, calibration_dir: Path) -> tuple[GelConfig, float, str]:
    """(gel, stiffening, source): the fitted ``gel.toml`` when present, else the rig file's nominal [gel]."""
    path = calibration_dir / "gel.toml"
    if path.exists():
        data = load_gel(path)
        try:
            gel = replace(rig.gel, youngs_modulus_mpa=float(data["youngs_modulus_mpa"]),
                          poisson_ratio=float(data.get("poisson_ratio", rig.gel.poisson_ratio)),
                          thickness_mm=float(data.get("thickness_mm", rig.gel.thickness_mm)))
        except (KeyError, TypeError, ValueError) as exc:
            raise GroundTruthError(f"{path}: needs youngs_modulus_mpa ({exc})") from None
        return gel, float(data.get("stiffening", 0.0)), str(path)
    return rig.gel, 0.0, "rig [gel] (nominal; no gel.toml)"


def lab_camera(rig: RigConfig, calibration_dir: Path) -> tuple[CameraModel, str]:
    """(camera, source): ``intrinsics.toml`` + ``extrinsics.toml`` from the calibration folder when both exist.

    Otherwise the rig file's nominal camera (``[camera]``: lens and sensor), flagged in the
    source string (:func:`labrig.calibration.files.uncalibrated_camera`).
    """
    intrinsics, extrinsics = calibration_dir / "intrinsics.toml", calibration_dir / "extrinsics.toml"
    if intrinsics.exists() and extrinsics.exists():
        return load_camera(intrinsics, extrinsics), f"{intrinsics} + {extrinsics}"
    return uncalibrated_camera(rig)


def lab_gel_pose(rig: RigConfig, calibration_dir: Path) -> tuple[Pose, str]:
    """(gel frame in machine coordinates, source): the rig registration when present, else the nominal pose."""
    path = calibration_dir / REGISTRATION_FILE
    pose = gel_pose(rig, path)
    return pose, str(path) if path.exists() else "rig [rig] nominal pose (no rig-registration.toml)"


@dataclass(frozen=True)
class LabInputs:
    rig: RigConfig
    gel: GelConfig
    stiffening: float
    camera: CameraModel
    gel_pose: Pose
    sources: dict[str, str]


def lab_inputs(rig: RigConfig, calibration_dir: str | Path | None = None, *, gel_pose: Pose | None = None,
               camera: CameraModel | None = None) -> LabInputs:
    """Everything the generator needs besides the recording; ``gel_pose``/``camera`` override (validation)."""
    folder = Path(calibration_dir) if calibration_dir is not None else DEFAULT_CALIBRATION_DIR
    gel, stiffening, gel_source = lab_gel(rig, folder)
    cam, cam_source = (camera, "given") if camera is not None else lab_camera(rig, folder)
    pose, pose_source = (gel_pose, "given") if gel_pose is not None else lab_gel_pose(rig, folder)
    return LabInputs(rig, gel, stiffening, cam, pose,
                     {"gel": gel_source, "camera": cam_source, "gel_pose": pose_source})
