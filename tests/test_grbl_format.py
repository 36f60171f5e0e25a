"""GRBL line formatting beside its parser: every line the formatters write reads back as what was written."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.devices.grbl_pose import GcodeFollower, PlannedMove
from labrig.devices.grbl_protocol import (
    LINE_END,
    Alarm,
    Echo,
    ErrorReply,
    GrblProtocol,
    GrblUsageError,
    Help,
    Message,
    Ok,
    Options,
    Parameter,
    ParserState,
    Probe,
    Setting,
    StartupLine,
    StartupResult,
    Status,
    Version,
    Welcome,
    classify_line,
    format_alarm,
    format_echo,
    format_error,
    format_help,
    format_message,
    format_number,
    format_ok,
    format_options,
    format_parameter,
    format_parser_state,
    format_probe,
    format_setting,
    format_startup_line,
    format_startup_result,
    format_status,
    format_version,
    format_welcome,
    jog_line,
    motion_line,
)

MM = st.floats(-999.0, 999.0, allow_nan=False)
XYZ = st.tuples(MM, MM, MM)
PRINTABLE = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=40)
WORD = st.text(st.characters(min_codepoint=0x21, max_codepoint=0x7E, exclude_characters="]"), min_size=1, max_size=8)
STATES = st.sampled_from(["Idle", "Run", "Hold:0", "Hold:1", "Jog", "Alarm", "Door:2", "Check", "Home", "Sleep"])


def received(text: str) -> object:
    """What the driver's protocol core makes of one line as GRBL sends it."""
    events = GrblProtocol().receive_data(text.encode("ascii") + LINE_END)
    assert len(events) == 1
    return events[0]


def mm3(values: tuple[float, ...]) -> tuple[float, ...]:
    return tuple(float(f"{v:.3f}") for v in values)


@settings(max_examples=300, deadline=None)
@given(
    STATES,
    st.booleans(),
    XYZ,
    st.one_of(st.none(), st.tuples(st.integers(0, 15), st.integers(0, 128))),
    st.one_of(st.none(), st.integers(1, 9_999_999)),
    st.floats(0, 30_000, allow_nan=False),
    st.one_of(st.none(), st.floats(0, 30_000, allow_nan=False)),
    st.sampled_from(["", "X", "XYZ", "PDHRS"]),
    st.one_of(st.none(), XYZ),
    st.one_of(st.none(), st.tuples(st.integers(10, 200), st.integers(25, 100), st.integers(10, 200))),
    st.sampled_from(["", "S", "CF", "F"]),
)
def test_status_reports_read_back(
    state: str,
    machine: bool,
    position: tuple[float, float, float],
    buffer: tuple[int, int] | None,
    line_number: int | None,
    feed: float,
    rpm: float | None,
    pins: str,
    wco: tuple[float, float, float] | None,
    overrides: tuple[int, int, int] | None,
    accessories: str,
) -> None:
    text = format_status(
        state, machine_mm=position if machine else None, work_mm=None if machine else position, buffer=buffer,
        line_number=line_number, feed_mm_min=feed, spindle_rpm=rpm, pins=pins, wco_mm=wco, overrides_pct=overrides,
        accessories=accessories,
    )  # fmt: skip
    event = received(text)
    assert isinstance(event, Status) and event.raw == text.encode()
    assert event.state_text == state
    assert (event.position_mm if machine else event.work_position_mm) == mm3(position)
    assert event.wco_in_report == (wco is not None) and event.wco_mm == (mm3(wco) if wco is not None else None)
    expected_free = (None, None) if buffer is None else buffer
    assert (event.planner_free_blocks, event.rx_free_bytes) == expected_free
    assert event.line_number == line_number and event.pins == pins
    assert event.feed_mm_min == float(f"{feed:.0f}")
    assert event.spindle_rpm == (None if rpm is None else float(f"{rpm:.0f}"))
    assert event.overrides_pct == overrides and event.accessories == (accessories or None)


def test_a_status_report_has_one_position() -> None:
    with pytest.raises(ValueError):
        format_status("Idle")
    with pytest.raises(ValueError):
        format_status("Idle", machine_mm=(0, 0, 0), work_mm=(0, 0, 0))


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 255))
def test_responses_and_alarms_read_back(code: int) -> None:
    assert classify_line(format_ok(), b"") == Ok(None)
    assert classify_line(format_error(code), b"") == ErrorReply(code, None)
    assert received(format_alarm(code)) == Alarm(code)


@settings(max_examples=200, deadline=None)
@given(PRINTABLE, WORD, st.lists(WORD, min_size=1, max_size=12))
def test_bracket_lines_read_back(text: str, word: str, words: list[str]) -> None:
    assert received(format_message(text.strip())) == Message(text.strip())
    assert received(format_help(text.strip())) == Help(text.strip())
    assert received(format_echo(text.strip())) == Echo(text.strip())
    assert received(format_parser_state(words)) == ParserState(tuple(words))
    version = word.replace(":", ".")
    assert received(format_version(version, text.strip())) == Version(version, text.strip())
    codes = word.replace(",", ".")
    assert received(format_options(codes, 15, 128)) == Options(codes, 15, 128)
    assert received(format_welcome(word)) == Welcome(word, ())


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(["G54", "G55", "G56", "G57", "G58", "G59", "G28", "G30", "G92"]), XYZ, MM, st.booleans())
def test_parameters_and_probes_read_back(name: str, values: tuple[float, float, float], tlo: float, touched: bool) -> None:
    assert received(format_parameter(name, values)) == Parameter(name, mm3(values))
    assert received(format_parameter("TLO", [tlo])) == Parameter("TLO", mm3((tlo,)))
    assert received(format_probe(values, touched)) == Probe(mm3(values), touched)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 255), st.floats(0, 1e6, allow_nan=False), st.booleans(), st.integers(0, 9), PRINTABLE, st.integers(1, 38))
def test_settings_and_startup_lines_read_back(number: int, value: float, integer: bool, index: int, line: str, code: int) -> None:
    setting = received(format_setting(number, value, integer=integer))
    assert isinstance(setting, Setting) and setting.number == number
    assert setting.value == float(f"{value:.0f}" if integer else f"{value:.3f}")
    line = line.strip()
    assert received(format_startup_line(index, line)) == StartupLine(index, line)
    assert received(format_startup_result(line, format_ok())) == StartupResult(line, None)
    assert received(format_startup_result(line, format_error(code))) == StartupResult(line, code)


@settings(max_examples=200, deadline=None)
@given(st.one_of(st.none(), MM), st.one_of(st.none(), MM), st.one_of(st.none(), MM), st.one_of(st.none(), st.floats(1, 5000)))
def test_motion_lines_are_valid_lines_that_move_where_asked(
    x: float | None, y: float | None, z: float | None, feed: float | None
) -> None:
    if x is None and y is None and z is None:
        with pytest.raises(GrblUsageError):
            motion_line(x, y, z, feed)
        return
    line = "G90" + motion_line(x, y, z, feed)
    GrblProtocol.check_line(line)
    effect = GcodeFollower().follow(line.encode())
    target = tuple(float(format_number(v)) if v is not None else 0.0 for v in (x, y, z))
    feed_read = None if feed is None else float(format_number(feed))
    assert effect.moves == (PlannedMove((target[0], target[1], target[2]), feed_read),)


@settings(max_examples=100, deadline=None)
@given(MM, st.floats(1, 5000))
def test_jog_lines_are_valid_lines_that_jog_by_what_was_asked(dx: float, feed: float) -> None:
    line = jog_line(dx, None, None, feed_mm_min=feed)
    GrblProtocol.check_line(line)
    effect = GcodeFollower().follow(line.encode())
    assert effect.moves == (PlannedMove((float(format_number(dx)), 0.0, 0.0), float(format_number(feed)), "jog"),)
    with pytest.raises(GrblUsageError, match="positive feed"):
        jog_line(dx, None, None, feed_mm_min=0.0)
