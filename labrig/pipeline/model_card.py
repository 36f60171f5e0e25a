"""The depth network's model card: the JSON beside each ``NAME.onnx``, read and checked once.

The card (``NAME.json``, written by :mod:`labrig.training.trainer`, :func:`write_card`) says what
the network is and how it was made. :class:`ModelCard` holds the fields that the pipeline, the
evaluation and training act on:

* ``scale_mm``: depth in mm of one normalised output unit (required, > 0);
* ``window_ms``: the span of the SAE the network was trained on, ending at the window's end (ms;
  absent: 10);
* ``inputs``: its channels, in order (:class:`~labrig.pipeline.depth_inputs.InputSpec`; absent:
  the SAE alone);
* ``architecture``: the U-Net's ``width``, ``pools`` and ``in_channels`` (:class:`UNetConfig`;
  absent in hand-made cards);
* ``loss.name``, ``augmentation.background_noise`` (trained on noisy windows), ``contact_anchor``
  (fields of :class:`~labrig.pipeline.anchor.AnchorParams` over its defaults), ``name``,
  ``training_data.campaign`` and ``command``.

The rest (training history, validation errors, provenance) is a record: :attr:`ModelCard.raw`
keeps the JSON as read, and :meth:`ModelCard.to_json` hands it back for writing. A card that
cannot be used raises one :class:`~labrig.errors.ModelCardError` line naming the file and the key.
"""

from __future__ import annotations

import copy
import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from labrig.errors import LabrigError, ModelCardError
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.anchor import AnchorParams
from labrig.pipeline.brightness import BOOLEAN_KEYS
from labrig.pipeline.depth_inputs import InputSpec
from labrig.pipeline.sae import UNET_SHAPE

CARD_FORMAT = "labrig.depthnet"
CARD_VERSION = 1
#: The SAE span (ms) of a card that names none: the paper's 10 ms.
DEFAULT_WINDOW_MS = 10.0
_ANCHOR_FIELDS = {name: f.type for name, f in AnchorParams.__dataclass_fields__.items()}


@dataclass(frozen=True)
class UNetConfig:
    """Shape of the U-Net: base width (channels at full resolution) and number of poolings."""

    width: int = 32
    pools: int = 4
    in_channels: int = 2

    def __post_init__(self) -> None:
        if self.width < 1 or self.pools < 1:
            raise ValueError("width and pools must be >= 1")
        for size in UNET_SHAPE:
            if size % (2 ** self.pools):
                raise ValueError(f"input {UNET_SHAPE} is not divisible by 2**{self.pools}")

    def to_dict(self) -> dict[str, Any]:
        return {"name": "unet", "width": self.width, "pools": self.pools, "in_channels": self.in_channels,
                "input_shape": [self.in_channels, *UNET_SHAPE], "output_shape": [1, *UNET_SHAPE],
                "grid_shape": list(GRID_SHAPE), "blocks": "2 x (conv3x3 + batchnorm + relu) per level",
                "down": "maxpool 2x2", "up": "transposed conv 2x2 + skip concatenation", "head": "conv1x1, linear"}


@dataclass(frozen=True)
class ModelCard:
    """A depth network's card, checked: what the pipeline, the evaluation and training act on.

    ``path``: the ``.json`` it was read from (None: built from a dict). ``raw``: the JSON as read.
    """

    scale_mm: float
    window_ms: float = DEFAULT_WINDOW_MS
    inputs: InputSpec = field(default_factory=InputSpec)
    architecture: UNetConfig | None = None
    name: str | None = None
    loss: str | None = None  # the training loss's name (labrig.training.loss)
    noise_trained: bool = False  # trained with background-noise augmentation
    contact_anchor: AnchorParams = field(default_factory=AnchorParams)
    training_campaign: str | None = None  # the campaign folder it was trained on
    command: str = ""  # the command that trained it
    path: Path | None = None
    raw: Mapping[str, Any] = field(default_factory=dict, compare=False, hash=False, repr=False)

    @classmethod
    def load(cls, path: str | Path) -> ModelCard:
        """The card at ``path`` (``NAME.json``)."""
        path = Path(path)
        if not path.exists():
            raise ModelCardError(f"{path}: no model card beside the network; export it again with `labrig train`")
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ModelCardError(f"{path} is not valid JSON ({exc.msg}, line {exc.lineno})") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ModelCardError(f"{path} cannot be read ({exc})") from None
        return cls.from_json(data, path)

    @classmethod
    def from_json(cls, data: Any, path: str | Path | None = None) -> ModelCard:
        """The card of a parsed JSON object; ``path`` names it in errors."""
        where = str(path) if path is not None else "model card"
        if not isinstance(data, dict) or data.get("format") != CARD_FORMAT:
            found = data.get("format") if isinstance(data, dict) else type(data).__name__
            raise ModelCardError(f"{where} is not a labrig depth-network model card (format {found!r})")
        fields = _Fields(data, where)
        version = data.get("format_version", CARD_VERSION)
        if version != CARD_VERSION or isinstance(version, bool):
            raise ModelCardError(f"{where}: 'format_version' {version!r} is not supported (this labrig reads "
                                 f"{CARD_VERSION}); use a labrig that wrote it, or train the network again")
        return cls(scale_mm=fields.positive("scale_mm"),
                   window_ms=fields.positive("window_ms", DEFAULT_WINDOW_MS),
                   inputs=fields.inputs(),
                   architecture=fields.architecture(),
                   name=fields.text("name"),
                   loss=fields.text("loss.name"),
                   noise_trained=bool(fields.section("augmentation").get("background_noise")),
                   contact_anchor=fields.anchor(),
                   training_campaign=fields.text("training_data.campaign"),
                   command=fields.text("command") or "",
                   path=Path(path) if path is not None else None,
                   raw=copy.deepcopy(data))

    def to_json(self) -> dict[str, Any]:
        """A copy of the card's JSON, for writing it back (with a section added or changed)."""
        return copy.deepcopy(dict(self.raw))

    @property
    def onnx(self) -> Path | None:
        """The network beside the card (``NAME.onnx``); None for a card built from a dict."""
        return self.path.with_suffix(".onnx") if self.path is not None else None

    @property
    def width(self) -> int | None:
        """The U-Net's base width; None when the card has no architecture."""
        return self.architecture.width if self.architecture is not None else None

    @property
    def sees_brightness(self) -> bool:
        """The network takes the brightness change since rest: the gel's state is in its input."""
        return "brightness" in self.inputs.kinds


class _Fields:
    """Typed reads from one card's JSON; each failure is one line naming the file and the (dotted) key."""

    def __init__(self, data: dict[str, Any], where: str) -> None:
        self.data, self.where = data, where

    def fail(self, key: str, what: str, value: Any) -> ModelCardError:
        return ModelCardError(f"{self.where}: '{key}' must be {what}, not {value!r}")

    def value(self, key: str) -> Any:
        """The value at a dotted key; None when it or a section above it is absent or null."""
        parent, _, last = key.rpartition(".")
        return (self.section(parent) if parent else self.data).get(last)

    def section(self, key: str) -> dict[str, Any]:
        """The object at a dotted key ({} when absent or null)."""
        node: Any = self.data
        for depth, part in enumerate(key.split(".")):
            node = node.get(part)
            if node is None:
                return {}
            if not isinstance(node, dict):
                raise self.fail(".".join(key.split(".")[:depth + 1]), "an object", node)
        return node

    def positive(self, key: str, default: float | None = None) -> float:
        value = self.value(key)
        if value is None:
            if default is None:
                raise ModelCardError(f"{self.where}: '{key}' is missing; the card of a trained network has it")
            return default
        if not _is_number(value) or value <= 0:
            raise self.fail(key, "a positive number", value)
        return float(value)

    def text(self, key: str) -> str | None:
        value = self.value(key)
        if value is not None and not isinstance(value, str):
            raise self.fail(key, "a string", value)
        return value

    def architecture(self) -> UNetConfig | None:
        section = self.section("architecture")
        if not section:
            return None
        sizes = {}
        for key in ("width", "pools", "in_channels"):
            value = section.get(key)
            if value is None and key != "width":
                continue
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise self.fail(f"architecture.{key}", "a positive integer", value)
            sizes[key] = value
        try:
            return UNetConfig(**sizes)
        except ValueError as exc:
            raise ModelCardError(f"{self.where}: 'architecture': {exc}") from None

    def inputs(self) -> InputSpec:
        if self.data.get("inputs") is None:
            return InputSpec()
        kinds = self.section("inputs").get("kinds")
        if not isinstance(kinds, list) or not all(isinstance(k, str) for k in kinds):
            raise self.fail("inputs.kinds", "a list of input names", kinds)
        self.positive("inputs.displacement_scale_mm", 1.0)
        for key, value in self.section("inputs.brightness").items():
            if key in BOOLEAN_KEYS:
                if not isinstance(value, bool):
                    raise self.fail(f"inputs.brightness.{key}", "true or false", value)
            elif not _is_number(value):
                raise self.fail(f"inputs.brightness.{key}", "a number", value)
        try:
            return InputSpec.from_card(self.data)
        except LabrigError as exc:
            raise ModelCardError(f"{self.where}: 'inputs': {exc}") from None

    def anchor(self) -> AnchorParams:
        section = self.section("contact_anchor")
        for key, value in section.items():
            if key not in _ANCHOR_FIELDS:
                raise ModelCardError(f"{self.where}: 'contact_anchor.{key}' is not a field of the anchor's noise "
                                     f"model; use {', '.join(sorted(_ANCHOR_FIELDS))}")
            integer = _ANCHOR_FIELDS[key] in (int, "int")
            if not _is_number(value) or (integer and not isinstance(value, int)):
                raise self.fail(f"contact_anchor.{key}", "an integer" if integer else "a number", value)
        return AnchorParams(**section)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def card_path(onnx_path: str | Path) -> Path:
    """The card beside a network: ``NAME.json`` for ``NAME.onnx``."""
    return Path(onnx_path).with_suffix(".json")


def write_card(card: Mapping[str, Any], path: str | Path) -> Path:
    """Write ``card`` (the JSON's fields; ``format`` and ``format_version`` are added) to ``path``, atomically,
    after checking that it reads back as a :class:`ModelCard`."""
    path = Path(path)
    data = {"format": CARD_FORMAT, "format_version": CARD_VERSION, **card}
    ModelCard.from_json(data, path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)
    return path


def find_models(folder: str | Path) -> list[ModelCard]:
    """The cards of every ``NAME.onnx`` + ``NAME.json`` pair in ``folder`` (each card's :attr:`ModelCard.onnx`).

    This is what ``labrig evaluate --models DIR`` reads: a card gives the window, the loss and the
    width of its network.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise LabrigError(f"{folder}: not a folder of depth networks")
    return [ModelCard.load(card_path(onnx)) for onnx in sorted(folder.glob("*.onnx")) if card_path(onnx).exists()]
