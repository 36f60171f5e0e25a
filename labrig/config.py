"""The rig configuration (calibration/rig.toml): gel, markers, camera, ROI, rig pose.

Frames and units
----------------
* **Gel frame**: origin at the centre of the undeformed top surface (the marker
  grid's centre), x along the marker columns, y along the rows, z out of the
  gel towards the indenter. Millimetres.
* **Machine frame**: the CNC's machine coordinates, mm.
* **Camera frame** (OpenCV): x right, y down in the image, z along the optical
  axis. Image coordinates in pixels, origin at the top-left pixel's centre.

Sections named ``sim.*`` are the virtual rig's truth (the true camera, the true
rig pose, the event model); everything else is what a lab knows about its rig.
The sections of an imperfect sensor (``sim.gel``, ``sim.markers``,
``sim.camera_delivery``, ``sim.ft``, :mod:`labrig.config_sim`) may be left out:
their defaults are the ideal sensor (the true gel is the nominal ``[gel]``); so may the
virtual CNC's limits (``sim.grbl``: GRBL 1.1h's defaults).
"""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.config_sim import (
    SimCameraDelivery,
    SimFt,
    SimGrbl,
    SimMarkers,
    check_imperfections,
    parse_grbl,
    parse_imperfections,
)
from labrig.errors import ConfigError

__all__ = ["ConfigError", "SimCameraDelivery", "SimFt", "SimGrbl", "SimMarkers"]

DEFAULT_RIG = Path(__file__).resolve().parent.parent / "calibration" / "rig.toml"
#: The default rig's calibration folder (gel, camera, rig registration), wherever the command runs from.
DEFAULT_CALIBRATION_DIR = str(DEFAULT_RIG.parent)


@dataclass(frozen=True)
class GelConfig:
    thickness_mm: float
    size_x_mm: float
    size_y_mm: float
    youngs_modulus_mpa: float
    poisson_ratio: float
    friction: float


@dataclass(frozen=True)
class MarkerConfig:
    rows: int
    cols: int
    pitch_mm: float
    diameter_mm: float

    def rest_positions_mm(self) -> npt.NDArray[np.float64]:
        """(rows*cols, 3) marker centres in the gel frame, row-major from -y, -x."""
        cols, rows = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        x = (cols.ravel() - (self.cols - 1) / 2) * self.pitch_mm
        y = (rows.ravel() - (self.rows - 1) / 2) * self.pitch_mm
        return np.stack([x, y, np.zeros_like(x)], axis=1)


@dataclass(frozen=True)
class CameraGeometry:
    width_px: int
    height_px: int
    pixel_um: float
    #: Nominal gel-to-camera rotation (Rodrigues, rad): how the camera is mounted, known before calibration.
    nominal_rotvec_rad: tuple[float, float, float]


@dataclass(frozen=True)
class Roi:
    """Region of interest in sensor pixels; x1, y1 exclusive."""

    x0_px: int
    y0_px: int
    x1_px: int
    y1_px: int

    @property
    def width_px(self) -> int:
        return self.x1_px - self.x0_px

    @property
    def height_px(self) -> int:
        return self.y1_px - self.y0_px


@dataclass(frozen=True)
class RigPose:
    gel_origin_machine_mm: tuple[float, float, float]
    gel_yaw_deg: float


@dataclass(frozen=True)
class SimCamera:
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, ...]
    gel_to_camera_rotvec_rad: tuple[float, float, float]
    gel_to_camera_translation_mm: tuple[float, float, float]


@dataclass(frozen=True)
class SimRigPose:
    gel_origin_machine_mm: tuple[float, float, float]
    gel_yaw_deg: float
    gel_tilt_deg: tuple[float, float]
    ft_axes_in_gel_rotvec_rad: tuple[float, float, float]
    ft_origin_in_gel_mm: tuple[float, float, float]


@dataclass(frozen=True)
class SimMechanics:
    mode: str
    grid_spacing_mm: float
    stiffening: float


@dataclass(frozen=True)
class SimLighting:
    membrane_level: float
    marker_level: float
    slope_gain: float
    led_on: bool


@dataclass(frozen=True)
class SimEvents:
    threshold_on: float
    threshold_off: float
    threshold_sigma: float
    refractory_us: float
    cutoff_hz: float
    leak_rate_hz: float
    shot_noise_rate_hz: float
    max_step_px: float


@dataclass(frozen=True)
class SimCameraClock:
    origin_us: int
    drift_ppm: float


@dataclass(frozen=True)
class SimConfig:
    camera: SimCamera
    rig_pose: SimRigPose
    mechanics: SimMechanics
    lighting: SimLighting
    events: SimEvents
    camera_clock: SimCameraClock
    #: The true gel (``[sim.gel]``; keys left out, or the whole section: the nominal ``[gel]``'s).
    gel: GelConfig
    #: The markers as printed, the camera's delivery, the F/T link (optional sections: :mod:`labrig.config_sim`).
    markers: SimMarkers
    camera_delivery: SimCameraDelivery
    ft: SimFt
    #: The virtual CNC's max rates and accelerations (``[sim.grbl]``; left out: GRBL 1.1h's defaults).
    grbl: SimGrbl = field(default_factory=SimGrbl)


@dataclass(frozen=True)
class RigConfig:
    gel: GelConfig
    markers: MarkerConfig
    camera: CameraGeometry
    roi: Roi
    rig: RigPose
    sim: SimConfig
    text: str
    path: Path


def load_rig(path: str | Path = DEFAULT_RIG) -> RigConfig:
    """Load and validate a rig TOML; each error names the file and the field."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such rig file") from None
    return parse_rig(text, path)


def parse_rig(text: str, path: Path) -> RigConfig:
    """Validate a rig TOML's ``text``; errors name ``path`` (where the text came from)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    sim = _table(data, "sim", path)
    gel = _build(GelConfig, data, "gel", path)
    markers, delivery, ft = parse_imperfections(sim, path)
    sim_gel = _true_gel(sim, gel, path)
    config = RigConfig(
        gel=gel,
        markers=_build(MarkerConfig, data, "markers", path),
        camera=_build(CameraGeometry, data, "camera", path),
        roi=_build(Roi, data, "roi", path),
        rig=_build(RigPose, data, "rig", path),
        sim=SimConfig(
            camera=_build(SimCamera, sim, "camera", path, "sim."),
            rig_pose=_build(SimRigPose, sim, "rig_pose", path, "sim."),
            mechanics=_build(SimMechanics, sim, "mechanics", path, "sim."),
            lighting=_build(SimLighting, sim, "lighting", path, "sim."),
            events=_build(SimEvents, sim, "events", path, "sim."),
            camera_clock=_build(SimCameraClock, sim, "camera_clock", path, "sim."),
            gel=sim_gel,
            markers=markers,
            camera_delivery=delivery,
            ft=ft,
            grbl=parse_grbl(sim, path),
        ),
        text=text,
        path=path,
    )
    _check(config)
    return config


#: Sections a rig file may leave out (their defaults: the ideal sensor, the true gel = [gel], GRBL's own limits).
OPTIONAL_SECTIONS = ("sim.gel", "sim.markers", "sim.camera_delivery", "sim.ft", "sim.grbl")

TomlValue = bool | int | float | str | tuple[float, ...] | tuple[int, ...] | tuple[tuple[float, float], ...]


def rig_with(rig: RigConfig, changes: Mapping[str, TomlValue]) -> RigConfig:
    """A copy of ``rig`` with some values changed, e.g. ``{"sim.events.shot_noise_rate_hz": 5.0}``.

    Keys are ``section.name`` (``sim.events.shot_noise_rate_hz``, ``gel.friction``). The TOML
    text is rewritten line by line (comments and layout kept), so the copy's ``text``, which a
    recording stores, states the changed values; ``path`` stays the original's. A key the
    text does not hold is a :class:`ConfigError`, except in the optional sections
    (:data:`OPTIONAL_SECTIONS`): there it is added (with its section if the text has none),
    so they can be set on any rig; the parse then checks the name.
    """
    lines = rig.text.splitlines(keepends=True)
    for key, value in changes.items():
        section, _, name = key.rpartition(".")
        if not section:
            raise ConfigError(f"{key!r}: give section.name, e.g. 'sim.events.shot_noise_rate_hz'")
        current, header_at = "", -1
        for i, line in enumerate(lines):
            header = _SECTION.match(line)
            if header:
                current = header.group(1).strip()
                header_at = i if current == section else header_at
                continue
            match = _ASSIGNMENT.match(line)
            if current == section and match and match.group("name") == name:
                lines[i] = f"{match.group('head')}{_toml_value(value)}{match.group('tail')}"
                break
        else:
            if section not in OPTIONAL_SECTIONS:
                raise ConfigError(f"{rig.path}: no key {name!r} in [{section}] to change")
            assignment = f"{name} = {_toml_value(value)}\n"
            if header_at >= 0:
                lines.insert(header_at + 1, assignment)
            else:
                if lines and not lines[-1].endswith("\n"):
                    lines[-1] += "\n"
                lines += ["\n", f"[{section}]\n", assignment]
    return parse_rig("".join(lines), rig.path)


_SECTION = re.compile(r"^\s*\[([^\[\]]+)\]\s*(#.*)?$")
_ASSIGNMENT = re.compile(r'^(?P<head>\s*(?P<name>[A-Za-z0-9_-]+)\s*=\s*)(?P<value>"[^"]*"|\[[^\]]*\]|[^#\s]+)'
                         r"(?P<tail>[^\S\n]*(#.*)?\n?)$")


def _toml_value(value: TomlValue) -> str:
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    return json.dumps(value)


def _table(data: dict[str, Any], name: str, path: Path, prefix: str = "") -> dict[str, Any]:
    table = data.get(name)
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: missing section [{prefix}{name}]")
    return table


def _build(cls: type, data: dict[str, Any], name: str, path: Path, prefix: str = "") -> Any:
    table = _table(data, name, path, prefix)
    names = [f.name for f in fields(cls)]
    unknown = sorted(set(table) - set(names))
    if unknown:
        raise ConfigError(f"{path}: [{prefix}{name}] unknown key {unknown[0]!r}; allowed: {', '.join(names)}")
    missing = [n for n in names if n not in table]
    if missing:
        raise ConfigError(f"{path}: [{prefix}{name}] missing {missing[0]!r}")
    values = {}
    for f in fields(cls):
        value = table[f.name]
        if isinstance(value, list):
            value = tuple(value)
        values[f.name] = value
    return cls(**values)


def _true_gel(sim: dict[str, Any], nominal: GelConfig, path: Path) -> GelConfig:
    """``[sim.gel]``: the true gel; keys left out (or the whole section) take the nominal ``[gel]``'s values."""
    table = sim.get("gel", {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [sim.gel] must be a table")
    names = [f.name for f in fields(GelConfig)]
    unknown = sorted(set(table) - set(names))
    if unknown:
        raise ConfigError(f"{path}: [sim.gel] unknown key {unknown[0]!r}; allowed: {', '.join(names)}")
    for key, value in table.items():
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise ConfigError(f"{path}: [sim.gel] {key} must be a number, not {value!r}")
    return replace(nominal, **{key: float(value) for key, value in table.items()})


def _check(config: RigConfig) -> None:
    where = str(config.path)
    for section, gel in (("gel", config.gel), ("sim.gel", config.sim.gel)):
        if not 0 < gel.poisson_ratio < 0.5:
            raise ConfigError(f"{where}: [{section}] poisson_ratio must be in (0, 0.5), not {gel.poisson_ratio}")
        for key in ("thickness_mm", "size_x_mm", "size_y_mm", "youngs_modulus_mpa"):
            if getattr(gel, key) <= 0:
                raise ConfigError(f"{where}: [{section}] {key} must be positive")
    roi, cam = config.roi, config.camera
    if not (0 <= roi.x0_px < roi.x1_px <= cam.width_px and 0 <= roi.y0_px < roi.y1_px <= cam.height_px):
        raise ConfigError(f"{where}: [roi] must lie inside the {cam.width_px}x{cam.height_px} sensor")
    if config.sim.mechanics.mode not in ("layer", "halfspace"):
        raise ConfigError(f"{where}: [sim.mechanics] mode must be 'layer' or 'halfspace'")
    if len(config.sim.camera.distortion) != 5:
        raise ConfigError(f"{where}: [sim.camera] distortion must be [k1, k2, p1, p2, k3]")
    mk, roi = config.markers, config.roi
    check_imperfections(config.sim.markers, config.sim.camera_delivery, config.sim.ft, mk.rows * mk.cols, mk.pitch_mm,
                        roi.width_px * roi.height_px, where)
