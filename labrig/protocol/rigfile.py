"""The rig file's [devices] and [safety] sections (optional; defaults: the embedded virtual rig).

[devices] is a :class:`DeviceConfig` (where the GRBL, the Bota and the camera
are), [safety] a :class:`~labrig.protocol.safety.SafetyLimits`. Read from the
rig TOML that :func:`labrig.config.load_rig` loaded, checked key by key, each
problem naming the file, the section and the key.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import tomllib
from dataclasses import dataclass
from typing import Any

from labrig.config import ConfigError, RigConfig
from labrig.errors import LabrigError
from labrig.protocol.safety import SafetyLimits

CAMERA_BACKENDS = ("metavision", "raw", "sim")


@dataclass(frozen=True)
class DeviceConfig:
    """Where the devices are. Empty ports with the ``sim`` camera and no socket: the virtual rig."""

    grbl_port: str = ""
    grbl_baud: int = 115200
    bota_port: str = ""
    bota_baud: int = 460800
    camera: str = "sim"
    camera_path: str = ""
    output_on: str = "M8"
    output_off: str = "M9"

    @property
    def virtual(self) -> bool:
        return not self.grbl_port and not self.bota_port and self.camera == "sim" and not self.camera_path

    @property
    def camera_is_file(self) -> bool:
        """``camera = "metavision"`` with a RAW file as ``camera_path``: the SDK's file device."""
        return self.camera == "metavision" and self.camera_path.lower().endswith(".raw")

    def camera_options(self, where: str | None = None) -> dict[str, Any]:
        """``open_camera`` options for this camera; ``where``: its socket or file if not ``camera_path``."""
        path = self.camera_path if where is None else where
        if self.camera != "metavision":
            return {"path": path}
        return {"path": path} if self.camera_is_file else {"serial": path}

    def check(self) -> None:
        if self.virtual:
            return
        missing = [name for name, value in (("grbl_port", self.grbl_port), ("bota_port", self.bota_port)) if not value]
        if self.camera == "sim" and not self.camera_path:
            missing.append("camera_path (the socket `labrig sim serve` prints)")
        if missing:
            raise LabrigError(f"[devices] names some devices but not {', '.join(missing)}: configure all of them, "
                              "or none for the embedded virtual rig")


def device_config(rig: RigConfig) -> DeviceConfig:
    """The [devices] section (missing: the embedded virtual rig)."""
    values = _section(rig, "devices", DeviceConfig)
    config = DeviceConfig(**values)
    if config.camera not in CAMERA_BACKENDS:
        raise ConfigError(f"{rig.path}: [devices] camera must be one of {', '.join(CAMERA_BACKENDS)}, not {config.camera!r}")
    for key in ("grbl_baud", "bota_baud"):
        if getattr(config, key) <= 0:
            raise ConfigError(f"{rig.path}: [devices] {key} must be positive")
    return config


def safety_limits(rig: RigConfig) -> SafetyLimits:
    """The [safety] section (missing keys: the defaults of :class:`SafetyLimits`)."""
    values = _section(rig, "safety", SafetyLimits)
    limits = SafetyLimits(**values)
    lo, hi = limits.workspace_min_mm, limits.workspace_max_mm
    if len(lo) != 3 or len(hi) != 3 or any(a >= b for a, b in zip(lo, hi, strict=True)):
        raise ConfigError(f"{rig.path}: [safety] workspace_min_mm must be three values each below workspace_max_mm's")
    for key in ("max_normal_force_n", "max_shear_force_n", "clearance_mm"):
        if getattr(limits, key) <= 0:
            raise ConfigError(f"{rig.path}: [safety] {key} must be positive")
    for key in ("gel_margin_mm", "body_margin_mm"):
        if getattr(limits, key) < 0:
            raise ConfigError(f"{rig.path}: [safety] {key} must not be negative")
    return limits


@functools.lru_cache(maxsize=8)
def _parsed(text: str) -> dict[str, Any]:
    """A rig file's TOML, parsed once per text (a campaign checks its rig for each of its recordings); read only."""
    return tomllib.loads(text)


def _section(rig: RigConfig, name: str, cls: type) -> dict[str, Any]:
    table = _parsed(rig.text).get(name, {})
    if not isinstance(table, dict):
        raise ConfigError(f"{rig.path}: [{name}] must be a table")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    values: dict[str, Any] = {}
    for key, value in table.items():
        if key not in fields:
            close = difflib.get_close_matches(key, fields, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ConfigError(f"{rig.path}: [{name}] unknown key {key!r}; {hint}allowed: {', '.join(fields)}")
        default = fields[key].default
        if isinstance(default, tuple):
            if not isinstance(value, list) or not all(isinstance(v, int | float) for v in value):
                raise ConfigError(f"{rig.path}: [{name}] {key} must be a list of numbers")
            value = tuple(float(v) for v in value)
        elif isinstance(default, float):
            if not isinstance(value, int | float) or isinstance(value, bool):
                raise ConfigError(f"{rig.path}: [{name}] {key} must be a number")
            value = float(value)
        elif not isinstance(value, type(default)):
            raise ConfigError(f"{rig.path}: [{name}] {key} must be a {type(default).__name__}, not {value!r}")
        values[key] = value
    return values
