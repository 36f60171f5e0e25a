"""The slip reflex, shearing to a tangential force and releasing to a force: the detector on the dense field and on
the net force, the held move's early ends, the protocol keys, and held shears on the virtual rig in virtual time
against the simulator's true onset of gross slip."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.evaluation.control import control_run
from labrig.indenters import Indenter, load_indenters
from labrig.protocol.feedback import EVENTS_LOOP_DEFAULTS
from labrig.protocol.files import load_protocol
from labrig.protocol.force_loop import ForceLoop, ForceLoopParams, HeldMove
from labrig.protocol.slip import ContactReading, SlipCheck, SlipDetector, SlipParams, SlipReflex
from labrig.protocol.spec import ApproachSpec, ProbeSpec, ProtocolError
from labrig.protocol.virtual_run import record_virtual
from labrig.recording import Recording

#: The sphere held at 1.5 N while shearing 2 mm at 2 mm/s: its contact slides as a whole after about 0.7 s.
SLIDING = ProbeSpec(
    "sphere", force_n=1.5, press_hold_s=0.5, wait_s=0.2, shear_mm=2.0, shear_speed_mm_s=2.0, slip_action="report",
    approach=ApproachSpec(start_height_mm=0.5, speed_mm_s=0.5, contact_force_n=0.1, max_travel_mm=2.0),
)


def _field(n_contact: int, n_at_friction: int, normal_n: float = 0.5, mu: float = 1.0) -> np.ndarray:
    """Marker forces on the gel (M, 3): ``n_contact`` pressed markers, ``n_at_friction`` of them at ``mu``."""
    forces = np.zeros((156, 3))
    forces[:n_contact, 2] = -normal_n
    forces[:n_contact, 0] = 0.3 * mu * normal_n
    forces[:n_at_friction, 0] = mu * normal_n
    forces[n_contact:, 2] = -0.001  # far from the contact: under min_marker_n
    return forces


def _reading(t_ns: int, forces: np.ndarray | None, net: tuple[float, float, float] = (0.0, 0.0, -3.0)) -> ContactReading:
    return ContactReading(t_ns, np.asarray(net, np.float64), forces)


def test_the_dense_field_tells_slip_when_the_share_at_friction_persists() -> None:
    detector = SlipDetector(1.0, SlipParams(share=0.9, persist=2))
    assert detector.share_at_friction(_field(10, 8)) == pytest.approx(0.8)
    assert not detector.update(_reading(1, _field(10, 8))).slipping
    assert not detector.update(_reading(2, _field(10, 9))).slipping  # once is not yet
    assert not detector.update(_reading(2, _field(10, 9))).slipping  # the same reading again counts once
    check = detector.update(_reading(3, _field(10, 10)))
    assert check.slipping and check.share == 1.0 and check.cue == "share"
    assert not detector.update(_reading(4, _field(10, 5))).slipping  # a stick breaks the run
    assert math.isnan(detector.share_at_friction(np.zeros((156, 3))))  # no contact: no share


def test_a_tangential_force_that_stops_rising_while_the_tool_shears_on_tells_slip() -> None:
    """Sticking, |Ft| rises 2 N/mm with the travel; sliding, it stays flat under friction at most markers (the
    estimated field alone never tells it). The stall is told once the last 0.1 mm of travel is flat; a flat |Ft| far
    under friction (a light stick) is not slip; a tool that has stopped adds nothing; with the stall off, never."""
    field = _field(10, 2)

    def shear(params: SlipParams, peak_n: float) -> float | None:
        """The travel (mm) at which slip is told, |Ft| = min(2 x, peak_n) at 2 N normal, mu 1; None: never."""
        detector = SlipDetector(1.0, params)
        for k, x in enumerate(np.arange(0.0, 1.0, 0.02)):  # a reading every 0.02 mm (10 ms at 2 mm/s)
            ft = min(2.0 * x, peak_n)
            if detector.update(_reading(k + 1, field, (ft, 0.0, -2.0)), travel_mm=float(x)).slipping:
                return float(x)
        return None

    told = shear(SlipParams(persist=2), 1.2)  # flat from 0.6 mm at 0.6 of friction
    assert told is not None and 0.64 <= told <= 0.74, told
    assert shear(SlipParams(persist=2), 0.4) is None  # flat from 0.2 mm at 0.2 of friction
    assert shear(SlipParams(persist=2, stall_ratio=None), 1.2) is None
    detector = SlipDetector(1.0, SlipParams(persist=1))
    for k in range(10):
        detector.update(_reading(k + 1, field, (0.04 * k, 0.0, -2.0)), travel_mm=0.02 * k)
    steady = detector.last.stiffness_ratio
    assert steady == pytest.approx(1.0)
    for k in range(10, 30):  # the tool has stopped: readings at the same place say nothing new of the slope
        assert detector.update(_reading(k + 1, field, (1.2, 0.0, -2.0)), travel_mm=0.18).stiffness_ratio == steady
    with pytest.raises(ValueError, match="stall_ratio"):
        SlipParams(stall_ratio=1.5)


def test_a_contact_field_that_stops_following_the_tool_tells_slip() -> None:
    """Sticking, the contact's markers are dragged 0.8 mm per mm of travel; sliding from 0.6 mm, they stay where they
    are while the estimated |Ft| keeps rising (as a late estimate's does). The field's stall is told within its
    0.05 mm span and two readings, and from the last three readings where they come further apart; markers off the
    contact (under a tenth of the largest normal force) do not count; with the cue off, the rising |Ft| never tells
    it."""
    rng = np.random.default_rng(3)

    def shear(params: SlipParams, step_mm: float = 0.02) -> float | None:
        detector = SlipDetector(1.0, params)
        for k, x in enumerate(np.arange(0.0, 1.0, step_mm)):
            forces = _field(10, 2)
            moved = np.zeros((156, 3))
            moved[:10, 0] = 0.8 * min(x, 0.6) + rng.normal(0.0, 0.002, 10)
            moved[10:, 0] = 5.0  # far off the contact: ignored
            reading = ContactReading(k + 1, np.array([2.0 * x, 0.0, -2.0]), forces, moved)
            check = detector.update(reading, travel_mm=float(x))
            if check.slipping:
                assert check.cue == "field stall"
                return float(x)
        return None

    told = shear(SlipParams(persist=2))
    assert told is not None and 0.62 <= told <= 0.68, told
    assert shear(SlipParams(persist=2, follow_ratio=None)) is None
    sparse = shear(SlipParams(persist=2), step_mm=0.04)  # a live pipeline that skipped every other window
    assert sparse is not None and 0.64 <= sparse <= 0.76, sparse
    detector = SlipDetector(1.0)
    forces, moved = _field(10, 2), np.zeros((156, 3))
    moved[:10, :2] = (0.3, 0.4)
    moved[10:, :2] = 9.0
    assert detector.contact_displacement_mm(forces, moved) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="follow_span_mm"):
        SlipParams(follow_span_mm=0.0)


def test_each_cue_must_persist_on_its_own() -> None:
    """A share at friction in one reading and a stall in the next are two cues told once each: not slip."""
    travel = np.arange(0.0, 0.4, 0.02)
    tangential = np.minimum(2.0 * travel, 0.4)  # flat from 0.2 mm at 0.67 of friction (mu 0.3, 2 N)

    def shear(share_at: int | None, readings: int) -> SlipCheck:
        detector = SlipDetector(0.3, SlipParams(persist=2))
        for k in range(readings):
            field = _field(10, 10 if k == share_at else 2, mu=0.3)
            check = detector.update(_reading(k + 1, field, (float(tangential[k]), 0.0, -2.0)), travel_mm=float(travel[k]))
        return check

    first = next(n for n in range(1, len(travel)) if shear(None, n).stiffness_ratio <= 0.1)
    assert shear(None, first + 1).slipping  # the stall alone, twice: slip
    both = shear(first - 2, first)  # the share one reading before the stall's first
    assert both.stiffness_ratio <= 0.1 and not both.slipping


def test_the_net_force_tells_slip_by_its_friction_ratio_and_press_asks_for_enough_normal_force() -> None:
    detector = SlipDetector(0.8, SlipParams(net_ratio=0.95, persist=1, press_ratio=0.5))
    check = detector.update(_reading(1, None, (1.0, 0.0, -2.0)))
    assert not check.slipping and check.friction_ratio == pytest.approx(1.0 / 1.6) and math.isnan(check.share)
    told = detector.update(_reading(2, None, (0.0, 1.55, -2.0)))
    assert told.slipping and told.cue == "net ratio"
    assert detector.press_target_n(_reading(3, None, (1.2, 0.0, -2.0))) == pytest.approx(1.2 / (0.5 * 0.8))


def _held(action: str | None = None, until_n: float | None = None) -> HeldMove:
    reflex = None if action is None else SlipReflex(action, SlipParams(persist=1), 1.0, press_limit_n=4.0)
    return HeldMove((0.0, 0.0, 0.0), (2.0, 0.0, 0.0), (0.0, 0.0, -1.0), 2.0, ForceLoop(2.0, ForceLoopParams()),
                    until_tangential_n=until_n, slip=reflex)


@pytest.mark.parametrize("action", ["report", "stop", "press"])
def test_a_held_shear_acts_on_slip_as_its_reflex_says(action: str) -> None:
    held = _held(action)
    here = (0.0, 0.0, 0.0)
    assert held.next_segment(0.0, 2.0, here, 0.0, contact=_reading(1, _field(10, 2), (0.5, 0.0, -2.0))) is not None
    slipping = _reading(2, _field(10, 10), (3.0, 0.0, -2.0))
    out = held.next_segment(0.01, 2.0, here, 0.01, contact=slipping)
    assert held.slipped_at_s == 0.01 and held.slip_check is not None and held.slip_check.slipping
    if action == "stop":
        assert out is None and held.ended_by == "slip"
        assert held.next_segment(0.02, 2.0, here, 0.02) is None  # it stays ended
    else:
        assert out is not None and held.ended_by is None
        # press: |Ft| / (0.7 mu) = 4.3 N, held at the reflex's limit 4 N; report: the target stays
        assert held.loop.target_n == (4.0 if action == "press" else 2.0)


def test_a_shear_to_a_tangential_force_ends_when_the_reading_reaches_it() -> None:
    held = _held(until_n=1.0)
    assert held.next_segment(0.0, 2.0, (0, 0, 0), 0.0, contact=_reading(1, None, (0.6, 0.7, -2.0))) is not None
    assert held.next_segment(0.01, 2.0, (0, 0, 0), 0.01, contact=_reading(2, None, (0.8, 0.7, -2.0))) is None
    assert held.ended_by == "tangential force"


def _protocol(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "p.toml"
    path.write_text('[probe]\nindenter = "sphere"\n[normal]\nforce_n = 3.0\nhold_s = 0.5\n' + text)
    return path


def test_the_protocol_keys_of_slip_tangential_targets_and_release(tmp_path: Path) -> None:
    spec = load_protocol(_protocol(tmp_path, '[shear]\ndistance_mm = 2.0\nforce_n = 1.2\n[slip]\naction = "press"\n'
                                             'share = 0.8\npersist = 3\nfriction = 0.7\nfollow_span_mm = 0.08\n'
                                             '[release]\nforce_n = 1.0\nhold_s = 0.4\n'))
    assert spec.shear_force_n == 1.2 and spec.slip_action == "press"
    assert spec.slip == SlipParams(share=0.8, persist=3, friction=0.7, follow_span_mm=0.08)
    assert spec.release_force_n == 1.0 and spec.release_hold_s == 0.4 and spec.holds_force


@pytest.mark.parametrize(("text", "said"), [
    ('[slip]\naction = "brake"\n', 'slip.action: must be "report" (record when the contact slips), "stop"'),
    ('[slip]\naction = "stop"\nshare = 1.5\n', "slip.share: must be a share in (0, 1], not 1.5"),
    ('[slip]\naction = "stop"\npersist = 0.5\n', "slip.persist: must be a whole number of readings"),
    ('[release]\nforce_n = 3.5\n', "3.5 N is not below the pressed force 3.0 N"),
])
def test_bad_slip_and_release_keys_get_one_line_each(tmp_path: Path, text: str, said: str) -> None:
    with pytest.raises(ProtocolError) as caught:
        load_protocol(_protocol(tmp_path, "[shear]\ndistance_mm = 1.0\n" + text))
    assert said in str(caught.value)


def test_a_slip_reflex_or_tangential_target_needs_a_held_shear(tmp_path: Path) -> None:
    path = tmp_path / "depth.toml"
    path.write_text('[probe]\nindenter = "sphere"\n[normal]\ndepth_mm = 1.0\n[shear]\nforce_n = 1.0\n'
                    '[slip]\naction = "stop"\n')
    with pytest.raises(ProtocolError) as caught:
        load_protocol(path)
    text = str(caught.value)
    assert "shears until a tangential force and needs the normal force held during the shears" in text
    assert "is the held shear's reflex and needs the normal force held during the shears" in text


@pytest.mark.slow
@pytest.mark.parametrize("feedback", ["ft", "events"])
def test_the_reflex_tells_a_sliding_sphere_within_50_ms_of_its_true_onset(rig: RigConfig, sphere: Indenter,
                                                                          tmp_path: Path, feedback: str) -> None:
    """Held at 1.5 N, the sphere's contact slides as a whole during the 2 mm shear (the sim's truth); the reflex
    reads the F/T's net force or the estimate's dense field (its share at friction, or its markers no longer
    following the tool) and tells it within 50 ms."""
    control = ForceLoopParams(**EVENTS_LOOP_DEFAULTS) if feedback == "events" else ForceLoopParams()
    result = record_virtual(replace(SLIDING, feedback=feedback, control=control), tmp_path / f"{feedback}.h5",
                            rig, sphere, seed=1)
    assert result.exit_status == "complete", result.reason
    run = control_run(result.path)
    assert run is not None and math.isfinite(run.slip_onset_s), "the contact never slid"
    assert abs(run.slip_onset_error_ms) <= 50.0, run.slip_onset_error_ms
    assert run.slip_cue in (("net ratio",) if feedback == "ft" else ("share", "field stall"))  # recorded too


@pytest.mark.slow
@pytest.mark.parametrize("indenter", ["cylinder", "ridge"])
def test_on_the_event_sensor_a_stall_tells_a_sliding_flat_punch_and_ridge(rig: RigConfig, tmp_path: Path,
                                                                         indenter: str) -> None:
    """Their estimated fields never reach friction at most markers (the share cue alone never told them); a stall
    does (the estimated |Ft|'s, or the contact's markers no longer following the tool), within 100 ms of the true
    onset: the normal force held, the estimate flattens a window or more after the contact slides."""
    shape = load_indenters()[indenter]
    spec = replace(SLIDING, indenter=indenter, feedback="events", control=ForceLoopParams(**EVENTS_LOOP_DEFAULTS))
    result = record_virtual(spec, tmp_path / f"{indenter}.h5", rig, shape, seed=1)
    assert result.exit_status == "complete", result.reason
    run = control_run(result.path)
    assert run is not None and math.isfinite(run.slip_onset_s), "the contact never slid"
    assert 0.0 <= run.slip_onset_error_ms <= 100.0, run.slip_onset_error_ms
    with Recording(result.path) as rec:  # the stalls are recorded: each slope's share of its steepest
        told = rec.column("control", "slipping") > 0
        stall = np.fmin(rec.column("control", "stiffness_ratio"), rec.column("control", "following_ratio"))
        age_us = rec.column("control", "reading_age_us")
    assert told.any() and np.nanmin(stall[told]) <= 0.1
    # the camera renders 10 ms behind where a loop reads it: a window's estimate is read within about 20 ms
    assert np.median(age_us) <= 21_000, np.median(age_us)


@pytest.mark.slow
def test_a_sticking_shear_tells_no_slip_and_a_stop_ends_a_sliding_shear(rig: RigConfig, sphere: Indenter,
                                                                        tmp_path: Path) -> None:
    sticking = replace(SLIDING, force_n=5.0, shear_mm=1.0)
    result = record_virtual(sticking, tmp_path / "stick.h5", rig, sphere, seed=1)
    run = control_run(result.path)
    assert result.exit_status == "complete" and run is not None
    assert math.isnan(run.slip_told_s) and math.isnan(run.slip_onset_s)
    stopped = record_virtual(replace(SLIDING, slip_action="stop"), tmp_path / "stop.h5", rig, sphere, seed=1)
    assert stopped.exit_status == "complete", stopped.reason
    with Recording(stopped.path) as rec:
        shear = next(p for p in rec.phases() if p.name == "shear")
        t = rec.column("truth/contact", "t_host_us")
        sliding = rec.column("truth/contact", "sliding")
    told = control_run(stopped.path)
    assert told is not None and math.isfinite(told.slip_told_s)
    told_us = told.origin_us + told.slip_told_s * 1e6
    # the shear ends once the CNC has stopped: 2 mm/s at 10 mm/s**2 takes 0.2 s, and it slid no longer
    assert shear.t_end_us - told_us < 0.3e6
    in_shear = (t >= shear.t_start_us) & (t <= shear.t_end_us) & (sliding > 0)
    assert in_shear.any() and np.ptp(t[in_shear]) < 0.3e6


@pytest.mark.slow
def test_a_shear_to_a_tangential_force_and_a_release_to_a_force(rig: RigConfig, sphere: Indenter,
                                                                tmp_path: Path) -> None:
    """Held at 4 N, Shear ends once the F/T's |Ft| reaches 1.5 N; Normal Up first releases to 1.5 N and holds it."""
    spec = replace(SLIDING, force_n=4.0, shear_mm=1.5, slip_action=None, shear_force_n=1.5, release_force_n=1.5,
                   release_hold_s=1.0)
    result = record_virtual(spec, tmp_path / "to-force.h5", rig, sphere, seed=1)
    assert result.exit_status == "complete", result.reason
    with Recording(result.path) as rec:
        phases = {p.name: p for p in rec.phases()}
        t = rec.column("ft", "t_host_us")
        force = rec.column("ft", "force_n").astype(np.float64)
    force -= force[:100].mean(axis=0)
    shear, up = phases["shear"], phases["normal_up"]
    at_end = (t >= shear.t_end_us - 20_000) & (t < shear.t_end_us)
    assert abs(np.hypot(force[at_end, 0], force[at_end, 1]).mean() - 1.5) < 0.3
    assert (shear.t_end_us - shear.t_start_us) / 1e6 < 0.9 * spec.shear_mm / spec.shear_speed_mm_s
    released = (t >= up.t_start_us + 750_000) & (t < up.t_start_us + 950_000)
    assert abs(np.abs(force[released, 2]).mean() - 1.5) < 0.3


def test_the_shipped_slip_reflex_protocol_loads_against_the_rig(rig: RigConfig) -> None:
    spec = load_protocol(Path(__file__).resolve().parent.parent / "protocols" / "slip-reflex.toml", rig, load_indenters())
    assert spec.slip_action == "stop" and spec.feedback == "events" and spec.reads_events
    assert spec.shear_held_n == 1.5 and spec.release_force_n == 0.5
