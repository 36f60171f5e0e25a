"""Study: can the normal displacement (depth map) be inferred from the tracked marker motion alone?

Issue 21, option 5: no network; depth from the in-plane marker displacements through the gel's
mechanics. What this study found (docs/depthnet.md, "Depth from marker motion alone"):

* In the virtual rig the normal and tangential contact problems are decoupled (Goodman; see
  :mod:`labrig.physics.mechanics.spectral`): pressing moves no marker in-plane (``/truth/markers``:
  0.0000 mm during Normal Down). The in-plane displacements carry no information on depth there,
  and on a real bonded near-incompressible layer the coupling is a few um per 0.1 mm of depth.
* What the camera does see is perspective: a marker pressed d mm towards the camera (30 mm below
  the surface) moves radially outward in the image by about f r d / Z^2 (0.9 px per mm of depth per
  mm off the optical axis on the default rig). So the tracked pixel motion does hold depth,
  off-axis, mixed with the in-plane motion of shear (a single view cannot tell a radial in-plane
  shift from a press without a prior).

The estimator here (:class:`ParallaxDepth`) inverts that: the markers' pixel displacements are
modelled as J_z d + J_t u_t (the camera's Jacobian at each marker's rest point; J_z the secant over
the current depth estimate), d = C_zz p with the surface pressure p >= 0 on the surface operator's
1 mm nodes (C_zz the bonded layer's condensed compliance, :mod:`labrig.pipeline.ifem`, gel from the
rig/calibration) and u_t the in-plane motion of a stuck contact (one rigid shift s over the
estimated contact set, C_tt restricted to it, traction-free elsewhere). Non-negative least squares
with a small ridge on p picks the contact set; it is refined twice. Zero pixel motion gives p = 0,
so zero depth, exactly.

For each recording (virtual rig, short probing runs recorded here, not in real time) it compares,
on the same 20,000-event windows: the sim's true depth (upper bound), the bundled depth network,
this estimator fed the tracker's positions, and fed the sim's true marker pixels (tracker error
removed). Depth MAE (total / in contact, mm), net-force MAE against ``/truth/marker_forces`` (N),
and the contact position error (px) through the pipeline's own forces stage.

    PYTHONPATH=. OPENBLAS_NUM_THREADS=1 .venv/bin/python tools/physics_depth_study.py --out /tmp/physdepth
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.optimize import nnls

from labrig.config import DEFAULT_RIG, load_rig
from labrig.dataset import sidecar_path
from labrig.evaluation.depth import per_map_errors_mm
from labrig.evaluation.measured import contact_centre_px
from labrig.groundtruth import generate, load_groundtruth, write_sidecar
from labrig.indenters import load_indenter
from labrig.physics.grid import GRID_SHAPE, network_grid_gel_mm
from labrig.pipeline import depth_sources, ifem, runtime
from labrig.pipeline.run_setup import PipelineSetup, setup_for_recording
from labrig.pipeline.windows import PAPER_WINDOW_EVENTS, window_ends_us
from labrig.recording import Recording

F64 = npt.NDArray[np.float64]

#: (name, location mm, depth mm, shear mm, indenter): off-axis and on-axis, pure press and sheared.
SCENES = (
    ("centre-sphere", (0.0, 0.0), 1.0, 0.5, "sphere"),
    ("offaxis-sphere", (6.0, -4.0), 1.2, 0.8, "sphere"),
    ("press-sphere", (8.0, 5.0), 1.0, 0.0, "sphere"),
    ("offaxis-cylinder", (-7.0, 3.0), 1.0, 0.6, "cylinder"),
    ("offaxis-square", (-4.0, -6.0), 1.2, 0.5, "square"),
)


def record_scenes(out: Path) -> list[Path]:
    """Record each scene (virtual rig, not real time) with its sidecar, unless already there."""
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    rig = load_rig(DEFAULT_RIG)
    paths = []
    for name, location, depth, shear, indenter_name in SCENES:
        path = out / f"{name}.h5"
        paths.append(path)
        if path.exists() and sidecar_path(path).exists():
            continue
        indenter = load_indenter(indenter_name)
        tool = probing_path(rig, indenter, location_mm=location, depth_mm=depth, shear_mm=shear,
                            normal_speed_mm_s=3.0, shear_speed_mm_s=3.0, wait_s=0.1, approach_mm=0.2)
        record_live(path, rig, indenter, tool, seed=3, realtime=False)
        write_sidecar(generate(path, rate_hz=100), sidecar_path(path))
    return paths


class ParallaxDepth:
    """Depth map (90 x 112, mm into the gel) from the markers' pixel displacements (M, 2) alone; see the module docstring."""

    def __init__(self, setup: PipelineSetup, ridge: float = 0.003, contact_floor: float = 0.05) -> None:
        rig, camera = setup.rig, setup.camera
        op = ifem.build_surface_operator(rig, ifem.SurfaceParams(youngs_modulus_mpa=setup.youngs_modulus_mpa,
                                                                 poisson_ratio=setup.poisson_ratio))
        xy = op.node_xy_mm
        self.node_xy_mm = xy  # (N, 2) gel frame, the 1 mm lattice over the marker cells
        self.n = len(xy)
        self.c_zz = np.linalg.inv(op.k_zz)  # mm/N: node forces -> normal displacement (up positive)
        self.c_tt = np.linalg.inv(op.k_tt)
        self.rest_mm = rig.markers.rest_positions_mm()
        self.markers = np.array([int(np.argmin(((xy - r[:2]) ** 2).sum(1))) for r in self.rest_mm])
        self.camera = camera
        self.jac = camera.jacobian_px_per_mm(self.rest_mm)  # (M, 2, 3) px/mm at rest
        self.sampler = _lattice_sampler(xy, network_grid_gel_mm(rig, camera).reshape(-1, 2))
        self.ridge, self.contact_floor = ridge, contact_floor

    def _normal_matrix(self, marker_depth_mm: F64) -> F64:
        """(2M, N): pixel displacement per unit node force (into the gel), perspective secant at the current depth.

        A marker pressed d mm into the gel sits at z = -d: its pixel moves by ``per_depth`` d."""
        per_depth = -self.jac[:, :, 2]
        deep = marker_depth_mm > 1e-3
        if deep.any():
            pressed = self.rest_mm[deep] - np.outer(marker_depth_mm[deep], [0.0, 0.0, 1.0])
            moved = self.camera.project(pressed) - self.camera.project(self.rest_mm[deep])
            per_depth[deep] = moved / marker_depth_mm[deep, None]
        return (per_depth[:, :, None] * self.c_zz[self.markers][:, None, :]).reshape(-1, self.n)  # depth = C_zz f

    def _shift_matrix(self, nodes: npt.NDArray[np.int64]) -> F64:
        """(2M, 2): pixel displacement per mm of rigid in-plane shift of the contact nodes (stuck, traction-free elsewhere)."""
        both = np.concatenate([nodes, self.n + nodes])
        unit = np.zeros((2 * nodes.size, 2))
        unit[: nodes.size, 0] = unit[nodes.size:, 1] = 1.0
        traction = np.linalg.solve(self.c_tt[np.ix_(both, both)], unit)
        ux = self.c_tt[self.markers][:, both] @ traction
        uy = self.c_tt[self.n + self.markers][:, both] @ traction
        return np.einsum("mij,mjk->mik", self.jac[:, :, :2], np.stack([ux, uy], 1)).reshape(-1, 2)

    def node_depth_mm(self, pixel_displacement: npt.ArrayLike) -> F64:
        """(N,) normal displacement at the surface nodes, mm into the gel, from (M, 2) pixel displacements."""
        y = np.asarray(pixel_displacement, np.float64).reshape(-1)
        if not np.any(y):
            return np.zeros(self.n)
        depth_at_markers = np.zeros(len(self.markers))
        force = np.zeros(self.n)
        shift_nodes = np.zeros(0, np.int64)
        for _ in range(3):
            g = self._normal_matrix(depth_at_markers)
            scale = np.linalg.norm(g) / np.sqrt(self.n) * self.ridge
            target = y
            if shift_nodes.size:
                # The shift is free: the best one for any pressure leaves the residual's part outside the
                # shift's column space, so project both sides onto its complement and solve for the pressure
                # alone (the exact minimiser, as a bounded least squares over both would give when converged).
                q, _ = np.linalg.qr(self._shift_matrix(shift_nodes))
                g, target = g - q @ (q.T @ g), y - q @ (q.T @ y)
            force, _ = nnls(np.vstack([g, scale * np.eye(self.n)]), np.concatenate([target, np.zeros(self.n)]),
                            maxiter=50 * self.n)
            depth_at_markers = self.c_zz[self.markers] @ force
            if force.max() <= 0:
                break
            shift_nodes = np.flatnonzero(force > self.contact_floor * force.max())
        return self.c_zz @ force

    def depth_map_mm(self, pixel_displacement: npt.ArrayLike) -> npt.NDArray[np.float32]:
        return np.asarray(self.sampler @ self.node_depth_mm(pixel_displacement), np.float32).reshape(GRID_SHAPE)


def _lattice_sampler(node_xy_mm: F64, points_mm: F64) -> sp.csr_matrix:
    """(P, N) bilinear interpolation from the regular node lattice to gel points; zero outside it."""
    xs, ys = np.unique(node_xy_mm[:, 0].round(9)), np.unique(node_xy_mm[:, 1].round(9))
    lut = np.full((len(ys), len(xs)), -1)
    row, col = np.searchsorted(ys, node_xy_mm[:, 1].round(9)), np.searchsorted(xs, node_xy_mm[:, 0].round(9))
    lut[row, col] = np.arange(len(node_xy_mm))
    fx = np.interp(points_mm[:, 0], xs, np.arange(len(xs)))
    fy = np.interp(points_mm[:, 1], ys, np.arange(len(ys)))
    inside = ((points_mm[:, 0] >= xs[0]) & (points_mm[:, 0] <= xs[-1]) & (points_mm[:, 1] >= ys[0])
              & (points_mm[:, 1] <= ys[-1])).astype(float)
    c0 = np.minimum(np.floor(fx).astype(int), len(xs) - 2)
    r0 = np.minimum(np.floor(fy).astype(int), len(ys) - 2)
    ax, ay = fx - c0, fy - r0
    rows, cols, vals = [], [], []
    for dr, dc, w in ((0, 0, (1 - ay) * (1 - ax)), (0, 1, (1 - ay) * ax), (1, 0, ay * (1 - ax)), (1, 1, ay * ax)):
        rows.append(np.arange(len(points_mm)))
        cols.append(lut[r0 + dr, c0 + dc])
        vals.append(w * inside)
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(len(points_mm), len(node_xy_mm)))


class _Given(depth_sources.DepthSource):
    """A depth source that returns the map it was handed (the study sets it before each back stage)."""

    needs_sae = False
    window_us: float | None = None

    def __init__(self, name: str) -> None:
        self.name = name
        self.map = np.zeros(GRID_SHAPE, np.float32)

    def depth_mm(self, sae_grid: object, t0_us: int, t1_us: int, n_events: int = 0) -> npt.NDArray[np.float32]:
        return self.map


@dataclass(frozen=True)
class Row:
    recording: str
    source: str
    depth_total_mm: float
    depth_contact_mm: float
    force_mae_n: tuple[float, float, float]
    position_px: float
    depth_ms: float


def study(path: Path, model: str, max_windows: int | None = None) -> list[Row]:
    """The four depth sources on one recording's 20,000-event windows (see the module docstring); with
    ``max_windows``, on its first windows only (a quick look)."""
    rec = Recording(path)
    gt = load_groundtruth(sidecar_path(path))
    setup = setup_for_recording(rec)
    estimator = ParallaxDepth(setup)
    t0, t1 = window_ends_us(rec, window_events=PAPER_WINDOW_EVENTS)
    t0, t1 = t0[:max_windows], t1[:max_windows]
    tm = rec.column("truth/markers", "t_host_us")
    true_px = rec.column("truth/markers", "position_px").astype(np.float64)
    index = np.atleast_1d(gt.nearest_index(t1.astype(np.float64)))
    true_maps, contact = gt.depth_mm[index], gt.contact_mask[index] > 0
    t_forces = rec.column("truth/marker_forces", "t_host_us")
    true_force = rec.column("truth/marker_forces", "force_n")[np.clip(np.searchsorted(t_forces, t1), 0, len(t_forces) - 1)].sum(1)
    centre = contact_centre_px(gt, t1, setup.camera)
    centre[~contact.reshape(len(t1), -1).any(1)] = np.nan
    network = depth_sources.depth_source("model", setup, model_path=model)  # as `labrig run` builds it
    sources = {"truth": depth_sources.TruthDepth(rec), f"model:{Path(model).stem}": network,
               "physics (tracked px)": _Given("physics-tracked"), "physics (true px)": _Given("physics-true")}
    rows = []
    for label, source in sources.items():
        pipe = runtime.Pipeline(setup, source)
        maps, forces, where, seconds = [], [], [], []
        for a, b in zip(t0, t1, strict=True):
            tracked = pipe.front(int(a), int(b), rec.events_between(a, b))
            if isinstance(source, _Given):
                if source.name == "physics-tracked":
                    motion = tracked.positions_px - setup.rest_px
                else:
                    i = int(np.clip(np.searchsorted(tm, b), 0, len(tm) - 1))
                    motion = true_px[i] - true_px[0]
                start = time.perf_counter()
                source.map = estimator.depth_map_mm(motion)
                seconds.append(time.perf_counter() - start)
            result = pipe.back(tracked)
            maps.append(result.depth_mm)
            forces.append(result.net_force_n)
            where.append(result.contact_px)
            if not isinstance(source, _Given):
                seconds.append(result.seconds["depth"])
        pred = np.clip(np.array(maps), 0.0, gt.scale_mm)
        errors = per_map_errors_mm(pred, np.clip(true_maps, 0.0, gt.scale_mm), contact)
        force_mae = np.nanmean(np.abs(np.array(forces) - true_force), axis=0)
        position = np.linalg.norm(np.array(where) - centre, axis=1)
        mean_px = float(np.nanmean(position)) if np.isfinite(position).any() else float("nan")
        rows.append(Row(path.stem, label, float(errors["total_mm"].mean()), float(np.nanmean(errors["contact_mm"])),
                        tuple(float(v) for v in force_mae), mean_px,
                        float(np.median(seconds) * 1e3)))
    rec.close()
    return rows


def main() -> None:
    from rich.console import Console
    from rich.table import Table

    from labrig import models

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("/tmp/physdepth"), help="folder for the recordings")
    parser.add_argument("--model", default=str(models.bundled_model_path()), help="the depth network to compare")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    parser.add_argument("--scenes", default="", help="comma-separated scene names (default: all)")
    parser.add_argument("--max-windows", type=int, default=None, help="only each recording's first windows")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    wanted = set(filter(None, args.scenes.split(",")))
    rows = []
    for path in record_scenes(args.out):
        if wanted and path.stem not in wanted:
            continue
        for row in study(path, args.model, args.max_windows):
            print(row, flush=True)
            rows.append(row)
    table = Table("recording", "depth source", "depth MAE total / contact (mm)", "force MAE x / y / z (N)",
                  "position (px)", "depth ms / window")
    for r in rows:
        table.add_row(r.recording, r.source, f"{r.depth_total_mm:.3f} / {r.depth_contact_mm:.3f}",
                      " / ".join(f"{v:.2f}" for v in r.force_mae_n), f"{r.position_px:.1f}", f"{r.depth_ms:.1f}")
    for source in dict.fromkeys(r.source for r in rows):
        mine = [r for r in rows if r.source == source]
        table.add_row("[b]mean[/b]", source, f"{np.mean([r.depth_total_mm for r in mine]):.3f} / "
                      f"{np.mean([r.depth_contact_mm for r in mine]):.3f}",
                      " / ".join(f"{v:.2f}" for v in np.mean([r.force_mae_n for r in mine], 0)),
                      f"{np.nanmean([r.position_px for r in mine]):.1f}", f"{np.median([r.depth_ms for r in mine]):.1f}")
    Console().print(table)
    if args.json:
        args.json.write_text(json.dumps([r.__dict__ for r in rows], indent=1))


if __name__ == "__main__":
    main()
