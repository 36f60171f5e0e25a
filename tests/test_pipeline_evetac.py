"""Evetac's published tracker: each rule of the algorithm pinned on hand-made events, and a moving dot tracked."""

from __future__ import annotations

import numpy as np
import pytest

from labrig.eventtypes import EVENT_DTYPE
from labrig.pipeline.evetac import (
    STEP,
    EvetacParams,
    EvetacTracker,
    Geometry,
    background_activity,
    neighbour_links,
)

D = 20.0  # dot size, px: band (9, 20], pull radius 25 px, clip 320 units
PITCH = 60.0


def single(**kw: object) -> EvetacTracker:
    """One dot at (100, 100), no noise filter unless asked."""
    settings = {"marker_diameter_px": D, "pitch_px": PITCH, "grid_rows": 1, "grid_cols": 1, "ba_window_us": None} | kw
    return EvetacTracker([[100.0, 100.0]], EvetacParams(**settings))  # type: ignore[arg-type]


def events(xy: list[tuple[float, float]] | np.ndarray, t_us: int | np.ndarray = 0) -> np.ndarray:
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    ev = np.zeros(len(xy), EVENT_DTYPE)
    ev["x"], ev["y"], ev["p"] = xy[:, 0], xy[:, 1], 1
    ev["t"] = t_us
    return ev


def move_of(tracker: EvetacTracker, ev: np.ndarray) -> np.ndarray:
    before = tracker.positions_px.copy()
    after, _ = tracker.update(ev)
    return after - before


def test_the_published_constants_carry_over_by_dot_size_and_pitch() -> None:
    geo = Geometry.for_rig(25.0, 61.5)  # Evetac's own geometry: its constants unchanged
    assert (geo.inner_px, geo.outer_px, geo.pull_radius_px, geo.clip) == pytest.approx((25 - 13.75, 25, 31.25, 400))
    assert geo.spring_gain == pytest.approx(7.5e-5) and geo.neighbour_cutoff_px == pytest.approx(105)
    small = Geometry.for_rig(12.5, 30.75)
    assert (small.inner_px, small.outer_px, small.clip) == pytest.approx((0.45 * 12.5, 12.5, 200))
    assert small.spring_gain == pytest.approx(4 * 7.5e-5) and small.neighbour_cutoff_px == pytest.approx(52.5)
    assert pytest.approx(1.2) == STEP * 400  # px per axis per slice at most, at Evetac's scale


def test_only_events_in_the_ring_band_pull() -> None:
    for dx, pulls in ((8.0, False), (10.0, True), (20.0, True), (21.0, False), (4.0, False)):  # band (9, 20]
        moved = move_of(single(), events([(100 + dx, 100)] * 12))
        assert bool(moved[0, 0] > 0) is pulls, dx
        assert moved[0, 1] == 0.0


def test_the_pull_is_toward_the_event_and_falls_with_distance() -> None:
    for dx in (10.0, 14.0, 18.0):  # 10 events, one non-zero component each: exactly the threshold
        moved = move_of(single(), events([(100 + dx, 100)] * 10))
        assert moved[0, 0] == pytest.approx(STEP * 10 * 2 * (25 - dx))  # below the clip
        left = move_of(single(), events([(100 - dx, 100)] * 10))
        assert left[0, 0] == pytest.approx(-moved[0, 0])
    near, far = (move_of(single(), events([(100 + dx, 100)] * 10))[0, 0] for dx in (10.0, 18.0))
    assert near > 2 * far > 0


def test_each_axis_sum_is_clipped_on_its_own() -> None:
    clip = 400 * D / 25
    moved = move_of(single(), events([(110, 110)] * 200))  # diagonal, far above the clip on both axes
    assert moved[0] == pytest.approx([STEP * clip, STEP * clip])
    lopsided = move_of(single(), events([(111, 100)] * 200 + [(100, 110)] * 8))  # x clipped, y not
    assert lopsided[0, 0] == pytest.approx(STEP * clip)
    assert lopsided[0, 1] == pytest.approx(STEP * 8 * 2 * (25 - 10))


def test_a_dot_moves_only_above_an_activity_threshold_growing_with_the_slice() -> None:
    assert [EvetacParams(slice_us=ms * 1000).activity_threshold for ms in range(1, 6)] == [10, 13, 16, 19, 22]
    diagonal = (108.0, 108.0)  # two non-zero components per event
    assert not move_of(single(), events([diagonal] * 4)).any()  # 8 < 10
    assert move_of(single(), events([diagonal] * 5)).all()  # 10
    assert not move_of(single(slice_us=2000), events([diagonal] * 6)).any()  # 12 < 13 in a 2 ms slice
    assert move_of(single(slice_us=2000), events([diagonal] * 7)).all()  # 14
    spread = events([diagonal] * 8, t_us=np.repeat([0, 1000], 4))  # 8 events over two 1 ms slices: 8 < 10 in each
    assert not move_of(single(), spread).any()
    with pytest.raises(ValueError, match="slice_us"):
        EvetacParams(slice_us=1500)


def test_neighbour_springs_act_only_on_moving_dots() -> None:
    rest = [[100.0, 100.0], [160.0, 100.0], [220.0, 100.0]]
    params = EvetacParams(marker_diameter_px=D, pitch_px=PITCH, grid_rows=1, grid_cols=3, ba_window_us=None)
    stretched = [[100.0, 100.0], [166.0, 100.0], [220.0, 100.0]]  # the middle dot 6 px right: both links strained
    burst = events([(112.0, 100.0)] * 10)  # activity on the first dot only

    with_springs = EvetacTracker(rest, params)
    with_springs.reset(stretched)
    after, moved = with_springs.update(burst)
    assert moved.tolist() == [True, False, False]
    np.testing.assert_array_equal(after[1:], np.asarray(stretched)[1:])  # strained, but quiet: no spring
    without = EvetacTracker(rest, EvetacParams(**{**params.__dict__, "springs": False}))
    without.reset(stretched)
    plain, _ = without.update(burst)
    link = 66.0**2 - 60.0**2  # |c1 - c0|^2 - d0^2, px^2
    spring = STEP * with_springs.geometry.spring_gain * (8 / 1) * 4 * 66.0 * link  # toward the stretched neighbour
    assert after[0, 0] - plain[0, 0] == pytest.approx(spring)
    assert after[0, 1] == plain[0, 1] == 100.0


def test_neighbours_are_the_8_neighbourhood_under_the_scaled_cutoff() -> None:
    r, c = np.divmod(np.arange(12), 4)
    rest = np.stack([c * PITCH, r * PITCH], 1).astype(float)
    neigh, rest_d2, correction = neighbour_links(rest, Geometry.for_rig(D, PITCH).neighbour_cutoff_px)
    counts = (neigh >= 0).sum(1)
    assert counts[5] == 8 and counts[0] == 3 and counts[1] == 5
    assert correction[0] == pytest.approx(8 / 3)
    assert sorted(rest_d2[5][neigh[5] >= 0]) == pytest.approx([PITCH**2] * 4 + [2 * PITCH**2] * 4)


def test_the_background_activity_filter_runs_first() -> None:
    surface = np.full((10, 10), np.iinfo(np.int64).min // 2, np.int64)
    ev = events([(5, 5), (5, 5), (6, 5), (2, 2), (7, 5), (9, 9)], t_us=np.array([0, 10, 20, 30, 200_000, 200_010]))
    keep = np.zeros(len(ev), np.bool_)
    background_activity(ev["x"], ev["y"], ev["t"], surface, np.int64(100_000), keep)
    # own pixel: no support; neighbour within 100 ms: kept; isolated: dropped; the neighbour 200 ms old: dropped
    assert keep.tolist() == [False, False, True, False, False, False]
    assert surface[5, 5] == 10 and surface[5, 7] == 200_000  # every event stamps its pixel, kept or not

    isolated = [(112.0, 96.0), (112.0, 99.0), (112.0, 102.0), (112.0, 105.0), (115.0, 92.0), (115.0, 108.0)]  # 2 px apart
    noisy = events(isolated * 1)  # in the band on the right: a pull without the filter, none with it
    assert move_of(single(), noisy).any()
    assert not move_of(single(ba_window_us=100_000), noisy).any()
    supported = events([(112.0, 100.0), (112.0, 101.0)] * 6, t_us=np.arange(12))
    assert move_of(single(ba_window_us=100_000), supported)[0, 0] > 0  # neighbouring pixels support each other


def rim_events(centre: np.ndarray, t0_us: int, rng: np.random.Generator, n: int = 24, radius: float = 10.0) -> np.ndarray:
    angle = rng.uniform(0, 2 * np.pi, n)
    xy = centre + radius * np.stack([np.cos(angle), np.sin(angle)], 1) + rng.normal(0, 0.5, (n, 2))
    return events(np.rint(xy), t_us=np.sort(rng.integers(t0_us, t0_us + 1000, n)))


def test_a_moving_dot_is_tracked() -> None:
    """A dot of D = 20 px (rim at 10 px) moving 40 px at 200 px/s, then resting: rim events every ms."""
    rng = np.random.default_rng(1)
    tracker = single(ba_window_us=100_000)
    errors = []
    for window in range(30):  # 10 ms windows
        slices = []
        for ms in range(10):
            t = window * 10 + ms
            true = np.array([100.0 + 0.2 * min(t, 200), 100.0 + 0.05 * min(t, 200)])
            slices.append(rim_events(true, t * 1000, rng))
        positions, moved = tracker.update(np.concatenate(slices))
        errors.append(np.linalg.norm(positions[0] - true))
    assert max(errors) < 3.0 and errors[-1] < 1.0  # px, against 42 px of travel
    assert moved.all()


def test_missing_markers_are_skipped_and_follow_their_neighbours() -> None:
    rest = [[100.0, 100.0], [160.0, 100.0], [220.0, 100.0]]
    params = EvetacParams(marker_diameter_px=D, pitch_px=PITCH, grid_rows=1, grid_cols=3, ba_window_us=None)
    on_middle = events([(172.0, 100.0)] * 12)  # in the middle dot's band only
    full = EvetacTracker(rest, params)
    assert full.update(on_middle)[1].tolist() == [False, True, False]
    holed = EvetacTracker(rest, params, observed=[True, False, True])
    after, moved = holed.update(on_middle)
    assert not moved.any()  # a missing dot's events pull nobody
    np.testing.assert_array_equal(after, rest)
    after, moved = holed.update(events([(112.0, 100.0)] * 12))  # the first dot moves right
    assert moved.tolist() == [True, False, False]
    shift = after[0, 0] - 100.0
    assert shift > 0
    assert after[1] == pytest.approx([160.0 + shift / 2, 100.0])  # the mean of its observed neighbours' moves
    with pytest.raises(ValueError, match="observed mask"):
        EvetacTracker(rest, params, observed=[True, False])


def test_the_pitch_and_springs_come_from_the_observed_dots() -> None:
    r, c = np.divmod(np.arange(12), 4)
    rest = np.stack([c * PITCH, r * PITCH], 1).astype(float) + 100
    params = EvetacParams(marker_diameter_px=D, grid_rows=3, grid_cols=4, ba_window_us=None)
    observed = np.ones(12, bool)
    observed[5] = False
    holed = EvetacTracker(rest, params, observed=observed)
    assert holed.geometry.neighbour_cutoff_px == pytest.approx(105 / 61.5 * PITCH)
    # 11 dots (marker 5 left out); 8-neighbourhood counts of a 3x4 grid, less one for each neighbour of the hole
    assert (holed._neigh >= 0).sum(1).tolist() == [2, 4, 4, 3, 4, 7, 5, 2, 4, 4, 3]
