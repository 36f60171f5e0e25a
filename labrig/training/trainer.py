"""Training the depth network on a campaign: Adam, checkpoints, resume, validation in mm, ONNX export.

Outputs for ``out = models/NAME``: ``NAME.onnx`` (the network), ``NAME.json`` (its model
card) and ``NAME.ckpt.pt`` (model, optimizer, step, elapsed time, sampler and torch RNG
states), written every ``checkpoint_every`` steps and at the end. ``resume=True``
continues from the checkpoint: with the same settings the losses after the resume are
those an uninterrupted run would have had (on CPU). A time budget counts the training
time of all sessions together.
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from labrig import __version__
from labrig.config import DEFAULT_CALIBRATION_DIR
from labrig.errors import LabrigError
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.depth_inputs import InputSpec
from labrig.pipeline.depthnet import DepthModel, UNetConfig, benchmark_ms, build_unet, export_onnx, parameter_count
from labrig.pipeline.model_card import write_card
from labrig.pipeline.sae import crop_from_unet
from labrig.training.crop import CropAugment
from labrig.training.data import PHASE_MARGIN_S, NoiseAugment, WindowSampler, fixed_set, open_campaign
from labrig.training.init import initial_network
from labrig.training.loss import DEFAULT_LAMBDA_C, LOSSES, depth_errors_mm, loss_function
from labrig.training.shift import ShiftAugment
from labrig.training.state_data import SELF_FEED_MAX, PreviousAugment, prepare_states, self_feed

DEFAULT_STEPS = 2000
VAL_SEED_OFFSET = 1_000_003
#: Settings that must match for a resume.
RESUME_KEYS = ("width", "pools", "window_ms", "loss", "lambda_c", "batch_size", "lr", "seed", "phases", "noise_hz",
               "inputs", "init", "shift_cells", "lr_schedule", "after_release_s", "crop_cells")
#: Resume keys a checkpoint may predate, with the value it then had.
RESUME_DEFAULTS: dict[str, object] = {"noise_hz": 0.0, "inputs": "sae", "init": None, "shift_cells": 0,
                                      "lr_schedule": "constant", "after_release_s": PHASE_MARGIN_S, "crop_cells": 0}
#: Learning-rate schedules: constant, or a cosine from ``lr`` down to ``lr * COSINE_FLOOR`` at the last step.
LR_SCHEDULES = ("constant", "cosine")
COSINE_FLOOR = 0.05
#: Translation augmentation by default (grid cells per axis, about 0.27 mm each on the reference rig).
DEFAULT_SHIFT_CELLS = 12
#: Lowest extra noise rate of the augmentation (Hz per pixel): below the sensor's own.
NOISE_MIN_HZ = 0.02


@dataclass
class TrainConfig:
    width: int = 8
    pools: int = 4
    window_ms: float = 10.0
    loss: str = "contact"
    lambda_c: float = DEFAULT_LAMBDA_C
    steps: int | None = None
    time_budget_min: float | None = None
    batch_size: int = 16
    lr: float = 1e-3
    seed: int = 0
    checkpoint_every: int = 200
    val_every: int = 200
    val_windows: int = 128
    phases: str = "probing"
    device: str = "auto"
    threads: int | None = None
    noise_hz: float = 0.0  # background-noise augmentation: up to this rate (Hz per pixel) on half the windows; 0: off
    inputs: str = "sae"  # the network's inputs (labrig.pipeline.depth_inputs.INPUT_SETS): sae, sae+disp, sae+disp+prev
    #: The camera and markers the tracker's displacement channels need.
    calibration_dir: str | None = DEFAULT_CALIBRATION_DIR
    #: Processes that build the recordings' state channels before training (None: one per core; 1: this one).
    workers: int | None = None
    #: The network to fine-tune (:func:`labrig.training.init.initial_network`: a bundled name or an .onnx), or None
    #: (fresh weights). Its width, pools, window and inputs must be this config's (:meth:`from_init` sets them).
    init: str | None = None
    #: Translation augmentation (:mod:`labrig.training.shift`): windows moved by up to this many grid cells per
    #: axis; 0: off.
    shift_cells: int = DEFAULT_SHIFT_CELLS
    lr_schedule: str = "constant"
    #: With ``phases`` "probing": windows drawn until this long after Normal Up ends (s).
    after_release_s: float = PHASE_MARGIN_S
    #: Patch training (:mod:`labrig.training.crop`): windows cut to this many grid cells square; 0: the whole grid.
    crop_cells: int = 0

    @classmethod
    def from_init(cls, init: str, inputs: str | None = None, **settings: Any) -> TrainConfig:
        """A config that fine-tunes ``init``: its architecture, window and inputs, the other ``settings`` as given.
        ``inputs``: another input set of the same channels (the same kinds, their settings changed: a state channel
        counted another way), which the network is then fine-tuned to read."""
        net = initial_network(init)
        if inputs is not None and InputSpec.named(inputs).kinds != InputSpec.named(net.inputs).kinds:
            raise LabrigError(f"--init {init} takes {net.inputs}: --inputs may change only how its channels are "
                                  f"made, not which ({inputs} has others)")
        return cls(width=net.width, pools=net.pools, window_ms=net.window_ms, inputs=inputs or net.inputs,
                   init=str(init), **settings)

    def check(self) -> None:
        if self.loss not in LOSSES:
            raise LabrigError(f"--loss must be one of {', '.join(LOSSES)}, not {self.loss!r}")
        if not 0.0 <= self.lambda_c <= 1.0:
            raise LabrigError("--lambda-c must be within [0, 1]")
        if self.width < 1 or self.pools < 1 or self.batch_size < 1 or self.lr <= 0:
            raise LabrigError("--width, --batch-size and --lr must be positive")
        if self.window_ms <= 0:
            raise LabrigError("--window-ms must be positive")
        if self.steps is not None and self.steps < 1:
            raise LabrigError("--steps must be >= 1")
        if self.time_budget_min is not None and self.time_budget_min <= 0:
            raise LabrigError("--time-budget-min must be positive")
        if self.phases not in ("probing", "all"):
            raise LabrigError("--phases must be probing or all")
        if self.noise_hz < 0:
            raise LabrigError("--noise-hz must be 0 (off) or a positive rate in Hz per pixel")
        if self.workers is not None and self.workers < 1:
            raise LabrigError("--workers must be at least 1")
        if not 0 <= self.shift_cells < 45:
            raise LabrigError("--shift-cells must be 0 (off) or a whole number of grid cells under 45 (half the grid)")
        if not 0.0 <= self.after_release_s <= 10.0:
            raise LabrigError("--after-release-s must be within [0, 10] s")
        if self.crop_cells and not (self.crop_cells % 2**self.pools == 0 and 0 < self.crop_cells <= GRID_SHAPE[0]):
            raise LabrigError(f"--crop-cells must be 0 (the whole grid) or a multiple of {2**self.pools} (2**pools) "
                              f"up to {GRID_SHAPE[0]}, not {self.crop_cells}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise LabrigError(f"--lr-schedule must be one of {', '.join(LR_SCHEDULES)}, not {self.lr_schedule!r}")
        if self.lr_schedule == "cosine" and self.steps is None:
            raise LabrigError("--lr-schedule cosine decays over --steps: give --steps")
        self.input_spec  # noqa: B018  (checks --inputs)

    @property
    def input_spec(self) -> InputSpec:
        """The network's input channels (:class:`~labrig.pipeline.depth_inputs.InputSpec`)."""
        return InputSpec.named(self.inputs)

    @property
    def noise(self) -> NoiseAugment | None:
        """The background-noise augmentation, or None."""
        return NoiseAugment(max_hz=self.noise_hz, min_hz=min(NOISE_MIN_HZ, self.noise_hz)) if self.noise_hz > 0 else None

    @property
    def crop(self) -> CropAugment | None:
        """The patch cut, or None."""
        return CropAugment(self.crop_cells) if self.crop_cells else None

    @property
    def shift(self) -> ShiftAugment | None:
        """The translation augmentation, or None."""
        return ShiftAugment(self.shift_cells) if self.shift_cells > 0 else None

    def lr_at(self, step: int) -> float:
        """The learning rate of step ``step`` (0-based) under ``lr_schedule``."""
        if self.lr_schedule == "constant" or not self.steps:
            return self.lr
        progress = min(step / self.steps, 1.0)
        return self.lr * (COSINE_FLOOR + (1.0 - COSINE_FLOOR) * 0.5 * (1.0 + math.cos(math.pi * progress)))

    @property
    def max_steps(self) -> int | None:
        if self.steps is None and self.time_budget_min is None:
            return DEFAULT_STEPS
        return self.steps


def output_paths(out: str | Path) -> dict[str, Path]:
    out = Path(out)
    if out.suffix in (".onnx", ".json"):
        out = out.with_suffix("")
    return {"onnx": out.with_name(out.name + ".onnx"), "card": out.with_name(out.name + ".json"),
            "checkpoint": out.with_name(out.name + ".ckpt.pt")}


def pick_device(name: str) -> Any:
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        return torch.device(name)
    except RuntimeError:
        raise LabrigError(f"--device {name!r} is not a torch device (auto, cpu, cuda, cuda:1)") from None


def predict_normalised(model: Any, sae: np.ndarray, device: Any, batch: int = 32) -> np.ndarray:
    """Network output (N, 90, 112) in normalised units, clipped to [0, 1], in eval mode."""
    import torch

    was = model.training
    model.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(sae), batch):
            y = model(torch.from_numpy(sae[i:i + batch]).to(device))[:, 0]
            out.append(crop_from_unet(y).clamp(0.0, 1.0).cpu().numpy())
    model.train(was)
    return np.concatenate(out) if out else np.zeros((0, 90, 112), np.float32)


def train(data_dir: str | Path | Sequence[str | Path], config: TrainConfig, out: str | Path, *, resume: bool = False,
          command: str = "", show_progress: bool = True,
          on_step: Callable[[int, float], None] | None = None) -> dict[str, Any]:
    """Train, export and return the model card (also written beside the .onnx)."""
    import torch

    config.check()
    paths = output_paths(out)
    if paths["checkpoint"].exists() and not resume:
        raise LabrigError(f"{paths['checkpoint']} exists: pass --resume to continue it, or choose another --out")
    if resume and not paths["checkpoint"].exists():
        raise LabrigError(f"--resume: no checkpoint {paths['checkpoint']} to continue")
    paths["onnx"].parent.mkdir(parents=True, exist_ok=True)
    if config.threads:
        torch.set_num_threads(config.threads)
    device = pick_device(config.device)
    data = open_campaign(data_dir, config.phases, config.after_release_s)
    try:
        window_us = config.window_ms * 1000.0
        torch.manual_seed(config.seed)
        spec = config.input_spec
        unet = UNetConfig(width=config.width, pools=config.pools, in_channels=spec.channels)
        model = build_unet(unet).to(device)
        init = _initial(config, data.scale_mm)
        if init is not None and not resume:
            model.load_state_dict(init.state_dict(device))
        optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
        prepare_states([src.path for split in ("train", "val") for src in data.sources.get(split, [])], spec,
                       config.calibration_dir, workers=config.workers)
        sampler = WindowSampler(data.sources["train"], window_us, config.seed, config.noise, spec, config.calibration_dir,
                                config.shift, config.crop, preload=True)
        val_sources = data.sources.get("val", [])
        val = fixed_set(val_sources, window_us, config.val_windows, config.seed + VAL_SEED_OFFSET, spec,
                        config.calibration_dir) if val_sources else None
        loss_fn = loss_function(config.loss, config.lambda_c)
        previous_channel = spec.channel_of("previous")
        scale = data.scale_mm
        step, elapsed_s, samples_s, history, val_history = 0, 0.0, 0.0, [], []
        if resume:
            ckpt = torch.load(paths["checkpoint"], map_location=device, weights_only=False)
            before = ckpt["config"]
            before = {**RESUME_DEFAULTS, **before}
            changed = [k for k in RESUME_KEYS if before.get(k) != getattr(config, k)]
            if changed:
                raise LabrigError(f"--resume: {', '.join(f'{k} was {before.get(k)!r}' for k in changed)} in "
                                  f"{paths['checkpoint']}; use the same settings or another --out")
            model.load_state_dict(ckpt["model"])
            optimizer.load_state_dict(ckpt["optimizer"])
            sampler.set_state(ckpt["sampler_rng"])
            torch.set_rng_state(ckpt["torch_rng"])
            step, elapsed_s, samples_s = int(ckpt["step"]), float(ckpt["elapsed_s"]), float(ckpt.get("samples_s", 0))
            history, val_history = list(ckpt["history"]), list(ckpt["val_history"])

        def validate() -> dict[str, Any] | None:
            if val is None:
                return None
            pred = predict_normalised(model, val[0], device) * scale
            return depth_errors_mm(pred, val[1] * scale, val[2])

        def save_checkpoint() -> None:
            tmp = paths["checkpoint"].with_name(f".{paths['checkpoint'].name}.{os.getpid()}.tmp")
            torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
                        "elapsed_s": elapsed_s, "samples_s": samples_s, "sampler_rng": sampler.state(),
                        "torch_rng": torch.get_rng_state(), "config": dataclasses.asdict(config),
                        "history": history, "val_history": val_history,
                        "val_before": init_card["val_before"] if init_card else None}, tmp)
            os.replace(tmp, paths["checkpoint"])

        budget_s = config.time_budget_min * 60.0 if config.time_budget_min else None
        max_steps = config.max_steps

        def done() -> bool:
            return (max_steps is not None and step >= max_steps) or (budget_s is not None and elapsed_s >= budget_s)

        init_card = None
        if init is not None:
            init_card = {**init.describe(), "val_before": validate() if not resume else ckpt.get("val_before")}
        model.train()
        last_val = val_history[-1][1] if val_history else None
        with _Progress(show_progress, max_steps, budget_s) as bar:
            bar.update(step, elapsed_s, history[-1][1] if history else None, last_val)
            while not done():
                t0 = time.perf_counter()
                sae, target, contact = sampler.batch(config.batch_size)
                t1 = time.perf_counter()
                x = torch.from_numpy(sae).to(device)
                y = torch.from_numpy(target).to(device)
                c = torch.from_numpy(contact).to(device)
                if previous_channel is not None:
                    x = self_feed(model, x, previous_channel, int(torch.randint(0, SELF_FEED_MAX + 1, (1,))))
                pred = model(x)[:, 0] if config.crop else crop_from_unet(model(x)[:, 0])
                loss = loss_fn(pred, y, c)
                for group in optimizer.param_groups:
                    group["lr"] = config.lr_at(step)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                step += 1
                value = float(loss.detach())
                history.append((step, value))
                if on_step is not None:
                    on_step(step, value)
                samples_s += t1 - t0
                if config.val_every and step % config.val_every == 0:
                    last_val = validate()
                    val_history.append((step, last_val))
                elapsed_s += time.perf_counter() - t0
                if config.checkpoint_every and step % config.checkpoint_every == 0:
                    save_checkpoint()
                bar.update(step, elapsed_s, _smooth(history), last_val)
        final_val = validate()
        if final_val is not None and (not val_history or val_history[-1][0] != step):
            val_history.append((step, final_val))
        save_checkpoint()
        n_samples = step * config.batch_size
        card = {
            "name": paths["onnx"].stem,
            "architecture": unet.to_dict(),
            "parameters": parameter_count(model),
            "scale_mm": scale,
            "normalisation": "depth_norm = clip(depth_mm / scale_mm, 0, 1); network output clipped to [0, 1]",
            "window_ms": config.window_ms,
            "input": "polarity-separated SAE on the 90 x 112 grid (labrig.pipeline.sae.sae_grid), zero-padded to "
                     "96 x 112; channel 0 OFF, 1 ON; latest event per cell, (t - t0) / window; then the channels "
                     "of 'inputs' (labrig.pipeline.depth_inputs)",
            "inputs": spec.to_card(),
            "loss": {"name": config.loss, "lambda_c": config.lambda_c if config.loss == "contact" else None},
            "training_data": data.describe(),
            "sampling": f"uniform recording, uniform start time within its {config.phases} phases"
                        + (f" (from {PHASE_MARGIN_S:g} s before Normal Down to {config.after_release_s:g} s after Normal Up)"
                           if config.phases == "probing" else "") + "; ground truth nearest to the window's last event",
            "augmentation": _augmentation(config),
            "init": init_card,
            "training": {"steps": step, "batch_size": config.batch_size, "samples": n_samples, "optimizer": "Adam",
                         "lr": config.lr, "lr_schedule": config.lr_schedule,
                         "lr_final": config.lr_at(max(step - 1, 0)), "seed": config.seed, "seconds": round(elapsed_s, 1),
                         "samples_per_s": round(n_samples / elapsed_s, 1) if elapsed_s > 0 else None,
                         "sampling_share": round(samples_s / elapsed_s, 3) if elapsed_s > 0 else None,
                         "time_budget_min": config.time_budget_min, "device": str(device),
                         "torch_threads": torch.get_num_threads(), "final_loss": _smooth(history),
                         "loss_history": [h for h in history if h[0] % max(1, step // 200) == 0 or h[0] == step],
                         "val_history": val_history},
            "val": final_val,
            "val_windows": config.val_windows,
            "command": command,
            "reproduce": _reproduce(data_dir, config, paths["onnx"].with_suffix(""), step),
            "labrig_version": __version__,
            "torch_version": torch.__version__,
            "machine": platform.machine(),
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
        }
        export_onnx(model, paths["onnx"], None)

        write_card(card, paths["card"])
        card["inference_ms_ort_1thread"] = round(benchmark_ms(paths["onnx"], threads=1), 3)
        write_card(card, paths["card"])
        return {**card, "onnx": str(paths["onnx"]), "card": str(paths["card"]),
                "checkpoint": str(paths["checkpoint"])}
    finally:
        data.close()


def _initial(config: TrainConfig, scale_mm: float) -> Any:
    """The network ``config.init`` names (:class:`~labrig.training.init.InitialNetwork`), checked against the
    config and the data, or None."""
    if config.init is None:
        return None

    net = initial_network(config.init)
    mismatched = [f"{key} {getattr(net, key)!r} (not {getattr(config, key)!r})"
                  for key in ("width", "pools", "window_ms") if getattr(net, key) != getattr(config, key)]
    if InputSpec.named(net.inputs).kinds != config.input_spec.kinds:
        mismatched.append(f"inputs {net.inputs!r} (not {config.inputs!r}, whose channels are others)")
    if mismatched:
        raise LabrigError(f"--init {config.init}: the network has {', '.join(mismatched)}; fine-tuning keeps them")
    if abs(net.scale_mm - scale_mm) > 1e-9:
        raise LabrigError(f"--init {config.init}: the network reads depth in units of {net.scale_mm:g} mm, the data's "
                          f"ground truth of {scale_mm:g} mm; regenerate it with labrig groundtruth --scale-mm "
                          f"{net.scale_mm:g}")
    return net


def _augmentation(config: TrainConfig) -> dict[str, Any] | None:
    """The card's augmentation section: background noise, the previous map's perturbation, the tracker's tracks."""
    out: dict[str, Any] = {}
    if config.noise:
        out["background_noise"] = config.noise.describe()
    if config.shift:
        out["translation"] = config.shift.describe()
    if config.crop:
        out["crop"] = config.crop.describe()
    if "previous" in config.input_spec.kinds:
        out["previous_map"] = {**PreviousAugment().describe(), "source": "ground truth nearest the previous window's "
                               "last event", "self_feed_steps": f"0-{SELF_FEED_MAX}, uniform per batch: the channel "
                               "replaced by the network's own answer (state_data.self_feed)"}
    if "brightness" in config.input_spec.kinds:
        out["brightness"] = {"source": "the recording's events integrated from its start in 10 ms steps (cached)",
                             "noise": "with background noise, its integrated count (state_data.integrated_noise)"
                             if config.noise else None}
    if "displacement" in config.input_spec.kinds:
        out["displacement"] = {"source": "the pipeline's tracker over each recording (10 ms windows, cached)",
                               "calibration": config.calibration_dir}
    return out or None


def _smooth(history: list[tuple[int, float]], n: int = 20) -> float | None:
    if not history:
        return None
    return round(float(np.mean([v for _, v in history[-n:]])), 6)


def _reproduce(data_dir: str | Path | Sequence[str | Path], c: TrainConfig, out: Path, steps: int) -> str:
    """A command that gives this model again (deterministic on CPU): the step count reached, not the budget."""
    folders = [str(data_dir)] if isinstance(data_dir, (str, Path)) else [str(d) for d in data_dir]
    shape = ["--init", c.init] if c.init is not None else ["--width", str(c.width), "--window-ms", f"{c.window_ms:g}"]
    parts = ["labrig", "train", *folders, *shape,
             "--loss", c.loss, "--steps", str(steps), "--seed", str(c.seed), "--batch-size", str(c.batch_size),
             "--lr", f"{c.lr:g}", "--shift-cells", str(c.shift_cells), "--out", str(out)]
    if c.lr_schedule != "constant":
        parts += ["--lr-schedule", c.lr_schedule]
    if c.pools != 4 and c.init is None:
        parts += ["--pools", str(c.pools)]
    if c.loss == "contact" and c.lambda_c != DEFAULT_LAMBDA_C:
        parts += ["--lambda-c", f"{c.lambda_c:g}"]
    if c.phases != "probing":
        parts += ["--phases", c.phases]
    if c.crop_cells:
        parts += ["--crop-cells", str(c.crop_cells)]
    if c.after_release_s != PHASE_MARGIN_S:
        parts += ["--after-release-s", f"{c.after_release_s:g}"]
    if c.noise_hz > 0:
        parts += ["--noise-hz", f"{c.noise_hz:g}"]
    if c.inputs != "sae":
        parts += ["--inputs", c.inputs]  # a fine-tune may read its network's channels made another way
        if c.calibration_dir not in (None, "calibration", DEFAULT_CALIBRATION_DIR) and "disp" in c.inputs:
            parts += ["--calibration", str(c.calibration_dir)]
    if c.val_every != 200 or c.val_windows != 128:
        parts += ["--val-every", str(c.val_every), "--val-windows", str(c.val_windows)]
    return " ".join(parts)


class _Progress:
    """A rich bar over steps (or the time budget) with the loss and the validation errors."""

    def __init__(self, enabled: bool, max_steps: int | None, budget_s: float | None) -> None:
        self.enabled = enabled
        self.max_steps = max_steps
        self.budget_s = budget_s
        self.bar: Any = None

    def __enter__(self) -> _Progress:
        if self.enabled:
            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            self.bar = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[info]}"),
                                TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True))
            self.bar.__enter__()
            by_steps = self.max_steps is not None and (self.budget_s is None)
            self.task = self.bar.add_task("train", total=self.max_steps if by_steps else self.budget_s, info="")
            self.by_steps = by_steps
        return self

    def update(self, step: int, elapsed_s: float, loss: float | None, val: dict[str, Any] | None) -> None:
        if self.bar is None:
            return
        info = f"step {step}" + (f"/{self.max_steps}" if self.max_steps else "")
        if loss is not None:
            info += f"  loss {loss:.4f}"
        if val and val.get("total_mm") is not None:
            info += (f"  val mm total {val['total_mm']:.3f} contact {val['contact_mm'] or 0:.3f} "
                     f"non-contact {val['noncontact_mm'] or 0:.3f}")
        done = step if self.by_steps else elapsed_s
        if not self.by_steps and self.max_steps:
            done = max(elapsed_s, step / self.max_steps * (self.budget_s or 0))
        self.bar.update(self.task, completed=done, info=info)

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.__exit__(*exc)


def split_errors(onnx_path: str | Path, data_dir: str | Path, split: str = "test", windows: int = 256, seed: int = 7,
                 threads: int = 1) -> dict[str, Any] | None:
    """Depth errors (mm) of an exported network on ``windows`` random windows of a split (None if it is empty).

    The windows are drawn with the card's window length and the paper's sampling, the same
    draw for every model given the same seed, so models can be compared on one set.
    """
    model = DepthModel(onnx_path, threads=threads)
    data = open_campaign(data_dir)
    try:
        sources = data.sources.get(split, [])
        if not sources:
            return None
        sae, target, contact = fixed_set(sources, model.window_ms * 1000.0, windows, seed, model.inputs)
        pred = np.concatenate([model.depth_mm(sae[i:i + 32]) for i in range(0, len(sae), 32)])
        return depth_errors_mm(pred, target * model.scale_mm, contact)
    finally:
        data.close()
