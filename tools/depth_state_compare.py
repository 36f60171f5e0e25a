"""Depth that carries state: the SAE-only network against networks that also take the gel's state, in one table.

Trains one network per input set (``labrig train --inputs``: ``sae``, the paper's;
``sae+disp``, + the tracker's marker displacement field; ``sae+disp+prev``, + the previous
depth map) on the same campaign with the same width, seed, batch and step budget, then runs
each through the whole pipeline (:func:`labrig.evaluation.forces.evaluate_forces`: the
tracker, the depth source from the one builder with its quiet hold and rest gate, the
inverse FEM) over the split's recordings and prints one table:

* depth MAE (mm) over the grid and over the true contact cells, of the maps the pipeline
  itself produced window after window (the stateful networks see their own previous map);
* force MAE x / y / z (N) and the contact position error (px), probing windows, as Table III;
* the normal force left after the press (mean |Fz| in N over the windows after Normal Up):
  a stale dent shows here;
* latency per window (median ms, one core): the depth stage and the whole pipeline.

    .venv/bin/python tools/depth_state_compare.py data/ --out models/state --width 8 --steps 2000
    .venv/bin/python tools/depth_state_compare.py data/ --out models/state --json

A variant whose network is already in ``--out`` (NAME.onnx + card) is only re-measured.
Writes ``OUT/compare.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
from rich.console import Console
from rich.table import Table

from labrig.dataset import Dataset
from labrig.errors import LabrigError
from labrig.evaluation.forces import ForceResult, ForceTask, evaluate_forces
from labrig.evaluation.tables import table3
from labrig.pipeline.depth_inputs import INPUT_SETS
from labrig.pipeline.model_card import ModelCard
from labrig.recording import Recording
from labrig.training import TrainConfig, output_paths, train

VARIANTS = tuple(INPUT_SETS)


@dataclass(frozen=True)
class VariantRow:
    """One variant's line of the table; errors in mm, N, px; times in ms."""

    variant: str
    depth_total_mm: float
    depth_contact_mm: float
    force_x_mae_n: float
    force_y_mae_n: float
    force_z_mae_n: float
    position_mae_px: float
    fz_after_release_n: float
    depth_ms: float
    pipeline_ms: float
    recordings: int
    windows: int
    train_steps: int
    train_s: float
    val_total_mm: float | None
    val_contact_mm: float | None


def after_release(result: ForceResult, normal_up_end_us: int) -> np.ndarray:
    """Windows that end after the press was released (the last Normal Up's end)."""
    return result.t1_us >= normal_up_end_us


def summarise(variant: str, results: Sequence[ForceResult], released: Sequence[np.ndarray],
              card: Mapping[str, Any]) -> VariantRow:
    """The table's row for one variant from its per-recording pipeline results."""
    rows = {r["axis"]: r for r in table3(results)}
    depth = np.concatenate([r.depth_mae_mm[r.probing] for r in results]) if results else np.zeros(0)
    contact = np.concatenate([r.depth_contact_mae_mm[r.probing] for r in results]) if results else np.zeros(0)
    contact = contact[np.isfinite(contact)]
    fz_after = np.concatenate([np.abs(r.predicted_n[m, 2]) for r, m in zip(results, released)]) if results else np.zeros(0)
    val = card.get("val") or {}
    training = card.get("training") or {}
    return VariantRow(
        variant=variant, depth_total_mm=_mean(depth[np.isfinite(depth)]), depth_contact_mm=_mean(contact),
        force_x_mae_n=float(rows["x"]["force_mae_n"]), force_y_mae_n=float(rows["y"]["force_mae_n"]),
        force_z_mae_n=float(rows["z"]["force_mae_n"]), position_mae_px=float(rows["total"]["position_mae_px"] or np.nan),
        fz_after_release_n=_mean(fz_after), depth_ms=float(np.median([r.stage_ms["depth"] for r in results])),
        pipeline_ms=float(np.median([r.total_ms for r in results])), recordings=len(results),
        windows=int(sum(len(r.t1_us) for r in results)), train_steps=int(training.get("steps", 0)),
        train_s=float(training.get("seconds", 0.0)), val_total_mm=val.get("total_mm"), val_contact_mm=val.get("contact_mm"))


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


def normal_up_end_us(path: Path) -> int:
    """End of the recording's last Normal Up phase (host us); the recording's end when it has none."""
    with Recording(path) as rec:
        ends = [p.t_end_us for p in rec.phases() if p.name == "normal_up"]
        return int(ends[-1]) if ends else int(np.iinfo(np.int64).max)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path, help="campaign folder with manifest.csv and NAME.gt.h5 sidecars")
    ap.add_argument("--out", type=Path, default=Path("models/state"), help="folder of the networks and compare.json")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated input sets ({', '.join(VARIANTS)})")
    ap.add_argument("--width", type=int, default=8)
    ap.add_argument("--steps", type=int, default=2000, help="training steps per variant (the same budget for each)")
    ap.add_argument("--batch-size", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1, help="torch training threads (default 1)")
    ap.add_argument("--val-windows", type=int, default=64)
    ap.add_argument("--split", default="test", help="the recordings measured (default test)")
    ap.add_argument("--recordings", type=int, default=0, help="measure only the first N of the split (0: all)")
    ap.add_argument("--window-events", type=int, default=20_000, help="evaluation windows (default 20000, the paper's)")
    ap.add_argument("--calibration", type=Path, default=Path("calibration"))
    ap.add_argument("--no-hold-rows", action="store_true",
                    help="also measure each stateful network with the quiet hold off (fed every window)")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = ap.parse_args(argv)
    console = Console(stderr=args.json)
    try:
        rows = compare(args, console)
    except LabrigError as exc:
        Console(stderr=True).print(f"[red]error:[/] {exc}")
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "compare.json").write_text(json.dumps([r.__dict__ for r in rows], indent=2) + "\n")
    if args.json:
        print(json.dumps([r.__dict__ for r in rows], indent=2))
    else:
        console.print(render(rows, args))
    return 0


def compare(args: argparse.Namespace, console: Console) -> list[VariantRow]:
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown or not variants:
        raise LabrigError(f"--variants: {', '.join(unknown) or 'none'}; choose from {', '.join(VARIANTS)}")
    recordings = [r.path for r in Dataset.open(args.data).require() if r.split == args.split]
    if args.recordings:
        recordings = recordings[:args.recordings]
    if not recordings:
        raise LabrigError(f"{args.data}: no complete recording in the {args.split} split")
    released_at = {p: normal_up_end_us(p) for p in recordings}
    rows = []
    for variant in variants:
        stem = args.out / f"depth-w{args.width}-{variant.replace('+', '-')}"
        paths = output_paths(stem)
        if not (paths["onnx"].exists() and paths["card"].exists()):
            console.print(f"[bold]{variant}[/]: training {args.steps} steps, width {args.width}")
            config = TrainConfig(width=args.width, steps=args.steps, batch_size=args.batch_size, seed=args.seed,
                                 threads=args.threads, device="cpu", inputs=variant, val_every=0,
                                 val_windows=args.val_windows, checkpoint_every=max(args.steps // 4, 1),
                                 calibration_dir=str(args.calibration))
            train(args.data, config, stem, resume=paths["checkpoint"].exists(),
                  command="tools/depth_state_compare.py " + " ".join(sys.argv[1:]), show_progress=not args.json)
        card = ModelCard.load(paths["card"]).raw  # checked; the row reads the training's records
        holds = (True, False) if args.no_hold_rows and variant != "sae" else (True,)
        for hold in holds:
            name = variant if hold else f"{variant} (no hold)"
            results, released = [], []
            for k, path in enumerate(recordings):
                console.print(f"[bold]{name}[/]: pipeline on {path.name} ({k + 1}/{len(recordings)})")
                result = evaluate_forces(ForceTask(str(path), str(paths["onnx"]), window_events=args.window_events,
                                                   calibration_dir=str(args.calibration), quiet_hold=hold))
                results.append(result)
                released.append(after_release(result, released_at[path]))
            rows.append(summarise(name, results, released, card))
    return rows


def render(rows: Sequence[VariantRow], args: argparse.Namespace) -> Table:
    table = Table(title=f"depth with state: {args.data} ({args.split}), width {args.width}, {args.steps} steps each, "
                        f"{args.window_events}-event windows")
    for column in ("inputs", "depth mm total / contact", "force MAE N x / y / z", "position px",
                   "|Fz| after release N", "depth / pipeline ms", "val mm total / contact", "train s"):
        table.add_column(column)
    for r in rows:
        val = f"{r.val_total_mm:.3f} / {r.val_contact_mm or float('nan'):.3f}" if r.val_total_mm is not None else "-"
        table.add_row(r.variant, f"{r.depth_total_mm:.3f} / {r.depth_contact_mm:.3f}",
                      f"{r.force_x_mae_n:.2f} / {r.force_y_mae_n:.2f} / {r.force_z_mae_n:.2f}",
                      f"{r.position_mae_px:.1f}", f"{r.fz_after_release_n:.2f}", f"{r.depth_ms:.2f} / {r.pipeline_ms:.1f}",
                      val, f"{r.train_s:.0f}")
    return table


if __name__ == "__main__":
    sys.exit(main())
