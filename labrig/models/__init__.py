"""The bundled depth network: trained on a virtual-rig campaign, shipped with its model card.

``NAME.onnx`` + ``NAME.json`` (the card: architecture, training data, window, loss, val and
test errors, and the exact command that reproduces it). ``labrig evaluate`` and
``labrig run --depth model`` use it unless given another model.
"""

from __future__ import annotations

from pathlib import Path

from labrig.errors import LabrigError

BUNDLED_NAME = "depth-w4-contact-10ms"
FOLDER = Path(__file__).resolve().parent


def bundled_model_path() -> Path:
    """The bundled ``.onnx`` (its card is the ``.json`` beside it)."""
    path = FOLDER / f"{BUNDLED_NAME}.onnx"
    if not path.exists() or not path.with_suffix(".json").exists():
        raise LabrigError(f"the bundled depth network {path.name} is missing from {FOLDER}; reinstall labrig, "
                          "or train one with `labrig train DATA/` and pass it with --model")
    return path
