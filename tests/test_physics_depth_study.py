"""The depth-from-marker-motion study (tools/physics_depth_study.py): rest state and a synthetic off-axis press."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from labrig.config import DEFAULT_RIG, load_rig
from labrig.pipeline.run_setup import setup_for_rig

TOOL = Path(__file__).resolve().parent.parent / "tools" / "physics_depth_study.py"


@pytest.fixture(scope="module")
def study_module():
    spec = importlib.util.spec_from_file_location("physics_depth_study", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def estimator(study_module):
    return study_module.ParallaxDepth(setup_for_rig(load_rig(DEFAULT_RIG), calibration_dir=None))


def test_rest_state_gives_exactly_zero_depth(estimator) -> None:
    n_markers = len(estimator.rest_mm)
    depth = estimator.depth_map_mm(np.zeros((n_markers, 2)))
    assert depth.shape == (90, 112)
    assert not np.any(depth)


def test_off_axis_press_is_found_with_its_sign_place_and_depth(estimator) -> None:
    """Markers pressed by a smooth pressure patch 8 mm off the camera axis, seen through the camera
    (pure parallax: pressing moves no marker in-plane): the peak comes back within a pitch, at 0.6-1.1 of
    its depth (the dent sits between two marker rows: the markers alone under-resolve its peak)."""
    centre = np.array([8.0, 4.0])
    node_xy = estimator.node_xy_mm
    force = np.exp(-((node_xy - centre) ** 2).sum(1) / (2 * 1.0**2))
    node_depth = estimator.c_zz @ force
    node_depth *= 0.8 / node_depth.max()
    marker_depth = node_depth[estimator.markers]
    pressed = estimator.rest_mm - np.outer(marker_depth, [0.0, 0.0, 1.0])
    motion = estimator.camera.project(pressed) - estimator.camera.project(estimator.rest_mm)
    estimate = estimator.node_depth_mm(motion)
    peak = node_xy[int(np.argmax(estimate))]
    assert np.linalg.norm(peak - centre) <= 2.0
    assert 0.6 * 0.8 <= estimate.max() <= 1.1 * 0.8
    assert estimate.min() > -0.2  # no spurious dent of the wrong sign
    far = np.linalg.norm(node_xy - centre, axis=1) > 6.0
    assert np.abs(estimate[far]).max() < 0.1


def test_the_study_compares_its_four_depth_sources_on_a_recording(study_module, tmp_path: Path, rig, sphere) -> None:
    """The study's own run on a short virtual probe (its first windows): truth, the bundled network (built as
    the pipeline builds it, with the run's setup), and the estimator on tracked and on true pixels."""
    from labrig import models
    from labrig.dataset import sidecar_path
    from labrig.groundtruth import generate, write_sidecar
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    out = tmp_path / "probe.h5"
    tool = probing_path(rig, sphere, location_mm=(6.0, -4.0), depth_mm=1.0, shear_mm=0.3, normal_speed_mm_s=4.0,
                        shear_speed_mm_s=4.0, wait_s=0.05, approach_mm=0.2)
    record_live(out, rig, sphere, tool, seed=3, realtime=False)
    write_sidecar(generate(out, rate_hz=100), sidecar_path(out))
    rows = study_module.study(out, str(models.bundled_model_path()), max_windows=6)
    assert [r.source for r in rows] == ["truth", f"model:{models.bundled_model_path().stem}", "physics (tracked px)",
                                        "physics (true px)"]
    assert all(np.isfinite(r.depth_total_mm) and np.all(np.isfinite(r.force_mae_n)) for r in rows)
    assert rows[0].depth_total_mm < 0.01  # the sim's own depth against its ground truth
