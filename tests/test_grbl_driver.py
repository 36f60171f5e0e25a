"""The GRBL driver against a scripted port: exact bytes out, exact bytes in (PyMeasure style)."""

from __future__ import annotations

import errno
import itertools
import threading
import time
from collections import deque

import pytest
import serial

from labrig.devices.grbl import (
    Grbl,
    GrblAlarm,
    GrblCommandError,
    GrblConnectionError,
    GrblTimeout,
    GrblUsageError,
    OutputEdge,
)
from labrig.devices.grbl_channel import StatusSample
from labrig.sim.grbl_settings import DEFAULT_SETTINGS
from labrig.sim.grbl_twin import BANNER

WELCOME = b"\r\n" + BANNER.encode() + b"\r\n"
UNLOCK = b"[MSG:'$H'|'$X' to unlock]\r\n"
IDLE = b"<Idle|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>\r\n"
SETTINGS = b"".join(
    b"$%d=%s\r\n" % (n, (b"%.3f" % v) if n >= 100 or n in (11, 12, 24, 25, 27) else b"%d" % v)
    for n, v in DEFAULT_SETTINGS.items()
)


class ScriptedPort:
    """A serial port that plays a script: each write must be the next expected bytes, then its reply is readable.

    Anything else written is recorded in ``unexpected``. ``push`` adds unsolicited bytes; ``unplug``
    makes every later read and write fail like a vanished USB device.
    """

    def __init__(self, script: list[tuple[bytes, bytes]]) -> None:
        self.script = deque(script)
        self.rx = bytearray()
        self.cond = threading.Condition()
        self.timeout: float | None = 0.01
        self.written: list[bytes] = []
        self.unexpected: list[bytes] = []
        self.unplugged = False
        self.closed = False

    @property
    def dtr(self) -> bool:
        return True

    @dtr.setter
    def dtr(self, value: bool) -> None:
        raise OSError(errno.ENOTTY, "Inappropriate ioctl for device")

    @property
    def in_waiting(self) -> int:
        with self.cond:
            return len(self.rx)

    def read(self, size: int = 1) -> bytes:
        with self.cond:
            if not self.rx and not self.unplugged:
                self.cond.wait(self.timeout)
            if self.unplugged:
                raise serial.SerialException("read failed: [Errno 5] Input/output error")
            data = bytes(self.rx[:size])
            del self.rx[:size]
            return data

    def write(self, data: bytes) -> int:
        with self.cond:
            if self.unplugged:
                raise serial.SerialException("write failed: [Errno 5] Input/output error")
            self.written.append(bytes(data))
            if self.script and self.script[0][0] == data:
                self.rx += self.script.popleft()[1]
                self.cond.notify_all()
            else:
                self.unexpected.append(bytes(data))
            return len(data)

    def push(self, data: bytes) -> None:
        with self.cond:
            self.rx += data
            self.cond.notify_all()

    def unplug(self) -> None:
        with self.cond:
            self.unplugged = True
            self.cond.notify_all()

    def reset_input_buffer(self) -> None:
        with self.cond:
            self.rx.clear()

    def close(self) -> None:
        self.closed = True

    def done(self) -> None:
        assert self.unexpected == [] and list(self.script) == []


def started(script: list[tuple[bytes, bytes]], **kwargs: object) -> tuple[Grbl, ScriptedPort]:
    """A driver connected without reset or settings (one status query), no automatic polling."""
    port = ScriptedPort([(b"?", IDLE), *script])
    grbl = Grbl(port, poll_hz=0, **kwargs)  # type: ignore[arg-type]
    info = grbl.connect(reset="none", read_settings=False)
    assert info.state == "Idle" and info.reset == "none"
    return grbl, port


def test_connect_soft_resets_on_a_port_without_dtr_and_reports_the_alarm() -> None:
    port = ScriptedPort(
        [
            (b"\x18", WELCOME + UNLOCK),
            (b"?", b"<Alarm|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>\r\n"),
            (b"$$\n", SETTINGS + b"ok\r\n"),
            (b"$X\n", b"[MSG:Caution: Unlocked]\r\nok\r\n"),
            (b"?", b"<Idle|MPos:0.000,0.000,0.000|FS:0,0|Ov:100,100,100>\r\n"),
        ]
    )
    port.push(b"stale bytes from before\r\n")  # flushed by connect
    with Grbl(port, poll_hz=0) as grbl:  # type: ignore[arg-type]
        info = grbl.connect()
        assert (info.version, info.state, info.reset, info.messages) == ("1.1h", "Alarm", "soft", ("'$H'|'$X' to unlock",))
        assert grbl.settings[110] == 500.0 and grbl.settings[11] == 0.01 and len(grbl.settings) == 34
        assert grbl.limits.accel_mm_s2 == (10.0, 10.0, 10.0)
        grbl.unlock()
        assert grbl.state == "Idle"
    port.done()
    assert not port.closed  # the caller's port stays open


def test_commands_are_the_expected_bytes() -> None:
    edges: list[OutputEdge] = []
    log: list[tuple[int, int, bytes]] = []
    grbl, port = started(
        [
            (b"G90G1X-10Y-2.5F600\n", b"ok\r\n"),
            (b"G91G0Z1\n", b"ok\r\n"),
            (b"G90G53G0X0\n", b"ok\r\n"),
            (b"$J=G91X1F100\n", b"ok\r\n"),
            (b"\x85", b""),
            (b"!", b""),
            (b"~", b""),
            (b"M8\n", b"ok\r\n"),
            (b"M9\n", b"ok\r\n"),
            (b"$120=250\n", b"ok\r\n"),
            (b"$G\n", b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\r\nok\r\n"),
        ],
        on_output=edges.append,
        on_gcode=lambda t, d, line: log.append((t, d, line)),
    )
    grbl.move_to(-10, -2.5, feed_mm_min=600)
    grbl.move_by(dz=1, feed_mm_min=None)
    grbl.move_to(x=0, feed_mm_min=None, machine=True)
    grbl.jog(x=1, feed_mm_min=100)
    grbl.jog_cancel()
    grbl.feed_hold()
    grbl.resume()
    on = grbl.set_output(True)
    grbl.set_output(False)
    grbl.write_setting(120, 250)
    reply = grbl.send("$G")
    assert reply.pushed[0].words[:2] == ("G0", "G54")  # type: ignore[attr-defined]
    assert [e.level for e in edges] == [1, 0] and edges[0] == on and on.t_sent_us <= on.t_ack_us
    assert grbl.settings[120] == 250.0 and grbl.limits.accel_mm_s2[0] == 250.0
    with pytest.raises(GrblUsageError):
        grbl.jog(x=1, feed_mm_min=0)
    with pytest.raises(GrblUsageError):
        grbl.move_to(feed_mm_min=100)
    with pytest.raises(GrblUsageError, match="real-time"):
        grbl.send("G1 X1 (really?)")
    grbl.close()
    port.done()
    sent = [line for _, d, line in log if d == 0]
    assert sent[:3] == [b"G90G1X-10Y-2.5F600", b"G91G0Z1", b"G90G53G0X0"] and b"\x85" in sent and b"?" not in sent
    assert [line for _, d, line in log if d == 1][:2] == [b"<Idle|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>", b"ok"]
    assert all(a[0] <= b[0] for a, b in itertools.pairwise(log))


def test_error_and_critical_alarm_become_typed_exceptions() -> None:
    grbl, port = started(
        [
            (b"G1X-1\n", b"error:22\r\n"),
            (b"G0X10\n", b"ALARM:2\r\n[MSG:Reset to continue]\r\n"),
            (b"\x18", b"ok\r\n" + WELCOME + UNLOCK),
            (b"?", b"<Alarm|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>\r\n"),
        ]
    )
    with pytest.raises(GrblCommandError, match=r"^GRBL error:22 feed rate not set in 'G1X-1'; give an F word") as err:
        grbl.send("G1X-1")
    assert err.value.code == 22
    t0 = time.monotonic()
    with pytest.raises(GrblAlarm, match=r"^ALARM:2 soft limit: target beyond travel; reset and re-home") as alarm:
        grbl.send("G0X10")  # GRBL holds this line's ok until a reset: do not wait for it
    assert alarm.value.critical and time.monotonic() - t0 < 1.0
    with pytest.raises(GrblAlarm, match="soft_reset"):
        grbl.send("$X")  # nothing is written while GRBL is locked
    info = grbl.soft_reset()
    assert info.state == "Alarm" and info.messages == ("'$H'|'$X' to unlock",)
    grbl.close()
    port.done()


def test_garbage_from_the_controller_is_skipped() -> None:
    log: list[bytes] = []
    grbl, port = started([(b"G4P0\n", b"\xff\xfe\x00?!noise\r\n\x00ok\r\n")], on_gcode=lambda t, d, line: log.append(line))
    port.push(b"\x80\x81\r\n[MSG:hello]\r\nnot grbl at all\r\n")
    grbl.send("G4P0")
    assert grbl.protocol.noise_bytes >= 4 and grbl.protocol.unrecognized_lines >= 1 and grbl.protocol.in_flight == ()
    assert b"\xff\xfe\x00?!noise" in log
    grbl.close()
    port.done()


def test_a_lost_ok_times_out_clearly() -> None:
    grbl, _ = started([(b"G1X-1F100\n", b"")], response_timeout_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(GrblTimeout, match=r"no response to 'G1X-1F100' after 0\.[34] s .*lost.*soft_reset\(\) clears"):
        grbl.send("G1X-1F100")
    assert 0.25 < time.monotonic() - t0 < 1.5
    grbl.close()


def test_an_unplugged_port_fails_fast() -> None:
    grbl, port = started([(b"G1X-1F100\n", b"")])
    threading.Timer(0.1, port.unplug).start()
    t0 = time.monotonic()
    with pytest.raises(GrblConnectionError, match="unplugged"):
        grbl.send("G1X-1F100", timeout_s=30)
    assert time.monotonic() - t0 < 1.0
    with pytest.raises(GrblConnectionError):
        grbl.status()
    grbl.close()


def test_character_counting_keeps_127_bytes_in_flight() -> None:
    """Lines go out while they fit; each ok lets exactly the lines that then fit follow."""
    grbl, port = started([])
    lines = [f"G1X-{i}.{i:03d}Y-{i}.5F1000" for i in range(1, 21)]  # 20-23 bytes each
    done: list[object] = []
    worker = threading.Thread(target=lambda: done.append(grbl.stream(lines)))
    port.script.clear()
    worker.start()

    def settle() -> list[bytes]:
        before = -1
        while len(port.written) != before:
            before = len(port.written)
            time.sleep(0.02)
        return [w for w in port.written if w != b"?"]

    sent = settle()
    assert sum(len(w) for w in sent) <= 127 and sum(len(w) for w in sent) + len(lines[len(sent)]) + 1 > 127
    assert sent == [line.encode() + b"\n" for line in lines[: len(sent)]]
    answered = 0
    while answered < len(lines):
        port.push(b"ok\r\n")
        answered += 1
        sent = settle()
        unanswered = sent[answered:]
        assert sum(len(w) for w in unanswered) <= 127
        if len(sent) < len(lines):
            assert sum(len(w) for w in unanswered) + len(lines[len(sent)]) + 1 > 127
    worker.join(2)
    result = done[0]
    assert result.lines == 20 and result.max_in_flight_bytes <= 127  # type: ignore[attr-defined]
    assert grbl.protocol.max_in_flight_bytes <= 127
    grbl.close()


def test_status_samples_carry_host_times_and_the_recording_columns() -> None:
    samples: list[StatusSample] = []
    grbl, port = started([(b"?", b"<Run|WPos:1.000,2.000,3.000|FS:600,0|WCO:-1.000,0.000,0.000>\r\n")], on_sample=samples.append)
    t0 = grbl.now_us()
    sample = grbl.status()
    assert sample.t_query_us is not None and t0 <= sample.t_query_us <= sample.t_host_us <= grbl.now_us()
    assert sample.position_mm == (0.0, 2.0, 3.0)  # machine = work + WCO
    assert sample.columns() == {
        "t_host_us": sample.t_host_us,
        "position_mm": (0.0, 2.0, 3.0),
        "feed_mm_min": 600.0,
        "state": "Run",
    }
    assert samples[-1] == sample
    grbl.close()
    port.done()


class WriteFailsAfterLastWords(ScriptedPort):
    """Answers every ``?``; once armed, one read delivers its last words after a poll falls due, and
    from then on writes fail (the USB device went away between a read and the next write)."""

    def __init__(self) -> None:
        super().__init__([])
        self.last_words: bytes | None = None

    def write(self, data: bytes) -> int:
        if data == b"?" and not self.unplugged:
            self.push(IDLE)
        with self.cond:
            if self.last_words == b"":
                raise serial.SerialException("write failed: [Errno 5] Input/output error")
        return super().write(data)

    def read(self, size: int = 1) -> bytes:
        if self.last_words:
            time.sleep(0.06)  # the next status poll (50 Hz) is due when this read returns
            with self.cond:
                data, self.last_words = self.last_words, b""
            return data
        return super().read(size)


def test_lines_read_just_before_the_port_fails_still_reach_the_callbacks() -> None:
    log: list[bytes] = []
    port = WriteFailsAfterLastWords()
    grbl = Grbl(port, poll_hz=50, on_gcode=lambda t, d, line: log.append(line))  # type: ignore[arg-type]
    grbl.connect(reset="none", read_settings=False)
    port.last_words = b"[MSG:last words]\r\n"
    end = time.monotonic() + 2.0
    while port.last_words and time.monotonic() < end:
        time.sleep(0.01)
    grbl.close()  # joins the I/O thread, which fails on its next status poll
    assert b"[MSG:last words]" in log
    with pytest.raises(GrblConnectionError, match="unplugged"):
        grbl.status()
