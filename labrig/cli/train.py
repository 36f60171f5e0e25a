"""``labrig train DATA [DATA ...]``: train the depth network on a campaign and export it with its model card.

Mount on the main app with :func:`add_train_commands`. User errors (no
manifest, missing sidecars, bad options, a checkpoint in the way) are
:class:`LabrigError` s, printed as one line by ``labrig``'s main.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from labrig.cli.console import calibration_folder, console, print_json


def train_command(
    data: Annotated[list[Path], typer.Argument(
        help="Campaign output folder(s): manifest.csv, recordings and NAME.gt.h5 sidecars; several pool their splits.")],
    width: Annotated[int | None, typer.Option(
        help="U-Net base width (channels at full resolution; 32 = the paper's 7.8 M; default 8).")] = None,
    pools: Annotated[int | None, typer.Option(help="Number of 2x2 poolings (96 x 112 allows up to 4; default 4).")] = None,
    window_ms: Annotated[float | None, typer.Option(help="Event window accumulated into the SAE (ms; default 10).")] = None,
    loss: Annotated[str, typer.Option(help="contact (contact-aware L1, the paper's) or uniform (plain L1).")] = "contact",
    lambda_c: Annotated[float, typer.Option(help="Weight of the contact term of the contact-aware loss.")] = 0.5,
    steps: Annotated[int | None, typer.Option(help="Training steps (default 2000 unless --time-budget-min).")] = None,
    time_budget_min: Annotated[float | None, typer.Option(
        help="Stop after this many minutes of training (all sessions of a resumed run together).")] = None,
    batch_size: Annotated[int, typer.Option(help="Windows per step.")] = 16,
    lr: Annotated[float, typer.Option(help="Adam learning rate.")] = 1e-3,
    lr_schedule: Annotated[str, typer.Option(
        help="constant, or cosine: from --lr down to 1/20 of it at the last of --steps.")] = "constant",
    seed: Annotated[int, typer.Option(help="Seed of the initial weights and the window sampler.")] = 0,
    out: Annotated[Path | None, typer.Option(
        help="Output stem: writes OUT.onnx, OUT.json (model card), OUT.ckpt.pt (default models/depth-wW-LOSS-Tms).")] = None,
    resume: Annotated[bool, typer.Option(help="Continue from OUT.ckpt.pt (same settings).")] = False,
    checkpoint_every: Annotated[int, typer.Option(help="Save a checkpoint every N steps.")] = 200,
    val_every: Annotated[int, typer.Option(help="Validation depth error every N steps (0: only at the end).")] = 200,
    val_windows: Annotated[int, typer.Option(help="Windows drawn once from the val split for validation.")] = 128,
    phases: Annotated[str, typer.Option(
        help="Sample windows in the probing phases (normal_down to normal_up, +-0.3 s) or all.")] = "probing",
    after_release_s: Annotated[float | None, typer.Option(
        help="With --phases probing: draw windows until this long after Normal Up ends (s): the released gel, which "
             "the brightness change since rest must read as flat (default 0.3).")] = None,
    device: Annotated[str, typer.Option(help="auto (CUDA when present), cpu, cuda.")] = "auto",
    threads: Annotated[int | None, typer.Option(help="Torch CPU threads (default: torch's).")] = None,
    noise_hz: Annotated[float, typer.Option(
        help="Background-noise augmentation: half the windows get extra noise events up to this rate "
             "(Hz per pixel, log-uniform from 0.02); 0: off.")] = 0.0,
    shift_cells: Annotated[int | None, typer.Option(
        help="Translation augmentation: each window, input and ground truth together, moved by up to this many grid "
             "cells per axis (about 0.27 mm each on the reference rig), so that the answer does not depend on where "
             "the campaign pressed; 0: off; default 12).")] = None,
    crop_cells: Annotated[int, typer.Option(
        help="Patch training: each window cut to this many grid cells square around its contact (a multiple of "
             "2**pools, e.g. 64: about 0.4 of a step's cost on the whole grid); the network still runs on the whole "
             "grid; 0: off.")] = 0,
    inputs: Annotated[str | None, typer.Option(
        help="The network's inputs: sae (the paper's), sae+disp (+ the tracker's marker displacement field), "
             "sae+disp+prev (+ the previous depth map), sae+bright (+ the brightness change since rest, the events' "
             "polarities integrated), sae+bright+disp, sae+bright-hold (the brightness change with the gated leak: "
             "a press held as long as it lasts), sae+bright-band (the same, the pixels' dead band undone); docs/depthnet.md. "
             "Default: sae.")] = None,
    init: Annotated[str | None, typer.Option(
        help="Fine-tune this network instead of starting from fresh weights: a bundled one (default) or the .onnx of "
             "one you trained (its card and NAME.ckpt.pt beside it). Its width, pools, window and inputs are kept "
             "(--inputs may name a set of the same channels made another way, which it then learns to read); "
             "the card says what it gained on the data's val split.")] = None,
    calibration: Annotated[Path | None, typer.Option(
        help="Calibration folder (camera, marker map) for the tracker behind the displacement channels (default: "
             "the folder of labrig's default rig).")] = None,
    workers: Annotated[int | None, typer.Option(
        help="Processes that build the recordings' state channels (tracks, brightness) before training "
             "(default: one per core).")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the model card as JSON.")] = False,
) -> None:
    """Train the depth U-Net on a campaign's train split; validate on its val split; export ONNX + model card."""
    from labrig.errors import LabrigError
    from labrig.training import TrainConfig, train

    settings: dict[str, Any] = dict(
        loss=loss, lambda_c=lambda_c, steps=steps, time_budget_min=time_budget_min, batch_size=batch_size, lr=lr,
        seed=seed, checkpoint_every=checkpoint_every, val_every=val_every, val_windows=val_windows, phases=phases,
        device=device, threads=threads, noise_hz=noise_hz, calibration_dir=str(calibration_folder(calibration)),
        workers=workers, lr_schedule=lr_schedule, crop_cells=crop_cells)
    for name, value in (("shift_cells", shift_cells), ("after_release_s", after_release_s)):
        if value is not None:
            settings[name] = value
    shape: dict[str, Any] = {"width": width, "pools": pools, "window_ms": window_ms, "inputs": inputs}
    if init is not None:
        given = [f"--{k.replace('_', '-')}" for k, v in shape.items() if v is not None and k != "inputs"]
        if given:
            raise LabrigError(f"--init keeps the network's shape: leave out {', '.join(given)}")
        config = TrainConfig.from_init(init, inputs, **settings)
    else:
        config = TrainConfig(**{k: v for k, v in shape.items() if v is not None}, **settings)
    config.check()
    if out is None:
        tuned = "-tuned" if init is not None else ""
        out = Path("models") / f"depth-w{config.width}-{loss}-{config.window_ms:g}ms{tuned}"
    command = "labrig " + shlex.join(sys.argv[1:]) if sys.argv and "train" in sys.argv else ""
    card = train(data[0] if len(data) == 1 else data, config, out, resume=resume, command=command,
                 show_progress=not as_json)
    if as_json:
        print_json(card)
        return
    _print_card(card)


def _print_card(c: dict[str, Any]) -> None:
    t = c["training"]
    d = c["training_data"]
    table = Table(title=f"depth network {c['name']}", show_header=False)
    table.add_column("")
    table.add_column("")
    table.add_row("network", f"U-Net width {c['architecture']['width']}, {c['architecture']['pools']} pools, "
                             f"{c['parameters']:,} parameters")
    table.add_row("data", f"{d['campaign']}: {d['split_counts']['train']} train / {d['split_counts']['val']} val / "
                          f"{d['split_counts']['test']} test recordings; scale {d['scale_mm']} mm per unit")
    table.add_row("inputs", ", ".join((c.get("inputs") or {}).get("kinds", ["sae"])))
    table.add_row("window, loss", f"{c['window_ms']:g} ms, {c['loss']['name']}"
                                  + (f" (lambda_c {c['loss']['lambda_c']})" if c["loss"]["lambda_c"] is not None else ""))
    table.add_row("training", f"{t['steps']} steps x {t['batch_size']} = {t['samples']:,} windows in {t['seconds']:.0f} s "
                              f"({t['samples_per_s'] or 0:.1f} windows/s on {t['device']}); final loss {t['final_loss']}")
    v = c.get("val")
    if v:
        table.add_row("val depth error", f"total {v['total_mm']:.4f} mm, contact {v['contact_mm'] or float('nan'):.4f} mm, "
                                         f"non-contact {v['noncontact_mm'] or float('nan'):.4f} mm ({v['maps']} windows)")
    else:
        table.add_row("val depth error", "[yellow]no val recordings[/]")
    init = c.get("init")
    if init and v and init.get("val_before"):
        before, after = init["val_before"], v
        nan = float("nan")
        table.add_row("fine-tuned from", f"{init['model']}: val depth error in contact "
                                         f"{before['contact_mm'] or nan:.4f} -> {after['contact_mm'] or nan:.4f} mm, "
                                         f"total {before['total_mm']:.4f} -> {after['total_mm']:.4f} mm")
    table.add_row("inference", f"{c['inference_ms_ort_1thread']:.2f} ms per window (onnxruntime, 1 thread)")
    table.add_row("files", f"{c['onnx']}\n{c['card']}\n{c['checkpoint']}")
    table.add_row("reproduce", c["reproduce"])
    console.print(table)


def add_train_commands(app: typer.Typer) -> None:
    """Mount ``train`` on the main app."""
    app.command("train")(train_command)
