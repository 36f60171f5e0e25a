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
        deadline = time.monotonic() + 2.0  # the pty and the port's host buffer fill first (about 80 KB)
        while server.ports["chatty"].dropped_bytes == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
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


class StallingRecorder:
    """A twin that keeps the server busy for ``stall_s`` when the host first writes (a starved
    server), and records the arrival stamps it is given."""

    def __init__(self, stall_s: float) -> None:
        self.stall_s = stall_s
        self.stamps: list[int] = []

    def receive(self, data: bytes, now_us: int) -> None:
        self.stamps.append(now_us)
        if len(self.stamps) == 1:
            time.sleep(self.stall_s)

    def transmit(self, now_us: int) -> bytes:
        return b""


@pytest.mark.parametrize("relayed", [False, True])
def test_a_relayed_port_stamps_bytes_when_they_arrive_not_when_the_server_gets_to_them(relayed: bool) -> None:
    twin = StallingRecorder(stall_s=0.2)
    with TwinServer({"dev": twin}, relayed={"dev"} if relayed else set()) as server:
        port = serial.Serial(server.paths["dev"], 115200, timeout=1.0)
        port.write(b"a")  # stalls the server for 0.2 s
        deadline = time.monotonic() + 2.0
        while not twin.stamps and time.monotonic() < deadline:
            time.sleep(0.001)
        written_us = time.monotonic_ns() // 1000
        port.write(b"b")
        deadline = time.monotonic() + 2.0
        while len(twin.stamps) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        port.close()
    late_us = twin.stamps[1] - written_us
    if relayed:
        assert 0 <= late_us < 20_000
    else:
        assert late_us > 100_000  # the server read it after its stall


def test_a_relayed_port_unplugs_and_its_relay_exits_with_the_server() -> None:
    from labrig.sim.serial_pty import RelayedPort

    with TwinServer({"echo": EchoUpper(), "gone": EchoUpper()}, relayed={"echo", "gone"}) as server:
        ports = dict(server.ports)
        echo = serial.Serial(server.paths["echo"], 115200, timeout=1.0)
        echo.write(b"hi\n")
        assert echo.readline() == b"HI\r\n"
        gone = serial.Serial(server.paths["gone"], 115200, timeout=0.2)
        server.unplug("gone")
        with pytest.raises(serial.SerialException):
            gone.write(b"x")
            gone.read(1)
        echo.close()
    for port in ports.values():
        assert isinstance(port, RelayedPort) and port._process.poll() is not None


def test_a_relay_exits_when_its_server_process_is_killed(tmp_path) -> None:  # type: ignore[no-untyped-def]
    import os
    import signal
    import subprocess
    import sys

    script = (
        "import sys, time\n"
        "from labrig.sim.serial_pty import TwinServer\n"
        "class T:\n"
        "    def receive(self, data, now_us): pass\n"
        "    def transmit(self, now_us): return b''\n"
        "s = TwinServer({'t': T()}, relayed={'t'}).start()\n"
        "print(s.ports['t']._process.pid, flush=True)\n"
        "time.sleep(60)\n"
    )
    server = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    relay_pid = int(server.stdout.readline())  # type: ignore[union-attr]
    os.kill(server.pid, signal.SIGKILL)
    server.wait()
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        try:
            os.kill(relay_pid, 0)
        except ProcessLookupError:
            return
        with open(f"/proc/{relay_pid}/stat") as f:  # reaped by init or a zombie of ours: gone either way
            if f.read().split()[2] == "Z":
                return
        time.sleep(0.05)
    os.kill(relay_pid, signal.SIGKILL)
    pytest.fail("the relay outlived its server by 2 s")


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


def test_a_late_reader_gets_every_byte_the_pty_could_not_take_in_order() -> None:
    from labrig.sim.serial_pty import HOST_BUFFER_BYTES, PtyPort

    port = PtyPort()
    try:
        reader = serial.Serial(port.path, 460800, timeout=0.2)  # opening flushes what the pty held
        sent = bytes(range(256)) * 160  # 40 KiB: more than a pty takes (about 17 KB), less than a host port holds
        for k in range(0, len(sent), 4096):  # a twin's burst after a stall, the reader late
            port.write(sent[k:k + 4096])
        assert port.pending_bytes > 0 and port.dropped_bytes == 0
        got = bytearray()
        deadline = time.monotonic() + 5.0
        while len(got) < len(sent) and time.monotonic() < deadline:
            got += reader.read(65536)
            port.flush()  # the server's tick
        reader.close()
        assert bytes(got) == sent and port.pending_bytes == 0
        port.write(b"z" * (HOST_BUFFER_BYTES + 50_000))  # nobody reads: beyond the pty and the host buffer, lost
        assert port.pending_bytes <= HOST_BUFFER_BYTES and port.dropped_bytes > 0
    finally:
        port.close()
