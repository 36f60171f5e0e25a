"""GRBL 1.1 sans-I/O core: every line GRBL sends, character counting, resets, code tables, fuzzing."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.devices.grbl_protocol import (
    ALARM_MEANINGS,
    ERROR_MEANINGS,
    Alarm,
    Echo,
    ErrorReply,
    GrblAlarm,
    GrblCommandError,
    GrblProtocol,
    GrblUsageError,
    Help,
    Message,
    Ok,
    Options,
    Parameter,
    ParserState,
    Probe,
    Realtime,
    Setting,
    StartupLine,
    StartupResult,
    Status,
    Unrecognized,
    Version,
    Welcome,
)


def one(core: GrblProtocol, data: bytes):
    events = core.receive_data(data)
    assert len(events) == 1, events
    return events[0]


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        (b"[MSG:Caution: Unlocked]", Message("Caution: Unlocked")),
        (b"[MSG:'$H'|'$X' to unlock]", Message("'$H'|'$X' to unlock")),
        (
            b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]",
            ParserState(("G0", "G54", "G17", "G21", "G90", "G94", "M5", "M9", "T0", "F0", "S0")),
        ),
        (b"[PRB:8.024,0.000,-0.700:0]", Probe((8.024, 0.0, -0.7), False)),
        (b"[PRB:1.000,2.000,3.000:1]", Probe((1.0, 2.0, 3.0), True)),
        (
            b"[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]",
            Help("$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x"),
        ),
        (b"[VER:1.1h.20190830:my rig]", Version("1.1h.20190830", "my rig")),
        (b"[OPT:V,15,128]", Options("V", 15, 128)),
        (b"[echo:G1X1]", Echo("G1X1")),
        (b"[G54:1.000,-2.500,0.000]", Parameter("G54", (1.0, -2.5, 0.0))),
        (b"[G92:0.000,0.000,0.000]", Parameter("G92", (0.0, 0.0, 0.0))),
        (b"[TLO:0.250]", Parameter("TLO", (0.25,))),
        (b"$0=10", Setting(0, "10")),
        (b"$11=0.010", Setting(11, "0.010")),
        (b"$132=200.000", Setting(132, "200.000")),
        (b"$N0=G54G21", StartupLine(0, "G54G21")),
        (b"$N1=", StartupLine(1, "")),
        (b">G54G20:ok", StartupResult("G54G20", None)),
        (b">G5:error:20", StartupResult("G5", 20)),
        (b"ALARM:2", Alarm(2)),
        (b"Grbl 1.1h ['$' for help]", Welcome("1.1h", ())),
        (b"hello there", Unrecognized(b"hello there")),
        (b"<Idle|MPos:1,2>junk", Unrecognized(b"<Idle|MPos:1,2>junk")),
        (b"[XYZ:1]", Unrecognized(b"[XYZ:1]")),
        (b"<|MPos:0,0,0>", Unrecognized(b"<|MPos:0,0,0>")),
        (b"<Idle|FS:0,0>", Unrecognized(b"<Idle|FS:0,0>")),
    ],
)
def test_every_push_line_is_classified(line: bytes, expected: object) -> None:
    assert one(GrblProtocol(), line + b"\r\n") == expected


def test_status_report_fields() -> None:
    core = GrblProtocol()
    s = one(
        core, b"<Hold:1|MPos:-1.000,2.500,-0.004|Bf:13,102|Ln:7|FS:250,1000|Pn:XPZ|WCO:1.000,0.000,0.000|Ov:110,50,100|A:SF>\r\n"
    )
    assert isinstance(s, Status)
    assert (s.state, s.substate, s.state_text) == ("Hold", 1, "Hold:1")
    assert s.position_mm == (-1.0, 2.5, -0.004)
    assert s.work_position_mm == (-2.0, 2.5, -0.004)
    assert s.wco_mm == (1.0, 0.0, 0.0) and s.wco_in_report
    assert (s.planner_free_blocks, s.rx_free_bytes, s.line_number) == (13, 102, 7)
    assert (s.feed_mm_min, s.spindle_rpm, s.pins) == (250.0, 1000.0, "XPZ")
    assert (s.overrides_pct, s.accessories) == ((110, 50, 100), "SF")
    # The WCO carries to later reports; WPos-only reports get their machine position from it.
    s2 = one(core, b"<Door:2|WPos:0.000,0.000,0.000|F:100>\r\n")
    assert (s2.state_text, s2.position_mm, s2.wco_in_report, s2.feed_mm_min, s2.spindle_rpm) == (
        "Door:2",
        (1.0, 0.0, 0.0),
        False,
        100.0,
        None,
    )
    for state in ("Idle", "Run", "Jog", "Alarm", "Check", "Home", "Sleep", "Hold:0"):
        assert one(core, f"<{state}|MPos:0.000,0.000,0.000|FS:0,0>\r\n".encode()).state_text == state


def test_character_counting_conversation() -> None:
    """Exact bytes out, exact bytes in: lines fill 127 bytes, each response frees the oldest."""
    core = GrblProtocol()
    line = b"G1X10.000Y20.000F500"  # 20 bytes + \n
    sent = []
    while core.can_send(line):
        sent.append(core.send_line(line, tag=len(sent)))
    assert sent == [line + b"\n"] * 6 and core.in_flight_bytes == 126
    assert not core.can_send(line) and core.can_send(b"")  # one byte left: an empty line still fits
    with pytest.raises(GrblUsageError, match="overflow"):
        core.send_line(line)
    # Real-time bytes take no buffer space.
    assert core.realtime(Realtime.STATUS) == b"?" and core.realtime(Realtime.FEED_HOLD) == b"!"
    assert core.in_flight_bytes == 126
    events = core.receive_data(b"<Run|MPos:0.000,0.000,0.000|FS:500,0>\r\nok\r\nerror:22\r\n[MSG:Pgm End]\r\nok")
    assert [type(e) for e in events] == [Status, Ok, ErrorReply, Message]
    assert events[1].sent.tag == 0 and events[2].sent.tag == 1 and events[2].code == 22
    assert core.in_flight_bytes == 4 * 21
    assert core.receive_data(b"\r\n")[0].sent.tag == 2  # the split 'ok' completes
    assert core.max_in_flight_bytes == 126


def test_every_line_ends_with_exactly_one_newline_and_misuse_is_ours() -> None:
    core = GrblProtocol()
    assert core.send_line("G4 P0.1") == b"G4 P0.1\n"
    for bad, why in [
        (b"G1X1\n", "terminator"),
        (b"G1X1\r", "terminator"),
        (b"G1 (what?) X1", "real-time"),
        (b"G1X1!", "real-time"),
        ("G1X1\u00b5".encode(), "0xc2"),
        (b"G1" + b"X1" * 40, "79-character"),
    ]:
        with pytest.raises(GrblUsageError, match=why):
            core.send_line(bad)
    assert core.in_flight_bytes == 8
    spaced = b"G1 X1 " + b" " * 60 + b"(a long comment is not stored)"  # GRBL stores neither spaces nor comments
    assert core.send_line(spaced) == spaced + b"\n"
    with pytest.raises(GrblUsageError):
        core.realtime(b"A")


def test_banner_is_a_reset_that_drops_the_accounting() -> None:
    core = GrblProtocol()
    core.send_line(b"G1X1F100", tag="a")
    core.send_line(b"G1X2", tag="b")
    core.realtime(Realtime.SOFT_RESET)
    with pytest.raises(GrblUsageError, match="welcome banner"):
        core.send_line(b"G1X3")
    events = core.receive_data(b"ALARM:3\r\n\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n")
    assert [type(e) for e in events] == [Alarm, Welcome, Message]
    assert [s.tag for s in events[1].dropped] == ["a", "b"]
    assert core.in_flight == () and core.in_flight_bytes == 0 and not core.reset_pending and core.version == "1.1h"
    assert core.alarm == 3


def test_critical_alarm_locks_until_the_banner_and_the_late_ok_answers_the_offending_line() -> None:
    core = GrblProtocol()
    core.send_line(b"G0X10", tag="offender")
    core.send_line(b"$X", tag="ignored")
    events = core.receive_data(b"ALARM:2\r\n[MSG:Reset to continue]\r\n")
    assert events == [Alarm(2), Message("Reset to continue")] and core.locked and events[0].critical
    core.realtime(Realtime.SOFT_RESET)
    events = core.receive_data(b"ok\r\n\r\nGrbl 1.1h ['$' for help]\r\n")
    assert events[0].sent.tag == "offender"
    assert [s.tag for s in events[1].dropped] == ["ignored"] and not core.locked


def test_noise_and_unmatched_responses_never_corrupt_the_accounting() -> None:
    core = GrblProtocol()
    core.send_line(b"G1X1F100", tag="x")
    events = core.receive_data(b"\xff\xfe\x00garbage\r\n\x00ok\r\n\xffok\r\n")
    assert isinstance(events[0], Unrecognized) and events[0].raw == b"\xff\xfe\x00garbage"
    assert events[1] == Ok(events[1].sent) and events[1].sent.tag == "x"
    assert events[2] == Ok(None) and core.unmatched_responses == 1
    assert core.noise_bytes == 5 and core.unrecognized_lines == 1 and core.in_flight_bytes == 0
    # An endless line without a terminator is cut, not buffered forever.
    small = GrblProtocol(max_line_bytes=16)
    assert len(small.receive_data(b"x" * 40)) == 2


def test_every_code_has_a_meaning_and_errors_say_what_to_do() -> None:
    assert set(ERROR_MEANINGS) >= set(range(1, 18)) | set(range(20, 39))
    assert set(ALARM_MEANINGS) == set(range(1, 11))
    assert str(GrblAlarm(2)) == "ALARM:2 soft limit: target beyond travel; reset and re-home"
    assert str(GrblAlarm(9)).startswith("ALARM:9 homing failed: limit switch not found")
    err = GrblCommandError(22, b"G1X5", index=3)
    assert str(err) == "GRBL error:22 feed rate not set in 'G1X5' (line 4); give an F word (jogs need F on every command)"
    assert "unknown error code 99" in str(GrblCommandError(99, None))


_VALID = [
    b"ok\r\n",
    b"error:20\r\n",
    b"ALARM:1\r\n",
    b"<Idle|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>\r\n",
    b"<Run|WPos:1.000,2.000,3.000|Bf:15,128|FS:100,0|Ov:100,100,100|A:F>\r\n",
    b"[MSG:Reset to continue]\r\n",
    b"[PRB:0.000,0.000,0.000:0]\r\n",
    b"$10=1\r\n",
    b">G21:ok\r\n",
    b"\r\nGrbl 1.1h ['$' for help]\r\n",
]


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(st.binary(max_size=40), st.sampled_from(_VALID)), max_size=30), st.integers(0, 40))
def test_fuzz_random_and_truncated_input_never_crashes(chunks: list[bytes], n_lines: int) -> None:
    core = GrblProtocol()
    for i in range(n_lines):
        if core.can_send(b"G1X1"):
            core.send_line(b"G1X1", tag=i)
    stream = b"".join(chunks)
    cut = len(stream) // 3
    for part in (stream[:cut], stream[cut:]):
        for event in core.receive_data(part):
            assert isinstance(
                event, (Ok, ErrorReply, Alarm, Status, Message, Welcome, Unrecognized, Probe, Setting, StartupResult)
            )
    assert core.in_flight_bytes == sum(s.n_bytes for s in core.in_flight) >= 0


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(_VALID), st.integers(0, 80), st.binary(max_size=8))
def test_fuzz_truncated_lines_are_unrecognized_or_valid(line: bytes, cut: int, tail: bytes) -> None:
    core = GrblProtocol()
    for event in core.receive_data(line[:cut] + tail + b"\n"):
        assert event is not None
