"""The rig as a lab knows it (calibration/rig.toml): gel, markers, camera, ROI, rig pose, contact model.

Frames and units
----------------
* **Gel frame**: origin at the centre of the undeformed top surface (the marker
  grid's centre), x along the marker columns, y along the rows, z out of the
  gel towards the indenter. Millimetres.
* **Machine frame**: the CNC's machine coordinates, mm.
* **Camera frame** (OpenCV): x right, y down in the image, z along the optical
  axis. Image coordinates in pixels, origin at the top-left pixel's centre.

What a lab knows about its rig: the nominal gel and marker lattice, the camera's sensor and
lens (nominal intrinsics, :meth:`labrig.physics.camera.CameraModel.nominal`, used until the
camera calibration replaces them), the ROI, the nominal rig pose and the contact model the
lab chooses (``[mechanics]``). The file's ``[devices]`` and ``[safety]`` sections are read by
:mod:`labrig.protocol`.

Sections named ``sim.*`` are the virtual rig's truth (the true camera, the true rig pose, the
event model). :class:`RigConfig` does not read them and a real rig's file has none; only the
simulator does (:mod:`labrig.sim.truth_config`, from the text a :class:`RigConfig` keeps).
"""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.errors import ConfigError

__all__ = ["ConfigError"]

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
    #: The lens' nominal focal length (mm); with ``pixel_um``, the nominal fx = fy (px). None: not stated.
    focal_length_mm: float | None = None
    #: Nominal distance (mm) from the camera centre to the gel surface along the optical axis. None: not stated.
    gel_distance_mm: float | None = None


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
class MechanicsModel:
    """``[mechanics]``: the contact model the lab fits and runs (optional section; these defaults)."""

    #: "layer" (a bonded thin layer) or "halfspace".
    mode: str = "layer"
    #: The contact tables' surface grid spacing (mm).
    grid_spacing_mm: float = 0.1


@dataclass(frozen=True)
class RigConfig:
    gel: GelConfig
    markers: MarkerConfig
    camera: CameraGeometry
    roi: Roi
    rig: RigPose
    #: The rig file's whole text (a recording stores it; the simulator reads its ``sim.*`` sections).
    text: str
    path: Path
    mechanics: MechanicsModel = field(default_factory=MechanicsModel)


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
    config = RigConfig(
        gel=parse_section(GelConfig, data, "gel", path),
        markers=parse_section(MarkerConfig, data, "markers", path),
        camera=parse_section(CameraGeometry, data, "camera", path),
        roi=parse_section(Roi, data, "roi", path),
        rig=parse_section(RigPose, data, "rig", path),
        text=text,
        path=path,
        mechanics=parse_section(MechanicsModel, data, "mechanics", path) if "mechanics" in data else MechanicsModel(),
    )
    _check(config)
    return config


#: Sections a rig file may leave out: the lab's contact model, and the virtual rig's imperfect sensor,
#: true gel and CNC limits (:mod:`labrig.sim.truth_config`; their defaults: the ideal sensor, [gel], GRBL's own).
OPTIONAL_SECTIONS = ("mechanics", "sim.gel", "sim.markers", "sim.camera_delivery", "sim.ft", "sim.grbl")

TomlValue = bool | int | float | str | tuple[float, ...] | tuple[int, ...] | tuple[tuple[float, float], ...] | list[int]


def rig_with(rig: RigConfig, changes: Mapping[str, TomlValue]) -> RigConfig:
    """A copy of ``rig`` with some values changed, e.g. ``{"sim.events.shot_noise_rate_hz": 5.0}``.

    Keys are ``section.name`` (``sim.events.shot_noise_rate_hz``, ``gel.friction``). The TOML
    text is rewritten line by line (comments and layout kept), so the copy's ``text``, which a
    recording stores, states the changed values; ``path`` stays the original's. A key the
    text does not hold is a :class:`ConfigError`, except in the optional sections
    (:data:`OPTIONAL_SECTIONS`): there it is added (with its section if the text has none),
    so they can be set on any rig; the parse then checks the name (the ``sim.*`` sections' parse:
    :func:`labrig.sim.truth_config.sim_config`).
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


def section_table(data: dict[str, Any], name: str, path: Path, prefix: str = "") -> dict[str, Any]:
    """The table ``[prefix + name]`` of parsed TOML ``data``; missing: a :class:`ConfigError` naming ``path``."""
    table = data.get(name)
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: missing section [{prefix}{name}]")
    return table


def parse_section(cls: type, data: dict[str, Any], name: str, path: Path, prefix: str = "") -> Any:
    """The dataclass ``cls`` from the table ``[prefix + name]``: every field without a default must be
    given, no other key may be; lists become tuples. Errors name ``path`` and the section."""
    table = section_table(data, name, path, prefix)
    names = [f.name for f in fields(cls)]
    unknown = sorted(set(table) - set(names))
    if unknown:
        raise ConfigError(f"{path}: [{prefix}{name}] unknown key {unknown[0]!r}; allowed: {', '.join(names)}")
    missing = [f.name for f in fields(cls) if f.name not in table and f.default is MISSING
               and f.default_factory is MISSING]
    if missing:
        raise ConfigError(f"{path}: [{prefix}{name}] missing {missing[0]!r}")
    values = {}
    for f in fields(cls):
        if f.name not in table:
            continue
        value = table[f.name]
        if isinstance(value, list):
            value = tuple(value)
        values[f.name] = value
    return cls(**values)


def _check(config: RigConfig) -> None:
    where = str(config.path)
    check_gel(config.gel, "gel", where)
    roi, cam = config.roi, config.camera
    if not (0 <= roi.x0_px < roi.x1_px <= cam.width_px and 0 <= roi.y0_px < roi.y1_px <= cam.height_px):
        raise ConfigError(f"{where}: [roi] must lie inside the {cam.width_px}x{cam.height_px} sensor")
    for key in ("focal_length_mm", "gel_distance_mm"):
        value = getattr(cam, key)
        if value is not None and not (isinstance(value, int | float) and not isinstance(value, bool) and value > 0):
            raise ConfigError(f"{where}: [camera] {key} must be a positive number, not {value!r}")
    check_mechanics_mode(config.mechanics.mode, "mechanics", where)


def check_gel(gel: GelConfig, section: str, where: str) -> None:
    """A gel's values in range (``section`` and ``where`` name it in the error)."""
    if not 0 < gel.poisson_ratio < 0.5:
        raise ConfigError(f"{where}: [{section}] poisson_ratio must be in (0, 0.5), not {gel.poisson_ratio}")
    for key in ("thickness_mm", "size_x_mm", "size_y_mm", "youngs_modulus_mpa"):
        if getattr(gel, key) <= 0:
            raise ConfigError(f"{where}: [{section}] {key} must be positive")


def check_mechanics_mode(mode: str, section: str, where: str) -> None:
    """A contact model's mode is one the contact tables know."""
    if mode not in ("layer", "halfspace"):
        raise ConfigError(f"{where}: [{section}] mode must be 'layer' or 'halfspace'")
