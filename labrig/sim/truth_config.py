"""The virtual rig's truth: the rig file's ``sim.*`` sections, read only by the simulator.

A rig file describes the rig as a lab knows it (:class:`labrig.config.RigConfig`); the
virtual rig adds what no real rig states: the true camera and rig pose, the true gel,
the mechanics it simulates, the lighting, the event camera's model and clock, and the
imperfect sensor (:mod:`labrig.sim.imperfections`). :func:`sim_config` reads them from
the text a :class:`~labrig.config.RigConfig` keeps, so a recording's stored rig text
reproduces its virtual rig. Required: ``[sim.camera]``, ``[sim.rig_pose]``,
``[sim.mechanics]``, ``[sim.lighting]``, ``[sim.events]``, ``[sim.camera_clock]``;
optional: ``[sim.gel]`` (keys left out, or the whole section: the nominal ``[gel]``'s),
``[sim.markers]``, ``[sim.camera_delivery]``, ``[sim.ft]``, ``[sim.grbl]``.

Frames and units as in :mod:`labrig.config`: the true camera is the OpenCV model
(px; distortion k1 k2 p1 p2 k3) with the gel->camera pose (Rodrigues rad, mm).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

from labrig.config import GelConfig, RigConfig, check_gel, check_mechanics_mode, parse_section
from labrig.errors import ConfigError
from labrig.indenters import Indenter
from labrig.physics.camera import CameraModel
from labrig.physics.mechanics import ContactTable
from labrig.sim.imperfections import (
    SimCameraDelivery,
    SimFt,
    SimGrbl,
    SimMarkers,
    check_imperfections,
    parse_grbl,
    parse_imperfections,
    sim_table,
)

__all__ = ["SimCamera", "SimCameraClock", "SimConfig", "SimEvents", "SimLighting", "SimMechanics", "SimRigPose",
           "sim_config", "true_camera", "true_contact_table"]


@dataclass(frozen=True)
class SimCamera:
    """``[sim.camera]``: true intrinsics (px), distortion (k1 k2 p1 p2 k3) and gel->camera pose (rad, mm)."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, ...]
    gel_to_camera_rotvec_rad: tuple[float, float, float]
    gel_to_camera_translation_mm: tuple[float, float, float]


@dataclass(frozen=True)
class SimRigPose:
    """``[sim.rig_pose]``: the true gel pose in machine coordinates (mm, deg) and the F/T sensor's pose in the gel."""

    gel_origin_machine_mm: tuple[float, float, float]
    gel_yaw_deg: float
    gel_tilt_deg: tuple[float, float]
    ft_axes_in_gel_rotvec_rad: tuple[float, float, float]
    ft_origin_in_gel_mm: tuple[float, float, float]


@dataclass(frozen=True)
class SimMechanics:
    """``[sim.mechanics]``: the contact model the virtual rig simulates."""

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
    """The virtual rig's truth (the rig file's ``sim.*`` sections)."""

    camera: SimCamera
    rig_pose: SimRigPose
    mechanics: SimMechanics
    lighting: SimLighting
    events: SimEvents
    camera_clock: SimCameraClock
    #: The true gel (``[sim.gel]``; keys left out, or the whole section: the nominal ``[gel]``'s).
    gel: GelConfig
    #: The markers as printed, the camera's delivery, the F/T link (optional sections: :mod:`labrig.sim.imperfections`).
    markers: SimMarkers
    camera_delivery: SimCameraDelivery
    ft: SimFt
    #: The virtual CNC's max rates and accelerations (``[sim.grbl]``; left out: GRBL 1.1h's defaults).
    grbl: SimGrbl = field(default_factory=SimGrbl)

    @classmethod
    def from_rig(cls, rig: RigConfig) -> SimConfig:
        """Parse and check the ``sim.*`` sections of ``rig``'s text; a rig without them is a :class:`ConfigError`."""
        return cls.from_text(rig.text, rig.path)

    @classmethod
    def from_text(cls, text: str, path: Path) -> SimConfig:
        """Parse and check the ``sim.*`` sections of a rig file's ``text`` (errors name ``path``)."""
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML ({exc})") from None
        sim = data.get("sim")
        if not isinstance(sim, dict):
            raise ConfigError(f"{path}: no virtual rig here: the simulator needs the rig file's [sim.*] sections "
                              "(calibration/rig.toml has them); for hardware, name the devices in [devices]")
        nominal = parse_section(GelConfig, data, "gel", path)
        markers, delivery, ft = parse_imperfections(sim, path)
        config = cls(
            camera=parse_section(SimCamera, sim, "camera", path, "sim."),
            rig_pose=parse_section(SimRigPose, sim, "rig_pose", path, "sim."),
            mechanics=parse_section(SimMechanics, sim, "mechanics", path, "sim."),
            lighting=parse_section(SimLighting, sim, "lighting", path, "sim."),
            events=parse_section(SimEvents, sim, "events", path, "sim."),
            camera_clock=parse_section(SimCameraClock, sim, "camera_clock", path, "sim."),
            gel=_true_gel(sim, nominal, path),
            markers=markers,
            camera_delivery=delivery,
            ft=ft,
            grbl=parse_grbl(sim, path),
        )
        config._check(data, path)
        return config

    def _check(self, data: dict[str, Any], path: Path) -> None:
        where = str(path)
        check_gel(self.gel, "sim.gel", where)
        check_mechanics_mode(self.mechanics.mode, "sim.mechanics", where)
        if len(self.camera.distortion) != 5:
            raise ConfigError(f"{where}: [sim.camera] distortion must be [k1, k2, p1, p2, k3]")
        markers, roi = data["markers"], data["roi"]
        check_imperfections(self.markers, self.camera_delivery, self.ft, markers["rows"] * markers["cols"],
                            markers["pitch_mm"], (roi["x1_px"] - roi["x0_px"]) * (roi["y1_px"] - roi["y0_px"]), where)


def sim_config(rig: RigConfig) -> SimConfig:
    """The virtual rig's truth for ``rig`` (parsed once per rig text)."""
    return _parsed(rig.text, rig.path)


@lru_cache(maxsize=64)
def _parsed(text: str, path: Path) -> SimConfig:
    return SimConfig.from_text(text, path)


def true_camera(rig: RigConfig) -> CameraModel:
    """The virtual rig's true camera: ``[sim.camera]`` on the ``[camera]`` sensor."""
    cam = sim_config(rig).camera
    return CameraModel(
        fx_px=float(cam.fx_px),
        fy_px=float(cam.fy_px),
        cx_px=float(cam.cx_px),
        cy_px=float(cam.cy_px),
        distortion=tuple(float(d) for d in cam.distortion),  # type: ignore[arg-type]
        gel_to_camera_rotvec_rad=tuple(float(r) for r in cam.gel_to_camera_rotvec_rad),  # type: ignore[arg-type]
        gel_to_camera_translation_mm=tuple(float(t) for t in cam.gel_to_camera_translation_mm),  # type: ignore[arg-type]
        width_px=rig.camera.width_px,
        height_px=rig.camera.height_px,
    )


def true_contact_table(indenter: Indenter, rig: RigConfig, **options: Any) -> ContactTable:
    """:meth:`ContactTable.build` with the virtual rig's true gel (``[sim.gel]``), mode, grid spacing and
    stiffening (``[sim.mechanics]``), and the footprint turned by the indenter's yaw relative to the true
    gel (``[sim.rig_pose] gel_yaw_deg``); ``options`` override any of these."""
    sim = sim_config(rig)
    options.setdefault("yaw_deg", indenter.footprint_yaw_deg(sim.rig_pose.gel_yaw_deg))
    options.setdefault("mode", sim.mechanics.mode)
    options.setdefault("spacing_mm", sim.mechanics.grid_spacing_mm)
    options.setdefault("stiffening", sim.mechanics.stiffening)
    return ContactTable.build(indenter, sim.gel, **options)


def _true_gel(sim: dict[str, Any], nominal: GelConfig, path: Path) -> GelConfig:
    """``[sim.gel]``: the true gel; keys left out (or the whole section) take the nominal ``[gel]``'s values."""
    table, where = sim_table(sim, "gel", GelConfig, path)
    for key, value in table.items():
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise ConfigError(f"{where} {key} must be a number, not {value!r}")
    return replace(nominal, **{key: float(value) for key, value in table.items()})
