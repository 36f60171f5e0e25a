"""Inverse FEM cost and locking: K build time (once), F = K U per window, 8-point vs B-bar stiffness.

Measured on the default rig (12 x 13 markers, 4 mm gel, 2 mm in-plane elements,
``--layers`` (4) layers, margins to the gel's edges):
* K build: assembly + static condensation, no cache (best of ``--repeat``), and
  loading it from the disk cache.
* F = K U: a (468 x 468) mat-vec per window, median over ``--matvecs`` calls, as a
  share of the 10 ms window.
* Locking at nu = 0.49: (a) on the condensed K, plain 2x2x2 over B-bar net normal
  force for the same smooth dimple (3 mm wide, 0.5 mm deep); (b) on a bonded
  layer under a cos load (16 mm wavelength, 1 mm elements), FE over exact
  stiffness for full integration and B-bar (1 = no locking).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from typing import Any

import numpy as np
from _common import bench_main, emit

from labrig.config import load_rig
from labrig.pipeline import ifem
from labrig.pipeline.forces import forces_from_displacements

WINDOW_S = 0.010


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", type=int, default=4, help="mesh layers through the gel")
    ap.add_argument("--repeat", type=int, default=3, help="K builds (best is reported)")
    ap.add_argument("--matvecs", type=int, default=2000, help="F = K U calls timed")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def run(layers: int = 4, repeat: int = 3, matvecs: int = 2000, progress: bool = True) -> dict[str, Any]:
    rig = load_rig()
    params = ifem.IfemParams(layers=layers)
    builds = []
    for _ in range(repeat):
        t = time.perf_counter()
        k = ifem.compute_stiffness(rig, params)
        builds.append(time.perf_counter() - t)
    with tempfile.TemporaryDirectory() as cache:
        ifem.build_stiffness(rig, params, cache_dir=cache)
        t = time.perf_counter()
        ifem.build_stiffness(rig, params, cache_dir=cache)
        load_s = time.perf_counter() - t
    rest = rig.markers.rest_positions_mm()
    u = np.zeros_like(rest)
    u[:, 2] = -0.5 * np.exp(-(rest[:, :2] ** 2).sum(1) / (2 * 1.5**2))
    times = []
    for _ in range(matvecs):
        t = time.perf_counter()
        forces_from_displacements(k, u)
        times.append(time.perf_counter() - t)
    if progress:
        print("locking checks at nu = 0.49 ...", flush=True)
    at = {name: ifem.compute_stiffness(rig, ifem.IfemParams(layers=layers, integration=name, poisson_ratio=0.49))
          for name in ("full", "bbar")}
    fz = {name: forces_from_displacements(kk, u)[:, 2].sum() for name, kk in at.items()}
    e = rig.gel.youngs_modulus_mpa
    sine = {name: ifem.sine_load_stiffness_ratio(e, 0.49, rig.gel.thickness_mm, integration=name) for name in ("full", "bbar")}
    return {
        "markers": len(rest), "layers": layers, "k_shape": list(k.shape),
        "k_build_s": min(builds), "k_cache_load_s": load_s,
        "fku_median_us": float(np.median(times) * 1e6),
        "fku_window_fraction": float(np.median(times) / WINDOW_S),
        "dimple_force_full_over_bbar_nu049": float(fz["full"] / fz["bbar"]),
        "sine_load_fe_over_exact_full_nu049": sine["full"],
        "sine_load_fe_over_exact_bbar_nu049": sine["bbar"],
    }


def render(f: dict[str, Any]) -> None:
    rows = [
        ["K build (assemble + condense), once", f"{f['k_build_s']:.3f} s", ""],
        ["K from the disk cache", f"{f['k_cache_load_s'] * 1e3:.1f} ms", ""],
        ["F = K U per window", f"{f['fku_median_us']:.1f} us", f"{f['fku_window_fraction']:.5f}"],
        ["nu 0.49 dimple force: 8-point / B-bar", f"{f['dimple_force_full_over_bbar_nu049']:.3f}", ""],
        ["nu 0.49 cos load, FE / exact: 8-point", f"{f['sine_load_fe_over_exact_full_nu049']:.3f}", ""],
        ["nu 0.49 cos load, FE / exact: B-bar", f"{f['sine_load_fe_over_exact_bbar_nu049']:.3f}", ""],
    ]
    emit(f"Inverse FEM: K {f['k_shape'][0]} x {f['k_shape'][1]}, {f['layers']} layers", ["figure", "value", "share of 10 ms"],
         rows, ["stiffness ratios above 1 are locking (too stiff)"])


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
