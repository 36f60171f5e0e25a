"""A stressed scene on the virtual rig: one short probing run with some sensor or motion knob pushed.

:class:`StressScene` holds every knob a stress axis may turn, as plain values (so it can be
part of a cached task's inputs); :func:`record_scene` simulates it into a recording with its
ground-truth sidecar. Each knob is the sim's own:

* motion: the probing path's depth (mm), shear distance (mm) and speed (mm/s, normal and
  shear alike), :func:`labrig.sim.motion.probing_path`;
* ``shot_noise_rate_hz``: the DVS pixels' noise events per pixel per second
  (``[sim.events] shot_noise_rate_hz``);
* ``marker_dimming``: the markers' brightness divided by this factor
  (``[sim.lighting] marker_level``), so their contrast against the black membrane falls;
* ``dead_side_mm``: a square of dead sensor pixels (no events), ``dead_side_mm`` wide on the
  gel and centred on the probed location (:class:`labrig.sim.rig.VirtualRig` ``dead_pixels``);
* ``stiffening``: the gel's large-strain stiffening (``[sim.mechanics] stiffening``; 0: a
  linear gel, the control for the force-range axis);
* ``sync_age_min``: the camera clock is not resynced: the recording maps camera time with an
  offset-only sync made this many minutes before the run, so the camera's true drift
  (``[sim.camera_clock] drift_ppm``) skews every event by drift x (age + t)
  (:func:`labrig.sim.live.record_live` ``camera_clock_model``). None: the recording's own fit;
* the markers as printed (``[sim.markers]``, seed: the scene's): ``position_error_mm``, each
  marker's placement error (std per gel axis, mm); ``missing_near_pct`` / ``missing_far_pct``:
  that percentage of the grid never printed, the markers nearest the press (the contact's
  own) or drawn at random among those more than :data:`FAR_FROM_PRESS_MM` from it
  (:func:`missing_markers`). The pipeline learns of them as a lab would, from an extrinsic
  calibration of that gel (:mod:`labrig.evaluation.stress_calibration`);
* ``burst_period_ms``: the camera's data reaches the host in USB bursts this far apart, with
  a jitter of :data:`BURST_JITTER` of the period (``[sim.camera_delivery]``); the recording's
  clock fit must see through them;
* the camera's response (``[sim.events]``): ``contrast_threshold`` (ln, ON and OFF alike; None: the
  rig's) and ``on_off_ratio``, C_on / C_off about the same geometric mean (1: as the rig has them);
  the light (``[sim.lighting]``): ``slope_gain``, the membrane's brightening per unit of surface
  slope under the LED ring, and ``membrane_level``, the black membrane's brightness (the markers'
  contrast against it falls as it rises); None: the rig's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labrig.clock import ClockModel
from labrig.config import DEFAULT_RIG, RigConfig, Roi, TomlValue, load_rig, rig_with
from labrig.dataset import sidecar_path
from labrig.errors import LabrigError
from labrig.groundtruth import generate, write_sidecar
from labrig.indenters import load_indenter
from labrig.recording import Recording
from labrig.sim.imperfections import printed_markers
from labrig.sim.live import record_live
from labrig.sim.motion import probing_path
from labrig.sim.rig import VirtualRig
from labrig.sim.truth_config import sim_config, true_camera

US_PER_MIN = 60_000_000
#: "Far" missing markers are drawn from those at least this far from the press (three pitches of the default gel), mm.
FAR_FROM_PRESS_MM = 6.0
#: USB burst jitter, as a fraction of the burst period.
BURST_JITTER = 0.2


@dataclass(frozen=True)
class StressScene:
    """One probing run: the sphere pressed ``depth_mm``, sheared ``shear_mm`` and back, at ``speed_mm_s``.

    Defaults: a 1 mm press with 0.5 mm of shear at 3 mm/s, 0.1 s waits (about 1.4 s in all);
    the sensor as the rig file says. See the module docstring for each knob.
    """

    rig: str = str(DEFAULT_RIG)
    indenter: str = "sphere"
    depth_mm: float = 1.0
    shear_mm: float = 0.5
    speed_mm_s: float = 3.0
    wait_s: float = 0.1
    approach_mm: float = 0.2
    shot_noise_rate_hz: float | None = None
    marker_dimming: float = 1.0
    dead_side_mm: float = 0.0
    sync_age_min: float | None = None
    stiffening: float | None = None
    position_error_mm: float = 0.0
    missing_near_pct: float = 0.0
    missing_far_pct: float = 0.0
    burst_period_ms: float = 0.0
    contrast_threshold: float | None = None
    on_off_ratio: float = 1.0
    slope_gain: float | None = None
    membrane_level: float | None = None
    seed: int = 3

    @property
    def changes_event_response(self) -> bool:
        """Whether the camera's thresholds or the light's slope gain differ from the rig's (a lab recalibrates
        them: ``labrig calibrate events`` with its press)."""
        return self.contrast_threshold is not None or self.on_off_ratio != 1.0 or self.slope_gain is not None

    def check(self) -> None:
        if self.depth_mm <= 0 or self.speed_mm_s <= 0 or self.shear_mm < 0 or self.wait_s < 0:
            raise LabrigError(f"stress scene: depth and speed must be positive, shear and waits not negative ({self})")
        if self.marker_dimming < 1:
            raise LabrigError(f"stress scene: marker_dimming is a factor >= 1 (markers that much dimmer), "
                              f"not {self.marker_dimming}")
        if self.dead_side_mm < 0 or (self.sync_age_min is not None and self.sync_age_min < 0):
            raise LabrigError("stress scene: dead_side_mm and sync_age_min must not be negative")
        if self.shot_noise_rate_hz is not None and self.shot_noise_rate_hz < 0:
            raise LabrigError(f"stress scene: shot_noise_rate_hz must not be negative, not {self.shot_noise_rate_hz}")
        if min(self.position_error_mm, self.missing_near_pct, self.missing_far_pct, self.burst_period_ms) < 0:
            raise LabrigError("stress scene: position_error_mm, missing_near_pct, missing_far_pct and burst_period_ms "
                              "must not be negative")
        if (self.contrast_threshold is not None and not 0.02 <= self.contrast_threshold <= 2.0) or self.on_off_ratio <= 0:
            raise LabrigError("stress scene: contrast_threshold must be in [0.02, 2] ln and on_off_ratio positive")
        if (self.slope_gain is not None and self.slope_gain < 0) or (
                self.membrane_level is not None and not 0 < self.membrane_level < 1):
            raise LabrigError("stress scene: slope_gain must not be negative and membrane_level must be in (0, 1)")
        if self.missing_near_pct + self.missing_far_pct > 50:
            raise LabrigError("stress scene: at most 50 % of the markers missing (missing_near_pct + missing_far_pct)")


def stressed_rig(scene: StressScene) -> RigConfig:
    """The scene's rig: the rig file with the scene's noise rate, marker brightness, stiffening, printed markers,
    USB bursts, contrast thresholds and light (its text says so)."""
    rig = load_rig(scene.rig)
    changes: dict[str, TomlValue] = {}
    if scene.stiffening is not None:
        changes["sim.mechanics.stiffening"] = float(scene.stiffening)
    if scene.shot_noise_rate_hz is not None:
        changes["sim.events.shot_noise_rate_hz"] = float(scene.shot_noise_rate_hz)
    if scene.marker_dimming != 1.0:
        changes["sim.lighting.marker_level"] = sim_config(rig).lighting.marker_level / scene.marker_dimming
    missing = sorted(set(missing_markers(rig, scene.missing_near_pct, near=True, seed=scene.seed))
                     | set(missing_markers(rig, scene.missing_far_pct, near=False, seed=scene.seed)))
    if scene.position_error_mm > 0 or missing:
        changes["sim.markers.seed"] = int(scene.seed)
        changes["sim.markers.position_error_mm"] = float(scene.position_error_mm)
        changes["sim.markers.missing"] = missing
    if scene.burst_period_ms > 0:
        changes["sim.camera_delivery.burst_period_ms"] = float(scene.burst_period_ms)
        changes["sim.camera_delivery.burst_jitter_ms"] = BURST_JITTER * float(scene.burst_period_ms)
    if scene.changes_event_response:
        events = sim_config(rig).events
        mean = (float(scene.contrast_threshold) if scene.contrast_threshold is not None
                else float(np.sqrt(events.threshold_on * events.threshold_off)))
        changes["sim.events.threshold_on"] = mean * float(np.sqrt(scene.on_off_ratio))
        changes["sim.events.threshold_off"] = mean / float(np.sqrt(scene.on_off_ratio))
    if scene.slope_gain is not None:
        changes["sim.lighting.slope_gain"] = float(scene.slope_gain)
    if scene.membrane_level is not None:
        changes["sim.lighting.membrane_level"] = float(scene.membrane_level)
    return rig_with(rig, changes) if changes else rig


def missing_markers(rig: RigConfig, percent: float, *, near: bool, seed: int = 0,
                    press_mm: tuple[float, float] = (0.0, 0.0)) -> list[int]:
    """Lattice indices (row-major) of ``round(percent / 100 x markers)`` markers: those nearest the press at
    ``press_mm`` (gel frame; ``near``), or drawn at random (``seed``) among those at least
    :data:`FAR_FROM_PRESS_MM` from it."""
    rest = rig.markers.rest_positions_mm()
    count = round(percent / 100 * len(rest))
    if count <= 0:
        return []
    distance = np.hypot(rest[:, 0] - press_mm[0], rest[:, 1] - press_mm[1])
    if near:
        return sorted(int(i) for i in np.argsort(distance, kind="stable")[:count])
    far = np.flatnonzero(distance >= FAR_FROM_PRESS_MM)
    if count > len(far):
        raise LabrigError(f"stress scene: {count} far markers asked, only {len(far)} are {FAR_FROM_PRESS_MM} mm from the press")
    return sorted(int(i) for i in np.random.default_rng([seed, 19]).choice(far, count, replace=False))


def dead_region_px(rig: RigConfig, side_mm: float, centre_mm: tuple[float, float] = (0.0, 0.0)) -> Roi | None:
    """Sensor pixels (the sim's true camera) covering a square ``side_mm`` wide on the gel around ``centre_mm``."""
    if side_mm <= 0:
        return None
    half = side_mm / 2
    corners = np.array([[centre_mm[0] + sx * half, centre_mm[1] + sy * half, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    px = true_camera(rig).project(corners)
    lo, hi = np.floor(px.min(axis=0)).astype(int), np.ceil(px.max(axis=0)).astype(int) + 1
    return Roi(int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))


def unsynced_camera_clock(rig: RigConfig, sync_age_min: float) -> ClockModel:
    """The camera clock model of an offset-only sync ``sync_age_min`` before the run (world time 0).

    The sync pinned device time to host time exactly but knew no drift (rate 1); the camera
    runs at ``[sim.camera_clock] drift_ppm``, so an event at world time t lands at
    t + drift x (age + t) in the recording.
    """
    clock = sim_config(rig).camera_clock
    t_sync_us = -float(sync_age_min) * US_PER_MIN
    device_at_sync = clock.origin_us + t_sync_us * (1 + clock.drift_ppm * 1e-6)
    return ClockModel(device_ref_us=device_at_sync, host_ref_us=t_sync_us, drift_ppm=0.0, method="unsynced")


@dataclass(frozen=True)
class SceneFacts:
    """Facts of a simulated scene, from the sim's truth."""

    duration_s: float  # simulated time
    events: int
    peak_force_n: float  # largest |force on the gel|
    peak_normal_n: float
    slip_ratio_max: float  # largest |tangential| / (friction x normal) from the shear to the unloading: 1 is gross slip
    clock_skew_max_ms: float  # the unsynced clock's largest event time error; 0 when synced
    markers_missing: int = 0  # markers never printed
    markers_missing_found: int | None = None  # of those, how many the scene's extrinsic calibration found (None: none run)
    markers_missing_false: int | None = None  # markers the calibration called missing that were printed
    rest_error_rms_px: float | None = None  # calibrated rest positions against the printed markers (sim's camera), px


def record_scene(scene: StressScene, out: str | Path) -> SceneFacts:
    """Simulate ``scene`` into the recording ``out`` (not real time) and write its sidecar ``NAME.gt.h5``."""
    scene.check()
    rig = stressed_rig(scene)
    indenter = load_indenter(scene.indenter)
    path = probing_path(rig, indenter, depth_mm=scene.depth_mm, shear_mm=scene.shear_mm,
                        normal_speed_mm_s=scene.speed_mm_s, shear_speed_mm_s=scene.speed_mm_s, wait_s=scene.wait_s,
                        approach_mm=scene.approach_mm)
    vr = VirtualRig(rig, indenter, seed=scene.seed, dead_pixels=dead_region_px(rig, scene.dead_side_mm))
    clock = None if scene.sync_age_min is None else unsynced_camera_clock(rig, scene.sync_age_min)
    result = record_live(out, rig, indenter, path, seed=scene.seed, realtime=False, virtual_rig=vr,
                         camera_clock_model=clock)
    write_sidecar(generate(out, rate_hz=100), sidecar_path(out))
    with Recording(out) as rec:
        t_us = rec.column("truth/contact", "t_host_us")
        force = rec.column("truth/contact", "force_n").astype(np.float64)
        phases = {p.name: p for p in reversed(rec.phases())}  # the first of each name
    normal = np.abs(force[:, 2])
    tangential = np.linalg.norm(force[:, :2], axis=1)
    sheared = np.zeros(len(t_us), bool)
    if "shear" in phases:  # a press without shear has none
        sheared = (t_us >= phases["shear"].t_start_us) & (t_us < phases["normal_up"].t_start_us) & (normal > 0)
    slip = tangential[sheared] / (sim_config(rig).gel.friction * normal[sheared]) if sheared.any() else np.zeros(1)
    drift = sim_config(rig).camera_clock.drift_ppm * 1e-6
    skew_ms = 0.0 if scene.sync_age_min is None else abs(drift) * (scene.sync_age_min * US_PER_MIN
                                                                   + path.duration_us) / 1e3
    return SceneFacts(duration_s=float(result.sim_duration_s), events=int(result.events),
                      peak_force_n=float(np.linalg.norm(force, axis=1).max()), peak_normal_n=float(normal.max()),
                      slip_ratio_max=float(slip.max()), clock_skew_max_ms=float(skew_ms),
                      markers_missing=len(printed_markers(sim_config(rig).markers, rig.markers.rest_positions_mm(),
                                                          rig.markers.diameter_mm).missing))
