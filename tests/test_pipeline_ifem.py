"""Inverse FEM: element and mesh checks, locking, the condensed K, F = K U against a forward solve, the cache."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse.linalg as sla

from labrig.config import RigConfig
from labrig.pipeline import ifem
from labrig.pipeline.forces import forces_from_displacements, net_force_n

E, NU = 0.4, 0.48


def _solve(k, n_dofs: int, fixed: dict[int, float], loads: np.ndarray | None = None) -> np.ndarray:
    """Forward FE solve with prescribed DOF values and nodal loads."""
    u = np.zeros(n_dofs)
    known = np.array(sorted(fixed))
    u[known] = [fixed[d] for d in known]
    free = np.setdiff1d(np.arange(n_dofs), known)
    f = np.zeros(n_dofs) if loads is None else loads
    rhs = f[free] - k[free][:, known] @ u[known]
    u[free] = sla.spsolve(k[free][:, free].tocsc(), rhs)
    return u


@pytest.mark.parametrize("integration", ifem.INTEGRATIONS)
def test_element_is_symmetric_with_six_rigid_modes(integration: str) -> None:
    ke = ifem.element_stiffness(2.0, 1.5, 1.0, E, NU, integration)
    assert np.allclose(ke, ke.T, atol=1e-14)
    eig = np.linalg.eigvalsh(ke)
    assert np.sum(np.abs(eig) < 1e-10 * eig.max()) == 6 and eig.min() > -1e-12


@pytest.mark.parametrize("integration", ifem.INTEGRATIONS)
def test_patch_test_reproduces_any_linear_field(integration: str) -> None:
    # Uneven spacing; a general linear field on the boundary must come out exactly inside.
    mesh = ifem.StructuredMesh(np.array([0.0, 0.7, 2.0, 2.5]), np.array([0.0, 1.2, 1.5, 3.0]),
                               np.array([-4.0, -2.5, -1.0, 0.0]), np.zeros(1, int), np.zeros(1, int))
    k = ifem.assemble(mesh, E, 0.49, integration)
    xyz = mesh.coordinates()
    grad = np.array([[1e-3, 2e-3, -1e-3], [0.5e-3, -2e-3, 3e-3], [-1e-3, 1e-3, 2e-3]])
    exact = (xyz @ grad.T + np.array([0.01, -0.02, 0.005])).ravel()
    lo, hi = xyz.min(0), xyz.max(0)
    boundary = np.flatnonzero(np.any(np.isclose(xyz, lo) | np.isclose(xyz, hi), axis=1))
    dofs = (3 * boundary[:, None] + np.arange(3)).ravel()
    u = _solve(k, k.shape[0], dict(zip(dofs.tolist(), exact[dofs])))
    assert np.abs(u - exact).max() < 1e-12
    # Rigid motions cost no force.
    assert np.abs(k @ np.tile([1.0, 0, 0], mesh.n_nodes)).max() < 1e-12


def _column(dx: float, layers: int, h: float = 4.0, width: float | None = None) -> ifem.StructuredMesh:
    x = np.linspace(0.0, width or dx, round((width or dx) / dx) + 1)
    return ifem.StructuredMesh(x, np.array([0.0, dx]), np.linspace(-h, 0.0, layers + 1), np.zeros(1, int), np.zeros(1, int))


@pytest.mark.parametrize("integration", ["bbar", "full"])
def test_constrained_layer_under_uniform_load_has_the_confined_stiffness(integration: str) -> None:
    # Laterally constrained layer (rollers), uniform normal displacement: p / u = M / h for any integration.
    h, nu, side = 4.0, 0.49, 2.0
    mesh = _column(1.0, 4, h, side)
    k = ifem.assemble(mesh, E, nu, integration)
    xyz = mesh.coordinates()
    fixed = {}
    for n, (_, _, z) in enumerate(xyz):
        fixed[3 * n] = fixed[3 * n + 1] = 0.0
        if z == -h:
            fixed[3 * n + 2] = 0.0
        elif z == 0.0:
            fixed[3 * n + 2] = -0.01
    u = _solve(k, k.shape[0], fixed)
    top = np.flatnonzero(xyz[:, 2] == 0.0)
    force = -(k @ u)[3 * top + 2].sum()
    stiffness = force / (0.01 * side * 1.0)
    assert stiffness == pytest.approx(ifem.confined_stiffness_n_per_mm3(E, nu, h), rel=1e-9)


def _sine_load_stiffness_ratio(integration: str, dx: float = 1.0, layers: int = 4) -> float:
    return ifem.sine_load_stiffness_ratio(E, 0.49, 4.0, element_mm=dx, layers=layers, integration=integration)


def test_bbar_does_not_lock_where_full_integration_does() -> None:
    full = _sine_load_stiffness_ratio("full")
    bbar = _sine_load_stiffness_ratio("bbar")
    sri = _sine_load_stiffness_ratio("sri")
    assert full > 1.2  # plain 2x2x2 hex8 is ~25 % too stiff at nu = 0.49 on 1 mm elements
    assert bbar == pytest.approx(1.0, abs=0.02) and sri == pytest.approx(1.0, abs=0.02)
    # And it converges: finer elements approach the layer's exact compliance.
    assert abs(_sine_load_stiffness_ratio("bbar", dx=0.5, layers=8) - 1) < abs(bbar - 1) + 1e-3


@pytest.fixture(scope="module")
def stiffness(rig: RigConfig) -> np.ndarray:
    return ifem.compute_stiffness(rig)


def test_condensed_stiffness_is_spd_and_holds_against_translation(rig: RigConfig, stiffness: np.ndarray) -> None:
    m = rig.markers.rows * rig.markers.cols
    assert stiffness.shape == (3 * m, 3 * m)
    assert np.abs(stiffness - stiffness.T).max() < 1e-12 * np.abs(stiffness).max()
    assert np.linalg.eigvalsh(stiffness).min() > 0
    for axis in range(3):
        u = np.zeros((m, 3))
        u[:, axis] = 0.1
        f = forces_from_displacements(stiffness, u)
        assert net_force_n(f)[axis] > 0.1  # the fixed bottom resists a rigid shift (N)
        assert np.sum(f * u) > 0


def test_forces_match_a_forward_solve(rig: RigConfig, stiffness: np.ndarray) -> None:
    mesh = ifem.marker_mesh(rig)
    k = ifem.assemble(mesh, rig.gel.youngs_modulus_mpa, rig.gel.poisson_ratio)
    rest = rig.markers.rest_positions_mm()
    r2 = (rest[:, :2] ** 2).sum(1)
    u = np.stack([0.1 * np.exp(-r2 / 20), -0.05 * np.exp(-r2 / 10), -0.8 * np.exp(-r2 / 8)], axis=1)
    markers = mesh.marker_nodes()
    fixed = {3 * n + c: u[i, c] for i, n in enumerate(markers) for c in range(3)}
    xyz = mesh.coordinates()
    for n in np.flatnonzero(xyz[:, 2] == -rig.gel.thickness_mm):
        fixed.update({3 * n + c: 0.0 for c in range(3)})
    full = _solve(k, k.shape[0], fixed)
    reactions = (k @ full)[(3 * markers[:, None] + np.arange(3)).ravel()].reshape(-1, 3)
    f = forces_from_displacements(stiffness, u)
    assert np.abs(f - reactions).max() < 1e-8 * np.abs(reactions).max()
    assert net_force_n(f)[2] < 0  # pressing in: force on the gel points down


def test_stiffness_is_cached_by_its_inputs(rig: RigConfig, stiffness: np.ndarray, tmp_path) -> None:  # type: ignore[no-untyped-def]
    k1 = ifem.build_stiffness(rig, cache_dir=tmp_path)
    assert np.array_equal(k1, stiffness)
    files = list((tmp_path / "ifem").glob("K-*.npz"))
    assert len(files) == 1
    assert np.array_equal(ifem.build_stiffness(rig, cache_dir=tmp_path), k1)
    soft = ifem.IfemParams(youngs_modulus_mpa=0.2)
    assert ifem.stiffness_key(rig, soft) != ifem.stiffness_key(rig)
    assert np.allclose(ifem.build_stiffness(rig, soft, cache_dir=tmp_path), k1 / 2)  # linear in E
    assert len(list((tmp_path / "ifem").glob("K-*.npz"))) == 2


def test_interpolated_refinement_lumps_forces_onto_markers(rig: RigConfig, stiffness: np.ndarray) -> None:
    fine = ifem.compute_stiffness(rig, ifem.IfemParams(refinement=2, layers=2))
    assert np.linalg.eigvalsh(fine).min() > 0
    m = rig.markers.rows * rig.markers.cols
    u = np.zeros((m, 3))
    u[:, 2] = -0.1
    # A uniform push: the refined mesh gives nearly the same total force as nodes at the markers.
    coarse_total = net_force_n(forces_from_displacements(ifem.compute_stiffness(rig, ifem.IfemParams(layers=2)), u))[2]
    assert net_force_n(forces_from_displacements(fine, u))[2] == pytest.approx(coarse_total, rel=0.1)
    with pytest.raises(ValueError):
        ifem.compute_stiffness(rig, ifem.IfemParams(refinement=2, layers=1, between_markers="nope"))
