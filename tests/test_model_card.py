"""The depth network's model card: the bundled cards parse, a card round-trips, a bad card is one clear line."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from labrig.config import RigConfig
from labrig.errors import LabrigError, ModelCardError
from labrig.models import BUNDLED, bundled_model_path
from labrig.pipeline.anchor import AnchorParams
from labrig.pipeline.depth_inputs import InputSpec
from labrig.pipeline.model_card import CARD_FORMAT, ModelCard, UNetConfig, card_path, write_card

ROOT = Path(__file__).resolve().parents[1]


def _bundled(name: str) -> ModelCard:
    return ModelCard.load(card_path(bundled_model_path(name)))


@pytest.mark.parametrize("name", sorted(BUNDLED))
def test_the_bundled_cards_parse(name: str) -> None:
    card = _bundled(name)
    assert card.scale_mm == 2.5 and card.window_ms == 10.0 and card.loss == "contact"
    assert card.architecture == UNetConfig(width=4, pools=4, in_channels=card.inputs.channels)
    assert card.name == bundled_model_path(name).stem and card.onnx == bundled_model_path(name)
    assert card.training_campaign and card.command.startswith(("labrig train", "python tools/depth_sweep.py"))
    assert card.contact_anchor == AnchorParams() and not card.noise_trained
    assert card.sees_brightness == (name == "default")
    assert card.inputs == (InputSpec.named("sae+bright-band") if name == "default" else InputSpec())


def test_a_card_round_trips_through_write_card(tmp_path: Path) -> None:
    card = _bundled("default")
    written = write_card({**card.to_json(), "note": "kept"}, tmp_path / "copy.json")
    again = ModelCard.load(written)
    assert replace(again, path=card.path) == card  # every typed field
    assert again.raw == {**card.raw, "note": "kept"}  # and the record, verbatim
    assert json.loads(written.read_text())["format"] == CARD_FORMAT
    changed = card.to_json()
    changed["window_ms"] = 20.0  # to_json hands out a copy
    assert card.raw["window_ms"] == 10.0 and card.window_ms == 10.0
    with pytest.raises(ModelCardError, match="'scale_mm' is missing"):
        write_card({"name": "x"}, tmp_path / "x.json")  # a writer cannot write a card that does not read back
    assert not (tmp_path / "x.json").exists()


def test_a_minimal_card_takes_the_defaults() -> None:
    card = ModelCard.from_json({"format": CARD_FORMAT, "scale_mm": 2.5})
    assert card.window_ms == 10.0 and card.inputs == InputSpec() and card.architecture is None and card.width is None
    assert card.path is None and card.onnx is None and card.name is None and card.command == ""
    anchored = ModelCard.from_json({"format": CARD_FORMAT, "scale_mm": 2.5, "contact_anchor": {"floor_mm": 0.1},
                                    "augmentation": {"background_noise": {"max_hz": 2.0}}})
    assert anchored.contact_anchor == AnchorParams(floor_mm=0.1) and anchored.noise_trained


BAD_CARDS: list[tuple[dict[str, Any], str]] = [
    ({"scale_mm": None}, "'scale_mm' is missing"),
    ({"scale_mm": "2.5"}, "'scale_mm' must be a positive number, not '2.5'"),
    ({"scale_mm": True}, "'scale_mm' must be a positive number"),
    ({"window_ms": -10}, "'window_ms' must be a positive number, not -10"),
    ({"format_version": 2}, "'format_version' 2 is not supported"),
    ({"inputs": "sae"}, "'inputs' must be an object"),
    ({"inputs": {"kinds": "sae"}}, "'inputs.kinds' must be a list of input names"),
    ({"inputs": {"kinds": ["sae", "colour"]}}, "'inputs': depth-network inputs must start with sae"),
    ({"inputs": {"kinds": ["sae"], "displacement_scale_mm": 0}}, "'inputs.displacement_scale_mm' must be a positive"),
    ({"inputs": {"kinds": ["sae", "brightness"], "brightness": {"tau_s": "30"}}}, "'inputs.brightness.tau_s' must be"),
    ({"inputs": {"kinds": ["sae", "brightness"], "brightness": {"dead_band": 1}}},
     "'inputs.brightness.dead_band' must be true or false"),
    ({"architecture": {"width": "4"}}, "'architecture.width' must be a positive integer, not '4'"),
    ({"architecture": {"width": 4, "pools": 6}}, "'architecture': input"),
    ({"loss": "contact"}, "'loss' must be an object, not 'contact'"),
    ({"loss": {"name": 3}}, "'loss.name' must be a string, not 3"),
    ({"contact_anchor": {"floor": 0.1}}, "'contact_anchor.floor' is not a field"),
    ({"contact_anchor": {"persist": 2.5}}, "'contact_anchor.persist' must be an integer"),
    ({"training_data": {"campaign": ["data/x"]}}, "'training_data.campaign' must be a string"),
]


@pytest.mark.parametrize(("change", "message"), BAD_CARDS)
def test_a_bad_card_is_one_line_naming_the_file_and_the_key(tmp_path: Path, change: dict[str, Any],
                                                             message: str) -> None:
    data = {**_bundled("sae-only").to_json(), **change}
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({k: v for k, v in data.items() if v is not None}))
    with pytest.raises(ModelCardError) as caught:
        ModelCard.load(path)
    text = str(caught.value)
    assert "\n" not in text and text.startswith(f"{path}: ") and message in text, text


def test_a_file_that_is_not_a_card_says_so(tmp_path: Path) -> None:
    with pytest.raises(ModelCardError, match="no model card beside the network"):
        ModelCard.load(tmp_path / "none.json")
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(ModelCardError, match="is not valid JSON"):
        ModelCard.load(tmp_path / "broken.json")
    (tmp_path / "list.json").write_text("[]")
    with pytest.raises(ModelCardError, match="not a labrig depth-network model card"):
        ModelCard.load(tmp_path / "list.json")


def test_run_and_evaluate_refuse_a_bad_card_in_one_line(small_recording: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(bundled_model_path("sae-only").read_bytes())
    card = {**_bundled("sae-only").to_json(), "inputs": {"kinds": ["sae", "colour"]}}
    card_path(bad).write_text(json.dumps(card))
    commands = [("run", small_recording, "--depth", "model", "--model", bad),
                ("evaluate", tmp_path, "--model", bad, "--out", tmp_path / "report")]
    procs = [subprocess.Popen([sys.executable, "-m", "labrig.cli", *map(str, args)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, cwd=ROOT) for args in commands]
    for args, proc in zip(commands, procs, strict=True):
        _, stderr = proc.communicate(timeout=120)
        lines = [line for line in stderr.splitlines() if line.strip()]
        assert proc.returncode == 2, (args, stderr)
        assert len(lines) == 1 and lines[0].startswith("error:") and "Traceback" not in stderr, (args, stderr)
        assert str(card_path(bad)) in lines[0] and "'inputs'" in lines[0], (args, stderr)


def test_the_card_chooses_the_depth_source_and_bad_settings_are_refused(rig: RigConfig) -> None:
    from labrig.pipeline import depth_sources, run_setup
    from labrig.pipeline.quiet import QuietParams

    setup = run_setup.setup_for_rig(rig, calibration_dir=None)
    baseline = depth_sources.model_depth("sae-only")
    assert type(baseline) is depth_sources.SaeNetworkDepth and baseline.hold is not None and not baseline.needs_counts
    bright = depth_sources.model_depth("default", setup=setup)
    assert type(bright) is depth_sources.BrightnessNetworkDepth and bright.needs_counts and bright.integrator is not None
    assert bright.card == _bundled("default")
    with pytest.raises(LabrigError, match="quiet hold does not apply"):
        depth_sources.model_depth("default", setup=setup, quiet=QuietParams())
    with pytest.raises(LabrigError, match="'auto', None or its parameters, not 'sometimes'"):
        depth_sources.model_depth("sae-only", quiet="sometimes")
    with pytest.raises(TypeError):
        depth_sources.ModelDepth(bright.model, setup, None)  # type: ignore[abstract]  # a design is a subclass


def test_a_bundled_networks_rebuild_names_every_training_it_was_fine_tuned_through(tmp_path: Path) -> None:
    """tools/bundle_model.py: a network fine-tuned from another lists the first training before its own."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location("bundle_model", Path(__file__).resolve().parent.parent / "tools"
                                                  / "bundle_model.py")
    assert spec is not None and spec.loader is not None
    tool = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = tool
    spec.loader.exec_module(tool)
    base = _bundled("default").to_json()
    first = write_card({**base, "command": "labrig train DATA --out first", "init": None}, tmp_path / "first.json")
    tuned = write_card({**base, "command": "labrig train DATA --init first.onnx --out tuned",
                        "init": {"model": "first", "onnx": str(tmp_path / "first.onnx"), "onnx_sha256": "ab"}},
                       tmp_path / "tuned.json")
    assert tool.training_commands(ModelCard.load(tuned)) == ["labrig train DATA --out first",
                                                             "labrig train DATA --init first.onnx --out tuned"]
    first.unlink()
    assert tool.training_commands(ModelCard.load(tuned))[0].startswith("(fine-tuned from ")
