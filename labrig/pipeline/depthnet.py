"""The depth network: a plain U-Net from a polarity-separated SAE to a normal-deformation map.

Input (B, C, 96, 112): the SAE on the network grid (:func:`labrig.pipeline.sae.sae_grid`)
zero-padded by :func:`labrig.pipeline.sae.pad_for_unet` (C = 2), followed by the state channels
the model card's ``inputs`` names (:mod:`labrig.pipeline.depth_inputs`: the markers'
displacement field, the previous estimate). Output (B, 1, 96, 112): depth
normalised to [0, 1] with the ground truth's global scale (``scale_mm`` mm per unit); crop
it back to 90 x 112 with :func:`labrig.pipeline.sae.crop_from_unet`.

Architecture: ``pools`` down-sampling stages (2 x 2 max pooling), each level two 3 x 3
convolutions with batch norm and ReLU; channels ``width * 2**level``; up-sampling by 2 x 2
transposed convolutions and skip concatenation; a 1 x 1 convolution to one channel, no
output activation (the trainer's L1 loss pulls it into [0, 1]; :class:`DepthModel` clips).
Width 32 with 4 poolings has 7.76 M parameters, the paper's size (7.9 M).

Deployment: :func:`export_onnx` writes ``NAME.onnx``; the model card ``NAME.json`` beside it
(:mod:`labrig.pipeline.model_card`) holds the architecture, the training data, window, loss,
validation errors and the command that made it. :class:`DepthModel` runs it with onnxruntime and returns millimetres.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Generator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.errors import LabrigError
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.model_card import ModelCard, UNetConfig, card_path, write_card
from labrig.pipeline.onnx_parts import PartedSession
from labrig.pipeline.sae import UNET_SHAPE, crop_from_unet, pad_for_unet

INPUT_NAME = "sae"  # the SAE-only network's input; a network with state channels takes STATE_INPUT_NAME
STATE_INPUT_NAME = "inputs"
OUTPUT_NAME = "depth"


def build_unet(config: UNetConfig | None = None, **kwargs: Any) -> Any:
    """A fresh :class:`torch.nn.Module` U-Net (``build_unet(width=8)`` or with a config)."""
    import torch
    from torch import nn

    cfg = config or UNetConfig(**kwargs)

    def block(c_in: int, c_out: int) -> nn.Sequential:
        return nn.Sequential(
            nn.Conv2d(c_in, c_out, 3, padding=1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True),
            nn.Conv2d(c_out, c_out, 3, padding=1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True),
        )

    class UNet(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.config = cfg
            chans = [cfg.width * 2 ** k for k in range(cfg.pools + 1)]
            self.down = nn.ModuleList([block(cfg.in_channels, chans[0])] +
                                      [block(chans[k - 1], chans[k]) for k in range(1, cfg.pools + 1)])
            self.pool = nn.MaxPool2d(2)
            self.up = nn.ModuleList([nn.ConvTranspose2d(chans[k], chans[k - 1], 2, stride=2)
                                     for k in range(cfg.pools, 0, -1)])
            self.merge = nn.ModuleList([block(2 * chans[k - 1], chans[k - 1]) for k in range(cfg.pools, 0, -1)])
            self.head = nn.Conv2d(chans[0], 1, 1)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            skips = []
            for k, level in enumerate(self.down):
                x = level(x if k == 0 else self.pool(x))
                skips.append(x)
            x = skips.pop()
            for up, merge in zip(self.up, self.merge):
                x = merge(torch.cat([skips.pop(), up(x)], dim=1))
            return self.head(x)

    return UNet()


def parameter_count(model: Any) -> int:
    return int(sum(p.numel() for p in model.parameters()))


def export_onnx(model: Any, path: str | Path, card: dict[str, Any] | None = None, opset: int = 17) -> Path:
    """Write ``model`` (eval mode, batch axis dynamic) to ``path`` (.onnx) and its card beside it (.json)."""
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    was_training = model.training
    model.eval()
    cpu = next(model.parameters()).device.type != "cpu"
    exported = model.to("cpu") if cpu else model
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    name = INPUT_NAME if exported.config.in_channels == 2 else STATE_INPUT_NAME
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(exported, (torch.zeros(1, exported.config.in_channels, *UNET_SHAPE),), str(tmp),
                              input_names=[name], output_names=[OUTPUT_NAME], opset_version=opset,
                              dynamic_axes={name: {0: "batch"}, OUTPUT_NAME: {0: "batch"}}, dynamo=False)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
        model.train(was_training)
    if card is not None:
        write_card(card, card_path(path))
    return path


class DepthModel:
    """A trained depth network run with onnxruntime: SAE (and state channels) in, depth in mm on the 90 x 112 grid out.

    ``DepthModel("models/depth-w8.onnx", threads=1)``; its model card (:attr:`card`, a
    :class:`~labrig.pipeline.model_card.ModelCard` read from the ``.json`` beside it) gives the
    scale (mm per normalised unit), the window the network was trained on and its inputs
    (:attr:`inputs`, a :class:`~labrig.pipeline.depth_inputs.InputSpec`).
    """

    def __init__(self, path: str | Path, threads: int = 1) -> None:
        import onnxruntime as ort

        self.path = Path(path)
        if self.path.suffix == ".json":
            self.path = self.path.with_suffix(".onnx")
        if not self.path.exists():
            raise LabrigError(f"{self.path}: no such depth network (.onnx); train one with `labrig train DATA/`")
        self.card = ModelCard.load(card_path(self.path))
        self.scale_mm = self.card.scale_mm
        self.window_ms = self.card.window_ms
        self.inputs = self.card.inputs
        options = ort.SessionOptions()
        options.intra_op_num_threads = max(1, int(threads))
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        try:
            self.session = ort.InferenceSession(str(self.path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types
            raise LabrigError(f"{self.path} cannot be loaded by onnxruntime ({str(exc).splitlines()[0]})") from None
        self.threads = options.intra_op_num_threads
        self._options = options
        self._parted: PartedSession | None = None
        self.input_name = self.session.get_inputs()[0].name
        declared = self.session.get_inputs()[0].shape
        if len(declared) == 4 and isinstance(declared[1], int) and declared[1] != self.inputs.channels:
            raise LabrigError(f"{self.path} takes {declared[1]} channels but its card names {self.inputs.channels} "
                              f"({', '.join(self.inputs.kinds)}); export it again with `labrig train`")

    @property
    def name(self) -> str:
        return self.path.stem

    def _batch(self, sae: npt.NDArray[np.float32]) -> tuple[npt.NDArray[np.float32], bool]:
        """(B, C, 96, 112) contiguous input of ``sae`` (..., C, 90|96, 112), and whether it was a single map."""
        x = np.asarray(sae, dtype=np.float32)
        if x.shape[-2:] == GRID_SHAPE:
            x = pad_for_unet(x)
        c = self.inputs.channels
        if x.shape[-3:] != (c, *UNET_SHAPE):
            raise LabrigError(f"the depth network {self.name} takes ({c}, 90 or 96, 112) inputs "
                              f"({', '.join(self.inputs.kinds)}), not {x.shape}")
        single = x.ndim == 3
        return np.ascontiguousarray(x[None] if single else x), single

    def normalised(self, sae: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """Raw network output in normalised units on the padded grid: (..., 96, 112) for (..., C, 90|96, 112),
        C the card's channels (2 for the SAE alone; see :func:`labrig.pipeline.depth_inputs.network_input`)."""
        x, single = self._batch(sae)
        out = self.session.run([OUTPUT_NAME], {self.input_name: x})[0]
        return out[0, 0] if single else out[:, 0]

    def split(self, parts: int) -> int:
        """Cut the network into ``parts`` runs of about equal cost for :meth:`depth_mm_steps`
        (:mod:`labrig.pipeline.onnx_parts`; the same operations, the same output); the number of parts made."""
        import onnx

        if self._parted is None or self._parted.requested != parts:
            self._parted = PartedSession(onnx.load(str(self.path)), parts, self._options)
        return len(self._parted)

    def depth_mm_steps(self, sae: npt.NDArray[np.float32]) -> Generator[None, None, npt.NDArray[np.float32]]:
        """:meth:`depth_mm` one part of the network per step (:meth:`split`; one part if it was not split): a
        generator that yields between the parts and returns the map."""
        x, single = self._batch(sae)
        if self._parted is None:
            out = self.session.run([OUTPUT_NAME], {self.input_name: x})[0]
        else:
            tensors = {self.input_name: x}
            yield from self._parted.steps(tensors)
            out = tensors[OUTPUT_NAME]
        return self._to_mm(out[0, 0] if single else out[:, 0])

    def depth_mm(self, sae: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """Depth in mm on the 90 x 112 grid (batched if ``sae`` is (B, 2, ...)), clipped to [0, scale]."""
        return self._to_mm(self.normalised(sae))

    def _to_mm(self, normalised: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        out = crop_from_unet(normalised)
        return (np.clip(out, 0.0, 1.0) * np.float32(self.scale_mm)).astype(np.float32)

    __call__ = depth_mm


def benchmark_ms(path: str | Path, threads: int = 1, repeats: int = 50, warmup: int = 5) -> float:
    """Median onnxruntime latency of one window (batch 1) in ms."""
    import time

    model = DepthModel(path, threads=threads)
    x = np.random.default_rng(0).random((model.inputs.channels, *UNET_SHAPE), dtype=np.float32)
    for _ in range(warmup):
        model.normalised(x)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        model.normalised(x)
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)
