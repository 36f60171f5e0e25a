"""The calibration target as events: blinking dots at poses, seen through the true camera model."""

from __future__ import annotations

import numpy as np
import pytest

from labrig.config import load_rig
from labrig.physics.target import target_pose
from labrig.sim.target_scene import TargetScene


def _on_event_image(events: np.ndarray, t0: int, t1: int) -> np.ndarray:
    sel = (events["t"] >= t0) & (events["t"] < t1) & (events["p"] == 1)
    image = np.zeros((720, 1280))
    np.add.at(image, (events["y"][sel], events["x"][sel]), 1)
    return image


def test_blinking_dots_make_events_centred_on_the_projected_dots() -> None:
    scene = TargetScene(load_rig(), seed=1)
    pose = target_pose([0.3, -0.2, 0.05], [1.0, -0.5, 30.0])
    rec = scene.blink_at([pose], blinks=2, half_period_us=20_000)
    view = rec.views[0]
    assert len(view.on_us) == len(view.off_us) == 2
    assert np.all(np.diff(rec.events["t"]) >= 0)
    image = _on_event_image(rec.events, view.on_us[0], view.off_us[0])
    true = scene.camera.project(scene.target.points_mm(), pose)
    errors, inside = [], 0.0
    for cx, cy in true:
        x0, y0 = round(cx) - 12, round(cy) - 12
        patch = image[y0 : y0 + 25, x0 : x0 + 25]
        yy, xx = np.mgrid[y0 : y0 + 25, x0 : x0 + 25]
        weight = patch.sum()
        inside += weight
        errors.append(np.hypot((patch * xx).sum() / weight - cx, (patch * yy).sum() / weight - cy))
    assert inside / image.sum() > 0.99  # ON events come from the dots
    assert np.mean(errors) < 0.15 and np.max(errors) < 0.5  # event centroids find the dots
    off = rec.events[(rec.events["t"] >= view.off_us[0]) & (rec.events["t"] < view.on_us[1])]
    assert (off["p"] == 0).mean() > 0.99  # switching off makes OFF events
    assert len(off) == pytest.approx(image.sum(), rel=0.1)  # the same log change down as up


def test_same_seed_same_events() -> None:
    pose = target_pose([0.0, 0.2, 0.0], [0.0, 0.0, 32.0])
    a = TargetScene(load_rig(), seed=4).blink_at([pose], blinks=1).events
    b = TargetScene(load_rig(), seed=4).blink_at([pose], blinks=1).events
    assert a.tobytes() == b.tobytes()
