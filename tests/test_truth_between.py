"""The sim's true depth between its solves: a linear blend in time, as the sim moves its markers."""

from __future__ import annotations

import numpy as np

from labrig.pipeline.depth_sources import truth_between


def test_times_between_solves_blend_the_two_maps_around_them() -> None:
    t_maps = np.array([0, 10, 30], np.int64)
    before, after, w = truth_between(t_maps, [-5, 0, 5, 10, 20, 30, 40])
    maps = np.array([0.0, 1.0, 3.0])
    blended = maps[before] * (1 - w) + maps[after] * w
    np.testing.assert_allclose(blended, [0.0, 0.0, 0.5, 1.0, 2.0, 3.0, 3.0])  # held at the ends


def test_one_map_serves_every_time() -> None:
    before, after, w = truth_between(np.array([7], np.int64), [0, 7, 100])
    assert before.tolist() == after.tolist() == [0, 0, 0] and w.tolist() == [0.0, 0.0, 0.0]
