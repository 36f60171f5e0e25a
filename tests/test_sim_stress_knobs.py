"""Knobs the stress suite turns: a rig copy with changed values, dead pixels, an unsynced camera clock model."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from labrig.clock import ClockModel
from labrig.config import ConfigError, RigConfig, Roi, rig_with
from labrig.indenters import Indenter
from labrig.physics.mechanics import ContactTable
from labrig.recording import Recording
from labrig.recording.finalize import store_clock_model
from labrig.sim.events import EventParams, EventSensor
from labrig.sim.rig import VirtualRig
from labrig.sim.truth_config import sim_config


def test_rig_with_changes_values_and_the_text(rig: RigConfig) -> None:
    changed = rig_with(rig, {"sim.events.shot_noise_rate_hz": 5.0, "sim.lighting.marker_level": 0.3,
                             "gel.friction": 0.5, "sim.camera.distortion": (0.0, 0.0, 0.0, 0.0, 0.0)})
    assert sim_config(changed).events.shot_noise_rate_hz == 5.0 and sim_config(changed).lighting.marker_level == 0.3
    assert changed.gel.friction == 0.5 and sim_config(changed).camera.distortion == (0.0,) * 5
    assert sim_config(changed).events.leak_rate_hz == sim_config(rig).events.leak_rate_hz and changed.path == rig.path
    assert "shot_noise_rate_hz = 5.0" in changed.text and "# relative brightness of a marker" in changed.text
    assert len(changed.text.splitlines()) == len(rig.text.splitlines())
    with pytest.raises(ConfigError, match=r"no key 'nope' in \[sim\.events\]"):
        rig_with(rig, {"sim.events.nope": 1.0})


def test_dead_pixels_emit_nothing_and_leave_the_others_alone() -> None:
    params = EventParams(shot_noise_rate_hz=200.0)
    dead = np.zeros((20, 30), bool)
    dead[5:10, 10:20] = True
    alive = EventSensor(params, 30, 20, np.full(600, 0.5), seed=1)
    partly = EventSensor(params, 30, 20, np.full(600, 0.5), seed=1, dead=dead)
    pixels = np.arange(600)
    brighter = np.full(600, 0.9)
    a = alive.step(0, 10_000, pixels, brighter)
    b = partly.step(0, 10_000, pixels, brighter)
    inside = dead[a["y"], a["x"]]
    assert inside.sum() > 50 and not dead[b["y"], b["x"]].any()
    assert np.array_equal(a[~inside], b)  # the same random draws: only the dead pixels' events go


def test_a_stored_clock_model_maps_the_camera_time(small_recording: Path, tmp_path: Path) -> None:
    copy = tmp_path / "copy.h5"
    shutil.copy(small_recording, copy)
    with Recording(copy) as rec:
        fitted = rec.clock_model("camera")
        before = rec.events_between(0, 2_000_000)
    stale = ClockModel(device_ref_us=fitted.device_ref_us, host_ref_us=fitted.host_ref_us + 5_000, drift_ppm=0.0,
                       method="unsynced")
    store_clock_model(copy, "camera", stale)
    with Recording(copy) as rec:
        assert rec.clock_model("camera").method == "unsynced"
        after = rec.events_between(0, 2_000_000)
    assert np.median(after["t"][:1000] - before["t"][:1000]) == pytest.approx(5_000, abs=1_000)


def test_a_virtual_rig_with_a_dead_region(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    roi = rig.roi
    dead = Roi(roi.x0_px - 5, roi.y0_px + 10, roi.x0_px + 20, roi.y0_px + 40)  # sticks out of the ROI on the left
    vr = VirtualRig(rig, sphere, table=table, dead_pixels=dead)
    assert vr.sensor.dead is not None and vr.sensor.dead.sum() == 20 * 30
    mask = vr.sensor.dead.reshape(roi.height_px, roi.width_px)
    assert mask[10:40, :20].all() and not mask[:10].any()


def test_record_live_keeps_an_unsynced_camera_clock(rig: RigConfig, sphere: Indenter, table: ContactTable,
                                                    tmp_path: Path) -> None:
    """An offset-only sync an hour before the run: the camera's 35 ppm drift puts every event 126 ms late."""
    from labrig.evaluation.stress_scene import unsynced_camera_clock
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    path = probing_path(rig, sphere, depth_mm=0.3, shear_mm=0.0, normal_speed_mm_s=10.0, wait_s=0.0, approach_mm=0.1)
    model = unsynced_camera_clock(rig, 60.0)
    out = tmp_path / "unsynced.h5"
    record_live(out, rig, sphere, path, seed=1, realtime=False, virtual_rig=VirtualRig(rig, sphere, table=table),
                camera_clock_model=model)
    skew_us = sim_config(rig).camera_clock.drift_ppm * 1e-6 * 60 * 60e6
    with Recording(out) as rec:
        assert rec.clock_model("camera") == model
        events = rec.events_between(0, 2e6)
        truth_start = int(rec.column("truth/contact", "t_host_us")[0])
    assert skew_us == pytest.approx(126_000)
    assert len(events) > 1000 and events["t"].min() >= truth_start + skew_us - 1
