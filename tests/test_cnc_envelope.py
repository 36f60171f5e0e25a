"""The hand tools' motion envelope: the envelope itself, GRBL's position through a program, and
`labrig cnc move|jog|send|stream` refusing motion outside it against the GRBL twin on a pty."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import typer
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from labrig.cli.devices import add_device_commands
from labrig.config import ConfigError, RigConfig, rig_with
from labrig.devices.grbl import Grbl
from labrig.devices.grbl_gcode import (
    Coordinates,
    GcodeError,
    ModalState,
    coordinates_from_parameters,
    interpret_jog,
    modal_state_from_report,
    words,
)
from labrig.devices.grbl_program import ProgramTracker, may_move
from labrig.indenters import load_indenters
from labrig.protocol.envelope import MotionEnvelope, most_conservative_indenter
from labrig.protocol.rigfile import safety_limits
from labrig.sim.grbl_twin import GrblTwin
from labrig.sim.serial_pty import TwinServer

FAST = {110: 6000, 111: 6000, 112: 3000, 120: 1000, 121: 1000, 122: 1000}
#: Above the default rig's gel: its surface centre is at machine (-100, -100, -90) for the tip, so at
#: Z -50 for the tool reference point of the 40 mm tools; this is 5 mm above that.
ABOVE_GEL = (-100.0, -100.0, -45.0)

app = typer.Typer()
add_device_commands(app)
runner = CliRunner()


# -- the envelope ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sphere_envelope(rig: RigConfig) -> MotionEnvelope:
    """The default rig with the sphere: tip 40 mm below the reference, 2.5 mm max depth, 6 mm footprint."""
    return MotionEnvelope.of(rig, load_indenters()["sphere"])


def test_points_inside_and_outside(sphere_envelope: MotionEnvelope) -> None:
    env = sphere_envelope
    assert env.surface_reference_z_mm == -50.0
    for inside in [(-100, -100, -45), (-100, -100, -52.5), (-112, -88, -52.4), (-30, -100, -150), (-100, -100, 0)]:
        assert env.point_problem(inside) is None, inside  # above, a press to max depth, beside the body, the top
    too_deep = env.point_problem((-100, -100, -80))
    assert too_deep is not None and "30.000 mm below the gel surface over the gel" in too_deep
    assert "max_depth_mm" in too_deep and "keep machine Z >= -52.500" in too_deep
    assert env.point_problem((-100, -100, -52.6)) is not None
    body = env.point_problem((-125, -100, -51))  # 25 mm from the centre: beyond gel + footprint (21), within 10 more
    assert body is not None and "sensor body" in body and "body_margin_mm" in body and ">= -50.000" in body
    workspace = env.point_problem((0, 0, 500))
    assert workspace is not None and "machine Z 500.000 mm is outside the workspace [-200, 0]" in workspace


def test_segments_are_checked_along_their_length(sphere_envelope: MotionEnvelope) -> None:
    env = sphere_envelope
    beside_low, other_side_low = (-40.0, -100.0, -80.0), (-160.0, -100.0, -80.0)
    assert env.point_problem(beside_low) is None and env.point_problem(other_side_low) is None
    through = env.segment_problem(beside_low, other_side_low)
    assert through is not None and "passes through the gel or the sensor body" in through and "Z >= -50.000" in through
    assert env.segment_problem((-40, -100, -45), (-160, -100, -45)) is None  # across above the surface
    assert env.segment_problem((-100, -100, -45), (-100, -100, -52.5)) is None  # a press to max depth
    assert env.segment_problem((-60, -100, -52), (-100, -100, -52)) is not None  # in from the side below the surface
    # Reached with the override, inside: only straight up is allowed.
    assert env.segment_problem((-100, -100, -60), (-100, -100, -40)) is None
    stuck = env.segment_problem((-100, -100, -60), (-95, -100, -40))
    assert stuck is not None and "already 10.000 mm below" in stuck and "straight up" in stuck


def test_the_gel_pose_body_margin_and_thickness_count(rig: RigConfig, sphere_envelope: MotionEnvelope) -> None:
    sphere = load_indenters()["sphere"]
    diagonal = (-72.0, -73.0, -60.0)  # 28, 27 mm off the centre, 10 mm below the surface
    assert sphere_envelope.point_problem(diagonal) is not None  # within the body (21 + 10, 20 + 10)
    assert MotionEnvelope.of(rig_with(rig, {"rig.gel_yaw_deg": 45.0}), sphere).point_problem(diagonal) is None
    assert MotionEnvelope.of(rig_with(rig, {"safety.body_margin_mm": 0.0}), sphere).point_problem((-125, -100, -51)) is None
    with pytest.raises(ConfigError, match=r"\[safety\] body_margin_mm must not be negative"):
        safety_limits(rig_with(rig, {"safety.body_margin_mm": -1.0}))
    thin = MotionEnvelope.of(rig_with(rig, {"gel.thickness_mm": 2.0}), sphere)
    assert thin.press_depth_mm == 2.0 and thin.point_problem((-100, -100, -52.2)) is not None


def test_the_default_indenter_is_the_most_conservative() -> None:
    indenters = load_indenters()
    chosen = most_conservative_indenter(indenters)
    lowest = min(ind.tool_offset_mm[2] for ind in indenters.values())
    assert chosen.tool_offset_mm[2] == lowest
    assert chosen.max_depth_mm == min(ind.max_depth_mm for ind in indenters.values() if ind.tool_offset_mm[2] == lowest)


# -- GRBL's position through a program ----------------------------------------------------------


def _tracker(position: tuple[float, float, float] = (-10.0, -10.0, -10.0)) -> ProgramTracker:
    coordinates = Coordinates(position_mm=list(position))
    coordinates.wcs_mm[0] = [-100.0, -100.0, -50.0]  # G54
    return ProgramTracker(ModalState(), coordinates)


def test_the_tracker_follows_modes_offsets_and_jogs() -> None:
    t = _tracker()
    assert t.line("g0 x0 (work zero) ; y is kept").segments == (((-10, -10, -10), (-100, -10, -10)),)
    assert t.line("G91 G1 Z-2 F100").segments[0][1] == (-100, -10, -12)
    assert t.line("G90 G53 G0 Z-5").segments[0][1] == (-100, -10, -5)
    assert t.line("G20 G0 X1").segments[0][1] == pytest.approx((-74.6, -10, -5))
    assert t.line("G21 G92 X0").segments == () and t.line("G0 X1").segments[0][1] == pytest.approx((-73.6, -10, -5))
    assert t.line("G92.1").segments == () and t.line("G10 L20 P1 Y0").segments == ()
    assert t.line("G0 Y2").segments[0][1] == pytest.approx((-73.6, -8, -5))
    assert t.line("M2").segments == () and t.modal.motion == (1, 0) and not t.modal.incremental
    assert t.line("G5").error_code == 20 and t.line("G1 X1 Q1").error_code == 20  # GRBL refuses them: nothing moves
    jogger = _tracker()
    assert jogger.line("$J=G91 X1 F100").segments == (((-10, -10, -10), (-9, -10, -10)),)
    assert jogger.line("$J=N5 G91 X1 F100").segments[0][1] == (-8, -10, -10)  # N is valid in a jog (GRBL 1.1)


def test_the_tracker_names_what_it_cannot_follow() -> None:
    for line, reason in [("G2 X1 Y1 I1 F100", "arc"), ("G38.2 Z-5 F10", "probing"), ("G28", "G28"), ("G30 Z-1", "G30"),
                         ("$N0=G0 Z-80", "startup line")]:
        assert reason in (_tracker().line(line).unchecked or ""), line
    t = _tracker()
    assert t.line("G2").unchecked is None and "arc" in (t.line("X1 Y1 I1 F100").unchecked or "")  # the modal mode
    t = _tracker()
    assert t.line("$H").segments == () and "'$H'" in (t.line("G0 X1").unchecked or "")
    t = _tracker()
    assert t.line("G0 X1").segments and "jogs mixed with G-code" in (t.line("$J=G91 X1 F100").unchecked or "")
    t = _tracker()
    assert t.line("$J=G91 X1 F100").segments and "jogs mixed with G-code" in (t.line("G92 X0").unchecked or "")
    locked = ProgramTracker(ModalState(), Coordinates(), alarm=True)
    assert locked.line("G0 X-1").error_code == 9 and locked.line("$J=G91X-1F100").error_code == 8
    assert locked.line("$X").segments == () and locked.line("G0 X-1").segments == (((0, 0, 0), (-1, 0, 0)),)
    assert may_move("g0 x1") and may_move("$J=G91Z1F10") and may_move("G28") and may_move("$N0=G0Z-1")
    assert not may_move("$G") and not may_move("M8") and not may_move("G5") and not may_move("$H") and not may_move("(X1)")


def test_jogs_keep_grbl_error_codes() -> None:
    for body, code in [("G1X1F10", 16), ("X1", 22), ("F100", 26), ("X1X2F10", 25), ("X1F-1", 4), ("N-1X1F1", 4)]:
        with pytest.raises(GcodeError) as error:
            interpret_jog(words(body), ModalState(), Coordinates())
        assert error.value.code == code, body


def test_the_tracker_ends_where_the_twin_does() -> None:
    """The same program through the tracker and through the GRBL twin (via the driver) ends at the
    same position with the same offsets, read back with the driver's ``gcode_state``."""
    program = ["G21 G90", "G10 L2 P2 X-50 Y-40 Z-10", "G55", "G0 X5 Y5", "G91 G1 X-2 Z-3 F2000", "G90 G92 X0 Y0",
               "G1 X1 Y-1", "G20 G0 X0.5", "G21 G53 G0 Z-5", "G92.1", "G10 L20 P1 X0", "G54 G0 X-1", "M2", "G0 Y-2"]
    twin = GrblTwin(settings=FAST, homed=True, power_on_physical_mm=(-20.0, -20.0, -20.0))
    with TwinServer({"grbl": twin}) as server, Grbl(server.paths["grbl"]) as grbl:
        grbl.connect(reset="none", read_settings=False)
        tracker = ProgramTracker(*grbl.gcode_state())
        for line in program:
            tracker.line(line)
            grbl.send(line)
        grbl.wait_idle(30.0)
        modal, coordinates = grbl.gcode_state()
        assert server.error is None
    assert tracker.position_mm == pytest.approx(coordinates.position_mm, abs=1e-3)
    assert np.asarray(tracker.coordinates.wcs_mm) == pytest.approx(np.asarray(coordinates.wcs_mm), abs=1e-3)
    assert tracker.coordinates.g92_mm == pytest.approx(coordinates.g92_mm, abs=1e-3)
    assert (tracker.modal.wcs, tracker.modal.incremental, tracker.modal.inches) == (modal.wcs, modal.incremental, modal.inches)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.text(alphabet="GMTFSXP0123456789.-+ eE", max_size=8), max_size=14),
       st.dictionaries(st.sampled_from(["G54", "G55", "G56", "G57", "G58", "G59", "G28", "G30", "G92", "TLO", "PRB"]),
                       st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4)))
def test_reading_the_parser_state_never_crashes(report: list[str], parameters: dict[str, list[float]]) -> None:
    """Whatever a controller answers to ``$G`` and ``$#``: a state, or ValueError (the driver's one-line GrblError)."""
    with contextlib.suppress(ValueError):
        modal_state_from_report(report)
    with contextlib.suppress(ValueError):
        coordinates_from_parameters(parameters, (0.0, 0.0, 0.0))


def test_the_parser_state_as_grbl_reports_it() -> None:
    report = ["G1", "G55", "G17", "G20", "G91", "G94", "M3", "M8", "T2", "F300", "S1000"]
    assert modal_state_from_report(report) == ModalState(
        motion=(1, 0), wcs=1, inches=True, incremental=True, spindle=3, flood=True, tool=2, feed_mm_min=300.0,
        spindle_rpm=1000.0)
    with pytest.raises(ValueError, match="no distance mode"):
        modal_state_from_report(["G0", "G54", "G17", "G21", "G94", "M5", "M9", "T0", "F0", "S0"])


# -- the hand tools against the twin --------------------------------------------------------------


@pytest.fixture
def twin_above_gel() -> Iterator[tuple[GrblTwin, TwinServer]]:
    """The GRBL twin homed, idle, with the tool 5 mm above the default rig's gel (soft limits off, as `sim serve`)."""
    twin = GrblTwin(settings=FAST, homed=True, power_on_physical_mm=ABOVE_GEL)
    with TwinServer({"grbl": twin}) as server:
        yield twin, server
        assert server.error is None


def _labrig(*args: str) -> subprocess.CompletedProcess[str]:
    """``labrig ARGS`` as a user runs it: user errors are one line on stderr and exit 2."""
    return subprocess.run([sys.executable, "-c", "from labrig import cli; cli.main()", *args],
                          capture_output=True, text=True, timeout=120)


def _assert_refused_and_still(done: subprocess.CompletedProcess[str], rig: tuple[GrblTwin, TwinServer], *expected: str) -> None:
    twin, server = rig
    assert done.returncode == 2 and done.stdout == "" and "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: refused before sending anything")
    for text in (*expected, "pass --outside-envelope to send it anyway"):
        assert text in lines[0]
    assert [line for line in twin.received if may_move(line)] == []  # nothing that moves reached the controller
    assert twin.state == "Idle" and tuple(twin.position_mm([server.now_us()])[0]) == pytest.approx(ABOVE_GEL)


def test_move_into_the_gel_is_refused(twin_above_gel: tuple[GrblTwin, TwinServer]) -> None:
    done = _labrig("cnc", "--port", twin_above_gel[1].paths["grbl"], "move", ",,-80")
    _assert_refused_and_still(done, twin_above_gel, "move to ,,-80", "machine Z -80.000 mm", "below the gel surface",
                              "whose tip reaches lowest; name the mounted one with --indenter")


def test_jog_into_the_gel_is_refused(twin_above_gel: tuple[GrblTwin, TwinServer]) -> None:
    done = _labrig("cnc", "--port", twin_above_gel[1].paths["grbl"], "--indenter", "sphere", "jog", ",,-40", "--feed", "600")
    _assert_refused_and_still(done, twin_above_gel, "jog by ,,-40", "machine Z -85.000 mm", "sphere's tip")


def test_send_through_the_gel_is_refused(twin_above_gel: tuple[GrblTwin, TwinServer]) -> None:
    done = _labrig("cnc", "--port", twin_above_gel[1].paths["grbl"], "send", "G0 X-40 Z-80")  # ends beside the gel, low
    _assert_refused_and_still(done, twin_above_gel, "'G0 X-40 Z-80'", "passes through the gel or the sensor body")


def test_stream_is_refused_before_its_first_line(twin_above_gel: tuple[GrblTwin, TwinServer], tmp_path: Path) -> None:
    program = tmp_path / "press.gcode"
    program.write_text("; a press too deep\nG90 G21\nG0 X-99\nG91\nG1 Z-10 F300\n")
    done = _labrig("cnc", "--port", twin_above_gel[1].paths["grbl"], "stream", str(program))
    _assert_refused_and_still(done, twin_above_gel, "press.gcode line 5 'G1 Z-10 F300'", "machine Z -55.000 mm")


def test_override_warns_and_moves_inside_moves_are_sent_as_before(twin_above_gel: tuple[GrblTwin, TwinServer]) -> None:
    twin, server = twin_above_gel
    port = server.paths["grbl"]
    result = runner.invoke(app, ["cnc", "--port", port, "move", ",,-60", "--outside-envelope"], catch_exceptions=False)
    assert result.exit_code == 0 and "warning: --outside-envelope" in result.stderr
    assert twin.position_mm([server.now_us()])[0][2] == pytest.approx(-60.0)
    result = runner.invoke(app, ["cnc", "--port", port, "move", ",,-45"], catch_exceptions=False)  # the way out: up
    assert result.exit_code == 0 and result.stderr == ""
    result = runner.invoke(app, ["cnc", "--port", port, "move", "-90,-100,-48", "--feed", "3000"], catch_exceptions=False)
    assert result.exit_code == 0 and "X -90.000  Y -100.000  Z -48.000" in result.stdout
    assert [line for line in twin.received if may_move(line)] == ["G90G0Z-60", "G90G0Z-45", "G90G1X-90Y-100Z-48F3000"]
