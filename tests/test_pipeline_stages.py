"""SAE, 3D displacements, forces and contact location (the stages around the tracker and the iFEM)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.config import RigConfig
from labrig.eventtypes import EVENT_DTYPE
from labrig.physics.grid import network_grid_pixels
from labrig.pipeline import sae
from labrig.pipeline.displacement import displacements_mm, marker_positions_mm, sample_grid
from labrig.pipeline.forces import contact_location, forces_from_displacements, net_force_n
from labrig.sim.truth_config import true_camera


def _events(rows: list[tuple[int, int, int, int]]) -> np.ndarray:
    ev = np.zeros(len(rows), EVENT_DTYPE)
    for name, col in zip(("x", "y", "p", "t"), zip(*rows)):
        ev[name] = col
    return ev


def test_sae_keeps_the_latest_event_per_pixel_and_polarity(rig: RigConfig) -> None:
    ev = _events([(10, 5, 1, 1000), (10, 5, 1, 7000), (10, 5, 0, 3000), (11, 5, 1, 11000), (2000 % 1280, 719, 0, 9999)])
    s = sae.sae_pixels(ev, 1000, 11000)
    assert s.shape == (2, 720, 1280) and s.dtype == np.float32
    assert s[1, 5, 10] == pytest.approx(0.6) and s[0, 5, 10] == pytest.approx(0.2)
    assert s[1, 5, 11] == 1.0  # clipped to the window
    assert s[0, 719, 2000 % 1280] == pytest.approx(0.8999)
    assert s.sum() == pytest.approx(0.6 + 0.2 + 1.0 + 0.8999)
    roi = sae.sae_roi(ev, 1000, 11000, rig.roi)
    assert roi.shape == (2, rig.roi.height_px, rig.roi.width_px) and roi.max() == 0.0  # all outside the ROI
    with pytest.raises(ValueError):
        sae.sae_pixels(ev, 5, 5)


def test_grid_sae_is_the_max_pooled_roi_sae(rig: RigConfig) -> None:
    rng = np.random.default_rng(1)
    n = 20_000
    roi = rig.roi
    ev = np.zeros(n, EVENT_DTYPE)
    ev["x"] = rng.integers(roi.x0_px - 5, roi.x1_px + 5, n)
    ev["y"] = rng.integers(roi.y0_px - 5, roi.y1_px + 5, n)
    ev["p"] = rng.integers(0, 2, n)
    ev["t"] = np.sort(rng.integers(0, 10_000, n))
    grid = sae.sae_grid(ev, 0, 10_000, roi)
    assert grid.shape == (2, 90, 112)
    assert np.array_equal(grid, sae.resize_to_grid(sae.sae_roi(ev, 0, 10_000, roi)))
    # An event at a grid cell's centre pixel lands in that cell.
    centre = np.rint(network_grid_pixels(rig)[40, 60]).astype(int)
    one = sae.sae_grid(_events([(centre[0], centre[1], 1, 5000)]), 0, 10_000, roi)
    assert one[1, 40, 60] == pytest.approx(0.5)
    padded = sae.pad_for_unet(grid)
    assert padded.shape == (2, 96, 112) and np.array_equal(sae.crop_from_unet(padded), grid)


def test_displacements_recover_a_known_3d_motion(rig: RigConfig) -> None:
    camera = true_camera(rig)
    rest = rig.markers.rest_positions_mm()
    r2 = (rest[:, :2] ** 2).sum(1)
    true_u = np.stack([0.3 * np.exp(-r2 / 30), -0.1 * np.exp(-r2 / 30), -1.0 * np.exp(-r2 / 10)], axis=1)
    px = camera.project(rest + true_u)
    u = displacements_mm(px, -true_u[:, 2], camera, rest, rig.roi)
    assert np.abs(u - true_u).max() < 1e-9
    assert np.abs(displacements_mm(camera.project(rest), 0.0, camera, rest, rig.roi)).max() < 1e-9
    assert np.allclose(marker_positions_mm(px, -true_u[:, 2], camera)[:, 2], true_u[:, 2])


def test_depth_maps_are_sampled_at_the_markers(rig: RigConfig) -> None:
    centres = network_grid_pixels(rig)
    grid = np.add.outer(np.arange(90) * 0.01, np.arange(112) * 0.001)  # bilinear, so sampling is exact
    assert np.allclose(sample_grid(grid, centres.reshape(-1, 2), rig.roi), grid.ravel())
    mid = (centres[10, 20] + centres[11, 21]) / 2
    assert sample_grid(grid, mid[None], rig.roi)[0] == pytest.approx((grid[10, 20] + grid[11, 21]) / 2)


def test_forces_net_force_and_contact_location(rig: RigConfig) -> None:
    k = np.diag(np.arange(1.0, 7.0))
    f = forces_from_displacements(k, np.array([[1.0, 1, 1], [0.5, 0.5, 0.5]]))
    assert np.allclose(f, [[1, 2, 3], [2, 2.5, 3]]) and np.allclose(net_force_n(f), [3, 4.5, 6])
    camera = true_camera(rig)
    depth = np.zeros((90, 112))
    assert contact_location(depth, rig.roi, camera) is None
    depth[30:33, 70:73] = 0.5
    depth[0, 0] = -0.2  # a bulge does not count
    loc = contact_location(depth, rig.roi, camera)
    assert loc is not None
    assert np.allclose(loc.position_px, network_grid_pixels(rig)[31, 71])
    assert np.allclose(loc.position_mm, camera.backproject_to_plane(loc.position_px[None])[0, :2])


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0.0, 0.01, 0.3]), st.sampled_from([0.0, 0.2, 0.5]))
def test_contact_location_is_the_weighted_centre_of_its_definition(rig: RigConfig, seed: int, threshold_mm: float,
                                                                   core_fraction: float) -> None:
    """The compiled core against its definition in numpy: the summed depth over the threshold, and the centre of
    mass of ``max(depth - core_fraction * peak, 0)`` over the contact cells, as the network grid's pixel."""
    rng = np.random.default_rng(seed)
    depth = (rng.random((90, 112)) - rng.random()) * rng.random() * 2
    camera = true_camera(rig)
    loc = contact_location(depth, rig.roi, camera, threshold_mm, core_fraction)
    contact = np.where(depth > threshold_mm, depth, 0.0)
    if contact.sum() <= 0:
        assert loc is None
        return
    w = np.where(contact > 0, np.maximum(contact - core_fraction * contact.max(), 0.0), 0.0)
    rows, cols = np.indices(depth.shape)
    r, c = (w * rows).sum() / w.sum(), (w * cols).sum() / w.sum()
    assert loc is not None and loc.weight_mm == pytest.approx(contact.sum(), rel=1e-12)
    lower = network_grid_pixels(rig)[int(r), int(c)]
    step = network_grid_pixels(rig)[1, 1] - network_grid_pixels(rig)[0, 0]
    assert np.allclose(loc.position_px, lower + step * [c - int(c), r - int(r)], atol=1e-9)


def test_contact_location_is_the_dents_core_not_its_faint_residue(rig: RigConfig) -> None:
    camera = true_camera(rig)
    depth = np.zeros((90, 112))
    depth[30:33, 70:73] = 1.0
    depth[60:80, 10:30] = 0.1  # a faint, wide residue: 400 cells, more summed depth than the dent's 9
    core = contact_location(depth, rig.roi, camera)
    whole = contact_location(depth, rig.roi, camera, core_fraction=0.0)
    assert core is not None and whole is not None
    assert np.allclose(core.position_px, network_grid_pixels(rig)[31, 71])
    assert np.linalg.norm(whole.position_px - core.position_px) > 100
    assert core.weight_mm == pytest.approx(49.0)
