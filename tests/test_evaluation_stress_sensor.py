"""The imperfect sensor's stress axes: printed markers (placement error, missing near and far) and USB bursts.

Each axis runs on a tiny grid (its baseline and one stressed value) of a short probe; the printed gels are
calibrated as a lab would (an LED-blink scene and the extrinsic calibration), never told the sim's markers.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labrig.config import load_rig
from labrig.errors import LabrigError
from labrig.evaluation.stress import StressResult, run_stress
from labrig.evaluation.stress_axes import SENSOR_AXES, axis_named
from labrig.evaluation.stress_calibration import calibrate_printed_markers
from labrig.evaluation.stress_scene import FAR_FROM_PRESS_MM, StressScene, missing_markers, stressed_rig
from labrig.executor import run_tasks
from labrig.sim.imperfections import printed_markers
from labrig.sim.truth_config import sim_config

#: A short probe (0.5 mm press, 0.2 mm of shear at 6 mm/s) so that each scene stays cheap.
SHORT = StressScene(depth_mm=0.5, shear_mm=0.2, speed_mm_s=6.0, wait_s=0.05, approach_mm=0.1)
TINY = {"marker_position": (0.0, 0.05), "missing_near": (0.0, 4.0), "missing_far": (0.0, 4.0), "usb_bursts": (0.0, 50.0)}


def test_missing_markers_near_and_far_from_the_press() -> None:
    rig = load_rig()
    rest = rig.markers.rest_positions_mm()
    near = missing_markers(rig, 2.0, near=True)
    assert len(near) == 3 and len(missing_markers(rig, 10.0, near=True)) == 16  # of 156
    assert np.hypot(*rest[near, :2].T).max() <= np.sort(np.hypot(*rest[:, :2].T))[2]  # the three nearest the press
    far = missing_markers(rig, 10.0, near=False, seed=3)
    assert len(far) == 16 and np.hypot(*rest[far, :2].T).min() >= FAR_FROM_PRESS_MM
    assert far == missing_markers(rig, 10.0, near=False, seed=3) != missing_markers(rig, 10.0, near=False, seed=4)
    assert missing_markers(rig, 0.0, near=True) == []


def test_the_scene_prints_the_gel_and_delivers_in_bursts() -> None:
    rig = stressed_rig(StressScene(position_error_mm=0.1, missing_near_pct=2.0, missing_far_pct=2.0,
                                   burst_period_ms=20.0, seed=5))
    printed = printed_markers(sim_config(rig).markers, rig.markers.rest_positions_mm(), rig.markers.diameter_mm)
    assert len(printed.missing) == 6 and not sim_config(rig).markers.ideal
    offsets = printed.rest_mm[:, :2] - rig.markers.rest_positions_mm()[:, :2]
    assert 0.07 < offsets.std() < 0.13  # 0.1 mm std per axis
    assert sim_config(rig).camera_delivery.burst_period_ms == 20.0 and sim_config(rig).camera_delivery.burst_jitter_ms == 4.0
    assert "[sim.markers]" in rig.text and "[sim.camera_delivery]" in rig.text  # the recording's rig says so
    assert sim_config(stressed_rig(StressScene())).markers.ideal
    for bad in ({"position_error_mm": -0.1}, {"burst_period_ms": -1.0}, {"missing_near_pct": 40, "missing_far_pct": 20}):
        with pytest.raises(LabrigError, match="stress scene"):
            StressScene(**bad).check()  # type: ignore[arg-type]


def test_a_printed_gel_needs_the_labs_intrinsics(tmp_path: Path) -> None:
    rig = stressed_rig(StressScene(missing_near_pct=2.0))
    with pytest.raises(LabrigError, match=r"no intrinsics\.toml"):
        calibrate_printed_markers(rig, tmp_path, tmp_path / "out")


class Runner:
    def __init__(self, cache: Path) -> None:
        self.cache = cache

    def __call__(self, kind: str, fn: Any, tasks: list[Any]) -> list[Any]:
        return list(run_tasks(fn, tasks, workers=1, cache_dir=self.cache))


@pytest.fixture(scope="module")
def suite(tmp_path_factory: pytest.TempPathFactory) -> StressResult:
    """The four axes on their tiny grids: five scenes (the short probe is every axis' baseline)."""
    axes = [replace(axis_named(key), reduced=TINY[key]) for key in SENSOR_AXES]
    return run_stress(Runner(tmp_path_factory.mktemp("sensor-stress")), grid="reduced", axes=axes, base=SHORT)


def test_every_sensor_axis_measures_every_method(suite: StressResult) -> None:
    assert {c.axis for c in suite.curves} == set(SENSOR_AXES)
    for c in suite.curves:
        assert np.all(np.isfinite(c.error)), (c.axis, c.method, c.error)
    methods = {c.method for c in suite.curves if c.axis == "missing_near"}
    assert methods == {"paper", "paper-published", "circle-fit", "evetac", "forces-truth", "forces-linear"}


def test_the_printed_gels_are_calibrated_and_every_missing_marker_found(suite: StressResult) -> None:
    position, near, far = (suite.scenes[key][1] for key in ("marker_position", "missing_near", "missing_far"))
    assert position.markers_missing == 0 and position.markers_missing_false == 0
    assert position.rest_error_rms_px < 0.3  # measured where printed (0.05 mm = 1.4 px std off the lattice)
    for facts in (near, far):
        assert facts.markers_missing == 6 == facts.markers_missing_found and facts.markers_missing_false == 0
    assert suite.scenes["usb_bursts"][1].markers_missing_found is None  # a perfect gel: the shipped calibration
    assert suite.scenes["marker_position"][0].markers_missing_found is None


def test_no_sensor_axis_breaks_the_bundled_tracker_or_the_forces_inside_its_tiny_grid(suite: StressResult) -> None:
    for b in suite.breakdowns:
        if b.method in ("paper", "forces-truth"):
            assert b.value is None, b
