"""The force monitor: limits trip once, an armed target fires once, baseline, peak and last sample."""

from __future__ import annotations

import math

import numpy as np
import pytest

from labrig.protocol.safety import ForceMonitor, SafetyLimits

LIMITS = SafetyLimits(max_normal_force_n=10.0, max_shear_force_n=3.0)


def monitor() -> tuple[ForceMonitor, list[str]]:
    calls: list[str] = []
    return ForceMonitor(LIMITS, on_trip=lambda: calls.append("trip")), calls


def test_normal_and_shear_limits_trip_once() -> None:
    m, calls = monitor()
    m.on_sample(1, (0.0, 0.0, -9.9))
    assert m.trip is None
    m.on_sample(2, (0.0, 0.0, -10.5))
    m.on_sample(3, (0.0, 0.0, -12.0))
    assert calls == ["trip"] and m.trip is not None and m.trip.t_host_ns == 2
    assert m.trip.force_n == (0.0, 0.0, -10.5) and "normal force" in m.trip.reason
    s, calls = monitor()
    s.on_sample(1, np.array([2.0, 2.5, 0.0]))  # |Fxy| = 3.2 N, as an array
    assert calls == ["trip"] and s.trip is not None and "shear force |Fxy| = 3.20 N" in s.trip.reason


def test_baseline_is_subtracted_before_the_limits() -> None:
    m, _calls = monitor()
    m.set_baseline([0.0, 0.0, -5.0])
    m.on_sample(1, (0.0, 0.0, -14.0))  # -9 N from the baseline
    assert m.trip is None and m.last_n.tolist() == [0.0, 0.0, -9.0]
    assert m.baseline_n.tolist() == [0.0, 0.0, -5.0]


def test_armed_target_fires_once_on_the_mean_of_the_last_samples() -> None:
    m, _ = monitor()
    fired: list[int] = []
    reached = m.arm("force", 2.0, lambda: fired.append(m.samples), average_samples=3)
    for i, fz in enumerate([-1.0, -3.0, -1.5, -1.0, -3.0, -3.0, -3.0]):
        m.on_sample(i, (0.1, 0.0, fz))
    assert fired == [6] and reached.is_set()  # the mean of 3 first exceeds 2 N at the sixth sample (7 / 3 N)
    assert m.reached_force_n == (0.1, 0.0, -3.0)


def test_peak_per_axis_restarts_on_assignment_and_keeps_a_nan() -> None:
    m, _ = monitor()
    for f in [(1.0, -2.0, 0.5), (-1.5, 1.0, -0.25)]:
        m.on_sample(0, f)
    assert m.peak_n.tolist() == [1.5, 2.0, 0.5] and m.samples == 2
    m.peak_n = np.zeros(3)
    m.on_sample(0, (0.25, 0.0, math.nan))
    m.on_sample(0, (0.0, 0.0, 1.0))
    assert m.peak_n[0] == 0.25 and math.isnan(m.peak_n[2])  # as np.maximum: a bad sample is not forgotten
    with pytest.raises(ValueError):
        m.peak_n = [1.0, 2.0]
