"""Depth stage with state: the cost of the state channels, side by side with the SAE alone.

Setup (not timed): one U-Net per input set of one width (``--width``, 4 like the bundled network;
latency does not depend on the weights, so they are untrained) exported to ONNX with cards
naming their inputs (``sae``, ``sae+disp``, ``sae+disp+prev``, ``sae+bright``, ``sae+bright+disp``), each behind a
:class:`~labrig.pipeline.depth_sources.ModelDepth` built by the one builder for the default
rig, the quiet hold and the rest gate off so that the network runs every window.
``--windows`` (300) windows of random SAEs, markers drifting off their rest and
``--events`` (1,500, a 10 ms window of the virtual rig's press) random events.

Measured: ``markers()`` + ``depth_mm()`` wall time per window (back-projection, raster,
stacking, onnxruntime on one thread), plus, for a brightness network, the front stage's
signed counts of the window's events and ``counts()`` (the integrator), median and p95, as a share of the 10 ms window, and
each stateful source as a ratio to the SAE-only one measured in the same run.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import bench_main, emit

from labrig.config import load_rig
from labrig.eventtypes import EVENT_DTYPE
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline import depth_sources, run_setup
from labrig.pipeline.brightness import signed_counts
from labrig.pipeline.depth_inputs import INPUT_SETS, InputSpec
from labrig.pipeline.depthnet import UNetConfig, build_unet, export_onnx

WINDOW_US = 10_000


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--windows", type=int, default=300, help="windows per source")
    ap.add_argument("--width", type=int, default=4, help="U-Net base width (4: the bundled network's)")
    ap.add_argument("--events", type=int, default=1500, help="events per window (the brightness channels count them)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def _time(source: depth_sources.ModelDepth, saes: np.ndarray, positions: np.ndarray, rest: np.ndarray,
          events: list[np.ndarray], roi: Any) -> np.ndarray:
    def window(k: int) -> None:
        if source.needs_counts:
            source.counts(signed_counts(events[k], roi), (k + 1) * WINDOW_US)
        source.markers(positions[k], rest)
        source.depth_mm(saes[k], k * WINDOW_US, (k + 1) * WINDOW_US, 1000)

    for k in range(5):  # warm-up
        window(k)
    times = []
    for k in range(len(saes)):
        t = time.perf_counter()
        window(k)
        times.append(time.perf_counter() - t)
    return np.array(times)


def _events(rng: np.random.Generator, roi: Any, n: int, k: int) -> np.ndarray:
    ev = np.zeros(n, EVENT_DTYPE)
    ev["x"] = rng.integers(roi.x0_px, roi.x1_px, n)
    ev["y"] = rng.integers(roi.y0_px, roi.y1_px, n)
    ev["p"] = rng.integers(0, 2, n)
    ev["t"] = np.sort(rng.integers(k * WINDOW_US, (k + 1) * WINDOW_US, n))
    return ev


def run(windows: int = 300, width: int = 4, events: int = 1500, progress: bool = True) -> dict[str, Any]:
    import torch

    torch.manual_seed(0)
    setup = run_setup.setup_for_rig(load_rig(), calibration_dir=None)
    rng = np.random.default_rng(0)
    saes = rng.random((windows, 2, *GRID_SHAPE), dtype=np.float32) * (rng.random((windows, 2, *GRID_SHAPE)) < 0.1)
    drift = np.cumsum(rng.normal(0.0, 0.05, (windows, *setup.rest_px.shape)), axis=0)
    positions = setup.rest_px[None] + drift
    roi = setup.rig.roi
    window_events = [_events(rng, roi, events, k) for k in range(windows)]
    figures: dict[str, Any] = {"windows": windows, "width": width, "window_ms": WINDOW_US / 1000,
                               "markers": len(setup.rest_px), "events_per_window": events}
    with tempfile.TemporaryDirectory() as folder:
        for name in INPUT_SETS:
            spec = InputSpec.named(name)
            path = Path(folder) / f"{name.replace('+', '-')}.onnx"
            card = {"name": path.stem, "scale_mm": 2.5, "window_ms": 10.0, "inputs": spec.to_card()}
            export_onnx(build_unet(UNetConfig(width=width, in_channels=spec.channels)), path, card)
            source = depth_sources.depth_source("model", setup, model_path=path, quiet=None, rest=None)
            assert isinstance(source, depth_sources.ModelDepth)
            if progress:
                print(f"timing {name} ...", flush=True)
            t = _time(source, saes, positions, setup.rest_px, window_events, roi)
            figures[name] = {"median_ms": float(np.median(t) * 1e3), "p95_ms": float(np.percentile(t, 95) * 1e3),
                             "median_window_fraction": float(np.median(t) / (WINDOW_US / 1e6)),
                             "p95_window_fraction": float(np.percentile(t, 95) / (WINDOW_US / 1e6))}
    for name in INPUT_SETS:
        figures[name]["over_sae_median"] = figures[name]["median_ms"] / figures["sae"]["median_ms"]
    return figures


def render(f: dict[str, Any]) -> None:
    rows = [[name, f"{f[name]['median_ms']:.3f}", f"{f[name]['p95_ms']:.3f}", f"{f[name]['median_window_fraction']:.4f}",
             f"{f[name]['p95_window_fraction']:.4f}", f"{f[name]['over_sae_median']:.2f}"] for name in INPUT_SETS]
    emit(f"Depth stage with state: width {f['width']}, {f['markers']} markers, per {f['window_ms']:.0f} ms window, one thread",
         ["inputs", "median ms", "p95 ms", "median / window", "p95 / window", "/ sae (median)"], rows,
         ["the network runs every window (quiet hold and rest gate off); the stateful rows add the markers' "
          "back-projection, the raster, the brightness count of the window's events and the wider input"])


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
