"""Presses held (labrig.evaluation.hold): the error at the start and at the end of a long wait, the force left after."""

from __future__ import annotations

import numpy as np
import pytest

from labrig.evaluation.forces import ForceResult
from labrig.evaluation.hold import force_after_release_n, held_presses, hold_summary

S = 1_000_000  # us per s


def _result(name: str, predicted_z: np.ndarray, measured_z: np.ndarray, t1_s: np.ndarray,
            phases: tuple[tuple[str, int, int], ...]) -> ForceResult:
    w = len(t1_s)
    t1 = (t1_s * S).astype(np.int64)
    zeros = np.zeros((w, 2))
    return ForceResult(
        t0_us=t1 - 10_000, t1_us=t1, predicted_n=np.column_stack([zeros, predicted_z]),
        measured_n=np.column_stack([zeros, measured_z]), truth_n=np.full((w, 3), np.nan),
        contact_error_px=np.full((w, 2), np.nan), marker_mae_n=np.full((w, 3), np.nan), probing=np.ones(w, bool),
        stage_ms=dict.fromkeys(("read", "sae", "track", "depth", "displacement", "forces"), 1.0), total_ms=6.0,
        drift_px=np.zeros(3), ft_axes="test", depth_source="model:x",
        youngs_modulus_mpa=0.4, recording=name, phases=phases)


# A 60 s hold after Normal Down (1-61 s), a 0.3 s wait after the shear, Normal Up ending at 63 s.
PHASES = (("normal_down", 0, 1 * S), ("wait", 1 * S, 61 * S), ("shear", 61 * S, 62 * S),
          ("wait", 62 * S, int(62.3 * S)), ("normal_up", int(62.3 * S), 63 * S), ("retract", 63 * S, 64 * S))


def _forgetting() -> ForceResult:
    """Measured -10 N all through the hold; the estimate fades from -9.5 N to -5 N, and holds -1 N after."""
    t = np.arange(0.05, 64.0, 0.1)
    measured = np.where((t > 1) & (t < 63), -10.0, 0.0)
    predicted = np.where((t > 1) & (t < 61), -9.5 + 4.5 * (t - 1) / 60, measured)
    predicted = np.where(t > 63, -1.0, predicted)
    return _result("fading.h5", predicted, measured, t, PHASES)


def test_a_fading_estimate_shows_as_a_larger_error_at_the_end_of_the_hold_and_a_force_left_after_release() -> None:
    (press,) = held_presses(_forgetting())
    assert press.wait_index == 0 and press.duration_s == pytest.approx(60.0) and press.measured_fz_n == pytest.approx(-10)
    assert press.fz_error_first_n == pytest.approx(0.5 + 4.5 * 2.5 / 60, abs=0.02)  # mean of the first 5 s
    assert press.fz_error_last_n == pytest.approx(0.5 + 4.5 * 57.5 / 60, abs=0.02)
    assert press.error_ratio_last_to_first == pytest.approx(7.0)
    assert force_after_release_n(_forgetting()) == pytest.approx(1.0)


def test_a_held_estimate_keeps_its_ratio_near_one_and_short_waits_are_not_held_presses() -> None:
    t = np.arange(0.05, 64.0, 0.1)
    measured = np.where((t > 1) & (t < 63), -10.0, 0.0)
    held = _result("held.h5", measured + 0.3, measured, t, PHASES)
    summary = hold_summary([held, _forgetting()])
    assert [p.recording for p in summary.presses] == ["held.h5", "fading.h5"]  # the 0.3 s waits are not held
    (press,) = held_presses(held)
    assert press.error_ratio_last_to_first == pytest.approx(1.0)
    assert summary.after_release_fz_n == pytest.approx((0.3 + 1.0) / 2)
    assert summary.error_ratio_last_to_first == pytest.approx(summary.fz_error_last_n / summary.fz_error_first_n)


def test_recordings_without_a_long_wait_give_no_presses_and_nan_figures() -> None:
    t = np.arange(0.05, 5.0, 0.1)
    short = (("wait", 1 * S, int(1.3 * S)), ("normal_up", 2 * S, 3 * S))
    summary = hold_summary([_result("short.h5", np.zeros(len(t)), np.zeros(len(t)), t, short)])
    assert summary.presses == () and np.isnan(summary.error_ratio_last_to_first) and np.isnan(summary.after_release_fz_n)
    assert np.isnan(force_after_release_n(_result("none.h5", np.zeros(len(t)), np.zeros(len(t)), t, ())))


def test_the_report_shows_the_held_presses_and_the_summary_carries_their_figures() -> None:
    from pathlib import Path

    from labrig.evaluation.evaluate import Evaluation, EvaluationSettings, headline
    from labrig.evaluation.report import Report
    from labrig.evaluation.report_sections import _forces_section

    ev = Evaluation(EvaluationSettings(Path("data")), [Path("fading.h5")], Path("m.onnx"), forces=[_forgetting()],
                    depth={"m.onnx": []})
    report = Report("test")
    _forces_section(report, ev)
    assert "hold" in report._keys["table"] and "hold_series" in report._keys["figure"]
    summary = headline(ev)
    assert summary["hold_presses"] == 1 and summary["hold_error_ratio_last_to_first"] == pytest.approx(7.0)
    assert summary["hold_fz_after_release_n"] == pytest.approx(1.0)
    assert summary["hold_fz_error_first_5s_n"] == pytest.approx(0.6875, abs=0.02)
