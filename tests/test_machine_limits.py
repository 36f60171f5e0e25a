"""The virtual CNC's machine limits ([sim.grbl]): parsed, honoured by both twins, and speeds checked against them."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from labrig.config import ConfigError, RigConfig, load_rig, parse_rig, rig_with
from labrig.indenters import Indenter, load_indenters
from labrig.protocol.files import PROTOCOLS_DIR, check_spec, load_campaign, load_protocol
from labrig.protocol.rigfile import DeviceConfig
from labrig.protocol.runner import ProbeRunner
from labrig.protocol.safety import SafetyError, SafetyLimits, SpeedLimits
from labrig.protocol.session import RigSession
from labrig.protocol.spec import ApproachSpec, ProbeSpec, ProtocolError
from labrig.protocol.variation import slowest_machine
from labrig.protocol.virtual_run import record_virtual
from labrig.sim.offline import OfflineRig, OfflineSinks, machine_limits
from labrig.sim.truth_config import sim_config
from labrig.sim.world import LiveWorld

FAST = {"sim.grbl.max_rate_mm_min": 3600.0, "sim.grbl.acceleration_mm_s2": 5000.0}
SPEC = ProbeSpec("sphere", depth_mm=0.5, normal_speed_mm_s=50.0, shear_mm=0.5, shear_speed_mm_s=50.0, wait_s=0.1,
                 approach=ApproachSpec(start_height_mm=0.3, speed_mm_s=1.0, max_travel_mm=1.5))


@pytest.fixture(scope="module")
def fast_rig(rig: RigConfig) -> RigConfig:
    return rig_with(rig, FAST)


# -- the section ------------------------------------------------------------------------------------


def test_the_default_rig_keeps_grbl_defaults(rig: RigConfig) -> None:
    assert sim_config(rig).grbl.max_rate_mm_min == (500.0, 500.0, 500.0)
    assert sim_config(rig).grbl.acceleration_mm_s2 == (10.0, 10.0, 10.0)
    assert machine_limits(rig).max_rate_mm_min == (500.0, 500.0, 500.0)


def test_a_number_sets_every_axis_and_a_list_each(rig: RigConfig) -> None:
    text = rig.text + "\n[sim.grbl]\nmax_rate_mm_min = [6000, 6000.0, 1200]\nacceleration_mm_s2 = 2500\n"
    grbl = sim_config(parse_rig(text, rig.path)).grbl
    assert grbl.max_rate_mm_min == (6000.0, 6000.0, 1200.0)
    assert grbl.acceleration_mm_s2 == (2500.0,) * 3
    assert grbl.max_rate_mm_s == (100.0, 100.0, 20.0)
    assert grbl.settings() == {110: 6000.0, 111: 6000.0, 112: 1200.0, 120: 2500.0, 121: 2500.0, 122: 2500.0}


@pytest.mark.parametrize(("section", "expected"), [
    ("max_rate_mm_min = 'fast'", "max_rate_mm_min must be a number (all axes) or [x, y, z]"),
    ("max_rate_mm_min = [100, 200]", "max_rate_mm_min must be a number (all axes) or [x, y, z]"),
    ("acceleration_mm_s2 = 0", "acceleration_mm_s2 must be positive on every axis"),
    ("max_rate_mm_min = [100, -5, 100]", "max_rate_mm_min must be positive on every axis"),
    ("max_rate_mm_min = 9000", "beyond GRBL's step rate (30000 Hz at 250 steps/mm): give at most 7200 mm/min"),
    ("max_feed = 100", "unknown key 'max_feed'; allowed: max_rate_mm_min, acceleration_mm_s2"),
])
def test_bad_values_are_refused_in_one_line(rig: RigConfig, section: str, expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        sim_config(parse_rig(rig.text + f"\n[sim.grbl]\n{section}\n", rig.path))
    message = str(info.value)
    assert "[sim.grbl]" in message and expected in message and "\n" not in message


def test_rig_with_adds_the_section_and_the_text_says_so(rig: RigConfig, fast_rig: RigConfig) -> None:
    assert "[sim.grbl]" not in rig.text and "[sim.grbl]" in fast_rig.text
    assert sim_config(fast_rig).grbl.max_rate_mm_min == (3600.0,) * 3
    assert sim_config(parse_rig(fast_rig.text, rig.path)).grbl == sim_config(fast_rig).grbl  # a recording's rig text keeps it


# -- both twins honour it ------------------------------------------------------------------------------


def _twin_speed_mm_s(rig: RigConfig, sphere: Indenter) -> tuple[float, bytes]:
    """Max speed of a 20 mm G1 at F3000 (50 mm/s) on the through-driver world's GRBL twin, and its $$."""
    twin = LiveWorld(rig, sphere, homed=True).grbl
    t0 = 1_000_000
    twin.receive(b"$$\n", t0)
    settings = b"".join(twin.transmit(t0 + k * 1000) for k in range(1, 200))
    t1 = t0 + 300_000
    twin.receive(b"G91G1X-20F3000\n", t1)
    t = t1 + np.arange(0, 3_000_000, 1000)
    twin.transmit(int(t[-1]))
    p = twin.position_mm(t)
    return float((np.linalg.norm(np.diff(p, axis=0), axis=1) / 1e-3).max()), settings


def test_the_live_world_twin_runs_at_the_rig_files_rate(rig: RigConfig, fast_rig: RigConfig, sphere: Indenter) -> None:
    fast, settings = _twin_speed_mm_s(fast_rig, sphere)
    assert fast == pytest.approx(50.0, rel=1e-3)
    assert b"$110=3600.000" in settings and b"$112=3600.000" in settings and b"$122=5000.000" in settings
    slow, settings = _twin_speed_mm_s(rig, sphere)
    assert slow == pytest.approx(500 / 60, rel=1e-3)  # the defaults: 50 mm/s asked, 8.3 mm/s run
    assert b"$110=500.000" in settings


def test_the_virtual_time_twin_runs_at_the_rig_files_rate(fast_rig: RigConfig, sphere: Indenter) -> None:
    statuses = []
    devices = OfflineRig(fast_rig, sphere, seed=0, start_tool_mm=(-100.0, -100.0, -40.0),
                         sinks=OfflineSinks(cnc=statuses.append))
    devices.move((-120.0, -100.0, -40.0), 3000.0)
    assert devices.wait_idle(2_000_000) is not None
    t = np.arange(devices.timeline.t_us - 1_000_000, devices.timeline.t_us, 1000.0)
    p = devices.timeline.positions_at(t)
    assert (np.linalg.norm(np.diff(p, axis=0), axis=1) / 1e-3).max() == pytest.approx(50.0, rel=1e-3)
    assert max(s.feed_mm_min for s in statuses) == 3000.0  # the CNC rows show the feed


# -- speeds are checked against it ---------------------------------------------------------------------


def test_speed_limits_name_the_key_and_the_limit(rig: RigConfig, fast_rig: RigConfig) -> None:
    found = dict(SpeedLimits.of_rig(rig).problems(SPEC))
    assert set(found) == {"normal_speed_mm_s", "shear_speed_mm_s"}
    assert found["normal_speed_mm_s"] == (
        "50 mm/s is above the virtual CNC's Z max rate 8.33 mm/s ([sim.grbl] max_rate_mm_min = 500 mm/min); raise "
        "max_rate_mm_min in the rig file's [sim.grbl] (or a campaign's [vary]), or give at most 8.33 mm/s")
    assert SpeedLimits.of_rig(fast_rig).problems(SPEC) == []
    assert SpeedLimits.of_rig(fast_rig).problems(replace(SPEC, approach=ApproachSpec(speed_mm_s=61.0)))[0][0] == \
        "approach.speed_mm_s"
    assert SpeedLimits.of_rig(rig).problems(replace(SPEC, shear_mm=0.0, normal_speed_mm_s=8.0)) == []  # no shear phase


def test_the_connected_grbls_settings_name_the_dollar_setting() -> None:
    limits = SpeedLimits.of_grbl({110: 3000.0, 111: 1200.0, 112: 600.0})
    assert limits is not None and SpeedLimits.of_grbl({110: 3000.0}) is None
    with pytest.raises(SafetyError) as info:
        limits.check(SPEC)
    message = str(info.value)
    assert message.startswith("refused before moving: normal.speed_mm_s 50 mm/s is above the connected GRBL's Z max rate 10")
    assert "($112 = 600 mm/min); raise $112 on the controller" in message
    assert "shear.speed_mm_s 50 mm/s is above the connected GRBL's Y max rate 20 mm/s ($111 = 1200 mm/min)" in message


def test_the_protocol_checker_refuses_too_fast_on_the_virtual_rig(rig: RigConfig, fast_rig: RigConfig,
                                                                   tmp_path: Path) -> None:
    indenters = load_indenters()
    path = tmp_path / "fast.toml"
    path.write_text('[probe]\nindenter = "sphere"\n[normal]\ndepth_mm = 1.0\nspeed_mm_s = 20.0\n')
    with pytest.raises(ProtocolError) as info:
        load_protocol(path, rig, indenters)
    assert str(info.value) == (f"{path}:5: normal.speed_mm_s: 20 mm/s is above the virtual CNC's Z max rate 8.33 mm/s "
                               "([sim.grbl] max_rate_mm_min = 500 mm/min); raise max_rate_mm_min in the rig file's "
                               "[sim.grbl] (or a campaign's [vary]), or give at most 8.33 mm/s")
    assert load_protocol(path, fast_rig, indenters).normal_speed_mm_s == 20.0
    hardware = parse_rig(rig.text.replace('grbl_port = ""', 'grbl_port = "/dev/ttyUSB0"'), rig.path)
    assert check_spec(replace(SPEC, shear_mm=0.0), hardware, indenters) == []  # the runner checks the controller


def test_record_virtual_refuses_before_any_move(rig: RigConfig, sphere: Indenter, tmp_path: Path) -> None:
    with pytest.raises(SafetyError, match=r"normal\.speed_mm_s 50 mm/s is above the virtual CNC's Z max rate 8\.33"):
        record_virtual(SPEC, tmp_path / "run.h5", rig, sphere)
    assert not (tmp_path / "run.h5").exists()


CAMPAIGN = """
[campaign]
name = "fast"
[vary]
{vary}
[[group]]
indenters = ["sphere"]
depth_mm = [0.5]
normal_speed_mm_s = [2.0, 50.0]
"""


@pytest.mark.parametrize(("vary", "refused"), [
    ('"sim.grbl.max_rate_mm_min" = [3600, 3600]', False),
    ('"sim.grbl.max_rate_mm_min" = [3600, 6000]', False),
    ('"sim.grbl.max_rate_mm_min" = [1200, 6000]', True),  # the slowest machine it draws is too slow
    ('"sim.events.shot_noise_rate_hz" = [0.05, 1.0]', True),
])
def test_a_campaign_checks_speeds_against_its_slowest_varied_machine(rig: RigConfig, tmp_path: Path, vary: str,
                                                                   refused: bool) -> None:
    path = tmp_path / "fast.toml"
    path.write_text(CAMPAIGN.format(vary=vary))
    if not refused:
        campaign = load_campaign(path, rig, load_indenters())
        assert campaign.variation is not None
        assert all(v >= 3600 for p in campaign.plans
                   for v in sim_config(campaign.variation.rig_for(rig, p.index)).grbl.max_rate_mm_min)
        return
    with pytest.raises(ProtocolError) as info:
        load_campaign(path, rig, load_indenters())
    assert str(info.value).startswith(f"{path}:9: group[1].normal_speed_mm_s: 50 mm/s is above the virtual CNC's Z max rate")


def test_slowest_machine_takes_the_low_end(rig: RigConfig, tmp_path: Path) -> None:
    path = tmp_path / "fast.toml"
    vary = '"sim.grbl.max_rate_mm_min" = [3000, 6000]\n"sim.grbl.acceleration_mm_s2" = [900, 2000]'
    path.write_text(CAMPAIGN.format(vary=vary))
    variation = load_campaign(path, rig, load_indenters()).variation
    assert variation is not None
    slow = sim_config(slowest_machine(rig, variation)).grbl
    assert slow.max_rate_mm_min == (3000.0,) * 3 and slow.acceleration_mm_s2 == (900.0,) * 3


def test_the_runner_checks_the_connected_grbl_before_moving(rig: RigConfig, sphere: Indenter, tmp_path: Path) -> None:
    """Through the drivers: the world process powers the twin on with the rig file's [sim.grbl];
    the runner reads it over $$ and refuses a faster run before the first move."""
    path = tmp_path / "rig.toml"
    path.write_text(rig.text + "\n[sim.grbl]\nmax_rate_mm_min = [3600, 3600, 1200]\nacceleration_mm_s2 = 2000\n")
    limited = load_rig(path)
    with RigSession(limited, DeviceConfig(), SafetyLimits(), indenter=sphere) as session:
        assert session.grbl is not None
        assert [session.grbl.settings[n] for n in (110, 111, 112, 120)] == [3600.0, 3600.0, 1200.0, 2000.0]
        start = session.grbl.position_mm
        runner = ProbeRunner.for_session(session)
        with pytest.raises(SafetyError, match=r"normal.speed_mm_s 50 mm/s is above the connected GRBL's Z max rate "
                                              r"20 mm/s \(\$112 = 1200 mm/min\)"):
            runner.run(SPEC, tmp_path / "run.h5")
        assert session.grbl.position_mm == start
    assert not (tmp_path / "run.h5").exists()


# -- the training campaign -------------------------------------------------------------------------------


def test_train_large_loads_with_its_vary_keys(rig: RigConfig) -> None:
    campaign = load_campaign(PROTOCOLS_DIR / "train-large.toml", rig, load_indenters())
    plans = campaign.plans
    assert 300 <= len(plans) <= 450
    splits = {s: sum(p.split == s for p in plans) for s in ("train", "val", "test")}
    assert splits["test"] == 0 and splits["train"] > 3 * splits["val"] > 0
    assert {p.spec.indenter for p in plans} == {"sphere", "cylinder", "square", "ridge"}
    assert max(max(p.spec.normal_speed_mm_s, p.spec.shear_speed_mm_s) for p in plans) >= 50
    assert min(p.spec.depth_mm or 9 for p in plans) <= 0.2
    assert campaign.variation is not None
    keys = {k.key: k for k in campaign.variation.keys}
    for key in ("sim.events.shot_noise_rate_hz", "sim.markers.contrast_variation", "sim.markers.position_error_mm",
                "sim.markers.missing_count", "sim.camera_delivery.burst_period_ms", "sim.grbl.max_rate_mm_min"):
        assert key in keys
    assert keys["sim.markers.seed"].recording_seed and keys["sim.camera_delivery.seed"].recording_seed
    assert keys["sim.events.shot_noise_rate_hz"].high == 2.0 and keys["sim.markers.missing_count"].high == 3
    for plan in plans[:: len(plans) // 6]:  # a few recordings' sensors: the rig takes every drawn value
        sensor = campaign.variation.rig_for(rig, plan.index)
        assert sim_config(sensor).grbl.max_rate_mm_min == (3600.0,) * 3 and sim_config(sensor).markers.seed == plan.index
        assert SpeedLimits.of_rig(sensor).problems(plan.spec) == []
