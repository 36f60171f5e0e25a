"""Twins on pseudo-terminals: a real pyserial port talks to a byte-level twin."""

from __future__ import annotations

import time

import pytest
import serial

from labrig.sim.serial_pty import TwinServer


class EchoUpper:
    """A toy twin: answers each line in upper case after 2 ms."""

    def __init__(self) -> None:
        self.buffer = b""
        self.outbox: list[tuple[int, bytes]] = []

    def receive(self, data: bytes, now_us: int) -> None:
        self.buffer += data
        while b"\n" in self.buffer:
            line, self.buffer = self.buffer.split(b"\n", 1)
            self.outbox.append((now_us + 2000, line.upper() + b"\r\n"))

    def transmit(self, now_us: int) -> bytes:
        due = [data for t, data in self.outbox if t <= now_us]
        self.outbox = [(t, d) for t, d in self.outbox if t > now_us]
        return b"".join(due)


def test_pyserial_talks_to_a_twin_over_a_pty() -> None:
    with TwinServer({"echo": EchoUpper()}) as server:
        port = serial.Serial(server.paths["echo"], 115200, timeout=1.0)
        port.write(b"hello\nworld\n")
        assert port.readline() == b"HELLO\r\n"
        assert port.readline() == b"WORLD\r\n"
        port.close()
        assert server.error is None


class Chatty:
    """A twin that talks all the time, whether anyone listens or not."""

    def receive(self, data: bytes, now_us: int) -> None:
        pass

    def transmit(self, now_us: int) -> bytes:
        return b"x" * 4096


def test_a_port_nobody_reads_does_not_stall_the_other_twins() -> None:
    with TwinServer({"chatty": Chatty(), "echo": EchoUpper()}) as server:
        port = serial.Serial(server.paths["echo"], 115200, timeout=1.0)
        for _ in range(3):
            port.write(b"ping\n")
            assert port.readline() == b"PING\r\n"
        port.close()
        assert server.ports["chatty"].dropped_bytes > 0 and server.error is None


def test_unplug_closes_one_port_and_the_other_twins_keep_running() -> None:
    with TwinServer({"gone": EchoUpper(), "echo": EchoUpper()}) as server:
        gone = serial.Serial(server.paths["gone"], 115200, timeout=1.0)
        echo = serial.Serial(server.paths["echo"], 115200, timeout=1.0)
        gone.write(b"before\n")
        assert gone.readline() == b"BEFORE\r\n"
        server.unplug("gone")
        assert server.unplugged == {"gone"}
        t0 = time.monotonic()
        with pytest.raises(serial.SerialException):
            gone.read(1)
        assert time.monotonic() - t0 < 0.5  # at once, not after the port's 1 s timeout
        with pytest.raises(serial.SerialException, match="write failed"):
            gone.write(b"after\n")
        echo.write(b"still here\n")
        assert echo.readline() == b"STILL HERE\r\n"
        gone.close()
        echo.close()
    assert server.error is None


class Brittle(EchoUpper):
    """Raises on a line that says 'boom' (a request the twin's model cannot serve), echoes the rest."""

    def receive(self, data: bytes, now_us: int) -> None:
        if b"boom" in data:
            raise ValueError("cannot serve boom")
        super().receive(data, now_us)


def test_a_twin_that_raises_on_a_request_reports_it_and_keeps_serving() -> None:
    with TwinServer({"brittle": Brittle(), "echo": EchoUpper()}) as server:
        brittle = serial.Serial(server.paths["brittle"], 115200, timeout=1.0)
        echo = serial.Serial(server.paths["echo"], 115200, timeout=1.0)
        brittle.write(b"boom\n")
        time.sleep(0.05)
        brittle.write(b"boom again\n")
        time.sleep(0.05)
        brittle.write(b"still here\n")
        assert brittle.readline() == b"STILL HERE\r\n"
        echo.write(b"ping\n")
        assert echo.readline() == b"PING\r\n"
        assert server.error is None
        assert [f.message for f in server.faults] == ["brittle receive: ValueError: cannot serve boom"]  # once a run
        brittle.close()
        echo.close()
