"""Markers as printed: measured rest positions, missing markers, residuals, and the pipeline that starts from them."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import erfc

from labrig.calibration.extrinsics import ExtrinsicsResult, extrinsics_from_frame, write_extrinsics
from labrig.calibration.files import CalibrationFileError, Intrinsics, load_extrinsics
from labrig.calibration.plots import plot_marker_residuals
from labrig.config import RigConfig
from labrig.eventtypes import EVENT_DTYPE
from labrig.pipeline import displacement, forces, ifem, run_setup
from labrig.pipeline.rest import RestParams, RestRefiner
from labrig.pipeline.tracking import Tracker, TrackerParams, marker_diameter_px
from labrig.pipeline.unobserved import completion_matrix, condense_unobserved
from labrig.sim.truth_config import true_camera


def true_diameter_px(rig: RigConfig) -> float:
    """The markers' image diameter through the virtual rig's true camera."""
    return marker_diameter_px(rig, true_camera(rig))


MISSING = (5, 70, 150)
OFF_SITE = 40  # printed 0.36 mm off its site


@pytest.fixture(scope="module")
def printed(rig: RigConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per-marker printing errors (M, 2) mm (0.05 mm std, one marker far off) and their true pixels (M, 2)."""
    rng = np.random.default_rng(0)
    rest = rig.markers.rest_positions_mm()
    error = rng.normal(0.0, 0.05, (len(rest), 2))
    error[OFF_SITE] = [0.3, -0.2]
    at = rest.copy()
    at[:, :2] += error
    return error, true_camera(rig).project(at)


@pytest.fixture(scope="module")
def calibrated(rig: RigConfig, printed: tuple[np.ndarray, np.ndarray]) -> ExtrinsicsResult:
    """The extrinsics of a synthetic LED frame: lit membrane, brighter discs where the markers are printed."""
    _, px = printed
    camera = true_camera(rig)
    radius = true_diameter_px(rig) / 2
    frame = np.full((camera.height_px, camera.width_px), 1.0)
    yy, xx = np.mgrid[0:camera.height_px, 0:camera.width_px]
    for i, (x, y) in enumerate(px):
        if i in MISSING:
            continue
        window = (slice(int(y) - 20, int(y) + 21), slice(int(x) - 20, int(x) + 21))
        r = np.hypot(xx[window] - x, yy[window] - y)
        frame[window] += erfc((r - radius) / (np.sqrt(2) * 0.8))
    frame += np.random.default_rng(1).normal(0.0, 0.3, frame.shape)
    return extrinsics_from_frame(np.clip(frame, 0, None), Intrinsics.from_camera(camera), rig.markers)


def test_calibration_finds_every_missing_marker_and_the_printed_positions(
        calibrated: ExtrinsicsResult, printed: tuple[np.ndarray, np.ndarray]) -> None:
    error, px = printed
    markers = calibrated.marker_map
    assert markers.missing_indices == list(MISSING)
    found = ~markers.missing
    assert np.abs(markers.rest_px[found] - px[found]).max() < 0.4  # measured where printed, not where nominal
    assert np.abs(markers.rest_px[MISSING, :] - markers.nominal_px[MISSING, :]).max() == 0.0
    worst = markers.worst(1)[0]
    assert (worst.index, worst.row, worst.col) == (OFF_SITE, 3, 1)
    assert worst.residual_mm == pytest.approx(np.hypot(0.3, 0.2), abs=0.04)
    assert not calibrated.in_pose[OFF_SITE] and calibrated.detected[OFF_SITE]  # measured, left out of the pose
    # The residual on the gel is the printing error less what the pose absorbed (a common shift and turn).
    spread = markers.residual_mm[found] - error[found]
    assert np.abs(spread - spread.mean(axis=0)).max() < 0.03
    summary = markers.summary()
    assert summary["markers_missing"] == list(MISSING) and summary["markers_missing_row_col"][0] == [0, 5]


def test_the_file_keeps_the_markers_as_printed_and_reads_old_files(calibrated: ExtrinsicsResult, tmp_path: Path) -> None:
    path = write_extrinsics(calibrated, tmp_path / "extrinsics.toml")
    loaded = load_extrinsics(path)
    assert loaded.format_version == 2 and loaded.marker_map.missing_indices == list(MISSING)
    np.testing.assert_allclose(loaded.marker_map.rest_px, calibrated.marker_map.rest_px)
    np.testing.assert_array_equal(loaded.marker_map.in_pose, calibrated.in_pose)
    np.testing.assert_allclose(loaded.marker_map.residual_mm, calibrated.marker_map.residual_mm)
    # Version 1 (no format_version, no missing list): its measured centres, nothing missing.
    old = Path(__file__).parents[1] / "calibration" / "extrinsics.toml"
    v1 = load_extrinsics(old)
    if v1.format_version == 1:
        assert v1.marker_map.missing_indices == [] and np.isfinite(v1.marker_map.rest_px).all()
    text = path.read_text()
    with pytest.raises(CalibrationFileError, match="format_version 9"):
        (tmp_path / "future.toml").write_text(text.replace("format_version = 2", "format_version = 9"))
        load_extrinsics(tmp_path / "future.toml")
    with pytest.raises(CalibrationFileError, match="missing does not match"):
        (tmp_path / "bad.toml").write_text(text.replace("missing = [5, 70, 150]", "missing = [5, 70]"))
        load_extrinsics(tmp_path / "bad.toml")
    assert plot_marker_residuals(loaded.marker_map, tmp_path / "map.png").stat().st_size > 10_000


def test_measured_rest_makes_no_false_displacement(rig: RigConfig, calibrated: ExtrinsicsResult,
                                                   printed: tuple[np.ndarray, np.ndarray], tmp_path: Path) -> None:
    """At rest the tracker sees the markers where they are printed: from the nominal lattice that is a
    displacement of the printing error (and a force); from the measured rest, none."""
    _, px = printed
    calibration = tmp_path / "cal"
    write_extrinsics(calibrated, calibration / "extrinsics.toml")
    camera = true_camera(rig)
    (calibration / "intrinsics.toml").write_text(
        "[intrinsics]\n" + "".join(f"{k} = {v!r}\n" for k, v in (
            ("fx_px", camera.fx_px), ("fy_px", camera.fy_px), ("cx_px", camera.cx_px), ("cy_px", camera.cy_px),
            ("distortion", list(camera.distortion)), ("width_px", camera.width_px), ("height_px", camera.height_px))))
    setup = run_setup.setup_for_rig(rig, calibration_dir=calibration)
    assert setup.sources["rest"].startswith("measured") and list(np.flatnonzero(setup.missing)) == list(MISSING)
    observed = setup.observed
    at_rest = np.where(observed[:, None], px, setup.rest_px)
    u = displacement.displacements_mm(at_rest, 0.0, setup.camera, setup.rest_mm(), rig.roi)
    nominal = displacement.displacements_mm(at_rest, 0.0, setup.camera, rig.markers.rest_positions_mm(), rig.roi)
    assert np.abs(u[observed]).max() < 0.015
    assert np.abs(nominal[OFF_SITE, :2]).max() > 0.2


def test_the_tracker_skips_missing_markers(rig: RigConfig) -> None:
    rest = true_camera(rig).project(rig.markers.rest_positions_mm())
    observed = np.ones(len(rest), bool)
    observed[[20, 21]] = False
    diameter = true_diameter_px(rig)
    tracker = Tracker(rest, TrackerParams(marker_diameter_px=diameter), observed=observed)
    # Every marker's disc moves along +x: ON on its leading edge, OFF on its trailing edge (centroids 2 px on).
    events = []
    for x, y in rest:
        for a in np.linspace(-np.pi / 2, np.pi / 2, 15):
            for r in (0.3, 0.45):
                events.append((x + 2 + r * diameter * np.cos(a), y + r * diameter * np.sin(a), 1))
                events.append((x + 2 - r * diameter * np.cos(a), y + r * diameter * np.sin(a), 0))
    ev = np.zeros(len(events), EVENT_DTYPE)
    ev["x"], ev["y"], ev["p"] = np.array([(round(x), round(y), p) for x, y, p in events]).T
    positions, updated = tracker.update(ev)
    assert updated[observed].all() and not updated[~observed].any()
    shift = positions - rest
    assert np.allclose(shift[~observed], shift[observed][:, None].mean(axis=0), atol=1.0)  # follows its neighbours
    assert (shift[~observed, 0] > 0.5).all() and np.isfinite(positions).all()
    assert (tracker.patches_px[~observed] == 0).all()
    # A missing marker's own events move nothing.
    quiet = Tracker(rest, TrackerParams(marker_diameter_px=diameter), observed=observed)
    only = ev[np.linalg.norm(np.stack([ev["x"], ev["y"]], 1) - rest[20], axis=1) < diameter]
    _, updated = quiet.update(only)
    assert not updated.any()


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n_missing=st.integers(1, 4))
def test_condensed_markers_carry_no_force(seed: int, n_missing: int) -> None:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(18, 18))
    k = a @ a.T + 18 * np.eye(18)  # 6 markers x 3 DOFs
    observed = np.ones(6, bool)
    observed[rng.choice(6, n_missing, replace=False)] = False
    u = rng.normal(size=(6, 3))
    u[~observed] = np.nan
    f = forces.forces_from_displacements(k, u, observed)
    assert np.isfinite(f).all() and np.allclose(f[~observed], 0.0)
    dofs = np.repeat(observed, 3)
    full = completion_matrix(k, dofs) @ np.nan_to_num(u.reshape(-1))
    assert np.allclose((k @ full)[~dofs], 0.0, atol=1e-9)  # the completed field leaves them force-free
    assert np.allclose(f.reshape(-1)[dofs], (k @ full)[dofs])
    assert np.allclose(condense_unobserved(k, np.ones(6, bool)), k)


def test_surface_forces_condense_missing_markers(rig: RigConfig) -> None:
    """A smooth in-plane field with a missing marker inside the contact gives the forces of the full grid."""
    operator = ifem.build_surface_operator(rig, ifem.SurfaceParams(margin_mm=4.0, layers=2))
    camera = true_camera(rig)
    rest = rig.markers.rest_positions_mm()
    depth = np.zeros((90, 112), np.float32)
    r2 = ((np.arange(112)[None] - 56) ** 2 + (np.arange(90)[:, None] - 45) ** 2).astype(np.float32)
    depth[:] = np.clip(0.5 - r2 / 400.0, 0, None)
    u = np.zeros((len(rest), 3))
    u[:, 0] = 0.1 * np.exp(-(rest[:, 0] ** 2 + rest[:, 1] ** 2) / 20.0)
    observed = np.ones(len(rest), bool)
    centre = int(np.argmin(np.linalg.norm(rest[:, :2], axis=1)))
    observed[centre] = False
    full = forces.SurfaceForces(operator, camera, rig.roi)(depth, u)
    holed_u = u.copy()
    holed_u[centre] = np.nan
    holed = forces.SurfaceForces(operator, camera, rig.roi, observed=observed)(depth, holed_u)
    assert np.isfinite(holed).all()
    assert forces.net_force_n(holed)[0] == pytest.approx(forces.net_force_n(full)[0], rel=0.1)
    assert forces.net_force_n(holed)[2] == pytest.approx(forces.net_force_n(full)[2], rel=1e-9)  # depth unchanged
    ignored = forces.SurfaceForces(operator, camera, rig.roi, observed=observed)(depth, np.nan_to_num(holed_u, nan=5.0))
    np.testing.assert_allclose(ignored, holed)  # the missing marker's value never counts


def test_rest_refines_from_quiet_windows_and_freezes_at_motion() -> None:
    calibrated = np.column_stack([np.arange(6.0) * 50, np.zeros(6)])
    observed = np.array([True, True, True, True, True, False])
    refiner = RestRefiner(calibrated, observed, RestParams(windows=10, max_shift_px=2.0))
    settled = calibrated + np.array([0.5, -0.25])
    settled[3] += 10.0  # a track that slipped: not a rest
    for _ in range(4):
        assert refiner.add(settled, 100, 10_000)
    np.testing.assert_allclose(refiner.rest_px[[0, 1, 2, 4]], settled[[0, 1, 2, 4]])
    np.testing.assert_allclose(refiner.rest_px[[3, 5]], calibrated[[3, 5]])  # slipped and missing: calibrated
    before = refiner.rest_px
    assert not refiner.add(settled + 5.0, 5_000, 10_000)  # motion: frozen
    assert refiner.rest_px is before and refiner.frozen
    s = refiner.summary()
    assert (s.windows, s.shifted_markers, s.rejected_markers) == (4, 4, 1)
    off = RestRefiner(calibrated, observed, RestParams(windows=0))
    assert not off.add(settled, 100, 10_000) and off.rest_px is not settled


def test_a_quiet_start_refines_nothing_the_tracker_did_not_see(rig: RigConfig) -> None:
    """With no motion the tracker stays put, so the refined rest is the calibrated one (the perfect-gel case)."""
    rest = true_camera(rig).project(rig.markers.rest_positions_mm())
    tracker = Tracker(rest, TrackerParams(marker_diameter_px=true_diameter_px(rig)))
    refiner = RestRefiner(rest)
    rng = np.random.default_rng(2)
    for _ in range(20):
        noise = np.zeros(300, EVENT_DTYPE)
        noise["x"], noise["y"], noise["p"] = rng.integers(0, 1280, 300), rng.integers(0, 720, 300), rng.integers(0, 2, 300)
        positions, _ = tracker.update(noise)
        refiner.add(positions, len(noise), 10_000)
    assert np.abs(refiner.rest_px - rest).max() < 0.05
    assert replace(refiner.params, windows=1).windows == 1


def led_frame(rig: RigConfig, px: np.ndarray, missing: tuple[int, ...], seed: int = 1) -> np.ndarray:
    """A synthetic LED frame: lit membrane, brighter discs at ``px`` but for the ``missing`` markers."""
    camera = true_camera(rig)
    radius = true_diameter_px(rig) / 2
    frame = np.full((camera.height_px, camera.width_px), 1.0)
    yy, xx = np.mgrid[0:camera.height_px, 0:camera.width_px]
    for i, (x, y) in enumerate(px):
        if i not in missing:
            window = (slice(int(y) - 20, int(y) + 21), slice(int(x) - 20, int(x) + 21))
            frame[window] += erfc((np.hypot(xx[window] - x, yy[window] - y) - radius) / (np.sqrt(2) * 0.8))
    return np.clip(frame + np.random.default_rng(seed).normal(0.0, 0.3, frame.shape), 0, None)


def test_a_badly_printed_gel_calibrates_without_false_missing_markers(rig: RigConfig) -> None:
    """0.2 mm std of placement error (a tenth of the pitch) and one marker 0.8 mm off: the nearest-neighbour
    pitch is biased short and a quarter-pitch association drops markers; every printed one must still be found."""
    rest = rig.markers.rest_positions_mm()
    error = np.random.default_rng(2).normal(0.0, 0.2, (len(rest), 2))
    error[OFF_SITE] = [0.8, 0.0]  # 0.4 pitch: beyond the association's tolerance, a free blob beside its site
    at = rest.copy()
    at[:, :2] += error
    px = true_camera(rig).project(at)
    result = extrinsics_from_frame(led_frame(rig, px, MISSING), Intrinsics.from_camera(true_camera(rig)),
                                   rig.markers)
    markers = result.marker_map
    assert markers.missing_indices == list(MISSING)
    found = ~markers.missing
    assert np.abs(markers.rest_px[found] - px[found]).max() < 0.5


def test_the_in_plane_fill_reproduces_a_stuck_contact_and_follows_a_peak() -> None:
    """Missing markers' in-plane displacement: a uniform shift (a stuck contact) and a linear field come
    back exactly; a smooth peak is followed far better than by zero force or the neighbours' mean."""
    from types import SimpleNamespace

    from labrig.pipeline.unobserved import fill_in_plane, in_plane_fill

    rows, cols = 12, 13
    m = rows * cols
    r, c = np.divmod(np.arange(m), cols)
    # cells of a 12 x 13 lattice on a node grid one finer: neighbouring cells share their border nodes
    nodes_r, nodes_c = np.divmod(np.arange((2 * rows + 1) * (2 * cols + 1)), 2 * cols + 1)
    cells = ((np.abs(nodes_r[None, :] - (2 * r[:, None] + 1)) <= 1)
             & (np.abs(nodes_c[None, :] - (2 * c[:, None] + 1)) <= 1)).astype(float)
    operator = SimpleNamespace(n_markers=m, cells=cells)
    d2 = (c - 6.2) ** 2 + (r - 5.4) ** 2
    observed = np.ones(m, bool)
    observed[np.argsort(d2)[:3]] = False
    fill = in_plane_fill(operator, observed)  # type: ignore[arg-type]
    for field in (np.full(m, 0.3), 0.01 * c - 0.02 * r):
        u = np.stack([field, -field, np.zeros(m)], axis=1)
        u[~observed, :2] = np.nan
        done = fill_in_plane(fill, u)
        assert np.allclose(done[:, 0], field) and np.allclose(done[:, 1], -field)
    bump = np.exp(-d2 / (2 * 1.2**2))
    u = np.stack([bump, np.zeros(m), np.zeros(m)], axis=1)
    u[~observed, 0] = np.nan
    lost = 1 - fill_in_plane(fill, u)[~observed, 0].sum() / bump[~observed].sum()
    neighbours_mean = 0.47  # the harmonic fill's loss on this bump
    assert 0 <= lost < 0.6 * neighbours_mean
