"""Inverse FEM: the gel's condensed surface stiffness K (3M x 3M, N/mm) at the markers.

The gel is a linear isotropic elastic block of 8-node bricks on a structured mesh
whose top nodes include one node per marker (in-plane refinement subdivides each
marker pitch; optional margins extend the block to the gel's edges), layers
through the thickness, bottom nodes fixed (bonded to the acrylic). Every other
DOF (interior, non-marker top nodes: traction-free) is removed by static
condensation, K_c = K_tt - K_ti K_ii^-1 K_it, so that forces on the gel at the
markers follow from their displacements as F = K_c U.

Units: mm and MPa (N/mm^2), so K is in N/mm. DOFs are marker-major (x, y, z per
marker), markers in the rig's order (row-major from -y, -x of the gel frame).

Plain 2x2x2 integration locks as nu -> 0.5; ``integration`` picks "bbar"
(mean dilatation, default), "sri" (the lambda part at the element centre) or
"full". K is cached as .npz under $LABRIG_CACHE (default ~/.cache/labrig)/ifem,
keyed by a hash of every input.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import cast

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from labrig.cache import cache_folder, cache_key
from labrig.config import GelConfig, RigConfig
from labrig.physics.mechanics.spectral import layer_normal_compliance

Array = npt.NDArray[np.float64]

#: Bump when the numerics change: old cache files are then ignored.
CACHE_VERSION = 1
INTEGRATIONS = ("bbar", "sri", "full")

# Local node n = i + 2 j + 4 k sits at reference coordinates (2i-1, 2j-1, 2k-1).
_LOCAL = np.array([[2 * (n & 1) - 1, 2 * ((n >> 1) & 1) - 1, 2 * ((n >> 2) & 1) - 1] for n in range(8)], float)
_GAUSS = _LOCAL / np.sqrt(3.0)


@dataclass(frozen=True)
class IfemParams:
    """Mesh and material choices; ``None`` material values come from the rig's gel."""

    layers: int = 4
    refinement: int = 1  # elements per marker pitch, in-plane
    integration: str = "bbar"
    extend_to_gel: bool = True  # mesh the margin between the outer markers and the gel's edges
    #: With refinement > 1, top nodes between markers are "free" (traction-free, condensed out) or
    #: "interpolated" (bilinear in the markers' displacements; their forces are lumped onto the markers).
    between_markers: str = "interpolated"
    youngs_modulus_mpa: float | None = None
    poisson_ratio: float | None = None


@dataclass(frozen=True)
class StructuredMesh:
    """Node coordinates along each axis (mm) and the marker nodes' top-layer indices."""

    x_mm: Array
    y_mm: Array
    z_mm: Array  # from -thickness (bottom, fixed) to 0 (top)
    marker_ix: npt.NDArray[np.int64]  # (M,) column index of each marker's node
    marker_iy: npt.NDArray[np.int64]

    @property
    def shape(self) -> tuple[int, int, int]:
        return len(self.x_mm), len(self.y_mm), len(self.z_mm)

    @property
    def n_nodes(self) -> int:
        nx, ny, nz = self.shape
        return nx * ny * nz

    def node(self, ix: npt.ArrayLike, iy: npt.ArrayLike, iz: npt.ArrayLike) -> npt.NDArray[np.int64]:
        nx, ny, _ = self.shape
        return np.asarray(ix) + nx * (np.asarray(iy) + ny * np.asarray(iz))

    def coordinates(self) -> Array:
        """(n_nodes, 3) node positions, mm, in node order."""
        z, y, x = np.meshgrid(self.z_mm, self.y_mm, self.x_mm, indexing="ij")
        return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)

    def marker_nodes(self) -> npt.NDArray[np.int64]:
        return self.node(self.marker_ix, self.marker_iy, len(self.z_mm) - 1)


def lame_mpa(youngs_modulus_mpa: float, poisson_ratio: float) -> tuple[float, float]:
    """(lambda, mu) in MPa."""
    e, nu = youngs_modulus_mpa, poisson_ratio
    return e * nu / ((1 + nu) * (1 - 2 * nu)), e / (2 * (1 + nu))


def confined_stiffness_n_per_mm3(youngs_modulus_mpa: float, poisson_ratio: float, thickness_mm: float) -> float:
    """Uniform normal load on a laterally constrained layer: pressure / displacement = M / h (N/mm^3)."""
    lam, mu = lame_mpa(youngs_modulus_mpa, poisson_ratio)
    return (lam + 2 * mu) / thickness_mm


def _strain_matrices(dx: float, dy: float, dz: float, points: Array) -> Array:
    """(P, 6, 24) strain-displacement matrices (Voigt: xx yy zz yz xz xy) at reference points."""
    scale = np.array([2 / dx, 2 / dy, 2 / dz])
    p = points[:, None, :]  # (P, 1, 3)
    lin = 1.0 + p * _LOCAL[None]  # (P, 8, 3): (1 + xi xi_n) per axis
    grads = np.empty((len(points), 8, 3))
    for a in range(3):
        others = [b for b in range(3) if b != a]
        grads[..., a] = _LOCAL[None, :, a] * lin[..., others[0]] * lin[..., others[1]] / 8.0 * scale[a]
    b = np.zeros((len(points), 6, 24))
    gx, gy, gz = grads[..., 0], grads[..., 1], grads[..., 2]
    b[:, 0, 0::3], b[:, 1, 1::3], b[:, 2, 2::3] = gx, gy, gz
    b[:, 3, 1::3], b[:, 3, 2::3] = gz, gy
    b[:, 4, 0::3], b[:, 4, 2::3] = gz, gx
    b[:, 5, 0::3], b[:, 5, 1::3] = gy, gx
    return b


def element_stiffness(dx: float, dy: float, dz: float, youngs_modulus_mpa: float, poisson_ratio: float,
                      integration: str = "bbar") -> Array:
    """The 24 x 24 stiffness (N/mm) of an axis-aligned dx x dy x dz brick (mm); DOFs node-major."""
    if integration not in INTEGRATIONS:
        raise ValueError(f"integration must be one of {INTEGRATIONS}, not {integration!r}")
    lam, mu = lame_mpa(youngs_modulus_mpa, poisson_ratio)
    m = np.array([1.0, 1, 1, 0, 0, 0])
    d_mu = mu * np.diag([2.0, 2, 2, 1, 1, 1])
    d_full = lam * np.outer(m, m) + d_mu
    w = dx * dy * dz / 8.0  # Gauss weight 1 times det J
    b = _strain_matrices(dx, dy, dz, _GAUSS)
    if integration == "full":
        return np.einsum("pia,ij,pjb->ab", b, d_full, b) * w
    if integration == "sri":
        b0 = _strain_matrices(dx, dy, dz, np.zeros((1, 3)))[0]
        div0 = m @ b0
        return np.einsum("pia,ij,pjb->ab", b, d_mu, b) * w + lam * np.outer(div0, div0) * dx * dy * dz
    div = np.einsum("i,pia->pa", m, b)  # (P, 24) dilatation rows
    div_mean = div.mean(axis=0)
    bbar = b + (m[None, :, None] / 3.0) * (div_mean - div)[:, None, :]
    return np.einsum("pia,ij,pjb->ab", bbar, d_full, bbar) * w


def assemble(mesh: StructuredMesh, youngs_modulus_mpa: float, poisson_ratio: float,
             integration: str = "bbar") -> sp.csr_matrix:
    """The global stiffness (3 n_nodes square, N/mm) of the structured mesh, no boundary conditions."""
    nx, ny, nz = mesh.shape
    dx, dy, dz = np.diff(mesh.x_mm), np.diff(mesh.y_mm), np.diff(mesh.z_mm)
    grid_x, grid_y, grid_z = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), np.arange(nz - 1), indexing="ij")
    ex, ey, ez = grid_x.ravel(), grid_y.ravel(), grid_z.ravel()
    sizes = np.round(np.stack([dx[ex], dy[ey], dz[ez]], axis=1), 12)
    unique, kind = np.unique(sizes, axis=0, return_inverse=True)
    ke = np.stack([element_stiffness(size_x, size_y, size_z, youngs_modulus_mpa, poisson_ratio, integration)
                   for size_x, size_y, size_z in unique])
    nodes = mesh.node(ex[:, None] + (_LOCAL[:, 0] > 0), ey[:, None] + (_LOCAL[:, 1] > 0), ez[:, None] + (_LOCAL[:, 2] > 0))
    dofs = (3 * nodes[:, :, None] + np.arange(3)).reshape(len(ex), 24)
    rows = np.broadcast_to(dofs[:, :, None], (len(ex), 24, 24)).ravel()
    cols = np.broadcast_to(dofs[:, None, :], (len(ex), 24, 24)).ravel()
    n = 3 * mesh.n_nodes
    return sp.coo_matrix((ke[kind.ravel()].ravel(), (rows, cols)), shape=(n, n)).tocsr()


def _axis_nodes(n_markers: int, pitch_mm: float, refinement: int, half_size_mm: float | None) -> tuple[Array, int]:
    """Node coordinates along one axis and the index of the first marker node."""
    half_span = (n_markers - 1) * pitch_mm / 2
    inner = np.linspace(-half_span, half_span, (n_markers - 1) * refinement + 1)
    margin = 0.0 if half_size_mm is None else half_size_mm - half_span
    if margin <= 1e-9:
        return inner, 0
    assert half_size_mm is not None
    n_margin = int(np.ceil(margin / (pitch_mm / refinement) - 1e-9))
    outer = np.linspace(half_span, half_size_mm, n_margin + 1)[1:]
    return np.concatenate([-outer[::-1], inner, outer]), n_margin


def marker_mesh(rig: RigConfig, params: IfemParams = IfemParams()) -> StructuredMesh:
    """The structured mesh with top nodes at the rig's markers."""
    mk, gel = rig.markers, rig.gel
    if params.layers < 1 or params.refinement < 1:
        raise ValueError("layers and refinement must be at least 1")
    x, x0 = _axis_nodes(mk.cols, mk.pitch_mm, params.refinement, gel.size_x_mm / 2 if params.extend_to_gel else None)
    y, y0 = _axis_nodes(mk.rows, mk.pitch_mm, params.refinement, gel.size_y_mm / 2 if params.extend_to_gel else None)
    z = np.linspace(-gel.thickness_mm, 0.0, params.layers + 1)
    rows, cols = np.divmod(np.arange(mk.rows * mk.cols), mk.cols)
    return StructuredMesh(x, y, z, x0 + params.refinement * cols, y0 + params.refinement * rows)


def condense(k_full: sp.spmatrix, kept_dofs: npt.NDArray[np.int64], fixed_dofs: npt.NDArray[np.int64]) -> Array:
    """Static condensation onto ``kept_dofs`` (in that order) with ``fixed_dofs`` clamped: dense K_c."""
    n = k_full.shape[0]
    inner = np.setdiff1d(np.arange(n), np.concatenate([kept_dofs, fixed_dofs]))
    k = k_full.tocsr()
    k_tt = k[kept_dofs][:, kept_dofs].toarray()
    k_it = k[inner][:, kept_dofs].toarray(order="F")
    lu = splu(k[inner][:, inner].tocsc(), permc_spec="MMD_AT_PLUS_A")
    kc = k_tt - k_it.T @ lu.solve(k_it)
    return (kc + kc.T) / 2


def _material(rig: RigConfig, params: IfemParams | SurfaceParams) -> tuple[float, float]:
    e = rig.gel.youngs_modulus_mpa if params.youngs_modulus_mpa is None else params.youngs_modulus_mpa
    nu = rig.gel.poisson_ratio if params.poisson_ratio is None else params.poisson_ratio
    return float(e), float(nu)


def stiffness_cache_dir(cache_dir: str | Path | None = None) -> Path:
    """``cache_dir``, else the cache root (:mod:`labrig.cache`); plus /ifem."""
    return cache_folder("ifem", cache_dir)


def stiffness_key(rig: RigConfig, params: IfemParams = IfemParams()) -> str:
    """A hash of every input of :func:`build_stiffness`."""
    e, nu = _material(rig, params)
    spec = {
        "version": CACHE_VERSION, "params": {**asdict(params), "youngs_modulus_mpa": e, "poisson_ratio": nu},
        "gel": [rig.gel.thickness_mm, rig.gel.size_x_mm, rig.gel.size_y_mm],
        "markers": [rig.markers.rows, rig.markers.cols, rig.markers.pitch_mm],
    }
    return cache_key(spec)


def build_stiffness(rig: RigConfig, params: IfemParams = IfemParams(), *, cache_dir: str | Path | None = None,
                    use_cache: bool = True) -> Array:
    """K (3M x 3M, N/mm): from the disk cache, or assembled, condensed and cached."""
    path = stiffness_cache_dir(cache_dir) / f"K-{stiffness_key(rig, params)}.npz"
    if use_cache and path.exists():
        try:
            with np.load(path) as data:
                return np.array(data["K"])
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache file: rebuild it
    start = time.perf_counter()
    k = compute_stiffness(rig, params)
    if use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
        np.savez(tmp, K=k, build_seconds=time.perf_counter() - start)
        os.replace(tmp, path)
    return k


def compute_stiffness(rig: RigConfig, params: IfemParams = IfemParams()) -> Array:
    """Assemble and condense K without the cache."""
    e, nu = _material(rig, params)
    mesh = marker_mesh(rig, params)
    k_full = assemble(mesh, e, nu, params.integration)
    bottom = mesh.node(*[a.ravel() for a in np.meshgrid(np.arange(mesh.shape[0]), np.arange(mesh.shape[1]), 0)])
    fixed = (3 * bottom[:, None] + np.arange(3)).ravel()
    if params.refinement == 1 or params.between_markers == "free":
        kept = (3 * mesh.marker_nodes()[:, None] + np.arange(3)).ravel()
        return condense(k_full, kept, fixed)
    if params.between_markers != "interpolated":
        raise ValueError(f"between_markers must be 'free' or 'interpolated', not {params.between_markers!r}")
    nodes, t = _surface_interpolation(mesh, rig.markers.rows, rig.markers.cols, params.refinement)
    kept = (3 * nodes[:, None] + np.arange(3)).ravel()
    k_surface = condense(k_full, kept, fixed)
    t3 = sp.kron(t, sp.identity(3), format="csr")
    k = np.asarray(t3.T @ (t3.T @ k_surface.T).T)
    return (k + k.T) / 2


def _surface_interpolation(mesh: StructuredMesh, rows: int, cols: int,
                           refinement: int) -> tuple[npt.NDArray[np.int64], sp.csr_matrix]:
    """Top nodes inside the marker grid and the bilinear map (n_nodes x M) from marker values to them."""
    ix0, iy0 = int(mesh.marker_ix[0]), int(mesh.marker_iy[0])
    ix = np.arange(ix0, ix0 + (cols - 1) * refinement + 1)
    iy = np.arange(iy0, iy0 + (rows - 1) * refinement + 1)
    gy, gx = np.meshgrid(iy, ix, indexing="ij")
    nodes = mesh.node(gx.ravel(), gy.ravel(), len(mesh.z_mm) - 1)
    fx, fy = (gx.ravel() - ix0) / refinement, (gy.ravel() - iy0) / refinement
    c0 = np.minimum(np.floor(fx).astype(np.int64), cols - 2)
    r0 = np.minimum(np.floor(fy).astype(np.int64), rows - 2)
    ax, ay = fx - c0, fy - r0
    row_idx, col_idx, val = [], [], []
    for dr, dc, w in ((0, 0, (1 - ay) * (1 - ax)), (0, 1, (1 - ay) * ax), (1, 0, ay * (1 - ax)), (1, 1, ay * ax)):
        row_idx.append(np.arange(len(nodes)))
        col_idx.append((r0 + dr) * cols + c0 + dc)
        val.append(w)
    t = sp.coo_matrix((np.concatenate(val), (np.concatenate(row_idx), np.concatenate(col_idx))),
                      shape=(len(nodes), rows * cols)).tocsr()
    t.eliminate_zeros()
    return nodes, t


def sine_load_stiffness_ratio(youngs_modulus_mpa: float, poisson_ratio: float, thickness_mm: float, *,
                              wavelength_mm: float = 16.0, element_mm: float = 1.0, layers: int = 4,
                              integration: str = "bbar") -> float:
    """FE over exact stiffness of a bonded layer under a normal load p cos(kx) (frictionless top, plane strain).

    A verification of the element and the mesh (locking shows as a ratio above 1): one
    half-wavelength, symmetry planes at the crests, the exact compliance from
    :func:`labrig.physics.mechanics.spectral.layer_normal_compliance`.
    """
    from scipy.sparse.linalg import spsolve


    h, p, half = thickness_mm, 1e-3, wavelength_mm / 2
    k_wave = 2 * np.pi / wavelength_mm
    x = np.linspace(0.0, half, round(half / element_mm) + 1)
    mesh = StructuredMesh(x, np.array([0.0, element_mm]), np.linspace(-h, 0.0, layers + 1), np.zeros(1, np.int64),
                          np.zeros(1, np.int64))
    k = assemble(mesh, youngs_modulus_mpa, poisson_ratio, integration)
    xyz = mesh.coordinates()
    n_dofs = k.shape[0]
    fixed = np.zeros(n_dofs, bool)
    fixed[1::3] = True  # plane strain
    fixed[0::3] |= np.isclose(xyz[:, 0], 0.0) | np.isclose(xyz[:, 0], half)  # symmetry at the crests
    bottom = np.isclose(xyz[:, 2], -h)
    fixed[0::3] |= bottom
    fixed[2::3] |= bottom
    loads = np.zeros(n_dofs)
    gx, gw = np.polynomial.legendre.leggauss(8)
    top = len(mesh.z_mm) - 1
    for e in range(len(x) - 1):
        a, b = x[e], x[e + 1]
        xs, w = (a + b) / 2 + (b - a) / 2 * gx, (b - a) / 2 * gw
        for ix, shape in ((e, (b - xs) / (b - a)), (e + 1, (xs - a) / (b - a))):
            nodes = mesh.node(ix, np.arange(2), top)
            loads[3 * nodes + 2] -= np.sum(p * np.cos(k_wave * xs) * shape * w) * element_mm / 2
    u = np.zeros(n_dofs)
    free = ~fixed
    u[free] = spsolve(k[free][:, free].tocsc(), loads[free])
    crest_uz = -u[3 * mesh.node(0, 0, top) + 2]
    gel = GelConfig(h, 1.0, 1.0, youngs_modulus_mpa, poisson_ratio, 0.0)
    return float(p * layer_normal_compliance(k_wave, gel) / crest_uz)


# -- Dense surface operator ---------------------------------------------------------------------
#
# The paper's K above has one top node per marker, so the surface between markers is bilinear
# in their displacements: far too stiff for a dimple one or two pitches wide. The surface
# operator meshes the top finely (``refinement`` elements per pitch) and takes the normal
# displacement at every top node inside the marker cells from the dense depth map, the in-plane
# one from the markers (natural cubic splines over the grid), and sums nodal forces over each
# marker's 2 x 2 mm cell (the cells of /truth/marker_forces).
#
# Two condensed stiffnesses of the top nodes inside the cells (everything else free, bottom
# fixed): K_zz for normal displacements with the surface free in-plane, K_tt for in-plane ones
# with the surface free normally (the classic split of normal and tangential contact problems,
# which the virtual rig's mechanics make too). Per window the displacements are prescribed only
# where the surface is pressed in (depth above a threshold: the contact and its rim) and the rest
# of the surface is traction-free: f_A = (C_AA)^-1 u_A with C = K^-1. So the bulge around a
# dimple comes from the model, not from the map (a network that clips depth at 0 has none, and
# prescribing such a map everywhere doubles the net force), and no traction appears where
# nothing touches. "field" mode prescribes every node instead: f = K u.

FORCE_MODES = ("contact", "field")
SURFACE_CACHE_VERSION = 3


@dataclass(frozen=True)
class SurfaceParams:
    """Mesh and material choices of :func:`build_surface_operator`."""

    refinement: int = 2  # elements per marker pitch in-plane over the marker cells (2: 1 mm)
    layers: int = 4
    #: Mesh beyond the marker cells, mm, in elements growing 1.5x up to ``margin_element_mm``;
    #: traction-free. The virtual rig's layer has no edges: about four thicknesses is enough (the net
    #: normal force of a bonded, nearly incompressible layer is a balance between the dimple and the
    #: bulge around it, so a block that ends at the cells is 20 % too soft). ``None``: the gel's own edges.
    margin_mm: float | None = 16.0
    margin_element_mm: float = 4.0
    integration: str = "bbar"
    youngs_modulus_mpa: float | None = None
    poisson_ratio: float | None = None


@dataclass(frozen=True)
class SurfaceOperator:
    """Per-marker forces (M, 3) N from the normal displacement at the top nodes and the markers' in-plane one.

    ``node_xy_mm`` (N, 2): top nodes (gel frame, at rest) inside the marker cells; ``k_zz`` (N, N)
    N/mm their condensed normal stiffness (surface free in-plane); ``k_tt`` (2N, 2N) N/mm their
    condensed in-plane stiffness (surface free normally; x of every node, then y); ``cells``
    (M, N) each node's share in each marker cell; ``interp`` (N, M) the markers' in-plane
    displacements to the nodes (natural cubic splines).
    """

    node_xy_mm: Array
    k_zz: Array
    k_tt: Array
    cells: Array
    interp: Array
    build_seconds: float = 0.0

    @property
    def n_markers(self) -> int:
        return self.cells.shape[0]

    def compliance(self, name: str) -> Array:
        """C = K^-1 (N/mm)^-1 of ``k_zz`` or ``k_tt`` (``name``), inverted once and kept."""
        c = self.__dict__.get(f"_inv_{name}")
        if c is None:
            c = np.linalg.inv(getattr(self, name))
            c = (c + c.T) / 2
            object.__setattr__(self, f"_inv_{name}", c)
        return c

    def precompute(self) -> SurfaceOperator:
        """Invert the stiffnesses the mixed solves read (C = K^-1, some hundred ms once), so that the first
        window does not pay for it; returns ``self``."""
        self.compliance("k_zz")
        self.compliance("k_tt")
        return self

    def node_forces_n(self, uz_nodes_mm: npt.ArrayLike, u_markers_mm: npt.ArrayLike, mode: str = "contact",
                      threshold_mm: float = 0.01) -> Array:
        """(N, 3) nodal forces on the gel; ``uz_nodes_mm`` (N,) up positive (pressed in: negative),
        ``u_markers_mm`` (M, 2|3) the markers' displacements (in-plane used).

        "contact": displacements prescribed where the surface is pressed deeper than
        ``threshold_mm`` (the contact and its rim), the rest of the surface traction-free in every
        direction; "field": prescribed on every node (the whole map, bulge included).
        """
        uz = np.asarray(uz_nodes_mm, np.float64)
        ut = self.interp @ np.asarray(u_markers_mm, np.float64)[:, :2]  # (N, 2)
        n = len(uz)
        out = np.zeros((n, 3))
        if mode == "field":
            out[:, 2] = self.k_zz @ uz
            out[:, :2] = (self.k_tt @ ut.T.reshape(-1)).reshape(2, n).T
            return out
        if mode != "contact":
            raise ValueError(f"mode must be one of {FORCE_MODES}, not {mode!r}")
        pressed = np.flatnonzero(uz < -threshold_mm)
        if pressed.size == 0:
            return out
        out[pressed, 2] = self._mixed_solve("k_zz", pressed, uz[pressed])
        both = np.concatenate([pressed, pressed + n])
        ft = self._mixed_solve("k_tt", both, ut[pressed].T.reshape(-1))
        out[pressed, 0], out[pressed, 1] = ft[: pressed.size], ft[pressed.size:]
        return out

    def _mixed_solve(self, name: str, held: npt.NDArray[np.int64], u: Array) -> Array:
        """Forces on the ``held`` DOFs with displacements ``u`` there and the others free.

        Small held sets: (C_hh)^-1 u with C = K^-1; large ones: the Schur complement over the
        free set, K_hh - K_hf K_ff^-1 K_fh, so a window costs at most a half-size solve.
        """
        from scipy.linalg import solve

        k = getattr(self, name)
        if 2 * held.size <= len(k):
            return np.asarray(solve(self.compliance(name)[np.ix_(held, held)], u, assume_a="pos"))
        free = np.setdiff1d(np.arange(len(k)), held)
        k_hu = k[np.ix_(held, held)] @ u
        if free.size == 0:
            return np.asarray(k_hu)
        k_fh = k[np.ix_(free, held)]
        return np.asarray(k_hu - k_fh.T @ solve(k[np.ix_(free, free)], k_fh @ u, assume_a="pos"))

    def forces_n(self, uz_nodes_mm: npt.ArrayLike, u_markers_mm: npt.ArrayLike, mode: str = "contact",
                 threshold_mm: float = 0.01) -> Array:
        """(M, 3) N on the gel per marker cell (pressing: Fz < 0); see :meth:`node_forces_n`."""
        return self.cells @ self.node_forces_n(uz_nodes_mm, u_markers_mm, mode, threshold_mm)

    def scaled(self, factor: float) -> SurfaceOperator:
        """The operator of a gel ``factor`` times stiffer (forces are linear in E)."""
        return SurfaceOperator(self.node_xy_mm, self.k_zz * factor, self.k_tt * factor, self.cells, self.interp,
                               self.build_seconds)


def _graded(start: float, stop: float, first_mm: float, growth: float, largest_mm: float) -> Array:
    """Node coordinates after ``start`` up to ``stop``, elements growing from ``first_mm``."""
    out, h = [start], first_mm
    while out[-1] < stop - 1e-9:
        h = min(h * growth, largest_mm)
        out.append(min(out[-1] + h, stop))
        if stop - out[-1] < 0.5 * h:
            out[-1] = stop
    return np.array(out[1:])


def surface_axis(n_markers: int, pitch_mm: float, refinement: int, margin_mm: float,
                 margin_element_mm: float = 4.0) -> Array:
    """Node coordinates along one axis: uniform over the marker cells, graded beyond them."""
    half = n_markers * pitch_mm / 2
    inner = np.linspace(-half, half, n_markers * refinement + 1)
    if margin_mm <= 1e-9:
        return inner
    outer = _graded(half, half + margin_mm, pitch_mm / refinement, 1.5, max(margin_element_mm, pitch_mm / refinement))
    return np.concatenate([-outer[::-1], inner, outer])


def surface_mesh(rig: RigConfig, params: SurfaceParams = SurfaceParams()) -> StructuredMesh:
    """The structured mesh of :func:`build_surface_operator` (its marker indices are unused: empty)."""
    mk, gel = rig.markers, rig.gel
    if params.layers < 1 or params.refinement < 1:
        raise ValueError("layers and refinement must be at least 1")
    axes = []
    for n, size in ((mk.cols, gel.size_x_mm), (mk.rows, gel.size_y_mm)):
        margin = params.margin_mm if params.margin_mm is not None else max(size / 2 - n * mk.pitch_mm / 2, 0.0)
        axes.append(surface_axis(n, mk.pitch_mm, params.refinement, margin, params.margin_element_mm))
    z = np.linspace(-gel.thickness_mm, 0.0, params.layers + 1)
    empty = np.zeros(0, np.int64)
    return StructuredMesh(axes[0], axes[1], z, empty, empty)


def cell_weights(coord_mm: Array, axis_mm: Array, centres_mm: Array, pitch_mm: float) -> Array:
    """(len(coord), len(centres)): share of each node's tributary interval in each cell along one axis.

    Nodes outside the cells get no weight; those on the outer edge count wholly in the outer cell."""
    i = np.searchsorted(axis_mm, coord_mm - 1e-9)
    n = len(axis_mm)
    lo = np.where(i > 0, (coord_mm + axis_mm[np.maximum(i - 1, 0)]) / 2, coord_mm)
    hi = np.where(i < n - 1, (coord_mm + axis_mm[np.minimum(i + 1, n - 1)]) / 2, coord_mm)
    a, b = centres_mm - pitch_mm / 2, centres_mm + pitch_mm / 2
    lo, hi = np.maximum(lo, a[0]), np.minimum(hi, b[-1])  # the outer nodes' forces go to the outer cells
    overlap = np.clip(np.minimum(hi[:, None], b[None]) - np.maximum(lo[:, None], a[None]), 0.0, None)
    return overlap / np.maximum(hi - lo, 1e-12)[:, None]


def spline_weights(coord_mm: Array, knots_mm: Array) -> Array:
    """(len(coord), len(knots)): natural cubic spline interpolation through the knots (linear beyond)."""
    from scipy.interpolate import CubicSpline

    return np.asarray(CubicSpline(knots_mm, np.eye(len(knots_mm)), axis=0, bc_type="natural")(coord_mm))


def _reaction_sums(k: sp.csr_matrix, prescribed: npt.NDArray[np.int64], fixed: npt.NDArray[np.int64],
                   sums: sp.csr_matrix, inputs: sp.csr_matrix) -> Array:
    """sums @ K_c @ inputs, K_c the condensation onto ``prescribed`` with ``fixed`` clamped and the rest free."""
    n = k.shape[0]
    free = np.setdiff1d(np.arange(n), np.concatenate([fixed, prescribed]))
    k_pp = k[prescribed][:, prescribed]
    k_fp = k[free][:, prescribed]
    lu = splu(k[free][:, free].tocsc(), permc_spec="MMD_AT_PLUS_A")
    direct = np.asarray((sums @ k_pp @ inputs).todense())
    if sums.shape[0] <= inputs.shape[1]:  # fewer right-hand sides from the summing side
        x = lu.solve(np.asarray((k_fp @ sums.T).todense(), order="F"))
        return direct - np.asarray((k_fp @ inputs).T @ x).T
    x = lu.solve(np.asarray((k_fp @ inputs).todense(), order="F"))
    return direct - np.asarray((sums @ k_fp.T) @ x)


def compute_surface_operator(rig: RigConfig, params: SurfaceParams = SurfaceParams()) -> SurfaceOperator:
    """Assemble and condense the surface operator (no cache)."""
    start = time.perf_counter()
    e, nu = _material(rig, params)
    mk = rig.markers
    mesh = surface_mesh(rig, params)
    k = assemble(mesh, e, nu, params.integration)
    nx, ny, nz = mesh.shape
    gy, gx = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    x, y = mesh.x_mm[gx.ravel()], mesh.y_mm[gy.ravel()]
    half_x, half_y = mk.cols * mk.pitch_mm / 2, mk.rows * mk.pitch_mm / 2
    inside = (np.abs(x) <= half_x + 1e-9) & (np.abs(y) <= half_y + 1e-9)
    top = mesh.node(gx.ravel()[inside], gy.ravel()[inside], nz - 1)
    bottom = mesh.node(gx.ravel(), gy.ravel(), 0)
    fixed = (3 * bottom[:, None] + np.arange(3)).ravel()
    cx = cast(Array, (np.arange(mk.cols) - (mk.cols - 1) / 2) * mk.pitch_mm)
    cy = cast(Array, (np.arange(mk.rows) - (mk.rows - 1) / 2) * mk.pitch_mm)
    xi, yi = x[inside], y[inside]
    wx, wy = cell_weights(xi, mesh.x_mm, cx, mk.pitch_mm), cell_weights(yi, mesh.y_mm, cy, mk.pitch_mm)
    cells = np.ascontiguousarray((wy[:, :, None] * wx[:, None, :]).reshape(len(xi), -1).T)  # (M, N): node -> cell
    sx, sy = spline_weights(xi, cx), spline_weights(yi, cy)
    interp = (sy[:, :, None] * sx[:, None, :]).reshape(len(xi), -1)
    interp[np.abs(interp) < 1e-12] = 0.0  # (N, M): marker values -> node values
    n = len(top)
    eye = sp.identity(n, format="csr")
    k_zz = _reaction_sums(k, 3 * top + 2, fixed, eye, eye)
    eye2 = sp.identity(2 * n, format="csr")
    k_tt = _reaction_sums(k, np.concatenate([3 * top, 3 * top + 1]), fixed, eye2, eye2)
    return SurfaceOperator(np.stack([xi, yi], 1), (k_zz + k_zz.T) / 2, (k_tt + k_tt.T) / 2, cells, interp,
                           time.perf_counter() - start)


def surface_key(rig: RigConfig, params: SurfaceParams = SurfaceParams()) -> str:
    """A hash of every input of :func:`build_surface_operator` except E (the operator is linear in E)."""
    _, nu = _material(rig, params)
    spec = {
        "version": SURFACE_CACHE_VERSION, "params": {**asdict(params), "youngs_modulus_mpa": None, "poisson_ratio": nu},
        "gel": [rig.gel.thickness_mm, rig.gel.size_x_mm, rig.gel.size_y_mm],
        "markers": [rig.markers.rows, rig.markers.cols, rig.markers.pitch_mm],
    }
    return cache_key(spec)


_SURFACE_ARRAYS = ("node_xy_mm", "k_zz", "k_tt", "cells", "interp")


def build_surface_operator(rig: RigConfig, params: SurfaceParams = SurfaceParams(), *,
                           cache_dir: str | Path | None = None, use_cache: bool = True) -> SurfaceOperator:
    """The surface operator from the disk cache (stored for E = 1 MPa, then scaled), or computed and cached."""
    e, _ = _material(rig, params)
    path = stiffness_cache_dir(cache_dir) / f"S-{surface_key(rig, params)}.npz"
    if use_cache and path.exists():
        try:
            with np.load(path) as data:
                node_xy_mm, k_zz, k_tt, cells, interp = (np.array(data[name]) for name in _SURFACE_ARRAYS)
                unit = SurfaceOperator(node_xy_mm, k_zz, k_tt, cells, interp, build_seconds=float(data["build_seconds"]))
            return unit.scaled(e)
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache file: rebuild it
    op = compute_surface_operator(rig, params)
    if use_cache:
        unit = op.scaled(1.0 / e)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
        np.savez(tmp, build_seconds=op.build_seconds, **{name: getattr(unit, name) for name in _SURFACE_ARRAYS})
        os.replace(tmp, path)
    return op
