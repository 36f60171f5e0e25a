"""Bota driver byte conversations against a scripted fake port (exact bytes out and in)."""

from __future__ import annotations

import errno
import logging
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np
import pytest
import serial

from labrig.clock import ManualClock
from labrig.devices.bota import (
    BotaCommandError,
    BotaDisconnected,
    BotaError,
    BotaSensor,
    BotaSettings,
    BotaTimeout,
)
from labrig.devices.bota_protocol import (
    BootInfo,
    CommSetup,
    Frame,
    Offsets,
    Status,
    cmd_config_mode,
    encode_boot_text,
    encode_frame,
)
from labrig.devices.bota_stream import FtSample, SensorState

BOOT = encode_boot_text(BootInfo(name="Rokubi", serial_number="SN42", firmware_version="2.1"), CommSetup())


def frames(t0_us: int, n: int, step_us: int = 1250, status: int = 0, fz: float = 10.0) -> bytes:
    return b"".join(
        encode_frame(Frame(status, (1.0, 2.0, fz), (0.1, 0.2, 0.3), (t0_us + i * step_us) % 2**32, 30.0)) for i in range(n)
    )


class ScriptedPort:
    """A pyserial-like port that answers exact writes from a script.

    ``script``: (bytes the host must write, bytes the device answers, host time [ns]
    at which the answer arrives). Writes are matched in order; anything else is
    recorded in ``mismatches``. ``dtr``: without modem lines (a pty) setting it
    raises ENOTTY; with them a low-high pulse delivers ``dtr_reply``.
    """

    def __init__(
        self,
        script: list[tuple[bytes, bytes, int]],
        clock: ManualClock | None = None,
        *,
        modem_lines: bool = False,
        dtr_reply: bytes = b"",
    ) -> None:
        self.script = deque(script)
        self.clock = clock
        self.modem_lines = modem_lines
        self.dtr_reply = dtr_reply
        self.writes: list[bytes] = []
        self.mismatches: list[bytes] = []
        self.dtr_log: list[bool] = []
        self.port = "scripted"
        self.baudrate = 460800
        self.timeout: float | None = None
        self.write_timeout: float | None = None
        self.is_open = True
        self.broken: Exception | None = None
        self._pending = bytearray()
        self._rx = bytearray()
        self._cond = threading.Condition()

    @property
    def written(self) -> bytes:
        return b"".join(self.writes)

    def deliver(self, data: bytes, t_ns: int | None = None) -> None:
        with self._cond:
            if t_ns is not None and self.clock is not None:
                self.clock.set_ns(max(t_ns, self.clock.now_ns()))
            self._rx += data
            self._cond.notify_all()

    def break_port(self) -> None:
        with self._cond:
            self.broken = serial.SerialException("read failed: [Errno 5] Input/output error")
            self._cond.notify_all()

    # -- the pyserial surface the driver uses --

    @property
    def dtr(self) -> bool:
        return self.dtr_log[-1] if self.dtr_log else True

    @dtr.setter
    def dtr(self, value: bool) -> None:
        if not self.modem_lines:
            raise OSError(errno.ENOTTY, "Inappropriate ioctl for device")
        self.dtr_log.append(value)
        if value and len(self.dtr_log) >= 2 and not self.dtr_log[-2]:
            self.deliver(self.dtr_reply)

    @property
    def in_waiting(self) -> int:
        with self._cond:
            if self.broken:
                raise OSError(errno.EIO, "Input/output error")
            return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        deadline = time.monotonic() + (self.timeout or 0.0)
        with self._cond:
            while not self._rx and not self.broken and time.monotonic() < deadline and self.is_open:
                self._cond.wait(deadline - time.monotonic())
            if self.broken:
                raise self.broken
            out = bytes(self._rx[:size])
            del self._rx[:size]
            return out

    def write(self, data: bytes) -> int:
        self.writes.append(bytes(data))
        self._pending += data
        if self.script:
            expected, reply, t_ns = self.script[0]
            if bytes(self._pending) == expected:
                self.script.popleft()
                self._pending.clear()
                if reply:
                    self.deliver(reply, t_ns)
            elif not expected.startswith(bytes(self._pending)):
                self.mismatches.append(bytes(self._pending))
                self._pending.clear()
        else:
            self.mismatches.append(bytes(data))
        return len(data)

    def flush(self) -> None:
        pass

    def cancel_read(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def close(self) -> None:
        self.is_open = False


def sensor_on(port: ScriptedPort, clock: ManualClock | None = None, **kwargs) -> tuple[BotaSensor, list[FtSample]]:
    got: list[FtSample] = []
    options = {"char_gap_s": 0.0, "ack_timeout_s": 1.0, "read_timeout_s": 0.01, "clock": clock or ManualClock()}
    options.update(kwargs)
    return BotaSensor(port, on_sample=got.append, **options), got


def connect_script() -> list[tuple[bytes, bytes, int]]:
    return [
        (b"#", BOOT + frames(500, 2), 1_000_000),
        (b"C", frames(3000, 1) + b"r,0,C,0\r\n", 2_000_000),
    ]


def test_connect_configure_run_stop_conversation() -> None:
    clock = ManualClock()
    run_frames = frames(10_000, 4)
    script = [
        *connect_script(),
        (b"c,0,1,0,4\n", b"r,0,c,0\r\n", 3_000_000),
        (b"f,64,0,0,1\n", b"r,0,f,0\r\n", 3_100_000),
        (b"b,-0.500,0.000,0.000,0.000,0.000,0.250\n", b"r,0,b,0\r\n", 3_200_000),
        (b"R", b"r,0,R,0\r\n" + run_frames, 4_000_000),
        (b"C", frames(15_000, 1) + b"r,0,C,0\r\n", 5_000_000),
    ]
    port = ScriptedPort(script, clock)
    sensor, got = sensor_on(port, clock)
    info = sensor.connect(boot_settle_s=1.0)
    assert info == BootInfo(True, "Rokubi", "SN42", "2.1", CommSetup())
    assert sensor.state is SensorState.CONFIG and got == []  # boot streaming is not delivered
    sensor.configure(BotaSettings(sinc_length=64, offsets=Offsets((-0.5, 0.0, 0.0), (0.0, 0.0, 0.25))))
    sensor.start()
    deadline = time.monotonic() + 2
    while len(got) < 4 and time.monotonic() < deadline:
        time.sleep(0.001)
    assert sensor.state is SensorState.RUNNING
    sensor.stop()
    assert sensor.state is SensorState.CONFIG
    sensor.close()
    assert port.mismatches == [] and not port.script
    assert port.written == b"#C" + b"c,0,1,0,4\nf,64,0,0,1\nb,-0.500,0.000,0.000,0.000,0.000,0.250\n" + b"RC"
    # Run frames stamped when their bytes arrived; the frame before the C ack is delivered too.
    assert [s.t_device_us for s in got] == [10_000, 11_250, 12_500, 13_750, 15_000]
    assert [s.t_host_ns for s in got] == [4_000_000] * 4 + [5_000_000]
    assert got[0] == FtSample(10_000, 4_000_000, (1.0, 2.0, 10.0), got[0].torque_nm, 0, 30.0)
    assert np.allclose(got[0].torque_nm, (0.1, 0.2, 0.3))
    stats = sensor.stats()
    assert (stats.frames, stats.frames_lost, stats.crc_errors, stats.sync_losses, stats.resyncs) == (5, 0, 0, 0, 0)


def test_reset_by_dtr_pulse_when_the_port_has_modem_lines() -> None:
    port = ScriptedPort([(b"C", b"r,0,C,0\r\n", 0)], modem_lines=True, dtr_reply=BOOT + frames(0, 1))
    sensor, _ = sensor_on(port)
    sensor.connect()
    sensor.close()
    assert port.dtr_log == [False, True] and port.written == b"C"


def test_connect_without_reset_attaches() -> None:
    port = ScriptedPort([(b"C", b"r,0,C,0\r\n", 0)])
    sensor, _ = sensor_on(port)
    assert sensor.connect(reset=False) == BootInfo()
    sensor.close()
    assert port.written == b"C"


def test_commands_are_typed_slowly_with_char_gap() -> None:
    port = ScriptedPort([*connect_script(), (b"c,0,1,0,4\n", b"r,0,c,0\r\n", 0), (b"f,64,0,0,1\n", b"r,0,f,0\r\n", 0)])
    sensor, _ = sensor_on(port, char_gap_s=0.001)
    t = time.monotonic()
    sensor.connect()
    sensor.configure(BotaSettings(sinc_length=64))
    sensor.close()
    assert port.writes[2:4] == [b"c", b","] and all(len(w) == 1 for w in port.writes)
    assert time.monotonic() - t >= 0.02


def test_rejected_command_raises_with_the_code() -> None:
    port = ScriptedPort([*connect_script(), (b"c,0,1,0,4\n", b"r,0,c,0\r\n", 0), (b"f,64,0,0,1\n", b"r,0,f,2\r\n", 0)])
    sensor, _ = sensor_on(port)
    sensor.connect()
    with pytest.raises(BotaCommandError, match=r"rejected 'f,64,0,0,1' \(r,0,f,2\)"):
        sensor.configure(BotaSettings(sinc_length=64))
    assert sensor.state is SensorState.CONFIG
    sensor.close()


def test_missing_ack_times_out() -> None:
    port = ScriptedPort([*connect_script(), (b"c,0,1,0,4\n", b"", 0)])
    sensor, _ = sensor_on(port, ack_timeout_s=0.1)
    sensor.connect()
    t = time.monotonic()
    with pytest.raises(BotaTimeout, match="acknowledgement of 'c,0,1,0,4'"):
        sensor.configure(BotaSettings())
    assert time.monotonic() - t < 0.5
    sensor.close()


def test_no_boot_text_times_out_clearly() -> None:
    port = ScriptedPort([(b"#", b"", 0)])
    sensor, _ = sensor_on(port)
    with pytest.raises(BotaTimeout, match="'App Init' after a reset by '#'"):
        sensor.connect(boot_timeout_s=0.1)
    sensor.close()
    assert sensor.state is SensorState.CLOSED


def test_wrong_state_is_refused() -> None:
    port = ScriptedPort(connect_script())
    sensor, _ = sensor_on(port)
    with pytest.raises(BotaError, match="not connected"):
        sensor.command(cmd_config_mode())
    sensor.connect()
    with pytest.raises(BotaError, match="not streaming"):
        sensor.tare(10)
    sensor.close()


def started(port: ScriptedPort, clock: ManualClock | None = None, **kwargs) -> tuple[BotaSensor, list[FtSample]]:
    sensor, got = sensor_on(port, clock, **kwargs)
    sensor.connect()
    sensor.configure(BotaSettings(sinc_length=64))
    sensor.start()
    return sensor, got


def run_script(after_r: bytes) -> list[tuple[bytes, bytes, int]]:
    return [
        *connect_script(),
        (b"c,0,1,0,4\n", b"r,0,c,0\r\n", 0),
        (b"f,64,0,0,1\n", b"r,0,f,0\r\n", 0),
        (b"R", b"r,0,R,0\r\n" + after_r, 0),
        (b"C", b"r,0,C,0\r\n", 0),
    ]


def wait_for(predicate, timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.001)


def test_gaps_crc_errors_and_garbage_are_counted() -> None:
    good = frames(0, 3)
    bad = bytearray(frames(3750, 1))
    bad[20] ^= 0x40
    stream = good + bytes(bad) + frames(5000, 2) + b"\x00\xaa\xff" + frames(7500, 1) + frames(10_000, 1)
    port = ScriptedPort(run_script(stream))
    sensor, got = started(port)
    wait_for(lambda: len(got) == 7)
    sensor.close()
    s = sensor.stats()
    assert [x.t_device_us for x in got] == [0, 1250, 2500, 5000, 6250, 7500, 10_000]
    assert (s.crc_errors, s.sync_losses, s.resyncs, s.skipped_bytes) == (1, 2, 2, 37 + 3)
    assert (s.frames_lost, s.gaps) == (1 + 1, 2)  # the bad frame (3750) and the missing 8750


def test_clock_jump_stall_and_unexpected_restart_are_reported() -> None:
    from labrig.clock import MonotonicClock

    port = ScriptedPort(run_script(frames(10_000, 3)))
    warnings: list[str] = []
    sensor, got = started(port, MonotonicClock(), stall_timeout_s=0.05, on_warning=warnings.append)
    wait_for(lambda: len(got) == 3)
    port.deliver(frames(500, 1))  # backwards
    wait_for(lambda: sensor.stats().clock_jumps == 1)
    wait_for(lambda: sensor.stats().stalls == 1)
    port.deliver(BOOT + frames(0, 1) + frames(10_000, 1))  # rebooted, now at its saved rate (100 Hz)
    wait_for(lambda: len(got) == 6)
    stats = sensor.stats()
    assert (stats.restarts, stats.frames_lost, stats.clock_jumps) == (1, 0, 1)  # no gap checks after a restart
    assert sensor.boot_info.app_init and sensor.state is SensorState.RUNNING
    assert [w.split(": ", 1)[1][:23] for w in warnings] == [
        "device timestamp steppe",
        "no frame for 0.05 s whi",
        "the sensor restarted by",
        "frame sync lost and fou",  # the boot text cut into the frames
    ]
    sensor.close()


def test_status_bits_are_counted_and_warned_rate_limited(caplog: pytest.LogCaptureFixture) -> None:
    stream = frames(0, 50, status=Status.OVERRANGE) + frames(62_500, 3, status=Status.INVALID_MEASUREMENTS | Status.THROTTLED)
    port = ScriptedPort(run_script(stream))
    warnings: list[str] = []
    with caplog.at_level(logging.WARNING, logger="labrig.devices.bota"):
        sensor, got = started(port, on_warning=warnings.append)
        wait_for(lambda: len(got) == 53)
        sensor.close()
    assert sensor.stats().status_frames == {"overrange": 50, "invalid_measurements": 3, "app_took_too_long": 3}
    assert len(warnings) == 3  # one per kind within the interval, though 56 flags were seen
    assert any("overrange" in w for w in warnings) and any("increase it" in w for w in warnings)
    assert len([r for r in caplog.records if "overrange" in r.getMessage()]) == 1


def test_tare_averages_and_subtracts() -> None:
    port = ScriptedPort(run_script(b""))
    sensor, got = started(port)
    result: list = []
    thread = threading.Thread(target=lambda: result.append(sensor.tare(4)))
    thread.start()
    time.sleep(0.05)
    port.deliver(frames(0, 2, fz=9.0) + frames(2500, 1, fz=99.0, status=Status.OVERRANGE) + frames(3750, 2, fz=11.0))
    thread.join(2)
    assert result[0] == Offsets((1.0, 2.0, 10.0), result[0].torque_nm)  # the overrange frame is left out
    port.deliver(frames(6250, 1, fz=12.5))
    wait_for(lambda: len(got) == 6)
    assert got[-1].force_n == (0.0, 0.0, 2.5)
    assert np.allclose(got[-1].torque_nm, 0.0, atol=1e-7)
    sensor.close()


def test_port_failure_ends_the_reader_and_is_reported() -> None:
    port = ScriptedPort(run_script(frames(0, 2)))
    errors: list[BotaError] = []
    sensor, got = started(port, on_error=errors.append)
    wait_for(lambda: len(got) == 2)
    port.break_port()
    wait_for(lambda: sensor.error is not None)
    assert isinstance(sensor.error, BotaDisconnected) and errors == [sensor.error]
    assert "disconnected" in str(sensor.error) and "reconnect" in str(sensor.error)
    assert "Input/output error" in sensor.reader_exit_reason
    assert sensor.state is SensorState.FAILED
    t = time.monotonic()
    with pytest.raises(BotaDisconnected):
        sensor.stop()
    sensor.close()
    assert time.monotonic() - t < 0.5


def test_callback_error_stops_the_reader() -> None:
    port = ScriptedPort(run_script(frames(0, 1)))
    sensor, _ = sensor_on(port)
    sensor.on_sample = lambda s: 1 / 0
    sensor.connect()
    sensor.configure(BotaSettings(sinc_length=64))
    sensor.start()
    wait_for(lambda: sensor.error is not None)
    assert "ZeroDivisionError" in str(sensor.error)
    sensor.close()


def test_ft_sink_puts_ft_rows(tmp_path: Path) -> None:
    from labrig.protocol.routing import ft_sink
    from labrig.recording import RecordingWriter
    from labrig.recording.reader import Recording

    clock = ManualClock(5_000_000_000)
    writer = RecordingWriter(tmp_path / "ft.h5", clock=clock).open()
    sink = ft_sink(writer)
    for i in range(3):
        sink(
            FtSample(
                (4_294_967_000 + 200 * i) % 2**32, 5_000_000_000 + 1_250_000 * i, (1.0, 2.0, 3.0 + i), (0.1, 0.2, 0.3), i, 25.0
            )
        )
    writer.close()
    with Recording(tmp_path / "ft.h5") as rec:
        ft = rec.stream("ft")
    assert ft["t_host_us"].tolist() == [0, 1250, 2500]
    assert ft["t_device_us"].tolist() == [4_294_967_000, 4_294_967_200, 104]  # raw, wrapped
    assert ft["force_n"][:, 2].tolist() == [3.0, 4.0, 5.0] and ft["status"].tolist() == [0, 1, 2]
