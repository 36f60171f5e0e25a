"""The bundled depth networks: trained on virtual-rig campaigns, shipped with their model cards.

``NAME.onnx`` + ``NAME.json`` (the card: architecture, inputs, training data, window, loss,
augmentation, val and test errors, and the exact command that reproduces it), and
``NAME.weights.pt`` (its torch weights, which ``labrig train --init`` fine-tunes).
``labrig evaluate`` and ``labrig run --depth model`` use ``default`` unless given another model:
the SAE and the brightness change since rest (:mod:`labrig.pipeline.brightness`), the gel's
state, held while the gel is loaded (the gated leak) and read under the reference light (the
camera's calibrated slope gain); ``labrig train --init default`` fine-tunes it. ``--model
sae-only`` picks the paper's network, the SAE alone, kept as the baseline it is compared with
(it needs the quiet hold, :mod:`labrig.pipeline.quiet`; docs/depthnet.md).
"""

from __future__ import annotations

from pathlib import Path

from labrig.errors import LabrigError

#: Bundled networks by the name ``--model`` accepts.
BUNDLED = {"default": "depth-w4-patch-10ms", "sae-only": "depth-w4-contact-10ms"}
BUNDLED_NAME = BUNDLED["default"]
FOLDER = Path(__file__).resolve().parent
#: A network's torch weights (its ``state_dict``) beside its ``.onnx``: ``NAME`` + this.
WEIGHTS_SUFFIX = ".weights.pt"


def bundled_model_path(name: str = "default") -> Path:
    """A bundled ``.onnx`` by its name in :data:`BUNDLED` (its card is the ``.json`` beside it)."""
    if name not in BUNDLED:
        raise LabrigError(f"no bundled depth network {name!r}; the bundled ones are {', '.join(BUNDLED)}")
    path = FOLDER / f"{BUNDLED[name]}.onnx"
    if not path.exists() or not path.with_suffix(".json").exists():
        raise LabrigError(f"the bundled depth network {path.name} is missing from {FOLDER}; reinstall labrig, "
                          "or train one with `labrig train DATA/` and pass it with --model")
    return path


def model_path(spec: str | Path) -> Path:
    """``--model``'s value: a bundled network's name (``default``, ``sae-only``) or an ``.onnx`` path."""
    if str(spec) in BUNDLED and not Path(spec).exists():
        return bundled_model_path(str(spec))
    return Path(spec)
