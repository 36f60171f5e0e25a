"""The GRBL 1.1h twin, byte for byte, on a manual host clock (no pty, no threads)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.sim.grbl_twin import BANNER, GrblTwin

WELCOME = b"\r\n" + BANNER.encode() + b"\r\n"
UNLOCK = b"[MSG:'$H'|'$X' to unlock]\r\n"
FAST = {110: 6000, 111: 6000, 112: 3000, 120: 500, 121: 500, 122: 500}
HOMING = {22: 1, 24: 600, 25: 3000, 27: 1.0}


class Host:
    """Talks to a twin on a manual clock: exact bytes out, exact bytes in."""

    def __init__(self, twin: GrblTwin, t_us: int = 1_000_000) -> None:
        self.twin = twin
        self.t = t_us
        twin.transmit(t_us)  # power on
        self.banner = self.wait(50_000)

    def wait(self, dt_us: int) -> bytes:
        self.t += dt_us
        return self.twin.transmit(self.t)

    def send(self, data: bytes, dt_us: int = 20_000) -> bytes:
        self.twin.receive(data, self.t)
        return self.wait(dt_us)

    def until(self, pattern: bytes, limit_us: int = 60_000_000, step_us: int = 100) -> tuple[int, bytes]:
        """Step until ``pattern`` has been received; (host time, bytes received)."""
        got = b""
        end = self.t + limit_us
        while pattern not in got:
            assert self.t < end, f"{pattern!r} never came; got {got!r}"
            got += self.wait(step_us)
        return self.t, got


def test_power_on_reports_and_unlock() -> None:
    host = Host(GrblTwin(settings={22: 1}))
    assert host.banner == WELCOME + UNLOCK
    assert host.send(b"?") == b"<Alarm|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>\r\n"  # no 'ok' after '?'
    assert host.send(b"G0X-1\n") == b"error:9\r\n"
    assert host.send(b"$X\n") == b"[MSG:Caution: Unlocked]\r\nok\r\n"
    assert host.send(b"?") == b"<Idle|MPos:0.000,0.000,0.000|FS:0,0|Ov:100,100,100>\r\n"
    assert host.send(b"?") == b"<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n"
    assert host.send(b"\n") == b"ok\r\n"
    assert host.send(b"G4P0.01\r\n") == b"ok\r\nok\r\n"  # '\r\n' is two lines: two oks
    assert Host(GrblTwin()).banner == WELCOME  # homing off: no lock


def test_dollar_commands() -> None:
    host = Host(GrblTwin())
    settings = host.send(b"$$\n", 100_000).split(b"\r\n")
    assert settings[0] == b"$0=10" and settings[8] == b"$11=0.010" and b"$130=200.000" in settings
    assert len(settings) == 34 + 2 and settings[-2] == b"ok"
    assert host.send(b"$\n") == b"[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]\r\nok\r\n"
    assert host.send(b"$G\n") == b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\r\nok\r\n"
    assert host.send(b"$I\n") == b"[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\nok\r\n"
    assert host.send(b"$N\n") == b"$N0=\r\n$N1=\r\nok\r\n"
    assert host.send(b"$#\n", 50_000).split(b"\r\n")[-5:] == [
        b"[G92:0.000,0.000,0.000]",
        b"[TLO:0.000]",
        b"[PRB:0.000,0.000,0.000:0]",
        b"ok",
        b"",
    ]
    assert host.send(b"g91 g1 (comment) f100 ; more\n") == b"ok\r\n"
    assert host.send(b"$g\n") == b"[GC:G1 G54 G17 G21 G91 G94 M5 M9 T0 F100 S0]\r\nok\r\n"


@pytest.mark.parametrize(
    ("line", "reply"),
    [
        (b"G5", b"error:20"),
        (b"1X", b"error:1"),
        (b"G1X", b"error:2"),
        (b"G1X-", b"error:2"),
        (b"G1X1.2.3", b"error:1"),
        (b"$Z", b"error:3"),
        (b"S-1", b"error:4"),
        (b"$H", b"error:5"),
        (b"$0=2", b"error:6"),
        (b"$20=1", b"error:10"),
        (b"G1X" + b"1" * 80, b"error:11"),
        (b"$100=4000", b"error:12"),
        (b"$J=G1X1F10", b"error:16"),
        (b"$JX1", b"error:3"),
        (b"G0G1X1", b"error:21"),
        (b"G1X1", b"error:22"),
        (b"$J=X1", b"error:22"),
        (b"G1.5X1", b"error:23"),
        (b"G92G1X1", b"error:24"),
        (b"G1X1X2F1", b"error:25"),
        (b"$J=F100", b"error:26"),
        (b"N10000000", b"error:27"),
        (b"G4", b"error:28"),
        (b"G59.1", b"error:29"),
        (b"G53G80X1", b"error:30"),
        (b"G80X1", b"error:31"),
        (b"G0X1P5", b"error:36"),
        (b"T300", b"error:38"),
        (b"G2X1Y1I1", b"error:20"),
        (b"$100=abc", b"error:2"),
        (b"$999=1", b"error:3"),
    ],
)
def test_error_codes(line: bytes, reply: bytes) -> None:
    host = Host(GrblTwin())
    assert host.send(line + b"\n") == reply + b"\r\n"


def test_motion_profile_state_and_position() -> None:
    twin = GrblTwin(settings=FAST)
    host = Host(twin)
    t0 = host.t
    assert host.send(b"G1X-10F600\n", 0) == b""  # 11 bytes at 86.8 us, then 250 us parsing
    t_ok, _ = host.until(b"ok\r\n")
    assert t_ok - t0 == pytest.approx(11 * 86.8 + 250 + 4 * 86.8, abs=101)
    host.wait(500_000)
    report = host.send(b"?")
    assert report.startswith(b"<Run|MPos:-4.9") and b"|FS:600,0|" in report
    t_done = t0 + 11 * 86.8 + 250 + (0.02 + 0.98 + 0.02) * 1e6  # 10 mm/s, 0.1 mm ramps at 500 mm/s^2
    assert twin.position_mm(t_done + 1)[0] == pytest.approx([-10.0, 0, 0])
    x = twin.position_mm(np.linspace(t0, t_done, 1000))[:, 0]
    assert np.all(np.diff(x) <= 1e-12) and x[0] == 0.0
    host.wait(600_000)
    assert host.send(b"?").startswith(b"<Idle|MPos:-10.000,0.000,0.000|FS:0,0")


def test_planner_holds_back_ok_when_full_and_reports_buffers() -> None:
    twin = GrblTwin(settings={10: 3, **FAST})
    host = Host(twin)
    program = b"G91G1F60\n" + b"X-1\n" * 20  # 1 mm/s moves: the planner fills
    out = host.send(program, 200_000)
    assert out == b"ok\r\n" * 16 and twin.planner_blocks == 15  # G91G1F60 and 15 moves
    report = host.send(b"?")
    assert report.startswith(b"<Run|MPos:") and b"|Bf:0,112|" in report  # 4 lines wait in the ring, 1 in the parser
    t_ok, _ = host.until(b"ok")
    t_first_planned = 1_050_000 + 13 * 86.8 + 250
    assert t_ok == pytest.approx(t_first_planned + 1.001e6 + 4 * 86.8, abs=150)  # a block ended: the next line got its ok
    assert twin.planner_blocks == 15 and twin.rx_overflow_bytes == 0


def test_rx_ring_overflows_silently() -> None:
    twin = GrblTwin(settings=FAST)
    host = Host(twin)
    host.send(b"G91G1F60\n" + b"X-1\n" * 20, 200_000)  # planner full, main loop blocked, 16 bytes in the ring
    burst = b"G1X-30Y-1F60\n" * 20  # 260 bytes at once
    host.send(burst, 50_000)
    assert twin.max_rx_fill_bytes == 128
    assert twin.rx_overflow_bytes == len(burst) - (128 - 16)  # what did not fit was dropped, and nothing said so


def test_feed_hold_resume_and_lines_during_hold() -> None:
    twin = GrblTwin(settings=FAST)
    host = Host(twin)
    host.send(b"G1X-20F1200\n", 300_000)
    host.send(b"!", 0)
    assert host.send(b"?", 2_000).startswith(b"<Hold:1|")
    host.wait(100_000)
    held = host.send(b"?")
    assert held.startswith(b"<Hold:0|") and b"FS:0," in held
    x_held = twin.position_mm(host.t)[0, 0]
    assert host.send(b"$G\n") == b"[GC:G1 G54 G17 G21 G90 G94 M5 M9 T0 F1200 S0]\r\nok\r\n"
    assert host.send(b"G1X-25\n") == b"ok\r\n"  # planned, not started
    assert host.send(b"G4P0\n", 300_000) == b""  # a sync: no ok while held
    assert host.send(b"$$\n") == b""  # queued behind the dwell
    assert twin.position_mm(host.t)[0, 0] == x_held
    out = host.send(b"~", 3_000_000)
    assert out.startswith(b"ok\r\n$0=10\r\n")  # the dwell ends once both moves ran, then $$ runs in Idle
    assert twin.position_mm(host.t)[0, 0] == pytest.approx(-25.0)


def test_jog_cancel_soft_limit_jog_and_parser_sync() -> None:
    twin = GrblTwin(settings={**FAST, **HOMING, 20: 1}, power_on_physical_mm=(-2, -2, -2))
    host = Host(twin)
    host.send(b"$H\n")
    host.until(b"ok\r\n")
    assert host.send(b"?").startswith(b"<Idle|MPos:-1.000,-1.000,-1.000|")
    assert twin.physical_offset_mm == pytest.approx((0.0, 0.0, 0.0))
    assert host.send(b"$J=G91X5F600\n") == b"error:15\r\n"  # beyond travel: refused, no alarm
    assert host.send(b"$J=G91X-50F600\n") == b"ok\r\n"
    assert host.send(b"?").startswith(b"<Jog|")
    assert host.send(b"G1X-2F100\n") == b"error:9\r\n"
    assert host.send(b"\x85", 300_000) == b""
    stopped = twin.position_mm(host.t)[0, 0]
    assert host.send(b"?").startswith(b"<Idle|")
    host.send(b"G91G1X-1F600\n", 500_000)  # relative to where the jog stopped
    assert twin.position_mm(host.t)[0, 0] == pytest.approx(stopped - 1.0, abs=0.004)


def test_soft_limit_alarm_locks_until_reset() -> None:
    twin = GrblTwin(settings={**FAST, **HOMING, 20: 1}, power_on_physical_mm=(-2, -2, -2))
    host = Host(twin)
    host.send(b"$H\n")
    host.until(b"ok\r\n")
    out = host.send(b"G1X-10F600\nG0X10\n", 2_000_000)
    assert out == b"ok\r\nALARM:2\r\n[MSG:Reset to continue]\r\n"  # after decelerating; no ok for G0X10
    x = twin.position_mm(host.t)[0, 0]
    assert -10.0 < x < -1.0  # stopped on the way, position kept
    assert host.send(b"?$X\n$H\n", 200_000) == b""  # locked: '?' and lines are ignored
    assert host.send(b"\x18") == b"ok\r\n" + WELCOME + UNLOCK
    assert host.send(b"?").startswith(b"<Alarm|MPos:%.3f," % x)
    assert host.send(b"$X\n") == b"[MSG:Caution: Unlocked]\r\nok\r\n"


def test_limit_alarms_switch_spindle_and_coolant_off_at_the_alarm() -> None:
    """GRBL's mc_reset stops the spindle, then the coolant, as a soft or hard limit trips, not at the reset after it."""
    twin = GrblTwin(settings={**FAST, **HOMING, 20: 1}, power_on_physical_mm=(-2, -2, -2))
    host = Host(twin)
    host.send(b"$H\n")
    host.until(b"ok\r\n")
    assert host.send(b"M3S1000\nM8\n") == b"ok\r\nok\r\n"
    assert host.send(b"G1X-10F600\nG0X10\n", 2_000_000).endswith(b"ALARM:2\r\n[MSG:Reset to continue]\r\n")
    off = [(name, level) for t_us, name, level in twin.outputs if level == 0 and t_us < host.t]
    assert off == [("spindle", 0), ("flood", 0)]  # while locked, before any reset
    host.send(b"\x18")
    host.send(b"$X\nM8\n")
    assert twin.outputs[-1][1:] == ("flood", 1)
    twin.trip_hard_limit(host.t)
    assert twin.outputs[-1] == (host.t, "flood", 0)


def test_reset_in_motion_is_alarm_3_and_keeps_position() -> None:
    twin = GrblTwin(settings=FAST)
    host = Host(twin)
    host.send(b"G1X-20F1200\nG1X-40\n", 300_000)
    x = twin.position_mm(host.t)[0, 0]
    assert host.send(b"\x18") == b"ALARM:3\r\n" + WELCOME + UNLOCK
    assert twin.position_mm(host.t + 1e6)[0, 0] == pytest.approx(x, abs=0.02)
    assert host.send(b"?").startswith(b"<Alarm|") and twin.planner_blocks == 0


def test_homing_failure_and_check_mode() -> None:
    far = GrblTwin(settings={**FAST, **HOMING}, power_on_physical_mm=(-5.0, -350.0, -1.0))  # Y beyond 1.5 x travel
    host = Host(far)
    host.send(b"$H\n")
    assert host.send(b"?") == b""  # silent while homing
    _, out = host.until(b"ok\r\n", limit_us=30_000_000, step_us=10_000)
    assert out.endswith(b"ALARM:9\r\nok\r\n")
    twin = GrblTwin(settings=FAST)
    host = Host(twin)
    assert host.send(b"$C\n") == b"[MSG:Enabled]\r\nok\r\n"
    assert host.send(b"G1X-50F100\nG4P10\n") == b"ok\r\nok\r\n"  # parsed, not executed
    assert host.send(b"?").startswith(b"<Check|MPos:0.000,0.000,0.000|")
    assert host.send(b"$C\n") == b"[MSG:Disabled]\r\nok\r\n" + WELCOME
    assert host.send(b"?").startswith(b"<Idle|")


def test_outputs_sync_with_motion_and_dwell() -> None:
    edges: list[tuple[int, str, int]] = []
    twin = GrblTwin(settings=FAST, on_output=lambda t, name, level: edges.append((t, name, level)))
    host = Host(twin)
    host.send(b"G1X-5F600\nM8\nG4P0.2\nM9\n", 0)
    t_ok, _ = host.until(b"ok\r\nok\r\n")
    t_move_end = 1_000_000 + 50_000 + 10 * 86.8 + 250 + 0.52e6
    assert edges[0][1:] == ("flood", 1) and edges[0][0] == pytest.approx(t_move_end, abs=2)  # M8 waited for the move
    assert t_ok - edges[0][0] == pytest.approx(4 * 86.8, abs=101)  # then its ok went out
    host.until(b"ok\r\nok\r\n")
    assert edges[1][1:] == ("flood", 0) and edges[1][0] - edges[0][0] == pytest.approx(0.2e6 + 2 * 250, abs=2)
    host.send(b"\xa0")  # real-time flood toggle
    assert edges[-1][1:] == ("flood", 1) and twin.outputs == edges


def test_eeprom_write_deafens_the_receiver_and_settings_persist() -> None:
    twin = GrblTwin()
    host = Host(twin)
    twin.receive(b"$110=1000\n", host.t)
    host.wait(2_000)
    assert host.send(b"?G0X-1\n", 50_000) == b"ok\r\n"  # arrived during the write: lost
    assert twin.rx_blackout_bytes == 7 and twin.settings[110] == 1000
    assert host.send(b"$N0=G91\n") == b"ok\r\n"
    assert host.send(b"\x18") == WELCOME + b">G91:ok\r\n"
    assert host.send(b"$G\n").startswith(b"[GC:G0 G54 G17 G21 G91 ")
    assert host.send(b"$SLP\n") == b"ok\r\n[MSG:Sleeping]\r\n"
    assert host.send(b"?$$\n").startswith(b"<Sleep|")
    assert host.send(b"\x18") == WELCOME + UNLOCK


def test_output_is_paced_at_the_baud_rate_and_latency_is_added() -> None:
    twin = GrblTwin(link_latency_us=1000)
    host = Host(twin)
    twin.receive(b"$I\n", host.t)
    reply = b"[VER:1.1h.20190830:]\r\n[OPT:V,15,128]\r\nok\r\n"
    t_first = host.t + 1000 + 3 * 86.8 + 250
    assert twin.transmit(math.floor(t_first + 1000 + 10.5 * 86.8)) == reply[:10]
    assert twin.transmit(math.ceil(t_first + 1000 + len(reply) * 86.8) + 1) == reply[10:]


def test_work_offsets_and_deterministic_output() -> None:
    def session() -> bytes:
        host = Host(GrblTwin(settings={10: 0, **FAST}))
        out = host.send(b"G10L20P1X5\n")  # EEPROM write: send-response only
        out += host.send(b"G1X0F600\n", 2_000_000)
        out += host.send(b"?")
        out += host.send(b"G92X0\n?M2\n")
        return out

    out = session()
    assert out.startswith(b"ok\r\nok\r\n<Idle|WPos:0.000,0.000,0.000|FS:0,0|WCO:-5.000,0.000,0.000>\r\n")
    assert out.endswith(b"ok\r\n[MSG:Pgm End]\r\nok\r\n")
    assert session() == out


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.binary(max_size=30), st.integers(0, 20_000)), max_size=25))
def test_fuzz_the_twin_never_crashes(chunks: list[tuple[bytes, int]]) -> None:
    twin = GrblTwin(settings={**FAST, **HOMING, 20: 1})
    host = Host(twin)
    for data, dt in chunks:
        host.send(data, dt)
        assert twin.rx_fill_bytes <= 128 and twin.planner_blocks <= 15
    host.send(b"\x18?")
    assert twin.position_mm([host.t]).shape == (1, 3)
