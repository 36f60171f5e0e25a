"""The stress axes of another lab's camera and light: the scene's knobs, and the contrast-threshold axis measured
with the thresholds recalibrated and with the reference camera's."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labrig.errors import LabrigError
from labrig.evaluation.stress import FORCES_MODEL, FORCES_MODEL_UNCALIBRATED, StressResult, run_stress
from labrig.evaluation.stress_axes import RESPONSE_AXES, axis_named
from labrig.evaluation.stress_scene import StressScene, stressed_rig
from labrig.executor import run_tasks
from labrig.models import bundled_model_path
from labrig.sim.truth_config import sim_config


def test_the_scene_sets_the_cameras_thresholds_and_the_light() -> None:
    rig = stressed_rig(StressScene(contrast_threshold=0.30, on_off_ratio=1.44, slope_gain=4.0, membrane_level=0.16))
    truth = sim_config(rig)
    assert truth.events.threshold_on == pytest.approx(0.36) and truth.events.threshold_off == pytest.approx(0.25)
    assert truth.lighting.slope_gain == 4.0 and truth.lighting.membrane_level == 0.16
    reference = stressed_rig(StressScene())
    assert (sim_config(reference).events.threshold_on, sim_config(reference).lighting.slope_gain) == (0.22, 2.5)
    asymmetric = stressed_rig(StressScene(on_off_ratio=1.6))  # about the rig's own geometric mean
    events = sim_config(asymmetric).events
    assert np.sqrt(events.threshold_on * events.threshold_off) == pytest.approx(0.22)
    assert StressScene(on_off_ratio=1.6).changes_event_response and StressScene(slope_gain=3.0).changes_event_response
    assert not StressScene(membrane_level=0.2).changes_event_response  # the log intensity does not see the level
    for bad in ({"contrast_threshold": 0.0}, {"on_off_ratio": 0.0}, {"membrane_level": 1.5}, {"slope_gain": -1.0}):
        with pytest.raises(LabrigError, match="stress scene"):
            StressScene(**bad).check()  # type: ignore[arg-type]
    assert set(RESPONSE_AXES) <= {axis_named(k).key for k in RESPONSE_AXES}


def test_the_light_is_recalibrated_with_the_protocols_press_on_the_scenes_own_sensor() -> None:
    import tomllib

    from labrig.evaluation.stress_calibration import SLOPE_PRESS_PROTOCOL, calibration_press

    scene = StressScene(slope_gain=1.0, contrast_threshold=0.3, shear_mm=0.5, burst_period_ms=20.0, seed=9)
    press = calibration_press(scene)
    protocol = tomllib.loads(SLOPE_PRESS_PROTOCOL.read_text())
    assert (press.depth_mm, press.wait_s, press.shear_mm) == (protocol["normal"]["depth_mm"],
                                                             protocol["wait"]["duration_s"], 0.0)
    assert (press.slope_gain, press.contrast_threshold, press.seed, press.burst_period_ms) == (1.0, 0.3, 9, 0.0)
    assert axis_named("led_slope_gain").event_calibration


class Runner:
    def __init__(self, cache: Path) -> None:
        self.cache = cache

    def __call__(self, kind: str, fn: Any, tasks: list[Any]) -> list[Any]:
        return list(run_tasks(fn, tasks, workers=1, cache_dir=self.cache))


@pytest.fixture(scope="module")
def threshold_axis(tmp_path_factory: pytest.TempPathFactory) -> StressResult:
    """The contrast-threshold axis at the reference camera's 0.22 and at 0.35, on the default probe."""
    axis = replace(axis_named("contrast_threshold"), reduced=(0.22, 0.35))
    return run_stress(Runner(tmp_path_factory.mktemp("response-stress")), grid="reduced", axes=[axis],
                      model=str(bundled_model_path()))


def test_recalibrating_the_thresholds_keeps_the_network_where_the_reference_cameras_lose_it(
        threshold_axis: StressResult) -> None:
    curves = {c.method: c for c in threshold_axis.curves}
    assert {FORCES_MODEL, FORCES_MODEL_UNCALIBRATED} <= set(curves)
    calibrated, uncalibrated = curves[FORCES_MODEL].error, curves[FORCES_MODEL_UNCALIBRATED].error
    assert calibrated[0] == pytest.approx(uncalibrated[0], rel=0.15)  # the reference camera: both about the same
    assert uncalibrated[1] > 1.5 * calibrated[1]  # 0.35 ln: counted in the reference camera's events, the dent shrinks
    assert calibrated[1] < 2.0 * calibrated[0]  # recalibrated: no breakdown


def test_the_uncalibrated_curve_starts_from_the_rigs_own_thresholds() -> None:
    """At the ON/OFF axis' baseline (ratio 1: the rig's camera) nothing is recalibrated, so the uncalibrated method's
    error there is the calibrated one's (a curve with no baseline could not break)."""
    from labrig.evaluation.stress import ForceStress, SceneMeasurement, _curve
    from labrig.evaluation.stress_scene import SceneFacts

    facts = SceneFacts(1.0, 10, 1.0, 1.0, 0.1, 0.0)
    base = SceneMeasurement(facts, {}, {"10ms": {FORCES_MODEL: ForceStress(5.0, 0.1, 0.1, 2.0, 10)}})
    pushed = SceneMeasurement(facts, {}, {"10ms": {FORCES_MODEL: ForceStress(6.0, 0.1, 0.1, 2.0, 10),
                                                   FORCES_MODEL_UNCALIBRATED: ForceStress(30.0, 0.6, 0.6, 2.0, 10)}})
    axis = replace(axis_named("on_off_ratio"), reduced=(1.0, 1.6))
    measured = {("on_off_ratio", 1.0): (base, "10ms"), ("on_off_ratio", 1.6): (pushed, "10ms")}
    curve = _curve(axis, "forces", FORCES_MODEL_UNCALIBRATED, [1.0, 1.6], measured)
    assert curve.error == [5.0, 30.0]
