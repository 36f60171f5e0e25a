"""The normal-force loop against a simulated gel: a Hertz spring, the feedback's delay, the segments' hold."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.protocol.force_loop import ForceLoop, ForceLoopParams, hold_rms_n, step_response

HERTZ_N_PER_MM_1_5 = 6.0  # F = c d^1.5: about 8.5 N/mm at 5 N, as the shipped sphere on the default gel


def _run(loop: ForceLoop, seconds: float, *, delay_s: float = 0.01, period_s: float = 0.002,
         unload_mm_s: float = 0.0, max_force_n: float = math.inf, stall_after_s: float = math.inf,
         start_depth_mm: float = 0.02) -> tuple[np.ndarray, np.ndarray, list[str | None]]:
    """The gel pressed by ``loop``'s commands: a reading every ``period_s`` (the force ``delay_s`` ago), each command
    held until the next; ``unload_mm_s``: the load drifts off (a shear unloading the normal); readings stop arriving
    after ``stall_after_s``. Returns times (s), true forces (N) and the stops."""
    dt = 0.0005
    steps = round(seconds / dt)
    per_reading = round(period_s / dt)
    depth = start_depth_mm
    speed = 0.0
    forces = np.zeros(steps)
    stops: list[str | None] = []
    for k in range(steps):
        t = k * dt
        forces[k] = min(HERTZ_N_PER_MM_1_5 * max(depth - unload_mm_s * t, 0.0) ** 1.5, max_force_n)
        if k % per_reading == 0:
            seen_t = min(t, stall_after_s)
            seen = forces[max(round((seen_t - delay_s) / dt), 0)]
            command = loop.update(t, float(seen), reading_t_s=seen_t)
            speed = command.speed_mm_s
            stops.append(command.stop)
        depth += speed * dt
    return np.arange(steps) * dt, forces, stops


def test_a_step_to_5_n_settles_without_overshoot_within_half_a_second() -> None:
    t, f, stops = _run(ForceLoop(5.0), 1.5)
    response = step_response(t, f, 5.0, start_n=0.0)
    assert response.overshoot_pct <= 10.0 and response.settling_s <= 0.5, response
    assert not any(stops)
    assert abs(f[-1] - 5.0) < 0.05


def test_the_integral_holds_the_force_while_a_shear_unloads_it() -> None:
    t, f, _ = _run(ForceLoop(5.0), 3.0, unload_mm_s=0.2)
    held = f[t > 1.0]
    assert hold_rms_n(held, 5.0) <= 0.3
    p_only, _, _ = _run(ForceLoop(5.0, ForceLoopParams(ki_mm_s_per_n_s=0.0)), 3.0, unload_mm_s=0.2)
    assert hold_rms_n(held, 5.0) < hold_rms_n(p_only[t > 1.0], 5.0)


def test_a_stalled_reading_stops_the_loop_and_it_stays_stopped() -> None:
    loop = ForceLoop(5.0)
    _, _, stops = _run(loop, 0.5, stall_after_s=0.2)
    first = next(i for i, s in enumerate(stops) if s)
    assert 0.2 <= first * 0.002 <= 0.2 + 0.02 + 0.004
    assert "stalled" in stops[first] and all(stops[first:])  # type: ignore[operator]
    assert loop.update(1.0, 5.0).speed_mm_s == 0.0


def test_an_unreachable_target_trips_as_saturated() -> None:
    _, _, stops = _run(ForceLoop(5.0, ForceLoopParams(saturation_s=1.0)), 2.0, max_force_n=3.0)
    reasons = [s for s in stops if s]
    assert reasons and "saturated" in reasons[0]


def test_gains_too_high_for_the_delay_trip_as_oscillating() -> None:
    params = ForceLoopParams(kp_mm_s_per_n=20.0, max_speed_mm_s=50.0)
    _, _, stops = _run(ForceLoop(5.0, params), 2.0, delay_s=0.05)
    first = next(i for i, s in enumerate(stops) if s)
    assert "oscillating" in stops[first] and first * 0.002 < 0.5  # type: ignore[operator]
    # the gains of the other tests, on the same delay, do not trip
    assert not any(_run(ForceLoop(5.0), 2.0, delay_s=0.05)[2])


@settings(max_examples=25, deadline=None)
@given(target=st.floats(1.0, 12.0), delay_ms=st.floats(0.0, 15.0))
def test_targets_and_delays_a_lab_uses_settle(target: float, delay_ms: float) -> None:
    t, f, stops = _run(ForceLoop(target), 2.0, delay_s=delay_ms / 1000)
    assert not any(stops)
    assert step_response(t, f, target, start_n=0.0).overshoot_pct <= 10.0
    assert abs(f[-1] - target) < 0.02 * target


def test_step_response_reads_a_first_order_curve() -> None:
    tau = 0.1
    t = np.linspace(-0.1, 2.0, 21001)
    f = np.where(t < 0, 1.0, 1.0 + 4.0 * (1 - np.exp(-np.clip(t, 0, None) / tau)))
    r = step_response(t, f, 5.0)
    assert r.start_n == 1.0 and r.overshoot_pct == 0.0
    assert r.rise_s == pytest.approx(tau * math.log(9), abs=2e-3)
    assert r.settling_s == pytest.approx(tau * math.log(20), abs=2e-3)
    assert math.isnan(step_response([0.0, 1.0], [0.0, 1.0], 5.0).settling_s)
    assert hold_rms_n([4.0, 6.0], 5.0) == 1.0


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="kp_mm_s_per_n"):
        ForceLoopParams(kp_mm_s_per_n=0.0)
    with pytest.raises(ValueError, match="ki_mm_s_per_n_s"):
        ForceLoopParams(ki_mm_s_per_n_s=-1.0)
    with pytest.raises(ValueError, match="target"):
        ForceLoop(-1.0)
    with pytest.raises(ValueError, match="step"):
        step_response([0.0, 1.0], [1.0, 1.0], 1.0)


def test_a_held_move_goes_along_the_plane_and_never_past_its_deepest_point() -> None:
    from labrig.protocol.force_loop import HeldMove

    normal = (0.0, 0.0, -1.0)  # pressing in is -z
    held = HeldMove((0.0, 0.0, -10.0), (1.0, 0.0, -12.0), normal, 1.0, ForceLoop(5.0), deepest_mm=(0.0, 0.0, -10.05))
    assert held.segments == 100
    ends = []
    t = 0.0
    while (out := held.next_segment(t, 0.0)) is not None:  # no force: the loop presses in at full speed
        assert not isinstance(out, str)
        end, feed_mm_min = out
        assert feed_mm_min > 0
        ends.append(end)
        t += 0.01
    ends_mm = np.array(ends)
    np.testing.assert_allclose(ends_mm[-1, :2], (1.0, 0.0), atol=1e-12)  # the target's place, its depth ignored
    assert ends_mm[:, 2].min() == pytest.approx(-10.05) and np.all(np.diff(ends_mm[:, 0]) > 0)
