"""A campaign's [vary] section: each virtual recording on a sensor of its own, drawn from its seed."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import pytest
from hypothesis import given
from hypothesis import strategies as st

from labrig.config import RigConfig, parse_rig
from labrig.indenters import DEFAULT_INDENTERS, Indenter, load_indenters
from labrig.protocol.files import load_campaign
from labrig.protocol.spec import ProtocolError
from labrig.protocol.variation import SensorVariation, VariedKey, parse_variation
from labrig.sim.truth_config import sim_config

CAMPAIGN = """
[campaign]
name = "vary"
seed = 3
protocol = "quick.toml"

[vary]
"sim.events.shot_noise_rate_hz" = [0.05, 2.0]
"sim.markers.missing_count" = [0, 3]
"sim.markers.seed" = "recording"

[[group]]
indenters = ["sphere"]
locations_mm = [[0.0, 0.0], [2.0, -1.0]]
depth_mm = [0.6]
"""

QUICK = """
[probe]
indenter = "sphere"
[approach]
start_height_mm = 0.3
speed_mm_s = 1.0
max_travel_mm = 1.5
[normal]
depth_mm = 0.6
speed_mm_s = 2.0
[wait]
duration_s = 0.05
[shear]
distance_mm = 0.3
speed_mm_s = 2.0
[retract]
height_mm = 0.5
"""


@pytest.fixture(scope="module")
def indenters() -> dict[str, Indenter]:
    return dict(load_indenters(DEFAULT_INDENTERS))


def _campaign(tmp_path: Path, text: str = CAMPAIGN) -> Path:
    (tmp_path / "quick.toml").write_text(QUICK)
    path = tmp_path / "vary.toml"
    path.write_text(text)
    return path


@given(seed=st.integers(0, 2**40))
def test_draws_are_fixed_by_the_seed_and_stay_in_their_ranges(seed: int) -> None:
    variation = SensorVariation((VariedKey("sim.events.shot_noise_rate_hz", 0.05, 2.0),
                                 VariedKey("sim.markers.missing_count", 0, 3, integer=True),
                                 VariedKey("sim.markers.seed", recording_seed=True)))
    values = variation.draw(seed)
    assert values == variation.draw(seed)
    assert 0.05 <= values["sim.events.shot_noise_rate_hz"] <= 2.0  # type: ignore[operator]
    assert values["sim.markers.missing_count"] in (0, 1, 2, 3)
    assert values["sim.markers.seed"] == seed


def test_recordings_of_a_campaign_get_their_own_sensor(tmp_path: Path, rig: RigConfig,
                                                        indenters: dict[str, Indenter]) -> None:
    campaign = load_campaign(_campaign(tmp_path), rig, indenters)
    assert campaign.variation is not None
    a, b = (campaign.variation.rig_for(rig, seed) for seed in (1, 2))
    assert sim_config(a).events.shot_noise_rate_hz != sim_config(b).events.shot_noise_rate_hz
    assert parse_rig(a.text, a.path) == a  # the recording stores text that states the drawn values
    assert a.gel == rig.gel and a.camera == rig.camera  # what the lab knows stays


@pytest.mark.parametrize("line, message", [
    ('"gel.friction" = [0.5, 0.9]', "only the virtual rig's truth varies"),
    ('"sim.ft.drop_probability" = 0.5', "give a range [low, high]"),
    ('"sim.ft.drop_probability" = [0.5, 0.1]', "reversed"),
    ('"sim.events.no_such_knob" = [0.0, 1.0]', "no_such_knob"),
    ('"sim.markers.position_error_mm" = [0.0, -1.0]', "reversed"),
    ('"sim.ft.drop_probability" = [0.0, 5.0]', "drop_probability"),
])
def test_a_bad_vary_key_is_refused_before_any_recording(tmp_path: Path, rig: RigConfig, indenters: dict[str, Indenter],
                                                         line: str, message: str) -> None:
    text = CAMPAIGN.replace('"sim.markers.seed" = "recording"', line)
    with pytest.raises(ProtocolError, match=message.replace("[", r"\[").replace("]", r"\]")):
        load_campaign(_campaign(tmp_path, text), rig, indenters)


def test_parse_keeps_the_good_keys_and_names_the_bad() -> None:
    variation, refused = parse_variation({"sim.ft.drop_probability": [0.0, 0.01], "camera.width": [1, 2]}, None)
    assert [k.key for k in variation.keys] == ["sim.ft.drop_probability"] and [k for k, _ in refused] == ["camera.width"]


def test_the_cli_records_each_sensor_in_virtual_time_and_refuses_vary_through_the_drivers(tmp_path: Path) -> None:
    path = _campaign(tmp_path)
    refused = subprocess.run([sys.executable, "-m", "labrig.cli", "campaign", str(path), "--out", str(tmp_path / "d"),
                              "--limit", "1"], capture_output=True, text=True, timeout=600)
    assert refused.returncode == 2 and "--virtual-time" in refused.stderr and "Traceback" not in refused.stderr
    done = subprocess.run([sys.executable, "-m", "labrig.cli", "campaign", str(path), "--out", str(tmp_path / "v"),
                           "--virtual-time", "--limit", "1"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    recording = next((tmp_path / "v").glob("*.h5"))
    with h5py.File(recording, "r") as f:
        rig_text = f.attrs["rig"]
    rig = parse_rig(str(rig_text), recording)
    campaign_seed_3_index_0 = 3 * 100_003
    assert sim_config(rig).markers.seed == campaign_seed_3_index_0


def test_an_error_line_keeps_its_brackets(tmp_path: Path) -> None:
    """Section names in error lines ([campaign], [vary]) are printed as written, not taken for markup."""
    path = tmp_path / "not-a-campaign.toml"
    path.write_text('[probe]\nindenter = "sphere"\n')
    done = subprocess.run([sys.executable, "-m", "labrig.cli", "campaign", str(path), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and "[campaign]: missing; start the file with [campaign]" in done.stderr


def test_a_campaign_that_varies_the_thresholds_calibrates_each_recordings_camera(tmp_path: Path) -> None:
    """Each recording gets ID.events.toml (its own camera's thresholds, fitted as `labrig calibrate events` fits
    them), and the pipeline's setup for that recording reads it before the calibration folder's; a campaign that
    leaves the thresholds alone writes none."""
    from labrig.dataset import events_sidecar_path
    from labrig.pipeline.run_setup import setup_for_recording
    from labrig.recording import Recording

    text = CAMPAIGN.replace('"sim.markers.seed" = "recording"', '"sim.markers.seed" = "recording"\n'
                            '"sim.events.threshold_on" = [0.30, 0.30]\n"sim.events.threshold_off" = [0.18, 0.18]')
    path = _campaign(tmp_path, text)
    done = subprocess.run([sys.executable, "-m", "labrig.cli", "campaign", str(path), "--out", str(tmp_path / "v"),
                           "--virtual-time", "--limit", "1"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    recording = next((tmp_path / "v").glob("*[0-9].h5"))
    sidecar = events_sidecar_path(recording)
    assert sidecar.exists()
    with Recording(recording) as rec:
        setup = setup_for_recording(rec)
    assert setup.sources["thresholds"] == str(sidecar) and setup.thresholds is not None
    assert float(setup.thresholds.on_ln.mean()) == pytest.approx(0.30, rel=0.05)
    assert float(setup.thresholds.off_ln.mean()) == pytest.approx(0.18, rel=0.05)
    (tmp_path / "p").mkdir()
    plain = subprocess.run([sys.executable, "-m", "labrig.cli", "campaign", str(_campaign(tmp_path / "p")),
                            "--out", str(tmp_path / "w"), "--virtual-time", "--limit", "1"],
                           capture_output=True, text=True, timeout=600)
    assert plain.returncode == 0, plain.stderr
    assert not list((tmp_path / "w").glob("*.events.toml"))
