"""The normal-force loop against a simulated gel (a Hertz spring) pressed by GRBL's planner (the motion timeline the
virtual CNC runs), the feedback late by a delay."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.devices.motion_profile import MachineLimits, MotionTimeline, make_block
from labrig.evaluation.control import hold_rms_n, step_response
from labrig.protocol.force_loop import ForceLoop, ForceLoopParams, HeldMove

HERTZ_N_PER_MM_1_5 = 6.0  # F = c d^1.5: about 8.5 N/mm at 5 N, as the shipped sphere on the default gel
NORMAL = (0.0, 0.0, -1.0)  # pressing in is -z


def _run(loop: ForceLoop, seconds: float, *, delay_s: float = 0.005, accel_mm_s2: float = 50.0,
         stiffness: float = HERTZ_N_PER_MM_1_5, power: float = 1.5, unload_mm_s: float = 0.0,
         max_force_n: float = math.inf, stall_after_s: float = math.inf, deepest_mm: float = -3.0,
         lateral_mm: float = 0.0, stamped_late: bool = True) -> tuple[np.ndarray, np.ndarray, list[str | None]]:
    """A held move of ``seconds`` from the contact point (z 0) on a gel ``F = stiffness d**power`` (``unload_mm_s``:
    the load drifts off, a shear unloading the normal): segments sent every ``segment_s`` one ahead into GRBL's
    planner (acceleration ``accel_mm_s2``), the loop reading the force ``delay_s`` ago (and nothing new after
    ``stall_after_s``; ``stamped_late`` False: the readings claim to be fresh). Returns times (s), true forces (N,
    every 0.5 ms) and the stops."""
    limits = MachineLimits(accel_mm_s2=(accel_mm_s2,) * 3)
    timeline = MotionTimeline(limits, (0.0, 0.0, 0.0), 0.0)
    held = HeldMove((0.0, 0.0, 0.0), (lateral_mm, 0.0, 0.0), NORMAL, 1.0 if lateral_mm else 2.0, loop,
                    (0.0, 0.0, deepest_mm), accel_mm_s2=accel_mm_s2, duration_s=seconds)

    def force(t_s: float) -> float:
        depth = -timeline.position_at(t_s * 1e6)[2] - unload_mm_s * t_s
        return min(stiffness * max(depth, 0.0) ** power, max_force_n)

    segment_us = round(loop.params.segment_s * 1e6)
    times, forces, stops = [], [], []
    t_us = 0
    while True:
        seen_s = min(max(t_us / 1e6 - delay_s, 0.0), stall_after_s)
        stamp_s = seen_s if stamped_late else t_us / 1e6
        out = held.next_segment(t_us / 1e6, force(seen_s), timeline.position_at(t_us), stamp_s,
                                timeline.position_at(stamp_s * 1e6))
        stops.append(out if isinstance(out, str) else None)
        if out is None or isinstance(out, str):
            break
        block = make_block(timeline.tail_mm, tuple(out[0]), out[1], limits)
        if block is not None:
            timeline.append(block, t_us)
            timeline.start(t_us)
        for k in range(segment_us // 500):
            times.append((t_us + 500 * k) / 1e6)
            forces.append(force(times[-1]))
        t_us += segment_us
        timeline.advance(t_us)
    return np.array(times), np.array(forces), stops


def test_a_step_to_5_n_settles_without_overshoot_within_half_a_second() -> None:
    t, f, stops = _run(ForceLoop(5.0), 1.5)
    response = step_response(t, f, 5.0, start_n=0.0)
    assert response.overshoot_pct <= 10.0 and response.settling_s <= 0.5, response
    assert not any(stops)
    assert abs(f[-1] - 5.0) < 0.05


def test_the_force_is_held_while_a_shear_unloads_it() -> None:
    t, f, stops = _run(ForceLoop(5.0), 3.0, unload_mm_s=0.2, lateral_mm=2.0)
    assert not any(stops)
    assert hold_rms_n(f[t > 1.0], 5.0) <= 0.1


def test_a_stiffer_contact_than_assumed_is_measured_and_still_not_overshot() -> None:
    """A flat punch on a stiff gel, 60 N/mm, four times the setting: the secant measured between readings raises
    the stiffness the loop assumes."""
    loop = ForceLoop(10.0, ForceLoopParams(stiffness_n_per_mm=15.0))
    t, f, stops = _run(loop, 1.5, stiffness=60.0, power=1.0)
    assert not any(stops)
    assert step_response(t, f, 10.0, start_n=0.0).overshoot_pct <= 10.0
    assert loop.stiffness_n_per_mm >= 60.0


def test_a_slow_cnc_is_not_overshot_either() -> None:
    """GRBL's default acceleration, 10 mm/s**2: the segments never ask more than a stop allows."""
    t, f, stops = _run(ForceLoop(5.0), 2.0, accel_mm_s2=10.0)
    assert not any(stops)
    assert step_response(t, f, 5.0, start_n=0.0).overshoot_pct <= 5.0 and abs(f[-1] - 5.0) < 0.1


def test_a_stalled_reading_stops_the_loop_and_it_stays_stopped() -> None:
    loop = ForceLoop(5.0)
    _, _, stops = _run(loop, 0.5, stall_after_s=0.2)
    assert stops[-1] is not None and "stalled" in stops[-1]
    stopped_at_s = (len(stops) - 1) * loop.params.segment_s
    assert 0.2 + 0.02 - 1e-9 <= stopped_at_s <= 0.2 + 0.02 + 0.01 + 1e-9
    assert loop.update(1.0, 5.0, 0.0).stop is not None


def test_an_unreachable_target_trips_as_saturated() -> None:
    _, _, stops = _run(ForceLoop(5.0, ForceLoopParams(saturation_s=0.5)), 2.0, max_force_n=3.0, deepest_mm=-1.5)
    assert stops[-1] is not None and "saturated" in stops[-1]


def test_a_feedback_later_than_its_stamps_trips_as_oscillating() -> None:
    """Readings 60 ms late that claim to be fresh, on a contact 30x stiffer than assumed: the goal swings across the
    target and the loop stops."""
    params = ForceLoopParams(stiffness_n_per_mm=2.0, oscillation_band_n=0.2)
    _, _, stops = _run(ForceLoop(5.0, params), 2.0, stiffness=60.0, power=1.0, delay_s=0.06, accel_mm_s2=500.0,
                       stamped_late=False)
    assert stops[-1] is not None and "oscillating" in stops[-1]


@settings(max_examples=15, deadline=None)
@given(target=st.floats(1.0, 12.0), delay_ms=st.floats(0.0, 15.0))
def test_targets_and_delays_a_lab_uses_settle(target: float, delay_ms: float) -> None:
    t, f, stops = _run(ForceLoop(target), 2.0, delay_s=delay_ms / 1000)
    assert not any(stops)
    assert step_response(t, f, target, start_n=0.0).overshoot_pct <= 10.0
    assert abs(f[-1] - target) < 0.02 * target


def test_an_error_well_beyond_the_scatter_is_acted_on_whole() -> None:
    told, clean = ForceLoop(5.0, ForceLoopParams(reading_noise_n=0.15)), ForceLoop(5.0)
    for loop in (told, clean):
        loop.update(0.0, 0.0, 0.0)
    far = told.update(0.01, 2.0, 0.0).goal_mm, clean.update(0.01, 2.0, 0.0).goal_mm
    assert far[0] == pytest.approx(far[1], rel=0.01)
    near = told.update(0.02, 4.9, 0.0).goal_mm, clean.update(0.02, 4.9, 0.0).goal_mm
    assert 0 < near[0] < 0.5 * near[1]


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
    with pytest.raises(ValueError, match="stiffness_n_per_mm"):
        ForceLoopParams(stiffness_n_per_mm=0.0)
    with pytest.raises(ValueError, match="acceleration"):
        HeldMove((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), NORMAL, 1.0, ForceLoop(1.0), accel_mm_s2=0.0)
    with pytest.raises(ValueError, match="target"):
        ForceLoop(-1.0)
    with pytest.raises(ValueError, match="step"):
        step_response([0.0, 1.0], [1.0, 1.0], 1.0)


def test_a_held_move_goes_along_the_plane_and_never_past_its_deepest_point() -> None:
    held = HeldMove((0.0, 0.0, -10.0), (1.0, 0.0, -12.0), NORMAL, 1.0, ForceLoop(5.0), deepest_mm=(0.0, 0.0, -10.05))
    assert held.segments == 100
    ends = []
    t = 0.0
    here = np.array([0.0, 0.0, -10.0])
    while (out := held.next_segment(t, 0.0, here)) is not None:  # no force: the loop presses in as far as allowed
        assert not isinstance(out, str)
        end, feed_mm_min = out
        assert feed_mm_min > 0
        ends.append(end)
        here = end  # an ideal machine
        t += 0.01
    ends_mm = np.array(ends)
    np.testing.assert_allclose(ends_mm[-1, :2], (1.0, 0.0), atol=1e-12)  # the target's place, its depth ignored
    assert ends_mm[:, 2].min() == pytest.approx(-10.05) and np.all(np.diff(ends_mm[:, 0]) > 0)
    speeds = np.diff(ends_mm[:, 2]) / 0.01
    assert np.all(np.abs(np.diff(speeds)) <= 10.0 * 0.01 + 1e-9)  # the normal speed changes by at most a dt


def test_a_hold_in_place_lasts_its_duration() -> None:
    held = HeldMove((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), NORMAL, 1.0, ForceLoop(5.0), duration_s=0.5)
    assert held.segments == 50 and held.place_mm((0.0, 0.0, -0.2)) == pytest.approx(0.2)


def _hold_on(loop: ForceLoop, reads, place_mm: float = 0.25, steps: int = 100,
             stiffness_n_per_mm: float = 20.0) -> list[float]:
    """``steps`` readings of a spring ``F = stiffness * place`` (N, place mm along the normal), the tool going to
    each goal at once; ``reads(true_n, peak_n)`` is what the feedback says. Returns the true forces."""
    true, peak = [], 0.0
    for k in range(steps):
        force = stiffness_n_per_mm * place_mm
        peak = max(peak, force)
        command = loop.update(k * 0.01, reads(force, peak), place_mm)
        assert command.stop is None, command.stop
        place_mm = command.goal_mm
        true.append(force)
    return true


def test_a_reading_that_cannot_see_the_unloading_backs_the_tool_off_once() -> None:
    """An event estimate reads a dent partly undone as it was (its pixels' dead band): here, the highest force so far
    and 0.3 N more. The loop backs off by what the first reading asked (0.3 N / 8 N/mm: 0.75 N on a 20 N/mm
    contact) and then holds, instead of walking the true force down reading after reading; an honest feedback (the
    F/T) goes on to the target as before."""
    blind = _hold_on(ForceLoop(5.0), lambda true, peak: peak + 0.3)
    assert blind[-1] == pytest.approx(5.0 - 20.0 * 0.3 / 8.0)
    assert blind[-50:] == [blind[-1]] * 50
    honest = _hold_on(ForceLoop(5.0), lambda true, peak: true, place_mm=0.3)
    assert abs(honest[-1] - 5.0) < 0.01


def test_on_the_step_a_late_reading_within_the_scatter_holds_the_tool_still_rather_than_turning_it_back() -> None:
    """A reading 0.4 N short, taken 0.04 mm back along the step: the whole error asks 0.05 mm in from there (8 N/mm),
    the part the scatter leaves 0.032 mm, behind the tool. On the step the tool holds still; once a reading has
    reached the target the same reading turns it back."""
    loop = ForceLoop(5.0, ForceLoopParams(reading_noise_n=0.3))
    trusted_mm = 0.4**3 / (0.4**2 + 0.3**2) / 8.0
    assert loop.update(0.0, 4.6, 0.0, place_now_mm=0.04).goal_mm == pytest.approx(0.04)
    assert loop.update(0.01, 4.6, 0.0, place_now_mm=0.06).goal_mm == pytest.approx(0.05)  # past the whole goal
    assert loop.update(0.02, 4.6, 0.0, place_now_mm=0.01).goal_mm == pytest.approx(trusted_mm)
    loop.update(0.03, 5.01, 0.0)
    assert loop.update(0.04, 4.6, 0.0, place_now_mm=0.04).goal_mm == pytest.approx(trusted_mm)


def test_a_scattered_reading_that_cannot_see_the_unloading_does_not_walk_the_force_down() -> None:
    """The same blind estimate, its readings scattered by 0.15 N (1 sigma) as an event estimate's are: a reading
    that fell by chance would pass for the unloading and start the next back-off, reading after reading, till the
    tool lifts off. Told the scatter (twice the readings' sigma: a back-off's first reading may itself be high),
    the loop calls a fall an unloading only once it stands out of the scatter."""
    def lowest(told_n: float, seed: int) -> float:
        rng = np.random.default_rng(seed)
        loop = ForceLoop(5.0, ForceLoopParams(reading_noise_n=told_n))
        return min(_hold_on(loop, lambda true, peak: peak + 0.3 + 0.15 * rng.standard_normal(), steps=200))

    assert all(lowest(0.3, seed) >= 5.0 - 20.0 * (0.3 + 3 * 0.15) / 8.0 for seed in range(6))
    assert np.mean([lowest(0.0, seed) for seed in range(6)]) < 0.0
    # told only the readings' own sigma, the back-offs still walk it down on most seeds
    assert sum(lowest(0.15, seed) < 2.5 for seed in range(6)) >= 4


def test_the_next_held_move_carries_the_back_off_on_for_the_same_target() -> None:
    """Its places are measured from its own start; a new target starts afresh."""
    first = ForceLoop(5.0)
    _hold_on(first, lambda true, peak: peak + 0.3, steps=3)
    start_1, start_2 = np.zeros(3), np.array([0.0, 0.0, -0.25])  # the second move starts 0.25 mm in (z down)
    moves = [HeldMove(start_1, start_1, NORMAL, 1.0, first, duration_s=0.1)]
    second = ForceLoop(5.0)
    moves.append(HeldMove(start_2, start_2, NORMAL, 1.0, second, duration_s=0.1, follows=moves[0]))
    assert first._backoff is not None and second._backoff is not None
    assert second._backoff[2] == pytest.approx(first._backoff[2] - 0.25)
    other = ForceLoop(3.0)
    HeldMove(start_2, start_2, NORMAL, 1.0, other, duration_s=0.1, follows=moves[0])
    assert other._backoff is None and other.stiffness_n_per_mm == first.stiffness_n_per_mm
