"""Calibration scenes recorded on the virtual rig: a blinking dot-grid target, the LED ring blinking,
and the LED ring dimmed and brightened along slow ramps.

``labrig calibrate intrinsics``, ``labrig calibrate extrinsics`` and ``labrig calibrate events``
record them when no recording is given; :mod:`labrig.calibration` analyses them like any
recording.

Both are written as ordinary labrig recordings (docs/recording-format.md):
events with the simulated camera clock (offset and drift, as the virtual rig
stamps them), event packets every ``PACKET_US`` of world time received at the
packet's end (recording host time = world time), the rig TOML, and
``extra_*`` metadata naming the scene (``extra_calibration_scene``), the seed
and the noise scale. The truth rides along as extra metadata too (JSON), so
calibration results can be scored; the calibration code never reads it.

``noise_scale`` multiplies the pixel model's noise: shot-noise and leak rates
and the per-pixel threshold spread (``threshold_sigma``), see
:mod:`labrig.sim.events`.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig, rig_with
from labrig.frames import Pose, matrix_to_rotvec, rotvec_to_matrix
from labrig.indenters import Indenter, load_indenter
from labrig.physics.camera import CameraModel
from labrig.physics.target import DotGridTarget, target_pose
from labrig.recording import RecordingMetadata, RecordingWriter
from labrig.sim.events import EventParams
from labrig.sim.rig import VirtualRig
from labrig.sim.target_scene import TargetScene
from labrig.sim.truth_config import sim_config

#: Event packet length written to the recording, world us.
PACKET_US = 5_000

SCENE_TARGET = "dot_grid_target"
SCENE_LED = "led_blink"
SCENE_LED_RAMPS = "led_ramps"


@dataclass(frozen=True)
class SceneResult:
    path: Path
    events: int
    duration_s: float
    views: int = 0


def noisy_rig(rig: RigConfig, noise_scale: float = 1.0) -> RigConfig:
    """The rig with its event noise (shot noise, leak, threshold spread) multiplied by ``noise_scale``."""
    if noise_scale < 0:
        raise ValueError("noise_scale must not be negative")
    ev = sim_config(rig).events
    return rig_with(rig, {"sim.events.shot_noise_rate_hz": ev.shot_noise_rate_hz * noise_scale,
                          "sim.events.leak_rate_hz": ev.leak_rate_hz * noise_scale,
                          "sim.events.threshold_sigma": ev.threshold_sigma * noise_scale})


def camera_clock_us(rig: RigConfig, t_world_us: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """The simulated camera's timestamps for world times (the virtual rig's clock: offset and drift)."""
    clock = sim_config(rig).camera_clock
    t = np.asarray(t_world_us, dtype=np.float64)
    return (clock.origin_us + np.floor(t * (1 + clock.drift_ppm * 1e-6))).astype(np.int64)


def _pose_json(pose: Pose) -> dict[str, list[float]]:
    return {"rotvec_rad": [float(v) for v in matrix_to_rotvec(pose.rotation)],
            "translation_mm": [float(v) for v in pose.translation_mm]}


def target_poses(camera: CameraModel, target: DotGridTarget, n_views: int, seed: int = 0,
                 *, max_tilt_deg: float = 35.0, distance_mm: tuple[float, float] = (24.0, 40.0),
                 margin_px: float = 30.0) -> list[Pose]:
    """``n_views`` varied poses with the whole target on the sensor.

    Distances are spread evenly over ``distance_mm`` (shuffled), tilts are
    drawn up to ``max_tilt_deg`` in a random direction (the first few views
    take the largest tilts, so short sequences still constrain the focal
    length), the in-plane angle is random, and the target's centre aims at a
    cycle of image regions (centre, corners, edges) so that the views together
    cover the sensor; an aim that would push dots off the sensor is pulled
    towards the centre until every dot is on it.
    """
    rng = np.random.default_rng(seed)
    aims = np.array([[0, 0], [-1, -1], [1, 1], [1, -1], [-1, 1], [0, -1], [0, 1], [-1, 0], [1, 0]], float)
    distances = np.linspace(distance_mm[0], distance_mm[1], max(n_views, 1))
    rng.shuffle(distances)
    points = target.points_mm()
    poses: list[Pose] = []
    for k in range(n_views):
        tilt = np.radians(max_tilt_deg) * (1.0 if k % 3 == 0 else rng.uniform(0.35, 1.0))
        phi = rng.uniform(0, 2 * np.pi)
        spin = rng.uniform(-0.5, 0.5) + (np.pi / 2 if k % 4 == 3 else 0.0)
        rot = _rotvec_compose([np.cos(phi) * tilt, np.sin(phi) * tilt, 0.0], [0.0, 0.0, spin])
        aim = aims[k % len(aims)]
        pose = _aimed_pose(camera, points, rot, aim, float(distances[k]), margin_px)
        while pose is None:  # too close to fit whole at any aim: step back
            distances[k] *= 1.08
            pose = _aimed_pose(camera, points, rot, aim, float(distances[k]), margin_px)
        poses.append(pose)
    return poses


def _aimed_pose(camera: CameraModel, points: npt.NDArray[np.float64], rot: npt.ArrayLike, aim: npt.NDArray[np.float64],
                z: float, margin_px: float) -> Pose | None:
    """The pose at depth ``z`` aimed as far towards ``aim`` as keeps every dot ``margin_px`` inside the sensor."""
    w, h = camera.width_px, camera.height_px
    for shrink in np.linspace(1.0, 0.0, 21):
        u = camera.cx_px + aim[0] * shrink * 0.5 * w
        v = camera.cy_px + aim[1] * shrink * 0.5 * h
        xy = camera.pixels_to_normalized([[u, v]])[0] * z
        pose = target_pose(rot, [xy[0], xy[1], z])
        px = camera.project(points, pose)
        if (px.min(axis=0) > margin_px).all() and px[:, 0].max() < w - margin_px and px[:, 1].max() < h - margin_px:
            return pose
    return None


def _rotvec_compose(first: list[float], second: list[float]) -> npt.NDArray[np.float64]:
    """Rotation vector of R(first) @ R(second)."""
    return matrix_to_rotvec(rotvec_to_matrix(first) @ rotvec_to_matrix(second))


def record_target_scene(
    path: str | Path,
    rig: RigConfig,
    n_views: int = 12,
    seed: int = 0,
    noise_scale: float = 1.0,
    *,
    target: DotGridTarget | None = None,
    blinks: int = 1,
    half_period_us: int = 10_000,
    overwrite: bool = False,
) -> SceneResult:
    """Record a dot-grid target blinking ``blinks`` times at each of ``n_views`` poses (virtual rig).

    The target geometry goes into ``extra_target_*`` metadata, the true poses
    into ``extra_truth_views_json`` (rotation vector rad, translation mm, on/off
    world times us).
    """
    path = Path(path)
    if overwrite and path.exists():
        path.unlink()
    target = target or DotGridTarget()
    rig = noisy_rig(rig, noise_scale)
    scene = TargetScene(rig, target, seed=seed, params=EventParams.from_rig(rig))
    poses = target_poses(scene.camera, target, n_views, seed)
    recording = scene.blink_at(poses, blinks=blinks, half_period_us=half_period_us)
    truth = [{**_pose_json(v.target_to_camera), "on_us": list(v.on_us), "off_us": list(v.off_us)} for v in recording.views]
    metadata = RecordingMetadata(
        protocol_toml="# calibration scene: a blinking dot-grid target at several poses (virtual rig)\n",
        rig_toml=rig.text,
        extra={
            "virtual_rig": True, "calibration_scene": SCENE_TARGET, "seed": seed, "noise_scale": float(noise_scale),
            "target_rows": target.rows, "target_cols": target.cols, "target_pitch_mm": target.pitch_mm,
            "target_dot_diameter_mm": target.dot_diameter_mm, "truth_views_json": json.dumps(truth),
        },
    )
    with RecordingWriter(path, metadata) as writer:
        _write_events(writer, rig, recording.events, 0)
    duration = (int(recording.events["t"][-1]) if len(recording.events) else 0) / 1e6
    return SceneResult(path, len(recording.events), duration, len(poses))


def record_led_blink(
    path: str | Path,
    rig: RigConfig,
    seed: int = 0,
    noise_scale: float = 1.0,
    *,
    blinks: int = 1,
    period_us: int = 40_000,
    lead_us: int = 10_000,
    indenter: Indenter | None = None,
    overwrite: bool = False,
) -> SceneResult:
    """Record the gel at rest while the LED ring goes off and on ``blinks`` times (virtual rig).

    The indenter is held 5 mm above the gel. Each blink: off at its start, on
    half a period later. The true gel-to-camera pose goes into
    ``extra_truth_gel_to_camera_json``.
    """
    path = Path(path)
    if overwrite and path.exists():
        path.unlink()
    rig = noisy_rig(rig, noise_scale)
    indenter = indenter or load_indenter("sphere")
    vr, still = _gel_at_rest(rig, indenter, seed)
    for k in range(blinks):
        vr.set_led(False, lead_us + k * period_us)
        vr.set_led(True, lead_us + k * period_us + period_us // 2)
    end_us = lead_us + blinks * period_us + lead_us
    metadata = RecordingMetadata(
        indenter=indenter.name,
        protocol_toml="# calibration scene: the LED ring blinking, gel at rest (virtual rig)\n",
        rig_toml=rig.text,
        extra={
            "virtual_rig": True, "calibration_scene": SCENE_LED, "seed": seed, "noise_scale": float(noise_scale),
            "truth_gel_to_camera_json": json.dumps(_pose_json(vr.camera.gel_to_camera)),
        },
    )
    n = 0
    with RecordingWriter(path, metadata) as writer:
        for t0 in range(0, end_us, period_us // 2):
            events = vr.advance(min(t0 + period_us // 2, end_us), still).events
            _write_events(writer, rig, events, t0)
            n += len(events)
    return SceneResult(path, n, end_us / 1e6, 0)


@dataclass(frozen=True)
class LedRamps:
    """The event-response scene's light: the LED ring dimmed from full to ``1 / ratio`` along a ramp of
    ``ramp_ms``, held ``hold_ms``, brightened back along a ramp, held, ``cycles`` times, after a quiet
    ``lead_ms`` at full light. Each ramp is ``steps`` equal steps of the log level (ln(ratio) / steps,
    well below a contrast threshold, so no pixel fires twice on one step)."""

    ratio: float = 3.0
    cycles: int = 10
    ramp_ms: float = 48.0
    hold_ms: float = 52.0
    lead_ms: float = 100.0
    steps: int = 12

    def __post_init__(self) -> None:
        if not (self.ratio > 1.0 and self.cycles >= 1 and self.steps >= 1 and self.ramp_ms > 0 and self.hold_ms > 0
                and self.lead_ms > 0):
            raise ValueError("LED ramps need ratio > 1, cycles and steps >= 1, and positive ramp, hold and lead times")

    def ramps_us(self) -> list[tuple[int, int, int]]:
        """(start, end, direction) of every ramp, world us: direction -1 dims, +1 brightens."""
        out, t = [], self.lead_ms * 1e3
        for _ in range(self.cycles):
            for direction in (-1, 1):
                out.append((round(t), round(t + self.ramp_ms * 1e3), direction))
                t += (self.ramp_ms + self.hold_ms) * 1e3
        return out

    def levels(self) -> list[tuple[int, float]]:
        """(world us, LED level) of every step of every ramp."""
        out = []
        for t0, t1, direction in self.ramps_us():
            for k in range(1, self.steps + 1):
                frac = k / self.steps if direction < 0 else 1.0 - k / self.steps
                out.append((round(t0 + (t1 - t0) * (k - 0.5) / self.steps), float(self.ratio ** -frac)))
        return out

    @property
    def duration_us(self) -> int:
        return round((self.lead_ms * 2 + self.cycles * 2 * (self.ramp_ms + self.hold_ms)) * 1e3)


def record_led_ramps(
    path: str | Path,
    rig: RigConfig,
    seed: int = 0,
    noise_scale: float = 1.0,
    *,
    ramps: LedRamps | None = None,
    indenter: Indenter | None = None,
    overwrite: bool = False,
) -> SceneResult:
    """Record the gel at rest while the LED ring is dimmed and brightened along slow ramps (virtual rig).

    Every pixel sees its log intensity fall and rise by ln(ratio) per cycle, whatever its brightness:
    the scene of ``labrig calibrate events``. The light's schedule (what a lab's LED driver is told)
    goes into ``extra_led_*`` metadata: ``extra_led_ratio``, ``extra_led_cycles`` and
    ``extra_led_ramps_json`` (start, end, direction of each ramp, host us = world us here); the true
    thresholds ride along in ``extra_truth_thresholds_json`` for scoring only.
    """
    path = Path(path)
    if overwrite and path.exists():
        path.unlink()
    ramps = ramps or LedRamps()
    rig = noisy_rig(rig, noise_scale)
    indenter = indenter or load_indenter("sphere")
    vr, still = _gel_at_rest(rig, indenter, seed)
    for t_us, level in ramps.levels():
        vr.set_led(level, t_us)
    ev = sim_config(rig).events
    metadata = RecordingMetadata(
        indenter=indenter.name,
        protocol_toml="# calibration scene: the LED ring dimmed and brightened along slow ramps, gel at rest (virtual rig)\n",
        rig_toml=rig.text,
        extra={
            "virtual_rig": True, "calibration_scene": SCENE_LED_RAMPS, "seed": seed, "noise_scale": float(noise_scale),
            "led_ratio": float(ramps.ratio), "led_cycles": int(ramps.cycles),
            "led_ramps_json": json.dumps([list(r) for r in ramps.ramps_us()]),
            "truth_thresholds_json": json.dumps({"threshold_on": ev.threshold_on, "threshold_off": ev.threshold_off,
                                                 "threshold_sigma": ev.threshold_sigma}),
        },
    )
    n, end_us, chunk_us = 0, ramps.duration_us, 50_000
    with RecordingWriter(path, metadata) as writer:
        for t0 in range(0, end_us, chunk_us):
            events = vr.advance(min(t0 + chunk_us, end_us), still).events
            _write_events(writer, rig, events, t0)
            n += len(events)
    return SceneResult(path, n, end_us / 1e6, 0)


def _gel_at_rest(rig: RigConfig, indenter: Indenter, seed: int
                 ) -> tuple[VirtualRig, Callable[[npt.ArrayLike], npt.NDArray[np.float64]]]:
    """A virtual rig and the tool path that holds the indenter 5 mm above the gel centre (the gel at rest)."""
    vr = VirtualRig(rig, indenter, seed=seed)
    above = vr.gel_in_machine.apply(np.array([[0.0, 0.0, 5.0]]))[0] - np.asarray(indenter.tool_offset_mm)

    def still(t_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        return np.tile(above, (np.atleast_1d(t_us).size, 1))

    return vr, still


def _write_events(writer: RecordingWriter, rig: RigConfig, events: npt.NDArray[np.void], t0_us: int) -> None:
    """Events (world us) from ``t0_us`` on as packets of PACKET_US (aligned to world time), each received at its end."""
    if len(events) == 0:
        return
    t = events["t"]
    edges = np.arange(t0_us - t0_us % PACKET_US, int(t[-1]) + 1 + PACKET_US, PACKET_US)
    bounds = np.searchsorted(t, edges)
    for k in range(len(edges) - 1):
        i0, i1 = int(bounds[k]), int(bounds[k + 1])
        if i1 > i0:
            ev = events[i0:i1]
            writer.put_events(ev["x"], ev["y"], ev["p"], camera_clock_us(rig, ev["t"]), int(edges[k + 1]))
