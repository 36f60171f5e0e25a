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

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from labrig.config import RigConfig

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
    ex, ey, ez = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), np.arange(nz - 1), indexing="ij")
    ex, ey, ez = ex.ravel(), ey.ravel(), ez.ravel()
    sizes = np.round(np.stack([dx[ex], dy[ey], dz[ez]], axis=1), 12)
    unique, kind = np.unique(sizes, axis=0, return_inverse=True)
    ke = np.stack([element_stiffness(*s, youngs_modulus_mpa, poisson_ratio, integration) for s in unique])
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


def _material(rig: RigConfig, params: IfemParams) -> tuple[float, float]:
    e = rig.gel.youngs_modulus_mpa if params.youngs_modulus_mpa is None else params.youngs_modulus_mpa
    nu = rig.gel.poisson_ratio if params.poisson_ratio is None else params.poisson_ratio
    return float(e), float(nu)


def stiffness_cache_dir(cache_dir: str | Path | None = None) -> Path:
    """``cache_dir``, else $LABRIG_CACHE, else ~/.cache/labrig; plus /ifem."""
    root = cache_dir or os.environ.get("LABRIG_CACHE") or Path.home() / ".cache" / "labrig"
    return Path(root) / "ifem"


def stiffness_key(rig: RigConfig, params: IfemParams = IfemParams()) -> str:
    """A hash of every input of :func:`build_stiffness`."""
    e, nu = _material(rig, params)
    spec = {
        "version": CACHE_VERSION, "params": {**asdict(params), "youngs_modulus_mpa": e, "poisson_ratio": nu},
        "gel": [rig.gel.thickness_mm, rig.gel.size_x_mm, rig.gel.size_y_mm],
        "markers": [rig.markers.rows, rig.markers.cols, rig.markers.pitch_mm],
    }
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:20]


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
    :func:`labrig.sim.mechanics.spectral.layer_normal_compliance`.
    """
    from scipy.sparse.linalg import spsolve

    from labrig.config import GelConfig
    from labrig.sim.mechanics.spectral import layer_normal_compliance

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
