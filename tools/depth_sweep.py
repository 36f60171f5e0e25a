"""Depth network sweep: accuracy against latency over U-Net widths, each trained under one fixed time budget.

Trains one model per width on a campaign (``labrig train`` in-process, same seed, window,
loss and time budget) into a folder that ``labrig evaluate --models DIR`` loads (NAME.onnx +
NAME.json each), then measures each: val and test depth MAE (mm, total / contact), and
onnxruntime latency per window on one thread. Prints a table with the issue's targets
(<= 5 ms per window, test MAE <= 0.091 mm total and <= 0.265 mm in contact, the paper's)
and writes ``DIR/sweep.json``.

    .venv/bin/python tools/depth_sweep.py data/                       # widths 4, 8, 16; 20 min each
    .venv/bin/python tools/depth_sweep.py data/ --widths 4,8,16 --budget-min 5 --out models/sweep
    .venv/bin/python tools/depth_sweep.py data/ --table2 --widths 8 --budget-min 5 --out models/sweep

``--table2`` trains the paper's Table II instead, at one width: the contact-aware loss with
windows of 5, 10, 30, 50 and 70 ms and the uniform loss at 10 ms (a model already in the
folder, e.g. the width sweep's 10 ms one, is only re-measured). ``labrig evaluate --models
DIR`` finds each row's model by its card.

A rerun resumes each width from its checkpoint (an interrupted sweep loses at most
``--checkpoint-every`` steps); a finished width is only re-measured.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from rich.console import Console
from rich.table import Table

from labrig.pipeline.depthnet import benchmark_ms
from labrig.training import TrainConfig, output_paths, train
from labrig.training.trainer import split_errors

TARGET_MS = 5.0
PAPER_TOTAL_MM = 0.091
PAPER_CONTACT_MM = 0.265
TABLE2_WINDOWS_MS = (5.0, 10.0, 30.0, 50.0, 70.0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path, help="campaign folder with manifest.csv and NAME.gt.h5 sidecars")
    ap.add_argument("--widths", default="4,8,16", help="comma-separated U-Net base widths (default 4,8,16)")
    ap.add_argument("--budget-min", type=float, default=20.0, help="training time per width, minutes (default 20)")
    ap.add_argument("--out", type=Path, default=Path("models/sweep"), help="folder of the models (default models/sweep)")
    ap.add_argument("--window-ms", type=float, default=10.0)
    ap.add_argument("--loss", default="contact", choices=("contact", "uniform"))
    ap.add_argument("--batch-size", type=int, default=16)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None, help="torch training threads (default: torch's)")
    ap.add_argument("--val-every", type=int, default=200)
    ap.add_argument("--checkpoint-every", type=int, default=200)
    ap.add_argument("--eval-windows", type=int, default=256, help="windows per split for the val/test MAE")
    ap.add_argument("--table2", action="store_true",
                    help="train the paper's Table II (windows 5-70 ms contact-aware, 10 ms uniform) at one width")
    ap.add_argument("--json", action="store_true", help="print the results as JSON")
    args = ap.parse_args(argv)

    widths = [int(w) for w in args.widths.split(",") if w.strip()]
    if len(widths) < 1 or any(w < 1 for w in widths):
        ap.error("--widths: give positive integers, e.g. 4,8,16")
    if args.table2 and len(widths) != 1:
        ap.error("--table2 trains at one width: give --widths W")
    configs = ([(widths[0], window, "contact") for window in TABLE2_WINDOWS_MS] + [(widths[0], 10.0, "uniform")]
               if args.table2 else [(width, args.window_ms, args.loss) for width in widths])
    console = Console(stderr=True)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for width, window_ms, loss in configs:
        stem = args.out / f"depth-w{width}-{loss}-{window_ms:g}ms"
        config = TrainConfig(width=width, window_ms=window_ms, loss=loss, time_budget_min=args.budget_min,
                             batch_size=args.batch_size, lr=args.lr, seed=args.seed, threads=args.threads,
                             val_every=args.val_every, checkpoint_every=args.checkpoint_every)
        console.print(f"[bold]width {width}[/]: {args.budget_min:g} min -> {stem}.onnx")
        command = (f"python tools/depth_sweep.py {args.data} --widths {args.widths} --budget-min {args.budget_min:g} "
                   f"--out {args.out} --window-ms {window_ms:g} --loss {loss} --seed {args.seed}"
                   + (" --table2" if args.table2 else ""))
        card = train(args.data, config, stem, resume=output_paths(stem)["checkpoint"].exists(), command=command,
                     show_progress=not args.json)
        onnx_path = output_paths(stem)["onnx"]
        val = split_errors(onnx_path, args.data, "val", args.eval_windows)
        test = split_errors(onnx_path, args.data, "test", args.eval_windows)
        latency = benchmark_ms(onnx_path, threads=1, repeats=200, warmup=20)
        t = card["training"]
        rows.append({"width": width, "window_ms": window_ms, "loss": loss, "parameters": card["parameters"],
                     "onnx": str(onnx_path),
                     "onnx_bytes": onnx_path.stat().st_size, "steps": t["steps"], "train_s": t["seconds"],
                     "samples_per_s": t["samples_per_s"], "final_loss": t["final_loss"], "ms_per_window_ort_1thread":
                     round(latency, 3), "val": val, "test": test, "reproduce": card["reproduce"]})
    summary = {"data": str(args.data), "budget_min": args.budget_min, "window_ms": args.window_ms, "loss": args.loss,
               "eval_windows": args.eval_windows, "targets": {"ms_per_window": TARGET_MS, "total_mm": PAPER_TOTAL_MM,
                                                              "contact_mm": PAPER_CONTACT_MM}, "widths": rows}
    (args.out / ("table2.json" if args.table2 else "sweep.json")).write_text(json.dumps(summary, indent=2) + "\n")
    if args.json:
        sys.stdout.write(json.dumps(summary, indent=2) + "\n")
        return 0
    what = "Table II models" if args.table2 else f"widths, {args.window_ms:g} ms, {args.loss} loss"
    table = Table(title=f"depth network sweep: {args.budget_min:g} min per model, {what}")
    for col in ("width", "window", "loss", "params", "steps", "windows/s", "val total", "val contact", "test total",
                "test contact", "ms/window (ort, 1 thr)", "targets"):
        table.add_column(col, justify="right")
    for r in rows:
        v, te = r["val"] or {}, r["test"] or {}
        misses = []
        if r["ms_per_window_ort_1thread"] > TARGET_MS:
            misses.append(f"+{r['ms_per_window_ort_1thread'] - TARGET_MS:.1f} ms")
        if te.get("total_mm") is not None and te["total_mm"] > PAPER_TOTAL_MM:
            misses.append(f"total +{te['total_mm'] - PAPER_TOTAL_MM:.3f} mm")
        if te.get("contact_mm") is not None and te["contact_mm"] > PAPER_CONTACT_MM:
            misses.append(f"contact +{te['contact_mm'] - PAPER_CONTACT_MM:.3f} mm")
        table.add_row(str(r["width"]), f"{r['window_ms']:g} ms", r["loss"], f"{r['parameters'] / 1e6:.2f} M",
                      str(r["steps"]), f"{r['samples_per_s']:.1f}",
                      _mm(v.get("total_mm")), _mm(v.get("contact_mm")), _mm(te.get("total_mm")), _mm(te.get("contact_mm")),
                      f"{r['ms_per_window_ort_1thread']:.2f}", "all met" if not misses else "misses " + ", ".join(misses))
    out = Console(width=None if sys.stdout.isatty() else 160)
    out.print(table)
    out.print(f"models and sweep.json in {args.out} (MAE on {args.eval_windows} random windows per split)")
    return 0


def _mm(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


if __name__ == "__main__":
    sys.exit(main())
