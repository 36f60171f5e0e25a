"""Rigid transforms."""

from __future__ import annotations

import numpy as np
import pytest

from labrig.frames import Pose, matrix_to_rotvec, rotvec_to_matrix, wrench_about, yaw_tilt_matrix


@pytest.mark.parametrize("rotvec", [[0, 0, 0], [0.1, -0.2, 0.3], [3.14, 0.0035, -0.0052], [0, np.pi, 0]])
def test_rotvec_round_trip(rotvec: list[float]) -> None:
    m = rotvec_to_matrix(rotvec)
    assert np.allclose(m @ m.T, np.eye(3)) and np.isclose(np.linalg.det(m), 1.0)
    assert np.allclose(rotvec_to_matrix(matrix_to_rotvec(m)), m, atol=1e-9)


def test_pose_inverse_and_compose() -> None:
    a = Pose(rotvec_to_matrix([0.1, 0.2, -0.3]), np.array([1.0, -2.0, 3.0]))
    b = Pose(yaw_tilt_matrix(30.0, (1.0, -2.0)), np.array([0.5, 0.0, -4.0]))
    p = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, 9.0]])
    assert np.allclose(a.inverse().apply(a.apply(p)), p)
    assert np.allclose(a.compose(b).apply(p), a.apply(b.apply(p)))
    assert np.allclose(yaw_tilt_matrix(90.0) @ [1, 0, 0], [0, 1, 0])


def test_torque_of_a_force_off_axis() -> None:
    # 10 N down (-z) applied 20 mm along +x from the origin: torque +0.2 N m about +y.
    assert np.allclose(wrench_about([0, 0, -10.0], [20.0, 0, 0], [0, 0, 0]), [0, 0.2, 0])
