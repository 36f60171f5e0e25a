"""Calibration files: ``intrinsics.toml`` and ``extrinsics.toml``, their loaders, and the calibrated camera.

Every key carries its unit in its name (px, mm, rad). The files are written
by hand (TOML is simple enough) and read with :mod:`tomllib`; a missing key
or a wrong shape is a one-line :class:`CalibrationFileError` naming the file
and the key. See docs/calibration.md for the keys. :func:`camera_model` picks
the camera a rig's calibration works with: the calibrated one, else the
rig file's nominal camera (:func:`uncalibrated_camera`, which says so once).

``extrinsics.toml`` versions (top-level ``format_version``; absent: 1): version 2 adds
the markers as printed to ``[markers]`` (``measured_px``, ``in_pose``, ``missing``,
``residual_px``, ``residual_mm``: :class:`~labrig.calibration.marker_map.MarkerMap`).
A version-1 file is read with the measured centres it has (``measured_px``; a marker
without one rests at its nominal projection) and no marker missing: version 1 did not
tell a missing marker from one left out of the pose.
"""

from __future__ import annotations

import datetime as _dt
import logging
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from labrig import __version__
from labrig.calibration.marker_map import BoolArray, MarkerMap
from labrig.config import CameraGeometry, RigConfig
from labrig.errors import CalibrationError, LabrigError
from labrig.physics.camera import CameraModel

Array = npt.NDArray[np.float64]

log = logging.getLogger(__name__)
#: The nominal cameras (``[camera]`` sections) :func:`uncalibrated_camera` has warned about, each once per process.
_WARNED_NOMINAL: set[CameraGeometry] = set()

DEFAULT_INTRINSICS = Path("calibration/intrinsics.toml")
DEFAULT_EXTRINSICS = Path("calibration/extrinsics.toml")
#: ``extrinsics.toml``'s format (module docstring); readers accept every older one.
EXTRINSICS_FORMAT_VERSION = 2


class CalibrationFileError(LabrigError):
    """A calibration file is missing or malformed."""


@dataclass(frozen=True)
class Intrinsics:
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, float, float, float, float]  # k1 k2 p1 p2 k3
    width_px: int = 1280
    height_px: int = 720
    rms_px: float = float("nan")
    n_views: int = 0
    path: Path | None = None

    @property
    def matrix(self) -> Array:
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @classmethod
    def from_camera(cls, camera: CameraModel) -> Intrinsics:
        return cls(camera.fx_px, camera.fy_px, camera.cx_px, camera.cy_px, camera.distortion, camera.width_px,
                   camera.height_px)


@dataclass(frozen=True)
class Extrinsics:
    """The gel-to-camera pose (``p_cam = R p_gel + t``) and the markers' rest positions."""

    rotvec_rad: tuple[float, float, float]
    translation_mm: tuple[float, float, float]
    rest_gel_mm: Array  # (N, 3)
    rest_px: Array  # (N, 2)
    detected: npt.NDArray[np.bool_]
    errors_px: Array
    mean_error_px: float
    std_error_px: float
    marker_map: MarkerMap  # the markers as printed: measured rest positions (px), missing markers, residuals
    path: Path | None = None
    format_version: int = EXTRINSICS_FORMAT_VERSION


def camera_from_calibration(intrinsics: Intrinsics, extrinsics: Extrinsics | None = None) -> CameraModel:
    """A :class:`CameraModel` with the calibrated intrinsics and (if given) the calibrated gel-to-camera pose.

    Without extrinsics the pose is the identity (gel frame = camera frame)."""
    rotvec = extrinsics.rotvec_rad if extrinsics else (0.0, 0.0, 0.0)
    translation = extrinsics.translation_mm if extrinsics else (0.0, 0.0, 0.0)
    return CameraModel(intrinsics.fx_px, intrinsics.fy_px, intrinsics.cx_px, intrinsics.cy_px, intrinsics.distortion,
                       rotvec, translation, intrinsics.width_px, intrinsics.height_px)


def load_camera(intrinsics_path: str | Path, extrinsics_path: str | Path | None = None) -> CameraModel:
    """The calibrated camera from its files."""
    extrinsics = load_extrinsics(extrinsics_path) if extrinsics_path is not None else None
    return camera_from_calibration(load_intrinsics(intrinsics_path), extrinsics)


def camera_model(rig: RigConfig, extrinsics_path: str | Path | None = None,
                 intrinsics_path: str | Path | None = None) -> tuple[CameraModel, str]:
    """(camera model, where it came from): the camera calibration (``intrinsics.toml`` and
    ``extrinsics.toml`` next to the rig file, or the paths given) when both exist, else the
    rig file's nominal camera (:func:`uncalibrated_camera`)."""
    extrinsics = Path(extrinsics_path) if extrinsics_path is not None else rig.path.parent / "extrinsics.toml"
    intrinsics = Path(intrinsics_path) if intrinsics_path is not None else rig.path.parent / "intrinsics.toml"
    if extrinsics.exists() and intrinsics.exists():
        return load_camera(intrinsics, extrinsics), f"{intrinsics} + {extrinsics}"
    if extrinsics_path is not None or intrinsics_path is not None:
        raise CalibrationError(f"the camera calibration needs both {intrinsics} and {extrinsics}; "
                               "run `labrig calibrate intrinsics` and `labrig calibrate extrinsics`")
    return uncalibrated_camera(rig)


def uncalibrated_camera(rig: RigConfig) -> tuple[CameraModel, str]:
    """(camera, source) without a camera calibration: the rig file's nominal camera
    (:meth:`CameraModel.nominal`: lens and sensor, no distortion). Warns once per nominal camera."""
    camera = CameraModel.nominal(rig)
    if rig.camera not in _WARNED_NOMINAL:
        _WARNED_NOMINAL.add(rig.camera)
        log.warning("no camera calibration: using the rig file's nominal camera ([camera]: %g mm lens, %g um pixels, "
                    "centred, no distortion); run `labrig calibrate intrinsics` and `labrig calibrate extrinsics`",
                    rig.camera.focal_length_mm, rig.camera.pixel_um)
    return camera, f"nominal camera ({rig.path} [camera]; no intrinsics.toml + extrinsics.toml)"


# -- writing ----------------------------------------------------------------------------------------


def save_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary file and a rename: a crash leaves the old file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.replace(path)
    return path


def _value(v: Any) -> str:
    if isinstance(v, bool | np.bool_):
        return "true" if v else "false"
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        f = float(v)
        return "nan" if math.isnan(f) else repr(f)
    if isinstance(v, str | Path):
        return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def toml_table(name: str, items: dict[str, Any], comments: dict[str, str] | None = None) -> str:
    comments = comments or {}
    lines = [f"[{name}]"]
    for key, v in items.items():
        if isinstance(v, np.ndarray) and v.ndim == 2:
            rows = ",\n".join("    " + _value(r) for r in v)
            lines.append(f"{key} = [\n{rows},\n]")
        else:
            lines.append(f"{key} = {_value(v)}" + (f"  # {comments[key]}" if key in comments else ""))
    return "\n".join(lines) + "\n"


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def provenance(path: Path | None, sha256: str) -> dict[str, Any]:
    """A calibration file's [source] table: the recording it came from, its SHA-256, labrig's version, the date."""
    return {"recording": str(path or ""), "recording_sha256": sha256, "labrig_version": __version__, "date": _now()}


def _read(path: str | Path) -> tuple[Path, dict[str, Any]]:
    path = Path(path)
    try:
        return path, tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationFileError(f"{path}: no such calibration file; run `labrig calibrate` first") from None
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationFileError(f"{path}: not valid TOML ({exc})") from None


def _get(path: Path, data: dict[str, Any], section: str, key: str) -> Any:
    try:
        return data[section][key]
    except (KeyError, TypeError):
        raise CalibrationFileError(f"{path}: missing [{section}] {key}") from None


def _array(path: Path, data: dict[str, Any], section: str, key: str, shape: tuple[int, ...]) -> Array:
    value = np.asarray(_get(path, data, section, key), dtype=np.float64)
    if value.ndim != len(shape) or any(s >= 0 and s != v for s, v in zip(shape, value.shape)):
        raise CalibrationFileError(f"{path}: [{section}] {key} has shape {value.shape}, expected {shape}")
    return value


def load_intrinsics(path: str | Path = DEFAULT_INTRINSICS) -> Intrinsics:
    path, data = _read(path)
    s = "intrinsics"
    dist = _array(path, data, s, "distortion", (5,))
    return Intrinsics(
        float(_get(path, data, s, "fx_px")), float(_get(path, data, s, "fy_px")),
        float(_get(path, data, s, "cx_px")), float(_get(path, data, s, "cy_px")),
        tuple(float(d) for d in dist),  # type: ignore[arg-type]
        int(_get(path, data, s, "width_px")), int(_get(path, data, s, "height_px")),
        float(data[s].get("rms_px", float("nan"))), int(data[s].get("n_views", 0)), path,
    )


def marker_map_table(marker_map: MarkerMap) -> dict[str, Any]:
    """The ``[markers]`` keys of a :class:`MarkerMap` (format version 2)."""
    return {
        "measured_px": marker_map.measured_px, "in_pose": [bool(v) for v in marker_map.in_pose],
        "missing": marker_map.missing_indices, "residual_px": marker_map.residual_px,
        "residual_mm": marker_map.residual_mm,
    }


def _marker_map(path: Path, data: dict[str, Any], version: int, rest_px: Array, rest_gel_mm: Array) -> MarkerMap:
    """The file's markers as printed; a version-1 file's from its measured centres, none missing."""
    n = len(rest_px)
    cols = int(data["markers"].get("cols", n))
    if version < 2:
        measured = (_array(path, data, "markers", "measured_px", (n, 2)) if "measured_px" in data["markers"]
                    else rest_px.copy())
        found = cast(BoolArray, np.isfinite(measured).all(axis=1))
        measured = np.where(found[:, None], measured, rest_px)
        return MarkerMap(cols, rest_px, measured, found, np.full((n, 2), np.nan))
    measured = _array(path, data, "markers", "measured_px", (n, 2))
    missing = np.zeros(n, bool)
    listed = np.asarray(_get(path, data, "markers", "missing"), np.int64).reshape(-1)
    if listed.size and (listed.min() < 0 or listed.max() >= n):
        raise CalibrationFileError(f"{path}: [markers] missing lists markers outside 0..{n - 1}")
    missing[listed] = True
    if (np.isfinite(measured).all(axis=1) == missing).any():
        raise CalibrationFileError(f"{path}: [markers] missing does not match the nan rows of measured_px")
    in_pose = np.asarray(_get(path, data, "markers", "in_pose"), bool)
    if in_pose.shape != (n,):
        raise CalibrationFileError(f"{path}: [markers] in_pose has shape {in_pose.shape}, expected ({n},)")
    return MarkerMap(cols, rest_px, measured, in_pose, _array(path, data, "markers", "residual_mm", (n, 2)))


def load_extrinsics(path: str | Path = DEFAULT_EXTRINSICS) -> Extrinsics:
    """``extrinsics.toml`` of any format version up to :data:`EXTRINSICS_FORMAT_VERSION`."""
    path, data = _read(path)
    version = data.get("format_version", 1)
    if not isinstance(version, int) or not 1 <= version <= EXTRINSICS_FORMAT_VERSION:
        raise CalibrationFileError(f"{path}: format_version {version!r} is not one this labrig reads "
                                   f"(1 to {EXTRINSICS_FORMAT_VERSION}); update labrig or recalibrate")
    rotvec = _array(path, data, "extrinsics", "rotation_rotvec_rad", (3,))
    translation = _array(path, data, "extrinsics", "translation_mm", (3,))
    rest = _array(path, data, "markers", "rest_gel_mm", (-1, 3))
    n = len(rest)
    rest_px = _array(path, data, "markers", "rest_px", (n, 2))
    return Extrinsics(
        tuple(float(v) for v in rotvec),  # type: ignore[arg-type]
        tuple(float(v) for v in translation),  # type: ignore[arg-type]
        rest,
        rest_px,
        np.asarray(_get(path, data, "markers", "detected"), dtype=bool),
        _array(path, data, "markers", "error_px", (n,)),
        float(_get(path, data, "extrinsics", "reprojection_mean_px")),
        float(_get(path, data, "extrinsics", "reprojection_std_px")),
        _marker_map(path, data, version, rest_px, rest),
        path,
        version,
    )
