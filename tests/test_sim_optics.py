"""The sim's camera model, membrane renderer and calibration-target scene."""

from __future__ import annotations

import numpy as np
import pytest

from labrig.config import RigConfig, rig_with
from labrig.frames import matrix_to_rotvec, rotvec_to_matrix
from labrig.physics.camera import CameraModel
from labrig.physics.target import DotGridTarget, target_pose
from labrig.sim import _render_kernels as _k
from labrig.sim.optics import Renderer
from labrig.sim.shading import DepthField, GridLookup
from labrig.sim.stepping import image_velocity_px_s, step_us
from labrig.sim.target import render_target
from labrig.sim.truth_config import sim_config, true_camera


@pytest.fixture(scope="module")
def camera(rig: RigConfig) -> CameraModel:
    return true_camera(rig)


def weighted_centroids(image: np.ndarray, background: float, centres_px: np.ndarray, x0: int, y0: int, half: int) -> np.ndarray:
    """Background-subtracted intensity centroids (N, 2), sensor px, in windows around centres."""
    out = []
    for cx, cy in centres_px:
        ix, iy = round(cx) - x0, round(cy) - y0
        win = image[iy - half : iy + half + 1, ix - half : ix + half + 1] - background
        ys, xs = np.mgrid[iy - half : iy + half + 1, ix - half : ix + half + 1]
        out.append([(win * (xs + x0)).sum() / win.sum(), (win * (ys + y0)).sum() / win.sum()])
    return np.array(out)


# -- camera -------------------------------------------------------------------------------------


def test_projection_matches_a_hand_computed_case() -> None:
    # 180 deg about x: gel (1, 2, 0) -> camera (1, -2, 10); normalised (0.1, -0.2), r^2 = 0.05.
    # k1 = 0.1: radial 1.005; p1 = 0.01: dx = 2 p1 x y = -0.0004, dy = p1 (r^2 + 2 y^2) = 0.0013.
    # x_d = 0.1005 - 0.0004 = 0.1001, y_d = -0.201 + 0.0013 = -0.1997 -> (50 + 10.01, 40 - 19.97).
    cam = CameraModel(100.0, 100.0, 50.0, 40.0, (0.1, 0.0, 0.01, 0.0, 0.0), (np.pi, 0.0, 0.0), (0.0, 0.0, 10.0))
    assert np.allclose(cam.project([[1.0, 2.0, 0.0]]), [[60.01, 20.03]], atol=1e-9)


def test_rig_camera_sees_the_gel_origin_near_the_principal_point(camera: CameraModel) -> None:
    # Gel origin -> camera (0.12, -0.08, 30): (641.3 + 840 * 0.004, 358.2 - 840 * 0.08 / 30), distortion < 1e-3 px.
    assert np.allclose(camera.project([[0.0, 0.0, 0.0]]), [[644.66, 355.96]], atol=1e-3)


def test_back_projection_round_trips(camera: CameraModel) -> None:
    rng = np.random.default_rng(0)
    px = rng.uniform([0, 0], [1279, 719], size=(2000, 2))
    on_gel = camera.backproject_to_plane(px)
    assert np.abs(on_gel[:, 2]).max() < 1e-9
    assert np.abs(camera.project(on_gel) - px).max() < 1e-6
    assert np.abs(camera.backproject_to_plane(px, z_mm=-1.5)[:, 2] + 1.5).max() < 1e-9
    rays = camera.pixel_rays(px)
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)
    assert np.abs(camera.normalized_to_pixels(rays[:, :2] / rays[:, 2:]) - px).max() < 1e-6
    gel = rng.uniform([-14, -13, -2], [14, 13, 0], size=(500, 3))
    back = camera.backproject_to_plane(camera.project(gel), z_mm=0.0)
    ray_point = camera.gel_to_camera.apply(gel)
    assert np.allclose(np.cross(camera.gel_to_camera.apply(back), ray_point), 0.0, atol=1e-9)


def test_compiled_projection_is_the_numpy_distortion_bit_for_bit() -> None:
    rng = np.random.default_rng(4)
    for _ in range(20):  # random lenses, strong distortion included, points in front of the camera
        k = tuple(rng.normal(0.0, [0.3, 0.3, 0.02, 0.02, 0.3]).tolist())
        cam = CameraModel(*rng.uniform([500, 500, 600, 300], [1000, 1000, 700, 400]).tolist(), k, (0.0, 0.0, 0.0),
                          (0.0, 0.0, 0.0))
        points = rng.uniform([-20, -20, 5], [20, 20, 40], size=(5, 37, 3))
        reference = cam.normalized_to_pixels(points[..., :2] / points[..., 2:3])
        np.testing.assert_array_equal(cam.project_camera(points), reference)  # any leading shape
        np.testing.assert_array_equal(cam.project_camera(points[0, 0]), reference[0, 0])  # one point
        np.testing.assert_array_equal(cam.project_camera(points[:, 3]), reference[:, 3])  # a strided view


def test_rodrigues_round_trip(camera: CameraModel) -> None:
    r = np.array(camera.gel_to_camera_rotvec_rad)
    assert np.allclose(matrix_to_rotvec(rotvec_to_matrix(r)), r, atol=1e-12)


def test_step_size_from_image_velocity(camera: CameraModel) -> None:
    assert step_us([[30.0, 40.0], [1.0, 0.0]], 0.2) == 4000  # 50 px/s -> 0.2 px in 4 ms
    assert step_us(np.zeros((3, 2)), 0.2, max_us=5000) == 5000
    v = image_velocity_px_s(camera, [[0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0]])  # 1 mm/s along gel x
    assert 27.0 < np.linalg.norm(v) < 28.5


# -- membrane -----------------------------------------------------------------------------------


def test_rest_marker_centroids_match_projections(rig: RigConfig) -> None:
    renderer = Renderer(rig)
    rest = rig.markers.rest_positions_mm()
    true = renderer.camera.project(rest)
    found = weighted_centroids(renderer.image, sim_config(rig).lighting.membrane_level, true, rig.roi.x0_px, rig.roi.y0_px, 12)
    error = np.linalg.norm(found - true, axis=1)
    assert error.shape == (156,)
    assert error.max() < 0.05, error.max()
    assert renderer.image.max() == pytest.approx(sim_config(rig).lighting.marker_level)
    assert renderer.image.min() == pytest.approx(sim_config(rig).lighting.membrane_level)


def bump(amplitude_mm: float, centre_mm: tuple[float, float] = (1.0, -1.0)) -> DepthField:
    x = np.linspace(-6.0, 6.0, 121) + centre_mm[0]
    y = np.linspace(-6.0, 6.0, 121) + centre_mm[1]
    xx, yy = np.meshgrid(x, y)
    depth = amplitude_mm * np.exp(-((xx - centre_mm[0]) ** 2 + (yy - centre_mm[1]) ** 2) / 4.0)
    return DepthField(x, y, depth)


def test_incremental_render_matches_full_render(rig: RigConfig) -> None:
    renderer = Renderer(rig)
    rest = rig.markers.rest_positions_mm()
    rng = np.random.default_rng(3)
    xyz = rest
    for k in range(12):
        xyz = rest + rng.normal(0.0, 0.05, rest.shape) * [1, 1, 0.2]
        depth = bump(0.05 * k) if k < 8 else None
        update = renderer.render(xyz, depth)
        assert np.unique(update.indices).size == update.indices.size
    full = renderer.render_full(xyz)
    # The dead band: a pixel is off by at most rel (old + new + 1e-3).
    assert np.abs(renderer.image - full).max() <= 2.001 * renderer.min_rel_change
    # A marker's pixels only: re-rendering the same scene reports nothing, moving one marker reports its patch.
    assert renderer.render(xyz).indices.size == 0
    moved = xyz.copy()
    moved[70, 0] += 0.02
    update = renderer.render(moved)
    y, x = np.divmod(update.indices, rig.roi.width_px)
    centre = renderer.camera.project(moved[70:71])[0] - [rig.roi.x0_px, rig.roi.y0_px]
    assert 0 < update.indices.size < 200
    assert np.hypot(x - centre[0], y - centre[1]).max() < 9


@pytest.mark.parametrize("contrast", [False, True])
def test_incremental_render_without_change_filter_is_the_full_render(rig: RigConfig, contrast: bool) -> None:
    # Small moves take the compiled rim update, large ones the whole-patch redraw; contrast per marker sends
    # every move through the redraw.
    rest = rig.markers.rest_positions_mm()
    rng = np.random.default_rng(5)
    ink = rng.uniform(0.6, 1.3, len(rest)) if contrast else None
    renderer = Renderer(rig, marker_contrast=ink, min_rel_change=0.0)
    for scale in (0.002, 0.003, 0.05, 0.002):
        xyz = rest + rng.normal(0.0, scale, rest.shape) * [1, 1, 0.2]
        renderer.render(xyz)
        assert np.abs(renderer.image - renderer.render_full(xyz)).max() < 1e-12


def test_slope_shading_brightens_the_contact_edge(rig: RigConfig) -> None:
    renderer = Renderer(rig)
    rest = rig.markers.rest_positions_mm()
    field = bump(0.4)
    update = renderer.render(rest, field)
    assert update.indices.size > 10_000
    # Brightness at a gel point on the bump's flank (between markers): 1 + gain * slope of the Gaussian.
    gel = np.array([[1.0 + 1.0, -1.0 + 1.0, 0.0]])  # 1.414 mm from the centre, between markers
    origin = np.array([rig.roi.x0_px, rig.roi.y0_px])
    sensor_px = np.round(renderer.camera.project(gel)[0])
    px = sensor_px.astype(int) - origin
    back = renderer.camera.backproject_to_plane(sensor_px[None, :])[0]
    r2 = (back[0] - 1.0) ** 2 + (back[1] + 1.0) ** 2
    slope = 0.4 * np.exp(-r2 / 4.0) * 2 * np.sqrt(r2) / 4.0
    expected = sim_config(rig).lighting.membrane_level * (1 + sim_config(rig).lighting.slope_gain * slope)
    assert renderer.image[px[1], px[0]] == pytest.approx(expected, rel=0.01)
    # Far from the bump the membrane is unshaded; lifting the indenter restores the rest image.
    assert renderer.image[5, 5] == pytest.approx(sim_config(rig).lighting.membrane_level)
    renderer.render(rest, None)
    assert np.abs(renderer.image - renderer.render_full(rest)).max() < 1e-12


def test_fused_shading_matches_the_full_render_exactly(rig: RigConfig) -> None:
    # Without the change filter, the incremental (compiled, fused) re-shade and composition give the
    # numpy render_full image bit for bit, for a new slope box and for a re-shade inside the same box.
    renderer = Renderer(rig, min_rel_change=0.0)
    rest = rig.markers.rest_positions_mm()
    for amplitude in (0.3, 0.35):
        field = bump(amplitude)
        renderer.render(rest, field)
        assert np.array_equal(renderer.image, renderer.render_full(rest, field))


def test_a_slowly_growing_dent_stays_within_the_reported_change(rig: RigConfig) -> None:
    # The default shade_tol re-shades only nodes whose slope moved by min_rel_change / (2 slope_gain):
    # after many small steps no pixel is further from the full render than the change filter allows
    # plus that bound, and fewer pixels are re-shaded than with shade_tol 0.
    rest = rig.markers.rest_positions_mm()
    lazy, eager = Renderer(rig), Renderer(rig, shade_tol=0.0)
    assert lazy.shade_tol == pytest.approx(lazy.min_rel_change / (2 * sim_config(rig).lighting.slope_gain))
    lazy_px = eager_px = 0
    for amplitude in np.linspace(0.3, 0.302, 12):
        field = bump(float(amplitude))
        lazy_px += lazy.render(rest, field).indices.size
        eager_px += eager.render(rest, field).indices.size
    full = lazy.render_full(rest, field)
    relative = np.abs(lazy.image - full) / np.maximum(full, 1e-3)
    assert relative.max() <= 2.5 * lazy.min_rel_change + 1e-9
    assert lazy_px < eager_px


def test_translate_nodes_reads_the_grid_at_the_translated_nodes() -> None:
    rng = np.random.default_rng(5)
    values = rng.random((7, 9))
    out = np.empty_like(values)
    _k.translate_nodes(values, 2.0, -1.0, out)  # whole nodes: the grid shifted, zeros where it ran off
    assert np.array_equal(out[1:, :7], values[:-1, 2:]) and not out[0].any() and not out[:, 7:].any()
    _k.translate_nodes(values, 0.3, 0.45, out)
    grid = (0.0, 8.0, 9, 0.0, 6.0, 7)
    jj, ii = np.mgrid[0:7, 0:9]
    nodes = np.stack([ii.ravel() + 0.3, jj.ravel() + 0.45], axis=1)
    assert np.allclose(out.ravel(), GridLookup.build(grid, nodes).sample(values, slice(None)), rtol=0.0, atol=1e-12)


def test_a_sliding_dent_is_shaded_on_the_grid_it_left(rig: RigConfig) -> None:
    # A field whose grid moves a fraction of a node per render (a sliding contact) is resampled onto the grid
    # shown: the renderer re-shades around the nodes whose slope moved, not the whole slope box, and stays within
    # the change filter plus the shading bound of the full render of the caller's own field.
    rest = rig.markers.rest_positions_mm()
    renderer = Renderer(rig)
    renderer.render(rest, bump(0.3, (0.0, 0.0)))
    whole = blocks = 0
    for k in range(1, 13):
        field = bump(0.3, (0.016 * k, 0.0))
        update = renderer.render(rest, field)
        assert update.block is not None
        blocks += update.block.changed.size
        whole += renderer.roi.width_px * renderer.roi.height_px
    full = renderer.render_full(rest, field)
    relative = np.abs(renderer.image - full) / np.maximum(full, 1e-3)
    assert relative.max() <= 2.5 * renderer.min_rel_change + 1e-9
    assert blocks < 0.5 * whole
    far = bump(0.3, (1.5, 0.0))  # more than FIXED_GRID_DRIFT_NODES away: taken as it is
    renderer.render(rest, far)
    assert renderer.image is not None and np.array_equal(renderer.render_full(rest, far) > 0, full > 0)


def test_led_off_is_dark(rig: RigConfig) -> None:
    renderer = Renderer(rig)
    rest = rig.markers.rest_positions_mm()
    update = renderer.render(rest, led=False)
    assert update.indices.size == rig.roi.width_px * rig.roi.height_px
    assert renderer.image.max() < 1e-6
    assert renderer.render_full(rest, led=False).max() < 1e-6
    renderer.render(rest, led=True)
    assert np.abs(renderer.image - renderer.render_full(rest, led=True)).max() < 1e-12
    dark_rig = rig_with(rig, {"sim.lighting.led_on": False})
    assert Renderer(dark_rig).image.max() < 1e-6


# -- calibration target -------------------------------------------------------------------------


def test_calibration_target_dots_land_where_the_camera_model_says(camera: CameraModel) -> None:
    target = DotGridTarget()
    pose = target_pose([0.3, -0.2, 0.05], [1.0, -0.5, 30.0])
    image = render_target(camera, target, pose)
    assert image.shape == (720, 1280)
    true = camera.project(target.points_mm(), pose)
    inside = (true[:, 0] > 20) & (true[:, 0] < 1259) & (true[:, 1] > 20) & (true[:, 1] < 699)
    assert inside.sum() == target.rows * target.cols  # the whole grid is in view at this pose
    found = weighted_centroids(image, target.plate_level, true[inside], 0, 0, 18)
    assert np.linalg.norm(found - true[inside], axis=1).max() < 0.05
    assert image.max() == pytest.approx(target.dot_level)
    # A pose with the plate behind the camera shows nothing.
    behind = render_target(camera, target, target_pose([0, 0, 0], [0, 0, -30.0]))
    assert np.all(behind == target.plate_level)


def test_backprojecting_to_a_plane_per_pixel_matches_the_numpy_path() -> None:
    """The compiled back-projection (every marker, every window) gives :meth:`backproject_to_plane`'s points for
    each pixel's own plane, distortion and a tilted camera included."""
    camera = CameraModel(905.0, 902.0, 641.0, 358.0, (-0.12, 0.03, 0.001, -0.002, 0.004), (0.02, -0.015, 0.4),
                         (0.6, -0.4, 31.0))
    rng = np.random.default_rng(3)
    px = rng.uniform([0, 0], [1280, 720], (300, 2))
    z = rng.uniform(-2.0, 0.5, 300)
    expected = np.array([camera.backproject_to_plane(p[None], float(zi))[0] for p, zi in zip(px, z, strict=True)])
    assert np.abs(camera.backproject_to_planes(px, z) - expected).max() < 1e-9
