"""Protocol and campaign files: loading, validation with line numbers, expansion, splits, overrides."""

from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path

import pytest

from labrig.config import RigConfig
from labrig.indenters import Indenter, load_indenters
from labrig.protocol import ApproachSpec, ProbeSpec, ProtocolError, apply_overrides, load_campaign, load_protocol
from labrig.protocol.files import DEFAULT_PROTOCOL, PROTOCOLS_DIR, TomlLocator
from labrig.protocol.split import assign_splits, split_counts


@pytest.fixture(scope="module")
def indenters() -> dict[str, Indenter]:
    return load_indenters()


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text.lstrip("\n"))
    return path


def _problems(exc: pytest.ExceptionInfo[ProtocolError]) -> dict[tuple[int, str], str]:
    """(line, field) -> message of each reported problem; also checks the message has one line each."""
    problems = exc.value.problems
    assert str(exc.value).splitlines() == [str(p) for p in problems]
    return {(p.line, p.field): p.message for p in problems}


# ----------------------------------------------------------------------------- specs


def test_default_protocol_is_the_dataclass_default(rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    spec = load_protocol(DEFAULT_PROTOCOL, rig, indenters)
    assert spec == ProbeSpec("sphere", depth_mm=1.5)
    assert spec.phases() == (
        "approach", "normal_down", "wait", "shear", "wait", "shear_opposite", "wait", "normal_up", "retract"
    )
    # 1.5 mm down and up at 1.5 mm/s, three 0.4 s waits, 1 mm out and back at 1.5 mm/s, 2 mm retract at 5 mm/s.
    assert spec.nominal_duration_s() == pytest.approx(2 * 1.0 + 3 * 0.4 + 2 * 1 / 1.5 + 0.4)


def test_no_shear_drops_the_shear_phases_and_targets_are_exclusive() -> None:
    spec = ProbeSpec("cylinder", force_n=5.0, shear_mm=0.0, max_depth_mm=1.0, wait_s=0.5)
    assert spec.phases() == ("approach", "normal_down", "wait", "normal_up", "retract")
    assert spec.nominal_duration_s() == pytest.approx(2 * 1.0 / 1.5 + 0.5 + 2.0 / 5.0)
    with pytest.raises(ProtocolError, match="exactly one"):
        ProbeSpec("sphere", depth_mm=1.0, force_n=2.0)
    with pytest.raises(ProtocolError, match="exactly one"):
        ProbeSpec("sphere")


# ----------------------------------------------------------------------------- the locator


def test_locator_finds_headers_keys_and_the_nth_array_table() -> None:
    text = (
        'title = "a [fake] header = 1"\n'          # 1
        "[probe]\n"                                # 2
        "indenter = 'sphere'  # x = 3\n"           # 3
        "locations = [\n"                          # 4
        "  [1, 2],\n"                              # 5
        "  [3, 4],  # y = 1\n"                     # 6
        "]\n"                                      # 7
        "after = 1\n"                              # 8
        "[[group]]\n"                              # 9
        "depth_mm = [1]\n"                         # 10
        "[[group]]\n"                              # 11
        "grid = { x_mm = [0, 1], nx = 2 }\n"       # 12
        'note = """\n'                             # 13
        "fake = 1\n"                               # 14
        '"""\n'                                    # 15
        "depth_mm = [2]\n"                         # 16
    )
    loc = TomlLocator(text)
    assert loc.line("", "title") == 1
    assert loc.line("probe") == 2 and loc.line("probe", "indenter") == 3
    assert loc.line("probe", "locations") == 4 and loc.line("probe", "after") == 8
    assert loc.line("group", "depth_mm", 0) == 10 and loc.line("group", "depth_mm", 1) == 16
    assert loc.line("group", None, 1) == 11 and loc.line("group", "grid", 1) == 12
    assert loc.line("group", "fake", 1) == 11  # inside a multi-line string: not a key; falls back to the header
    assert loc.line("nothing", "x") == 1


# ----------------------------------------------------------------------------- protocol errors


def test_toml_syntax_error_gives_line_and_column(tmp_path: Path) -> None:
    path = _write(tmp_path, "p.toml", '[probe]\nindenter = "sphere"\n[normal]\ndepth_mm = 1.5 mm\n')
    with pytest.raises(ProtocolError, match=r"p\.toml:4:\d+: not valid TOML"):
        load_protocol(path)


def test_protocol_problems_are_all_reported_with_lines(tmp_path: Path, rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    path = _write(tmp_path, "bad.toml", """
[probe]
indenter = "sphere"
location_mm = [14.0, 0.0]

[normal]
depth = 1.5
sped_mm_s = 2.0

[wait]
duration_s = "long"

[shear]
speed_mm_s = -1.0

[retreat]
height_mm = 2.0
""")
    with pytest.raises(ProtocolError) as exc:
        load_protocol(path, rig, indenters)
    found = _problems(exc)
    assert set(found) == {
        (3, "probe.location_mm"), (6, "normal.depth"), (7, "normal.sped_mm_s"), (10, "wait.duration_s"),
        (13, "shear.speed_mm_s"), (15, "[retreat]"),
    }
    assert "give a unit: depth_mm or force_n" in found[(6, "normal.depth")]
    assert "did you mean 'speed_mm_s'" in found[(7, "normal.sped_mm_s")]
    assert "must be a number" in found[(10, "wait.duration_s")]
    assert "must be positive" in found[(13, "shear.speed_mm_s")]
    assert "did you mean 'retract'" in found[(15, "[retreat]")]
    assert "off the gel" in found[(3, "probe.location_mm")] and "|x| <= 9" in found[(3, "probe.location_mm")]
    assert all(str(p).startswith(f"{path}:") for p in exc.value.problems)


def test_protocol_limits_indenter_and_exclusive_targets(tmp_path: Path, rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    path = _write(tmp_path, "deep.toml", '[probe]\nindenter = "cylinder"\n[normal]\ndepth_mm = 2.0\n')
    with pytest.raises(ProtocolError) as exc:
        load_protocol(path, rig, indenters)
    assert "max_depth_mm 1.5" in _problems(exc)[(4, "normal.depth_mm")]

    path = _write(tmp_path, "force.toml", '[probe]\nindenter = "sphere"\n[normal]\nforce_n = 30\n')
    with pytest.raises(ProtocolError) as exc:
        load_protocol(path, rig, indenters)
    assert "max_normal_force_n 22" in _problems(exc)[(4, "normal.force_n")]

    path = _write(tmp_path, "both.toml", '[probe]\nindenter = "spere"\n[normal]\ndepth_mm = 1\nforce_n = 5\n')
    with pytest.raises(ProtocolError) as exc:
        load_protocol(path, rig, indenters)
    found = _problems(exc)
    assert "both depth_mm and force_n" in found[(5, "normal")]
    assert "known: sphere, cylinder, square, ridge" in found[(2, "probe.indenter")]

    path = _write(tmp_path, "root.toml", 'depth_mm = 1.0\n[probe]\nindenter = "sphere"\n')
    with pytest.raises(ProtocolError, match=r"root\.toml:1: depth_mm: is outside any section; move it under \[normal\]"):
        load_protocol(path)

    # Without rig and indenters only the file itself is checked.
    ok = _write(tmp_path, "ok.toml", '[probe]\nindenter = "spere"\nlocation_mm = [50, 0]\n')
    assert load_protocol(ok).location_mm == (50.0, 0.0)


def test_a_sheared_position_off_the_gel_is_caught(tmp_path: Path, rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    path = _write(tmp_path, "p.toml", '[probe]\nindenter = "sphere"\nlocation_mm = [8.5, 0]\n[shear]\ndistance_mm = 1.0\n')
    with pytest.raises(ProtocolError, match=r"p\.toml:3: probe\.location_mm: .*sheared 1 mm.*shear less"):
        load_protocol(path, rig, indenters)
    path.write_text('[probe]\nindenter = "sphere"\nlocation_mm = [8.5, 0]\n[shear]\ndirection_deg = 180.0\n')
    assert load_protocol(path, rig, indenters).location_mm == (8.5, 0.0)


# ----------------------------------------------------------------------------- campaigns


def _campaign(tmp_path: Path, body: str) -> Path:
    shutil.copy(DEFAULT_PROTOCOL, tmp_path / "probe.toml")
    return _write(tmp_path, "c.toml", body)


def test_campaign_problems_are_all_reported_with_lines(tmp_path: Path, rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    path = _campaign(tmp_path, """
[campaign]
name = "t"
seed = 3
protcol = "probe.toml"

[split]
train = 5
val = 2
test = 1

[[group]]
indenters = ["sphere", "cone"]

[[group]]
indenters = ["cylinder"]
locations_mm = [[0, 0], [13, 0]]
depth_mm = [1.0, 1.6]

[[group]]
indenter = ["ridge"]
grid = {x_mm = [0, 1], y_mm = [0, 0], nx = 0, ny = 1}
force = [3]
""")
    with pytest.raises(ProtocolError) as exc:
        load_campaign(path, rig, indenters)
    found = _problems(exc)
    assert "did you mean 'protocol'" in found[(4, "campaign.protcol")]
    assert "unknown indenter 'cone'; known: sphere, cylinder, square, ridge" in found[(12, "group[1].indenters")]
    assert "off the gel" in found[(16, "group[2].locations_mm")]
    assert "max_depth_mm 1.5" in found[(17, "group[2].depth_mm")]
    assert "did you mean 'indenters'" in found[(20, "group[3].indenter")]
    assert "whole number >= 1" in found[(21, "group[3].grid.nx")]
    assert "give a unit: depth_mm or force_n" in found[(22, "group[3].force")]
    assert len(found) == 7  # split totals are not judged while groups are broken


def test_split_counts_must_add_up(tmp_path: Path, rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    path = _campaign(tmp_path, """
[campaign]
name = "t"

[split]
train = 3
val = 1
test = 1

[[group]]
indenters = ["sphere", "cylinder"]
depth_mm = [0.5, 1.0]
""")
    with pytest.raises(ProtocolError) as exc:
        load_campaign(path, rig, indenters)
    assert "= 5 but the campaign has 4 recordings" in _problems(exc)[(4, "split")]
    path.write_text(path.read_text().replace("train = 3", "train = 0.5").replace("val = 1", "val = 0.25")
                    .replace("test = 1", "test = 0.5"))
    with pytest.raises(ProtocolError, match=r"c\.toml:4: split: fractions add up to 1.25"):
        load_campaign(path, rig, indenters)
    path.write_text(path.read_text().replace("test = 0.5", "test = 0.25"))
    assert load_campaign(path, rig, indenters).split_counts() == {"train": 2, "val": 1, "test": 1}


def test_single_bracket_group_and_bad_base_protocol(tmp_path: Path, rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    path = _campaign(tmp_path, '[campaign]\nname = "t"\n\n[group]\nindenters = ["sphere"]\n')
    with pytest.raises(ProtocolError, match=r"c\.toml:4: \[group\]: write \[\[group\]\]"):
        load_campaign(path, rig, indenters)
    _write(tmp_path, "base.toml", '[probe]\nindenter = "sphere"\n[wait]\nduration = 0.3\n')
    path.write_text('[campaign]\nname = "t"\nprotocol = "base.toml"\n[[group]]\nwait_s = [0.3]\n')
    with pytest.raises(ProtocolError, match=r"base\.toml:4: wait\.duration: no unit; give a unit: duration_s"):
        load_campaign(path, rig, indenters)


def test_groups_expand_as_cartesian_products(tmp_path: Path, rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    path = _campaign(tmp_path, """
[campaign]
name = "t"
seed = 5
repetitions = 2

[[group]]
indenters = ["sphere", "square"]
grid = {x_mm = [-2, 2], y_mm = [-1, 1], nx = 3, ny = 2}
force_n = [4, 8]

[[group]]
locations_mm = [1.0, 2.0]
shear_mm = [0]
repetitions = 1
""")
    campaign = load_campaign(path, rig, indenters)
    assert len(campaign) == 2 * 6 * 2 * 2 + 1
    first = campaign.plans[0]
    assert first.id == "t-000" and first.spec.indenter == "sphere" and first.spec.location_mm == (-2.0, -1.0)
    assert first.spec.force_n == 4.0 and first.spec.depth_mm is None  # the group's target replaces the base's
    assert [p.repetition for p in campaign.plans[:2]] == [0, 1]
    assert {p.spec.location_mm for p in campaign.plans[:24]} == {(x, y) for x in (-2.0, 0.0, 2.0) for y in (-1.0, 1.0)}
    last = campaign.plans[-1]
    assert last.spec == ProbeSpec("sphere", location_mm=(1.0, 2.0), depth_mm=1.5, shear_mm=0.0) and last.group == 1
    assert campaign.indenters() == ("sphere", "square")
    assert sum(len(v) for v in campaign.by_split().values()) == len(campaign)


# ----------------------------------------------------------------------------- the shipped campaigns and splits


def test_paper_campaign_has_the_papers_shape(rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    campaign = load_campaign(PROTOCOLS_DIR / "paper.toml", rig, indenters)
    assert len(campaign) == 219
    assert campaign.split_counts() == {"train": 154, "val": 52, "test": 13}
    for split, plans in campaign.by_split().items():
        assert {p.spec.indenter for p in plans} == set(indenters), split
    assert 17 * 60 * 0.85 <= campaign.total_nominal_s() <= 17 * 60 * 1.15
    assert [p.index for p in campaign.plans] == list(range(219))
    assert len({p.id for p in campaign.plans}) == 219
    for plan in campaign.plans:
        assert plan.spec.depth_mm is not None and plan.spec.depth_mm <= indenters[plan.spec.indenter].max_depth_mm


def test_split_is_reproducible_and_follows_the_seed(tmp_path: Path, rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    text = (PROTOCOLS_DIR / "paper.toml").read_text()
    shutil.copy(DEFAULT_PROTOCOL, tmp_path / "probe.toml")
    a = _write(tmp_path, "a.toml", text)
    b = _write(tmp_path, "b.toml", text.replace("seed = 2024", "seed = 7"))
    first = [p.split for p in load_campaign(a, rig, indenters).plans]
    assert first == [p.split for p in load_campaign(a, rig, indenters).plans]
    other = [p.split for p in load_campaign(b, rig, indenters).plans]
    assert other != first and Counter(other) == Counter(first)


def test_demo_campaign_is_tiny_and_has_a_test_recording(rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    campaign = load_campaign(PROTOCOLS_DIR / "demo.toml", rig, indenters)
    assert len(campaign) == 6 and len(campaign.indenters()) == 2
    counts = campaign.split_counts()
    assert counts["test"] >= 1 and counts["train"] >= counts["val"] >= 1
    assert campaign.total_nominal_s() < 60


def test_split_helpers() -> None:
    assert split_counts(219) == {"train": 154, "val": 52, "test": 13}
    assert split_counts(6) == {"train": 3, "val": 2, "test": 1}
    assert split_counts(10, {"train": 0.8, "val": 0.2, "test": 0.0}) == {"train": 8, "val": 2, "test": 0}
    for n in (1, 2, 7, 50, 133):
        counts = split_counts(n)
        strata = [i % 3 for i in range(n)]
        splits = assign_splits(strata, counts, seed=1)
        assert Counter(splits) == {k: v for k, v in counts.items() if v}
    # Each stratum gets its share of every split to within one recording.
    strata = ["a"] * 40 + ["b"] * 30 + ["c"] * 20
    splits = assign_splits(strata, {"train": 60, "val": 20, "test": 10}, seed=3)
    for stratum, size in Counter(strata).items():
        got = Counter(s for s, k in zip(splits, strata) if k == stratum)
        assert abs(got["test"] - size / 9) <= 1 and abs(got["val"] - size * 2 / 9) <= 1
    with pytest.raises(ValueError):
        assign_splits(strata, {"train": 1}, seed=0)


# ----------------------------------------------------------------------------- overrides


def test_overrides_from_the_command_line(rig: RigConfig, indenters: dict[str, Indenter]) -> None:
    base = ProbeSpec("sphere", depth_mm=1.5, approach=ApproachSpec(start_height_mm=1.0))
    moved = apply_overrides(base, at="2.5,-1", rig=rig, indenters=indenters)
    assert moved.location_mm == (2.5, -1.0) and moved.depth_mm == 1.5
    by_force = apply_overrides(moved, force=12.0)
    assert by_force.force_n == 12.0 and by_force.depth_mm is None and by_force.approach.start_height_mm == 1.0
    assert apply_overrides(by_force, depth=2.0).depth_mm == 2.0
    assert apply_overrides(base, at=(1, 2), wait_s=0.2).wait_s == 0.2
    assert apply_overrides(base, force_n=3.0, wait_s=None) == ProbeSpec("sphere", force_n=3.0, approach=base.approach)
    with pytest.raises(ProtocolError, match="--depth/--force: both given"):
        apply_overrides(base, depth=1.0, force=2.0)
    with pytest.raises(ProtocolError, match="--at: '2;3' is not a location"):
        apply_overrides(base, at="2;3")
    with pytest.raises(ProtocolError, match=r"--depth: must be positive"):
        apply_overrides(base, depth=-1.0)
    with pytest.raises(ProtocolError, match=r"--at: \(20, 0\) is off the gel"):
        apply_overrides(base, at="20,0", rig=rig, indenters=indenters)
    with pytest.raises(ProtocolError, match=r"--depth: 3.0 mm is beyond the sphere's max_depth_mm 2.5"):
        apply_overrides(base, depth=3.0, rig=rig, indenters=indenters)
    with pytest.raises(ProtocolError, match="wait: no unit; give a unit: wait_s"):
        apply_overrides(base, wait=0.2)


def test_a_depth_at_the_gel_models_max_depth_is_refused_before_any_move(tmp_path: Path, rig: RigConfig,
                                                                        indenters: dict[str, Indenter]) -> None:
    """Pressed exactly to max_depth_mm, a run ends beyond the gel model (the contact is found a little
    into the gel): the checker refuses it and says how deep a press may go."""
    path = _write(tmp_path, "edge.toml", """
[campaign]
name = "edge"

[[group]]
indenters = ["cylinder"]
locations_mm = [[0, 0]]
depth_mm = [1.5]

[[group]]
indenters = ["sphere"]
locations_mm = [[0, 0]]
force_n = [3]
max_depth_mm = 2.5

[[group]]
indenters = ["sphere"]
locations_mm = [[0, 0]]
depth_mm = [2.45]
""")
    with pytest.raises(ProtocolError) as exc:
        load_campaign(path, rig, indenters)
    found = _problems(exc)
    assert set(found) == {(7, "group[1].depth_mm"), (13, "group[2].max_depth_mm")}
    assert "no headroom" in found[(7, "group[1].depth_mm")] and "use at most 1.45 mm" in found[(7, "group[1].depth_mm")]
    assert "use at most 2.45 mm" in found[(13, "group[2].max_depth_mm")]


def test_a_held_force_and_its_loop_are_read_and_checked(tmp_path: Path, rig: RigConfig,
                                                        indenters: dict[str, Indenter]) -> None:
    from labrig.protocol.feedback import EVENTS_READING_NOISE_N, EVENTS_STALE_AFTER_S, VIRTUAL_RIG_EVENTS_STALE_AFTER_S
    from labrig.protocol.files import on_virtual_camera
    from labrig.protocol.force_loop import ForceLoopParams

    def on_events_text(path: Path) -> str:
        return path.read_text().replace('"ft"', '"events"')

    good = _write(tmp_path, "held.toml", """
[probe]
indenter = "sphere"
[normal]
depth_mm = 1.0
[shear]
distance_mm = 1.0
hold_force_n = 4.0
[control]
feedback = "ft"
stiffness_n_per_mm = 12.0
max_speed_mm_s = 1.5
""")
    spec = load_protocol(good, rig, indenters)
    assert spec.shear_hold_force_n == 4.0 and spec.feedback == "ft" and spec.press_hold_s is None
    assert spec.control == ForceLoopParams(stiffness_n_per_mm=12.0, max_speed_mm_s=1.5)
    on_events = load_protocol(_write(tmp_path, "events.toml", on_events_text(good)), rig, indenters)
    assert on_events.feedback == "events" and on_events.control.stale_after_s == EVENTS_STALE_AFTER_S
    assert on_events.control.reading_noise_n == EVENTS_READING_NOISE_N > spec.control.reading_noise_n == 0.0
    told = load_protocol(_write(tmp_path, "told.toml", on_events_text(good) + "stale_after_s = 0.05\n"), rig, indenters)
    assert told.control.stale_after_s == 0.05 and told.control.reading_noise_n == EVENTS_READING_NOISE_N
    quiet = load_protocol(_write(tmp_path, "quiet.toml", on_events_text(good) + "reading_noise_n = 0\n"), rig,
                          indenters)
    assert quiet.control.reading_noise_n == 0.0 and quiet.control.stale_after_s == EVENTS_STALE_AFTER_S
    # The embedded virtual rig's camera runs late on a small host: its events loop waits longer unless told.
    virtual, note = on_virtual_camera(on_events, on_events_text(good))
    assert virtual.control.stale_after_s == VIRTUAL_RIG_EVENTS_STALE_AFTER_S > EVENTS_STALE_AFTER_S
    assert note is not None and "stale_after_s" in note and "\n" not in note
    assert virtual.control.max_speed_mm_s == on_events.control.max_speed_mm_s
    assert on_virtual_camera(told, on_events_text(good) + "stale_after_s = 0.05\n") == (told, None)
    assert on_virtual_camera(spec, good.read_text()) == (spec, None)  # the F/T loop: unchanged
    bad = _write(tmp_path, "bad.toml", """
[probe]
indenter = "sphere"
[normal]
depth_mm = 1.0
hold_s = 1.0
[shear]
distance_mm = 0.0
hold_force_n = 400.0
[control]
feedback = "camera"
stiffness_n_per_mm = -1.0
gain = 2
reading_noise_n = -0.1
""")
    with pytest.raises(ProtocolError) as exc:
        load_protocol(bad, rig, indenters)
    problems = _problems(exc)
    assert 'must be "ft" (the F/T sensor) or "events"' in problems[(10, "control.feedback")]
    assert "must be positive" in problems[(11, "control.stiffness_n_per_mm")]
    assert "unknown key" in problems[(12, "control.gain")]
    assert "must not be negative" in problems[(13, "control.reading_noise_n")]
    text = str(exc.value)
    assert "distance_mm = 0 has none" in text and "max_normal_force_n" in text
    assert "give [normal] force_n instead of depth_mm, or drop hold_s" in text
