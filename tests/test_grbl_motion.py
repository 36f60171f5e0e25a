"""Trapezoidal planning shared by the GRBL twin and the driver's pose reconstruction."""

from __future__ import annotations

import math

import numpy as np
import pytest

from labrig.devices.motion_profile import (
    MachineLimits,
    MotionTimeline,
    Segment,
    junction_speed_mm_s,
    make_block,
    plan_speeds,
    positions_at,
    quantize_mm,
    trapezoid,
)

FAST = MachineLimits(max_rate_mm_min=(6000.0, 6000.0, 3000.0), accel_mm_s2=(500.0, 500.0, 250.0))


def covered(pieces: list[tuple[float, float, float]]) -> float:
    return sum(v * t + 0.5 * a * t * t for v, a, t in pieces)


def test_trapezoid_cruises_and_triangle_when_short() -> None:
    pieces = trapezoid(10.0, 0.0, 10.0, 0.0, 100.0)  # 0.5 mm to reach 10 mm/s
    assert [(v, a) for v, a, _ in pieces] == [(0.0, 100.0), (10.0, 0.0), (10.0, -100.0)]
    assert covered(pieces) == pytest.approx(10.0)
    assert sum(t for *_, t in pieces) == pytest.approx(0.1 + 0.9 + 0.1)
    short = trapezoid(0.25, 0.0, 10.0, 0.0, 100.0)  # peak sqrt(a L) = 5 mm/s
    assert len(short) == 2 and short[0][2] == pytest.approx(0.05) and covered(short) == pytest.approx(0.25)
    entered_fast = trapezoid(5.0, 20.0, 10.0, 0.0, 100.0)  # above nominal: slow down first
    assert entered_fast[0][1] < 0 and covered(entered_fast) == pytest.approx(5.0)
    assert trapezoid(0.0, 0.0, 10.0, 0.0, 100.0) == []


def test_blocks_respect_each_axis_and_drop_sub_step_moves() -> None:
    b = make_block((0, 0, 0), (10, 0, 10), 6000, FAST)
    assert b is not None
    assert b.nominal_mm_s == pytest.approx(50.0 * math.sqrt(2))  # Z (3000 mm/min) limits the diagonal
    assert b.accel_mm_s2 == pytest.approx(250.0 * math.sqrt(2))
    rapid = make_block((0, 0, 0), (10, 0, 0), None, FAST)
    assert rapid is not None and rapid.rapid and rapid.nominal_mm_s == pytest.approx(100.0)
    assert make_block((0, 0, 0), (0.001, 0, 0), 100, FAST) is None  # less than one step at 250 steps/mm
    assert quantize_mm((0.001, 0.003, -1.0021), (250, 250, 250)) == (0.0, 0.004, -1.004)


def test_junctions_straight_corner_reversal() -> None:
    a = make_block((0, 0, 0), (1, 0, 0), 6000, FAST)
    straight = make_block((1, 0, 0), (2, 0, 0), 6000, FAST)
    corner = make_block((1, 0, 0), (1, 1, 0), 6000, FAST)
    back = make_block((1, 0, 0), (0, 0, 0), 6000, FAST)
    assert a and straight and corner and back
    assert junction_speed_mm_s(a, straight, 0.01) == math.inf
    assert junction_speed_mm_s(a, back, 0.01) == 0.0
    s = math.sqrt(0.5)  # 90 degrees: sin(45 deg)
    assert junction_speed_mm_s(a, corner, 0.01) == pytest.approx(math.sqrt(500 * 0.01 * s / (1 - s)))
    speeds = plan_speeds([1.0, 1.0, 1.0], [50.0] * 3, [500.0] * 3, [0.0, math.inf, math.inf], 0.0)
    assert speeds[0][0] == 0.0 and speeds[-1][1] == 0.0
    assert speeds[0][1] == pytest.approx(math.sqrt(2 * 500 * 1.0)) and speeds[1][1] == pytest.approx(math.sqrt(2 * 500 * 1.0))


def test_timeline_runs_holds_resumes_and_keeps_history() -> None:
    tl = MotionTimeline(FAST)
    b = make_block((0, 0, 0), (20, 0, 0), 1200, FAST)  # 20 mm/s, 0.4 mm ramps
    assert b is not None
    tl.append(b, 0.0)
    assert tl.state == "queued"
    assert tl.start(0.0) and tl.state == "run"
    assert tl.next_event_us() == pytest.approx((0.04 + 0.96 + 0.04) * 1e6)
    tl.hold(500_000.0)  # at cruise: stops 0.4 mm further
    assert tl.state == "hold"
    stopped_at = tl.next_event_us()
    assert stopped_at == pytest.approx(540_000.0)
    tl.advance(600_000.0)
    assert tl.state == "held" and tl.position_mm[0] == pytest.approx(0.4 + 9.2 + 0.4)
    assert tl.resume(700_000.0) and tl.state == "run"
    tl.advance(5e6)
    assert tl.state == "idle" and tl.position_mm == (20.0, 0.0, 0.0)
    t = np.linspace(0, 3e6, 3001)
    x = tl.positions_at(t)[:, 0]
    v = np.diff(x) / np.diff(t) * 1e6
    assert x[0] == 0 and x[-1] == 20.0 and np.all(v >= -1e-9) and v.max() <= 20.0 + 1e-6
    assert np.all(x[(t >= 540_000) & (t <= 700_000)] == pytest.approx(10.0))
    segments = tl.segments()
    assert positions_at(segments, t) == pytest.approx(tl.positions_at(t))


def test_timeline_blends_collinear_blocks_and_cancel_flushes() -> None:
    tl = MotionTimeline(FAST)
    end = (0.0, 0.0, 0.0)
    for i in range(1, 6):
        b = make_block(end, (2.0 * i, 0, 0), 3000, FAST)
        assert b is not None
        end = b.end_mm
        tl.append(b, 0.0)
    tl.start(0.0)
    tl.advance(0.12e6)  # cruising at 50 mm/s through the junctions
    assert tl.speed_mm_s == pytest.approx(50.0) and len(tl.queue) >= 2
    tl.cancel(0.12e6)
    tl.advance(1e6)
    assert tl.state == "idle" and tl.queue == ()
    # The ramp up lost 2.5 mm against cruising all along, the ramp down adds 2.5 mm.
    assert tl.position_mm[0] == pytest.approx(50.0 * 0.12 - 0.05 * 50.0 + 2.5, abs=1e-6)
    tl.stop(2e6)
    tl.set_position((-1.0, -1.0, -1.0), 2e6)
    assert tuple(tl.positions_at(2e6)[0]) == (-1.0, -1.0, -1.0)
    assert tl.segments()[-1].tag == "jump"


def test_segment_algebra() -> None:
    seg = Segment(0.0, 1e6, (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), 2.0, 2.0)
    assert seg.distance_mm == 3.0 and seg.end_mm == (1.0, 3.0, 0.0) and seg.v_end_mm_s == 4.0 and seg.t_end_us == 1e6
    out = positions_at([seg], [-1.0, 0.5e6, 2e6], initial_mm=(9.0, 9.0, 9.0))
    assert out.tolist() == [[9.0, 9.0, 9.0], [1.0, 1.25, 0.0], [1.0, 3.0, 0.0]]


def test_shift_plan_moves_the_current_motion_in_time() -> None:
    def run(shift_us: float) -> MotionTimeline:
        tl = MotionTimeline(FAST)
        b = make_block((0, 0, 0), (10, 0, 0), 1200, FAST)
        assert b is not None
        tl.append(b, 1e6)
        tl.start(1e6)
        tl.advance(1.1e6)  # part of the move is history already
        assert tl.shift_plan(shift_us) == shift_us
        return tl

    reference = run(0.0)
    t = np.linspace(0.9e6, 2e6, 500)
    for shift_us in (-700.0, 1500.0):
        shifted = run(shift_us)
        assert shifted.positions_at(t + shift_us) == pytest.approx(reference.positions_at(t), abs=1e-9)
    assert run(-5e6).segments()[0].t_start_us == pytest.approx(1e6 - 5e6)  # nothing before the motion to protect


def test_a_long_run_of_jogs_keeps_every_position_and_looks_it_up_the_same_either_way() -> None:
    """Hundreds of short moves (a force loop's jogs every 10 ms) grow the history past its first allocation; every
    time reads the same position from the vectorised and the one-time lookup, and from a table built afresh from
    the segments (history and plan alike)."""
    tl = MotionTimeline(FAST)
    t_us, x = 1e6, 0.0
    for k in range(300):
        b = make_block((x, 0, 0), (x + 0.02 * (1 + k % 3), 0.01 * (k % 2), 0), 600, FAST)
        assert b is not None
        x = b.end_mm[0]
        tl.append(b, t_us)
        if k == 0:
            tl.start(t_us)
        t_us += 10_000
        tl.advance(t_us)
        tl.position_at(t_us)  # lookups between the moves, as the twins' samplers make them
    times = np.linspace(0.5e6, t_us + 0.5e6, 997)
    vectorised = tl.positions_at(times)
    one_by_one = np.array([tl.position_at(float(t)) for t in times])
    afresh = positions_at(tl.segments(), times, (0.0, 0.0, 0.0))
    assert len(tl.segments(include_plan=False)) > 16  # past the table's first allocation
    np.testing.assert_array_equal(vectorised, one_by_one)
    np.testing.assert_array_equal(vectorised, afresh)
