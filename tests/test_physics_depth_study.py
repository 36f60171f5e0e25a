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
def estimator():
    spec = importlib.util.spec_from_file_location("physics_depth_study", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module.ParallaxDepth(setup_for_rig(load_rig(DEFAULT_RIG), calibration_dir=None))


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

