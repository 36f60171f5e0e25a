"""Device faults, driver against twin over pseudo-terminals: every fault is reported as a typed error that
says what happened and what to do, nothing waits without a bound, and what was recorded before it is kept.

Each driver call that could hang runs through :func:`bounded`, which fails the test instead of hanging.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labrig.devices.bota import BotaDisconnected, BotaSensor, BotaSettings
from labrig.devices.bota_protocol import cmd_config_mode
from labrig.devices.bota_stream import FtSample, SensorState
from labrig.devices.grbl import Grbl, GrblAlarm, GrblConnectionError, GrblTimeout
from labrig.devices.grbl_channel import StatusSample
from labrig.devices.grbl_protocol import Realtime
from labrig.protocol.routing import ft_sink
from labrig.recording import Recording, RecordingWriter
from labrig.sim.bota_twin import BotaTwin, BotaTwinParams
from labrig.sim.grbl_twin import GrblTwin
from labrig.sim.serial_pty import TwinServer

FAST = {110: 6000, 111: 6000, 112: 3000, 120: 1000, 121: 1000, 122: 1000}


def bounded(fn: Callable[[], Any], limit_s: float) -> tuple[Any, BaseException | None, float]:
    """Run ``fn`` in a thread: (result, exception, seconds). A call still running after ``limit_s`` is a hang."""
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["result"] = fn()
        except BaseException as exc:
            box["error"] = exc

    t0 = time.monotonic()
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(limit_s)
    assert not thread.is_alive(), f"{fn} hung for more than {limit_s} s"
    return box.get("result"), box.get("error"), time.monotonic() - t0


def later(delay_s: float, fn: Callable[[], Any]) -> threading.Timer:
    timer = threading.Timer(delay_s, fn)
    timer.start()
    return timer


def wait_until(predicate: Callable[[], bool], timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


# -- GRBL --------------------------------------------------------------------------------------


class OutputTap:
    """Serves a GRBL twin, with faults on demand from the server thread: drop the n-th ``ok``,
    or reset the twin as a power dip or another program writing 0x18 would."""

    def __init__(self, twin: GrblTwin, drop_ok: int | None = None) -> None:
        self.twin = twin
        self.drop_ok = drop_ok
        self.oks = 0
        self.pending = b""
        self.reset_now = threading.Event()

    def receive(self, data: bytes, now_us: int) -> None:
        self.twin.receive(data, now_us)

    def transmit(self, now_us: int) -> bytes:
        if self.reset_now.is_set():
            self.reset_now.clear()
            self.twin.receive(Realtime.SOFT_RESET, now_us)
        self.pending += self.twin.transmit(now_us)
        *lines, self.pending = self.pending.split(b"\n")
        out = b""
        for line in lines:
            if line == b"ok\r":
                self.oks += 1
                if self.oks == self.drop_ok:
                    continue
            out += line + b"\n"
        return out


@contextlib.contextmanager
def grbl_rig(drop_ok: int | None = None, **grbl_kwargs: Any) -> Iterator[tuple[GrblTwin, OutputTap, TwinServer, Grbl]]:
    twin = GrblTwin(settings=FAST, power_on_physical_mm=(-2.0, -2.0, -1.0))
    tap = OutputTap(twin, drop_ok)
    with TwinServer({"grbl": tap}) as server:
        grbl = Grbl(server.paths["grbl"], **grbl_kwargs)
        try:
            yield twin, tap, server, grbl
        finally:
            grbl.close()
        assert server.error is None


def start_stream(grbl: Grbl, lines: list[str], **kwargs: Any) -> tuple[threading.Thread, list[BaseException]]:
    errors: list[BaseException] = []

    def run() -> None:
        try:
            grbl.stream(lines, **kwargs)
        except BaseException as exc:
            errors.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, errors


def test_grbl_unplugged_mid_stream_fails_fast_and_the_recording_keeps_what_came(tmp_path: Path) -> None:
    writer = RecordingWriter(tmp_path / "cnc.h5").open()
    samples: list[StatusSample] = []
    log: list[tuple[int, int, bytes]] = []

    def on_sample(s: StatusSample) -> None:
        samples.append(s)
        writer.put("cnc", **s.columns())

    def on_gcode(t: int, d: int, line: bytes) -> None:
        log.append((t, d, line))
        writer.put("gcode", t_host_us=t, direction=d, line=line)

    with grbl_rig(on_sample=on_sample, on_gcode=on_gcode, clock=writer.clock, time_base_ns=writer.t0_host_ns) as (
        twin,
        _,
        server,
        grbl,
    ):
        grbl.connect()
        thread, errors = start_stream(grbl, [f"G1X-{i}Y-{i}F300" for i in range(1, 40)], timeout_s=60)
        wait_until(lambda: sum(s.state == "Run" for s in samples) >= 3)
        server.unplug("grbl")
        thread.join(2.0)
        assert not thread.is_alive(), "the stream hung on a vanished port"
        assert isinstance(errors[0], GrblConnectionError)
        assert "unplugged" in str(errors[0]) and "reconnect" in str(errors[0])
        for call in (grbl.status, lambda: grbl.send("G4P0"), grbl.wait_idle):
            _, error, took = bounded(call, 1.0)
            assert isinstance(error, GrblConnectionError) and took < 0.5
        sent = [line for _, d, line in log if d == 0 and line not in Realtime.ALL]
        assert len(sent) == grbl.protocol.lines_sent  # every line written was logged, even the last ones
        executed = list(twin.received)
        assert [line.encode() for line in executed] == sent[: len(executed)]
    writer.abort(f"CNC failed: {errors[0]}")
    with Recording(tmp_path / "cnc.h5") as rec:
        cnc, gcode, status = rec.stream("cnc"), rec.stream("gcode"), rec.exit_status
    assert status == "aborted"
    assert cnc["t_host_us"].tolist() == [s.t_host_us for s in samples] and len(samples) >= 4
    assert cnc["position_mm"].tolist() == [list(s.position_mm) for s in samples]
    assert gcode["line"].tolist() == [line for _, _, line in log]


def test_grbl_hard_limit_mid_move_is_a_prompt_alarm_then_reset_and_unlock_recover() -> None:
    with grbl_rig() as (twin, _, server, grbl):
        grbl.connect()
        grbl.move_to(-20, feed_mm_min=1200)
        later(0.2, lambda: twin.trip_hard_limit(server.now_us()))
        _, error, took = bounded(lambda: grbl.wait_idle(timeout_s=30), 3.0)
        assert isinstance(error, GrblAlarm) and error.code == 1 and error.critical and took < 1.0
        assert str(error).startswith("ALARM:1 hard limit triggered; position likely lost")
        _, error, took = bounded(grbl.status, 2.0)  # GRBL ignores '?' now: say so at once
        assert isinstance(error, GrblAlarm) and "soft_reset()" in str(error) and took < 0.2
        _, error, _ = bounded(lambda: grbl.send("$X"), 2.0)
        assert isinstance(error, GrblAlarm) and "soft_reset()" in str(error)
        stopped = twin.position_mm(server.now_us())[0]
        assert -19 < stopped[0] < -0.5  # stopped dead on the way
        info = grbl.soft_reset()
        assert info.state == "Alarm" and "'$H'|'$X' to unlock" in info.messages
        assert grbl.position_mm == pytest.approx(tuple(stopped), abs=1e-3)
        grbl.unlock()
        grbl.move_by(dx=-1, feed_mm_min=1200, wait=True)
        assert grbl.position_mm[0] == pytest.approx(stopped[0] - 1.0, abs=0.004)  # type: ignore[index]
        assert grbl.pose_at(grbl.now_us())[0] == pytest.approx(stopped[0] - 1.0, abs=0.004)


def test_grbl_hard_limit_while_streaming_keeps_the_line_accounting_sane() -> None:
    with grbl_rig() as (twin, _, server, grbl):
        grbl.connect()
        program = [f"G1X-{0.5 * i:.1f}F1200" for i in range(1, 31)]  # more than the planner holds
        thread, errors = start_stream(grbl, program)
        wait_until(lambda: twin.planner_blocks >= 15)
        twin.trip_hard_limit(server.now_us())
        thread.join(1.0)
        assert not thread.is_alive() and isinstance(errors[0], GrblAlarm) and errors[0].code == 1
        assert grbl.protocol.locked and grbl.protocol.in_flight  # GRBL sits on them until the reset
        grbl.soft_reset()
        assert grbl.protocol.in_flight == () and grbl.protocol.in_flight_bytes == 0
        assert grbl.protocol.unmatched_responses == 0  # the late ok answered the line GRBL was busy with
        grbl.unlock()
        x0 = grbl.position_mm[0]  # type: ignore[index]
        grbl.stream([f"G91G1X-{0.1:.1f}F3000"] * 10 + ["G90"])
        assert grbl.wait_idle().position_mm[0] == pytest.approx(x0 - 1.0, abs=0.004)
        assert twin.rx_overflow_bytes == 0 and grbl.protocol.max_in_flight_bytes <= 127


def test_grbl_lost_ok_times_out_then_soft_reset_restores_the_accounting() -> None:
    with grbl_rig(drop_ok=3, response_timeout_s=0.3) as (twin, _, _, grbl):
        grbl.connect(read_settings=False)
        _, error, took = bounded(lambda: grbl.stream([f"G1X-{i}F6000" for i in range(1, 6)]), 3.0)
        assert isinstance(error, GrblTimeout) and took < 2.0
        assert "so the 'ok' was lost" in str(error) and "soft_reset() clears the line accounting" in str(error)
        stuck = grbl.protocol.in_flight
        assert len(stuck) == 1 and grbl.protocol.in_flight_bytes == stuck[0].n_bytes  # one answer short, never negative
        _, error, took = bounded(lambda: grbl.send("G4P0"), 2.0)  # still one answer short: said again, no hang
        assert isinstance(error, GrblTimeout) and took < 0.5
        grbl.soft_reset()
        assert grbl.protocol.in_flight == () and grbl.protocol.unmatched_responses == 0
        grbl.stream([f"G1X-{0.2 * i:.1f}Y-1F6000" for i in range(1, 41)])
        assert grbl.wait_idle().position_mm == (-8.0, -1.0, 0.0)
        assert twin.rx_overflow_bytes == 0 and twin.max_rx_fill_bytes <= 127


def test_grbl_unexpected_reset_mid_stream_is_alarm_3_and_the_driver_resyncs_on_the_banner() -> None:
    with grbl_rig() as (twin, tap, _, grbl):
        grbl.connect()
        thread, errors = start_stream(grbl, [f"G1X-{0.5 * i:.1f}F1200" for i in range(1, 31)])
        wait_until(lambda: twin.planner_blocks >= 15)
        tap.reset_now.set()  # a reset the driver did not ask for
        thread.join(1.0)
        assert not thread.is_alive() and isinstance(errors[0], GrblAlarm) and errors[0].code == 3
        assert "reset and dropped" in str(errors[0]) and "re-home" in str(errors[0])
        assert grbl.protocol.in_flight == () and not grbl.protocol.reset_pending
        sample = grbl.status()
        where = twin.position_mm(grbl.now_us())[0]
        assert sample.state == "Alarm" and sample.position_mm == pytest.approx(tuple(where), abs=1e-3)
        grbl.unlock()
        grbl.move_by(dx=-1, feed_mm_min=3000, wait=True)
        assert grbl.pose_at(grbl.now_us()) == pytest.approx(where - [1.0, 0, 0], abs=0.004)


def test_grbl_stream_held_by_a_feed_hold_waits_without_timing_out_and_a_reset_releases_it() -> None:
    with grbl_rig(response_timeout_s=0.2) as (twin, _, _, grbl):
        grbl.connect()
        grbl.move_to(-20, feed_mm_min=1200)
        grbl.feed_hold()
        thread, errors = start_stream(grbl, [f"G1X-{20 + 0.1 * i:.1f}" for i in range(1, 31)])
        held_since = time.monotonic()
        # planner full: GRBL withholds the ok (waited for, not slept: a loaded host is slow to fill it)
        wait_until(lambda: twin.planner_blocks == 15 and bool(grbl.protocol.in_flight), timeout_s=5.0)
        time.sleep(max(0.0, 0.6 - (time.monotonic() - held_since)))  # three response timeouts
        assert not errors, f"a hold holds back oks, that is no fault: {errors!r}"
        assert thread.is_alive(), "the stream must still be waiting"
        assert twin.state.startswith("Hold"), twin.state
        _, error, took = bounded(grbl.soft_reset, 3.0)
        assert error is None and took < 1.0
        thread.join(1.0)
        assert not thread.is_alive() and isinstance(errors[0], GrblAlarm) and errors[0].code == 3
        assert grbl.protocol.in_flight == () and grbl.status().state == "Alarm"


# -- Bota ----------------------------------------------------------------------------------------


@contextlib.contextmanager
def bota_rig(**sensor_kwargs: Any) -> Iterator[tuple[BotaTwin, TwinServer, BotaSensor]]:
    twin = BotaTwin(BotaTwinParams(boot_delay_us=50_000))
    with TwinServer({"ft": twin}) as server:
        wait_until(lambda: twin.mode == "run")
        sensor = BotaSensor(server.paths["ft"], char_gap_s=0.001, **sensor_kwargs)
        try:
            yield twin, server, sensor
        finally:
            sensor.close()
        assert server.error is None


def test_bota_unplugged_mid_stream_keeps_the_recorded_frames(tmp_path: Path) -> None:
    writer = RecordingWriter(tmp_path / "ft.h5").open()
    sink = ft_sink(writer)
    got: list[FtSample] = []
    errors: list[Exception] = []

    def on_sample(sample: FtSample) -> None:
        got.append(sample)
        sink(sample)

    with bota_rig(clock=writer.clock, on_sample=on_sample, on_error=errors.append) as (_, server, sensor):
        sensor.connect(boot_timeout_s=2.0)
        sensor.configure(BotaSettings(sinc_length=64))
        sensor.start()
        wait_until(lambda: len(got) >= 200)
        server.unplug("ft")
        wait_until(lambda: sensor.error is not None and bool(errors), 1.0)  # the callback follows the error
        assert isinstance(sensor.error, BotaDisconnected) and errors == [sensor.error]
        assert "disconnected" in str(sensor.error) and "reconnect" in str(sensor.error)
        n = len(got)
        time.sleep(0.05)
        assert len(got) == n and sensor.state is SensorState.FAILED  # nothing after the fault
    writer.abort(f"F/T sensor failed: {errors[0]}")
    with Recording(tmp_path / "ft.h5") as rec:
        ft, status = rec.stream("ft"), rec.exit_status
    assert status == "aborted" and len(ft["t_device_us"]) == n
    assert ft["t_device_us"].tolist() == [s.t_device_us for s in got]
    assert ft["t_host_us"].tolist() == [(s.t_host_ns - writer.t0_host_ns) // 1000 for s in got]
    assert np.array_equal(ft["force_n"], np.array([s.force_n for s in got], dtype=ft["force_n"].dtype))
    assert set(np.diff(ft["t_device_us"]).tolist()) == {1250}  # every frame up to the fault, none lost


def test_bota_unplugged_while_a_caller_waits_for_samples_raises_at_once() -> None:
    with bota_rig() as (_, server, sensor):
        sensor.connect(boot_timeout_s=2.0)
        sensor.configure(BotaSettings(sinc_length=512))
        sensor.start()
        later(0.1, lambda: server.unplug("ft"))
        _, error, took = bounded(lambda: sensor.tare(10_000, timeout_s=60), 2.0)  # would take 100 s
        assert isinstance(error, BotaDisconnected) and took < 0.5
        _, error, took = bounded(lambda: sensor.command(cmd_config_mode()), 1.0)
        assert isinstance(error, BotaDisconnected) and took < 0.1
        _, error, took = bounded(sensor.close, 2.0)
        assert error is None and sensor.state is SensorState.CLOSED

