"""Depth network: training throughput per width, and inference latency against the pipeline's budget.

Setup (not timed): one simulated probe (sphere, 1 mm, 1 mm shear) with its ground-truth
sidecar, as a tiny campaign (the same recording as train and val).

Measured side by side in one run, per U-Net width (default 4, 8, 16, 32):
* training: ``--steps`` Adam steps of batch 16 through :func:`labrig.training.train`
  (windows made in the main process, as in a real run); samples per second and the ratio
  to the paper-size width 32; then the smallest width again with patch training
  (``--crop-cells``, 64 by default), its windows per second against the whole grid's;
* inference: onnxruntime on one thread against torch eager on one thread (median per
  window), and the onnxruntime latency as a share of the 5 ms the pipeline allows the depth
  stage (below 1: within budget) and of a 10 ms window.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import bench_main, emit

DEPTH_BUDGET_MS = 5.0


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--widths", default="4,8,16,32", help="comma-separated U-Net base widths")
    ap.add_argument("--steps", type=int, default=12, help="timed training steps per width (after 2 warm-up steps)")
    ap.add_argument("--repeats", type=int, default=100, help="inference runs per width (median kept)")
    ap.add_argument("--crop-cells", type=int, default=64, help="the patch of the patch-training row (0: no such row)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def tiny_campaign(folder: Path) -> Path:
    from labrig.config import load_rig
    from labrig.dataset import sidecar_path
    from labrig.groundtruth import generate, write_sidecar
    from labrig.indenters import load_indenter
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    rig, sphere = load_rig(), load_indenter("sphere")
    tool = probing_path(rig, sphere, location_mm=(1.0, -1.0), depth_mm=1.0, shear_mm=1.0, wait_s=0.2)
    record_live(folder / "a.h5", rig, sphere, tool, realtime=False)
    write_sidecar(generate(folder / "a.h5", rate_hz=100), sidecar_path(folder / "a.h5"))
    shutil.copy(folder / "a.h5", folder / "b.h5")
    shutil.copy(folder / "a.gt.h5", folder / "b.gt.h5")
    (folder / "manifest.csv").write_text("id,split,status,file,sha256\na,train,complete,a.h5,\nb,val,complete,b.h5,\n")
    return folder


def torch_eager_ms(width: int, repeats: int) -> float:
    import numpy as np
    import torch

    from labrig.pipeline.depthnet import build_unet
    from labrig.pipeline.sae import UNET_SHAPE

    torch.set_num_threads(1)
    net = build_unet(width=width).eval()
    x = torch.rand(1, 2, *UNET_SHAPE)
    times = []
    with torch.no_grad():
        for i in range(repeats + 3):
            t = time.perf_counter()
            net(x)
            if i >= 3:
                times.append(time.perf_counter() - t)
    return float(np.median(times) * 1e3)


def run(widths: str = "4,8,16,32", steps: int = 12, repeats: int = 100, crop_cells: int = 64,
        progress: bool = True) -> dict[str, Any]:
    import torch

    from labrig.pipeline.depthnet import benchmark_ms
    from labrig.training import TrainConfig, output_paths, train

    torch_threads = torch.get_num_threads()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        data = tiny_campaign(Path(tmp))
        for width in (int(w) for w in widths.split(",")):
            if progress:
                print(f"width {width} ...", file=sys.stderr)
            stem = Path(tmp) / f"w{width}"
            card = train(data, TrainConfig(width=width, steps=steps + 2, val_every=0, val_windows=8,
                                           checkpoint_every=10_000), stem, show_progress=False)
            history = card["training"]
            onnx = output_paths(stem)["onnx"]
            ort_ms = benchmark_ms(onnx, threads=1, repeats=repeats, warmup=5)
            eager_ms = torch_eager_ms(width, max(repeats // 4, 10))
            torch.set_num_threads(torch_threads)
            rows.append({"width": width, "parameters": card["parameters"], "steps": history["steps"],
                         "samples_per_s": history["samples_per_s"], "window_share": history.get("sampling_share"),
                         "ort_ms": ort_ms, "torch_eager_ms": eager_ms, "ort_vs_eager": ort_ms / eager_ms,
                         "ort_vs_budget": ort_ms / DEPTH_BUDGET_MS, "ort_vs_window": ort_ms / 10.0})
        patch = None
        if crop_cells:
            width = min(int(w) for w in widths.split(","))
            card = train(data, TrainConfig(width=width, steps=steps + 2, val_every=0, val_windows=8, checkpoint_every=10_000,
                                           crop_cells=crop_cells), Path(tmp) / "patch", show_progress=False)
            whole = next(r for r in rows if r["width"] == width)
            patch = {"width": width, "crop_cells": crop_cells, "samples_per_s": card["training"]["samples_per_s"],
                     "window_share": card["training"]["sampling_share"],
                     "throughput_vs_whole_grid": card["training"]["samples_per_s"] / whole["samples_per_s"]}
    ref = next((r for r in rows if r["width"] == 32), rows[-1])
    for r in rows:
        r["throughput_vs_w32"] = r["samples_per_s"] / ref["samples_per_s"]
    return {"rows": rows, "patch": patch, "torch_threads": torch_threads, "batch_size": 16, "budget_ms": DEPTH_BUDGET_MS}


def render(f: dict[str, Any]) -> None:
    emit(
        f"Depth network: training (batch {f['batch_size']}, torch on {f['torch_threads']} threads) and inference "
        "(one thread)",
        ["width", "params", "train windows/s", "vs width 32", "ort ms", "torch eager ms", "ort / eager",
         f"ort / {f['budget_ms']:g} ms budget", "ort / 10 ms window"],
        [[str(r["width"]), f"{r['parameters'] / 1e6:.2f} M", f"{r['samples_per_s']:.1f}",
          f"{r['throughput_vs_w32']:.2f}", f"{r['ort_ms']:.2f}", f"{r['torch_eager_ms']:.2f}",
          f"{r['ort_vs_eager']:.2f}", f"{r['ort_vs_budget']:.2f}", f"{r['ort_vs_window']:.2f}"] for r in f["rows"]],
        ["Training windows/s include making each window (SAE from the recording) in the main process. "
         "Budget: the pipeline allows the depth stage 5 ms of a 10 ms window on one core."],
    )
    patch = f.get("patch")
    if patch:
        emit(f"Patch training, width {patch['width']}: windows cut to {patch['crop_cells']} x {patch['crop_cells']} cells",
             ["train windows/s", "vs the whole grid", "share making windows"],
             [[f"{patch['samples_per_s']:.1f}", f"{patch['throughput_vs_whole_grid']:.2f}",
               f"{patch['window_share']:.2f}"]], [])


SINGLE_THREAD = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def main(argv: list[str] | None = None) -> None:
    if argv is None and any(os.environ.get(var) != "1" for var in SINGLE_THREAD[:1]):
        os.environ.update({"OPENBLAS_NUM_THREADS": "1"})
        os.execv(sys.executable, [sys.executable, *sys.argv])
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
