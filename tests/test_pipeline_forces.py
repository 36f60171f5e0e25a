"""Dense forces: the surface operator against the virtual rig's truth, with true inputs and through the pipeline.

The recording: a 6 mm sphere 1 mm deep, 0.5 mm shear along +x, large-strain stiffening off
(the sim's forces are then linear in E), the gel's modulus as `labrig calibrate gel` fits it
on the virtual rig (0.40 MPa, the rig's value).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from labrig.config import RigConfig, rig_with
from labrig.indenters import Indenter
from labrig.pipeline import depth_sources, displacement, forces, ifem, run_setup, runtime
from labrig.recording import Recording
from labrig.sim.live import record_live
from labrig.sim.motion import probing_path
from labrig.sim.truth_config import true_camera

NORMAL_HOLD_US = 550_000  # mid-way through the first Wait (normal only)
SHEAR_HOLD_US = 817_000  # mid-way through the Wait after the shear


@pytest.fixture(scope="module")
def linear_rig(rig: RigConfig) -> RigConfig:
    return rig_with(rig, {"sim.mechanics.stiffening": 0.0})


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory, linear_rig: RigConfig, sphere: Indenter) -> Path:
    path = probing_path(linear_rig, sphere, depth_mm=1.0, shear_mm=0.5, normal_speed_mm_s=3.0, shear_speed_mm_s=3.0,
                        wait_s=0.1)
    out = tmp_path_factory.mktemp("forces") / "sphere.h5"
    record_live(out, linear_rig, sphere, path, seed=5, realtime=False)
    return out


@pytest.fixture(scope="module")
def truth(recording: Path) -> dict[str, dict[str, np.ndarray]]:
    with Recording(recording) as rec:
        return {name: rec.stream(name) for name in ("truth/markers", "truth/depth", "truth/marker_forces")}


@pytest.fixture(scope="module")
def operator(rig: RigConfig) -> ifem.SurfaceOperator:
    return ifem.build_surface_operator(rig)  # disk-cached after the first run (about 15 s)


def _true_inputs(truth: dict[str, dict[str, np.ndarray]], t_us: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(true marker pixels, true depth map, true per-marker forces) at the solve nearest after ``t_us``."""
    depth = truth["truth/depth"]
    k = int(np.searchsorted(depth["t_host_us"], t_us))
    markers = truth["truth/markers"]
    j = int(np.searchsorted(markers["t_host_us"], depth["t_host_us"][k]))
    return (markers["position_px"][j].astype(np.float64), depth["depth_mm"][k].astype(np.float64),
            truth["truth/marker_forces"]["force_n"][k].astype(np.float64))


def test_surface_operator_is_consistent(rig: RigConfig, operator: ifem.SurfaceOperator) -> None:
    m = rig.markers.rows * rig.markers.cols
    n = len(operator.node_xy_mm)
    assert operator.k_zz.shape == (n, n) and operator.k_tt.shape == (2 * n, 2 * n)
    assert operator.cells.shape == (m, n) and operator.interp.shape == (n, m)
    for k in (operator.k_zz, operator.k_tt):
        assert np.abs(k - k.T).max() < 1e-10 * np.abs(k).max()
        assert np.linalg.eigvalsh(k).min() > 0
    # Every node's tributary area is shared out over the cells exactly once.
    assert np.allclose(operator.cells.sum(axis=0), 1.0)
    # A uniform in-plane shift of every marker: a net force along the shift, none across it.
    f = operator.forces_n(np.zeros(n), np.tile([0.1, 0.0], (m, 1)), mode="field")
    net = f.sum(axis=0)
    assert net[0] > 0.5 and abs(net[1]) < 1e-9 * net[0] and net[2] == 0
    # No contact, no force, whatever the markers do.
    assert not operator.forces_n(np.zeros(n), np.tile([0.1, 0.0], (m, 1))).any()
    # The in-plane splines reproduce a linear field exactly.
    xs = np.linspace(-12, 12, 13)
    w = ifem.spline_weights(np.array([-13.0, -3.3, 0.25, 12.7]), xs)
    assert np.allclose(w @ (0.3 * xs - 1), 0.3 * np.array([-13.0, -3.3, 0.25, 12.7]) - 1)


def test_operator_is_cached_and_linear_in_the_modulus(rig: RigConfig, operator: ifem.SurfaceOperator, tmp_path) -> None:  # type: ignore[no-untyped-def]
    soft = ifem.SurfaceParams(youngs_modulus_mpa=rig.gel.youngs_modulus_mpa / 2)
    assert ifem.surface_key(rig, soft) == ifem.surface_key(rig)  # E is not part of the key
    cached = ifem.build_surface_operator(rig, soft)
    assert np.allclose(cached.k_zz, operator.k_zz / 2) and np.allclose(cached.k_tt, operator.k_tt / 2)
    assert ifem.surface_key(rig, ifem.SurfaceParams(poisson_ratio=0.45)) != ifem.surface_key(rig)


def test_grid_sampling_matrix_matches_bilinear_sampling(rig: RigConfig) -> None:
    grid = np.random.default_rng(1).random((90, 112))
    px = np.array([[rig.roi.x0_px - 5.0, rig.roi.y0_px + 3.2], [640.3, 360.9], [rig.roi.x1_px + 2.0, 500.0]])
    matrix = displacement.grid_sampling_matrix(px, rig.roi, grid.shape)
    assert np.allclose(matrix @ grid.ravel(), displacement.sample_grid(grid, px, rig.roi))


def test_true_inputs_give_the_sims_forces(rig: RigConfig, operator: ifem.SurfaceOperator,
                                          truth: dict[str, dict[str, np.ndarray]]) -> None:
    """True marker pixels and depth map: the paper's K over-predicts Fz by about 55 %, the surface operator
    is within a few per cent in net force and four times closer per marker."""
    camera = true_camera(rig)
    rest = rig.markers.rest_positions_mm()
    rest_px = camera.project(rest)
    surface = forces.SurfaceForces(operator, camera, rig.roi)
    k_paper = ifem.build_stiffness(rig)
    for t_us in (NORMAL_HOLD_US, SHEAR_HOLD_US):
        px, depth, f_true = _true_inputs(truth, t_us)
        u = displacement.displacements_mm(px, depth, camera, rest, rig.roi, sample_px=rest_px)
        f = surface(depth, u)
        net, net_true = f.sum(axis=0), f_true.sum(axis=0)
        assert abs(net[2] / net_true[2] - 1) < 0.03
        mae = np.abs(f - f_true).mean(axis=0)
        assert mae[2] < 0.006 and mae[0] < 0.003 and mae[1] < 0.002  # N per marker
        paper = forces.forces_from_displacements(k_paper, u)
        assert paper.sum(axis=0)[2] / net_true[2] > 1.3
        assert np.abs(paper - f_true).mean(axis=0)[2] > 2 * mae[2]
        # The network's maps stop at 0 (no bulge): the contact formulation does not need it.
        clipped = surface(np.clip(depth, 0, None), u)
        assert np.allclose(clipped, f, atol=1e-3 * np.abs(f).max())
        # Prescribing the whole map (bulge included) is close too; without the bulge it doubles Fz.
        assert abs(surface(depth, u, "field").sum(axis=0)[2] / net_true[2] - 1) < 0.06
        assert surface(np.clip(depth, 0, None), u, "field").sum(axis=0)[2] / net_true[2] > 1.8
    assert abs(net[0] / net_true[0] - 1) < 0.05  # shear at the sheared hold


def with_true_camera(setup: run_setup.PipelineSetup) -> run_setup.PipelineSetup:
    """``setup`` with the virtual rig's true camera and the lattice through it (a perfect camera calibration)."""
    camera = true_camera(setup.rig)
    return replace(setup, camera=camera, rest_px=camera.project(setup.rig.markers.rest_positions_mm()),
                   sources={**setup.sources, "camera": "the virtual rig's true camera"})


def test_full_pipeline_matches_the_sims_net_force_mid_hold(rig: RigConfig, recording: Path) -> None:
    """Tracker on the events + the true depth map + the dense operator: Fz within 10 % mid-hold."""
    with Recording(recording) as rec:
        tf = rec.stream("truth/marker_forces")
        setup = with_true_camera(run_setup.setup_for_recording(rec, calibration_dir=None,
                                                               youngs_modulus_mpa=rig.gel.youngs_modulus_mpa))
        pipe = runtime.Pipeline(setup, depth_sources.TruthDepth(rec))
        results = list(pipe.run(rec, end_us=SHEAR_HOLD_US + 20_000))
    for t_us in (NORMAL_HOLD_US, SHEAR_HOLD_US):
        r = min(results, key=lambda r: abs(r.t1_us - t_us))
        k = int(np.searchsorted(tf["t_host_us"], r.t1_us))
        k = k if k < len(tf["t_host_us"]) else k - 1
        f_true = tf["force_n"][k].astype(np.float64)
        net_true = f_true.sum(axis=0)
        assert abs(r.net_force_n[2] / net_true[2] - 1) < 0.10
        assert np.abs(r.forces_n - f_true).mean(axis=0).max() < 0.02  # N per marker
        assert np.hypot(*r.contact_mm) < 0.3  # the contact is at the gel's centre
    assert abs(r.net_force_n[0] / net_true[0] - 1) < 0.15  # shear, with the tracker's lag


def test_the_default_calibration_does_not_depend_on_the_working_folder(rig: RigConfig, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    # A relative "calibration" folder once made `labrig evaluate` run from elsewhere fall back, silently, to a
    # linear gel and the nominal camera (the normal force 25 % low on deep presses).
    from labrig.config import DEFAULT_CALIBRATION_DIR

    monkeypatch.chdir(tmp_path)
    setup = run_setup.setup_for_rig(rig)
    gel_toml = str(Path(DEFAULT_CALIBRATION_DIR) / "gel.toml")
    assert setup.sources["stiffening"] == gel_toml
    assert setup.sources["modulus"] == gel_toml
    assert setup.stiffening > 0
    assert "extrinsics.toml" in setup.sources["camera"]


@pytest.mark.parametrize("mode", ["contact", "field"])
def test_a_prepared_map_gives_the_operators_forces(operator: ifem.SurfaceOperator, mode: str) -> None:
    """map_forces.prepare(...)(u) equals the operator's per-window solve: small and large pressed sets (the
    Schur branch), none pressed, and missing markers filled in."""
    from labrig.pipeline import map_forces
    from labrig.pipeline.unobserved import fill_in_plane, in_plane_fill

    rng = np.random.default_rng(7)
    xy = operator.node_xy_mm
    missing = np.zeros(operator.n_markers, bool)
    missing[[5, 77]] = True
    fill = in_plane_fill(operator, ~missing)
    for radius_mm in (0.0, 3.0, 40.0):  # no contact, a dimple, the whole surface pressed
        r = np.hypot(xy[:, 0] - 1.0, xy[:, 1] + 2.0)
        uz = -1.2 * np.clip(1 - (r / radius_mm) ** 2, 0, None) if radius_mm else np.zeros(len(xy))
        prepared = map_forces.prepare(operator, uz, mode, 0.01, fill)
        for _ in range(3):
            u = rng.normal(0, 0.2, (operator.n_markers, 3))
            u[missing] = np.nan
            expected = operator.forces_n(uz, fill_in_plane(fill, u), mode, 0.01)
            got = prepared(u)
            assert np.abs(got - expected).max() <= 1e-9 * max(1.0, np.abs(expected).max())
        if mode == "contact" and radius_mm == 0.0:
            assert np.all(prepared(u) == 0.0)


def test_the_map_work_path_gives_the_reference_forces_window_by_window(recording: Path) -> None:
    """1 ms windows, depth every 10 ms, three markers missing: the default path (each depth map's work done once,
    compiled back-projection) and the reference path agree per marker within 1e-6 N, window by window."""
    with Recording(recording) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=None)
        missing = np.zeros(len(setup.rest_px), bool)
        missing[[20, 84, 150]] = True
        setup = replace(setup, missing=missing)
        runs = [list(runtime.Pipeline(setup, depth_sources.TruthDepth(rec), depth_every_us=10_000, reference=ref)
                     .run(rec, window_us=1_000, concurrent=False, end_us=900_000)) for ref in (False, True)]
    fast, reference = runs
    assert len(fast) == len(reference) == 900
    for a, b in zip(fast, reference, strict=True):
        assert np.abs(a.forces_n - b.forces_n).max() <= 1e-6
        assert np.abs(a.displacement_mm - b.displacement_mm).max() <= 1e-9
        assert np.array_equal(a.contact_px, b.contact_px, equal_nan=True)
    assert min(r.net_force_n[2] for r in fast) < -1.0 and max(np.abs(r.net_force_n[0]) for r in fast) > 0.1


def test_a_pressed_set_seen_again_reuses_its_factorisation(operator: ifem.SurfaceOperator) -> None:
    from labrig.pipeline import map_forces

    xy = operator.node_xy_mm
    dimple = -np.clip(1 - (np.hypot(xy[:, 0], xy[:, 1]) / 3.0) ** 2, 0, None)
    cache = map_forces.SolverCache(size=2)
    u = np.random.default_rng(1).normal(0, 0.1, (operator.n_markers, 3))
    first = map_forces.prepare(operator, dimple, cache=cache)(u)
    deeper = map_forces.prepare(operator, 1.5 * dimple, cache=cache)(u)  # the same nodes pressed
    assert (cache.hits, cache.misses) == (1, 1)
    np.testing.assert_allclose(deeper[:, 2], 1.5 * first[:, 2], rtol=1e-9)
    np.testing.assert_allclose(deeper, operator.forces_n(1.5 * dimple, u), atol=1e-9)
    for radius_mm in (2.0, 4.0):  # two new sets: the first one is dropped
        map_forces.prepare(operator, -np.clip(1 - (np.hypot(xy[:, 0], xy[:, 1]) / radius_mm) ** 2, 0, None), cache=cache)
    map_forces.prepare(operator, dimple, cache=cache)
    assert cache.misses == 4


def test_warming_up_leaves_the_run_as_it_was(recording: Path) -> None:
    """A pipeline taken through :meth:`Pipeline.warm_up` (throwaway state) gives the same windows as one that was not,
    with the bundled network (whose source keeps the brightness state) at 1 ms windows, depth every 10 ms."""
    from labrig.models import bundled_model_path

    with Recording(recording) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=None)
        runs = []
        for warm in (True, False):
            source = depth_sources.depth_source("model", setup, rec, bundled_model_path(), threads=1)
            pipe = runtime.Pipeline(setup, source, depth_every_us=10_000)
            if warm:
                assert pipe.warm_up() > 0
            runs.append(list(pipe.run(rec, window_us=1_000, concurrent=False, end_us=700_000)))
    warmed, cold = runs
    assert len(warmed) == len(cold) == 700
    for a, b in zip(warmed, cold, strict=True):
        assert np.array_equal(a.positions_px, b.positions_px)
        assert np.array_equal(a.forces_n, b.forces_n)
        assert np.array_equal(a.depth_mm, b.depth_mm)
    assert min(r.net_force_n[2] for r in warmed) < -0.5
