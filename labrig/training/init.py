"""The network a fine-tuning run starts from (``labrig train --init``): its card, its torch weights, its settings.

A network is an ``.onnx`` with its card beside it (``NAME.json``) and its torch weights: a
bundled network's ``NAME.weights.pt`` (:data:`labrig.models.WEIGHTS_SUFFIX`, the model's
``state_dict`` alone) or a training run's ``NAME.ckpt.pt`` (the checkpoint, whose ``model``
entry is the ``state_dict``). The ONNX graph cannot serve: its batch norms are folded into
the convolutions. Fine-tuning keeps the network's architecture, window and inputs, so those
come from its card, not from the command line.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from labrig.cache import sha256_of
from labrig.errors import LabrigError
from labrig.models import WEIGHTS_SUFFIX, model_path
from labrig.pipeline.depth_inputs import INPUT_SETS, InputSpec
from labrig.pipeline.model_card import ModelCard, card_path


@dataclass(frozen=True)
class InitialNetwork:
    """A trained network to fine-tune: where it lies and the settings it was trained with."""

    onnx: Path
    weights: Path
    card: ModelCard
    inputs: str  # the name of its input set (labrig.pipeline.depth_inputs.INPUT_SETS)
    width: int
    pools: int
    window_ms: float
    scale_mm: float

    def state_dict(self, device: Any) -> dict[str, Any]:
        """The network's torch weights, on ``device``."""
        import torch

        saved = torch.load(self.weights, map_location=device, weights_only=False)
        return saved["model"] if isinstance(saved, dict) and "model" in saved else saved

    def describe(self) -> dict[str, Any]:
        """The fine-tuned card's ``init`` section (before the validation errors are added)."""
        return {"model": self.card.name or self.onnx.stem, "onnx": str(self.onnx),
                "onnx_sha256": sha256_of(self.onnx), "weights": self.weights.name}


def weights_beside(onnx: Path) -> Path | None:
    """The torch weights of the network ``onnx``: ``NAME.weights.pt`` or ``NAME.ckpt.pt`` beside it, or None."""
    for suffix in (WEIGHTS_SUFFIX, ".ckpt.pt"):
        candidate = onnx.with_name(onnx.stem + suffix)
        if candidate.exists():
            return candidate
    return None


def initial_network(spec: str | Path) -> InitialNetwork:
    """``--init``'s value: a bundled network's name (``default``) or a trained network's ``.onnx``."""
    onnx = model_path(spec).with_suffix(".onnx")
    if not onnx.exists() or not onnx.with_suffix(".json").exists():
        raise LabrigError(f"--init {spec}: no network {onnx} with its card {onnx.with_suffix('.json').name}; give a "
                          "bundled name (default) or the .onnx of a network you trained")
    weights = weights_beside(onnx)
    if weights is None:
        raise LabrigError(f"--init {spec}: {onnx.name} has no torch weights beside it ({onnx.stem}{WEIGHTS_SUFFIX} or "
                          f"{onnx.stem}.ckpt.pt); fine-tune a network trained by `labrig train`, which writes them")
    card = ModelCard.load(card_path(onnx))
    names = [name for name in INPUT_SETS if InputSpec.named(name) == card.inputs]
    if not names:
        raise LabrigError(f"--init {spec}: its inputs {list(card.inputs.kinds)} match none of --inputs' sets; "
                          "it cannot be fine-tuned by this labrig")
    if card.architecture is None:
        raise LabrigError(f"--init {spec}: its card {card.path} has no 'architecture' (width, pools); fine-tune a "
                          "network trained by `labrig train`")
    return InitialNetwork(onnx=onnx, weights=weights, card=card, inputs=names[0], width=card.architecture.width,
                          pools=card.architecture.pools, window_ms=card.window_ms, scale_mm=card.scale_mm)
