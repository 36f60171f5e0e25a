"""The intrinsic-calibration scene as events: a dot-grid target blinking at a series of poses.

Event cameras see only change, so intrinsic calibration shows them a target
whose dots blink (a back-lit plate or a screen) while it is held still at
several poses (a plate moved between blinks with its dots dark makes no
events on its uniform plate). :class:`TargetScene` renders that on the
camera's whole sensor through the same camera model and DVS pixel model as
the membrane: at each pose the dots switch on and off ``blinks`` times (each
switch ramps over ``switch_us``; the photoreceptors' low-pass spreads the
events), then the next pose follows. The truth (each pose and when its blinks
happened) comes back with the events, so calibration can be scored.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig
from labrig.eventtypes import EVENT_DTYPE
from labrig.frames import Pose
from labrig.physics.camera import CameraModel
from labrig.physics.target import DotGridTarget
from labrig.sim.events import EventParams, EventSensor
from labrig.sim.target import render_target
from labrig.sim.truth_config import true_camera


@dataclass(frozen=True)
class TargetView:
    """One pose of the target and the world times (us) its dots switched on and off."""

    target_to_camera: Pose
    on_us: tuple[int, ...]
    off_us: tuple[int, ...]


@dataclass(frozen=True)
class TargetRecording:
    """Events (EVENT_DTYPE, world us) of a blink sequence and its truth."""

    events: npt.NDArray[np.void]
    views: tuple[TargetView, ...]
    target: DotGridTarget
    camera: CameraModel


class TargetScene:
    """A dot-grid target in front of the rig's camera (true intrinsics), on the whole sensor."""

    def __init__(
        self,
        rig: RigConfig,
        target: DotGridTarget | None = None,
        *,
        seed: int = 0,
        params: EventParams | None = None,
    ) -> None:
        self.camera = true_camera(rig)
        self.target = target or DotGridTarget()
        width, height = self.camera.width_px, self.camera.height_px
        self._dark = np.full(width * height, self.target.plate_level)
        self.sensor = EventSensor(params or EventParams.from_rig(rig), width, height, self._dark, seed=seed)

    def blink_at(
        self,
        poses: list[Pose],
        *,
        blinks: int = 2,
        half_period_us: int = 20_000,
        switch_us: int = 20,
    ) -> TargetRecording:
        """Blink the dots ``blinks`` times at each pose (on for ``half_period_us``, then off as long)."""
        if blinks < 1 or half_period_us <= switch_us or switch_us < 1:
            raise ValueError("need blinks >= 1 and half_period_us > switch_us >= 1")
        chunks: list[npt.NDArray[np.void]] = []
        views: list[TargetView] = []
        for pose in poses:
            lit = render_target(self.camera, self.target, pose).ravel()
            dots = np.flatnonzero(lit != self._dark)
            on_times: list[int] = []
            off_times: list[int] = []
            for _ in range(blinks):
                for level, times in ((lit[dots], on_times), (self._dark[dots], off_times)):
                    t0 = self.sensor.t_us
                    times.append(t0)
                    chunks.append(self.sensor.step(t0, t0 + switch_us, dots, level))
                    chunks.append(self.sensor.step(t0 + switch_us, t0 + half_period_us, dots[:0], level[:0]))
            views.append(TargetView(pose, tuple(on_times), tuple(off_times)))
        events = np.concatenate(chunks) if chunks else np.zeros(0, EVENT_DTYPE)
        return TargetRecording(events, tuple(views), self.target, self.camera)
