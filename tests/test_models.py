"""The bundled depth networks: found by name, shipped with their cards, small."""

from __future__ import annotations

from pathlib import Path

import pytest

from labrig.errors import LabrigError
from labrig.models import BUNDLED, bundled_model_path, model_path
from labrig.pipeline.model_card import ModelCard


@pytest.mark.parametrize("name", sorted(BUNDLED))
def test_each_bundled_network_ships_with_its_card(name: str) -> None:
    path = bundled_model_path(name)
    card = ModelCard.load(path.with_suffix(".json")).to_json()
    assert path.stat().st_size < 10_000_000
    assert card["window_ms"] == 10.0 and card["bundled"]["reason"]
    assert card["reproduce"].startswith("labrig train ")
    rebuild = " ".join(card["bundled"].get("rebuild") or [card["reproduce"]])
    assert ("--inputs sae+bright" in rebuild) == (name == "default")


def test_the_default_sees_the_gels_state_and_the_baseline_does_not() -> None:
    from labrig.pipeline.depth_inputs import InputSpec

    default = ModelCard.load(bundled_model_path().with_suffix(".json")).to_json()
    assert InputSpec.from_card(default).kinds == ("sae", "brightness")
    held = default["inputs"]["brightness"]
    assert held["rest_tau_s"] > 0 and held["reference_slope_gain"] > 0  # the gated leak, the reference light
    assert InputSpec.from_card(ModelCard.load(bundled_model_path("sae-only").with_suffix(".json")).to_json()).kinds == ("sae",)


def test_model_names_and_paths(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert model_path("sae-only") == bundled_model_path("sae-only")
    assert model_path("default") == bundled_model_path()
    assert model_path(tmp_path / "mine.onnx") == tmp_path / "mine.onnx"
    monkeypatch.chdir(tmp_path)
    (tmp_path / "default").write_text("")  # a file of that name wins over the bundled name
    assert model_path("default") == Path("default")
    with pytest.raises(LabrigError, match="the bundled ones are default, sae-only"):
        bundled_model_path("huge")
