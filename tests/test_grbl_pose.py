"""The GRBL pose model fed by hand (no port, no thread), and the serial link's failure latch."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from labrig.clock import ManualClock
from labrig.devices.grbl_pose import GcodeFollower, LineEffect, PlannedMove, PoseModel
from labrig.devices.grbl_protocol import Status, classify_line, format_status
from labrig.devices.motion_profile import MachineLimits
from labrig.devices.serial_link import LinkFailure, SerialLink

BYTE_US = 10 * 1e6 / 115200


def report(state: str, position: tuple[float, float, float]) -> tuple[Status, int]:
    text = format_status(state, machine_mm=position, feed_mm_min=0.0, spindle_rpm=0.0)
    event = classify_line(text, text.encode())
    assert isinstance(event, Status)
    return event, len(text)


def test_the_follower_tracks_modal_state_and_marks_what_it_cannot_follow() -> None:
    follower = GcodeFollower()
    assert follower.follow(b"G21 G90 G1 X-10 F600 (comment)") == LineEffect((PlannedMove((-10.0, 0.0, 0.0), 600.0),))
    assert follower.follow(b"g91 y-2") == LineEffect((PlannedMove((-10.0, -2.0, 0.0), 600.0),))
    assert follower.follow(b"G20G1Z-1") == LineEffect((PlannedMove((-10.0, -2.0, -25.4), 600.0),))  # F stays mm/min
    assert follower.follow(b"G4P0.5").dwell_s == 0.5
    assert follower.follow(b"G2X1Y1I1").resync and follower.follow(b"$H").resync
    assert follower.follow(b"$J=G90G21X-1F100") == LineEffect((PlannedMove((-1.0, -2.0, -25.4), 100.0, "jog"),))


def test_answered_moves_are_planned_and_a_report_at_rest_anchors_the_pose() -> None:
    pose = PoseModel(BYTE_US)
    pose.limits = MachineLimits(accel_mm_s2=(1000.0, 1000.0, 1000.0))
    idle, n = report("Idle", (0.0, 0.0, 0.0))
    pose.status_report(idle, line_bytes=n, t_us=0, t_query_us=None, lines_in_flight=False)
    effect = pose.line_sent(b"G1X-6F600")  # 10 mm/s: 0.6 s plus the ramps
    assert pose.line_answered(effect, 1_000_000.0, error=False)  # a cycle started
    t = np.array([1_000_000.0, 1_400_000.0, 2_000_000.0])
    x = pose.positions_at(t)[:, 0]
    assert x[0] == pytest.approx(0.0, abs=1e-3) and -6.0 < x[1] < -2.0 and x[2] == pytest.approx(-6.0)
    segments = pose.segments()
    assert segments[-1].end_mm == pytest.approx((-6.0, 0.0, 0.0))
    # The machine says it is at rest elsewhere (steps lost, a reset): the pose jumps there.
    idle, n = report("Idle", (-5.0, 0.0, 0.0))
    pose.status_report(idle, line_bytes=n, t_us=3_000_000, t_query_us=2_999_000, lines_in_flight=False)
    assert pose.positions_at(np.array([3_100_000.0]))[0] == pytest.approx((-5.0, 0.0, 0.0))
    assert pose.link_latency_us == 0.0  # fewer than three answered queries


def test_errors_checks_and_resets_do_not_move_the_pose() -> None:
    pose = PoseModel(BYTE_US)
    assert not pose.line_answered(pose.line_sent(b"G1X-5F600"), 1_000.0, error=True)
    pose.checking = True
    assert not pose.line_answered(pose.line_sent(b"G1X-5F600"), 2_000.0, error=False)
    pose.checking = False
    pose.controller_reset(3_000.0)
    assert pose.positions_at(np.array([10_000_000.0]))[0] == pytest.approx((0.0, 0.0, 0.0))


class _Port:
    """Bytes to read once, then timeouts."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.timeout: float | None = None
        self.written: list[bytes] = []

    @property
    def in_waiting(self) -> int:
        return len(self.data)

    def read(self, size: int = 1) -> bytes:
        out, self.data = self.data[:size], self.data[size:]
        if not out:
            time.sleep(self.timeout or 0.0)
        return out

    def write(self, data: bytes) -> int:
        self.written.append(data)
        return len(data)

    def close(self) -> None:
        pass


def test_a_failing_callback_is_latched_once_and_stops_the_reader() -> None:
    failures: list[Exception] = []
    stopped = threading.Event()

    def broken(data: bytes, t_ns: int) -> None:
        raise ZeroDivisionError("bad chunk")

    link = SerialLink(
        _Port(b"abc"), baudrate=115200, clock=ManualClock(7), error_for=lambda f: RuntimeError(f"{f.kind}: {f.cause}"),
        on_chunk=broken, on_failure=failures.append, on_stop=stopped.set, read_timeout_s=0.001,
    )  # fmt: skip
    link.open()
    link.start()
    assert stopped.wait(2.0)
    assert [str(e) for e in failures] == ["callback: bad chunk"] and link.error is failures[0]
    assert "ZeroDivisionError" in link.exit_reason
    with pytest.raises(RuntimeError, match="callback: bad chunk"):
        link.raise_if_failed()
    assert link.fail(RuntimeError("later")) is failures[0] and len(failures) == 1  # the first failure wins
    link.open()  # a new connection clears the latch
    assert link.error is None and link.write(b"x") == 7
    link.close()


def test_chunks_are_stamped_when_read_and_a_closed_link_refuses_writes() -> None:
    clock = ManualClock(1_000)
    chunks: list[tuple[bytes, int]] = []
    got = threading.Event()

    def on_chunk(data: bytes, t_ns: int) -> None:
        chunks.append((data, t_ns))
        got.set()

    def error_for(failure: LinkFailure) -> Exception:
        return RuntimeError(failure.kind)

    link = SerialLink(_Port(b"ok\r\n"), baudrate=115200, clock=clock, error_for=error_for, on_chunk=on_chunk,
                      read_timeout_s=0.001)
    link.open()
    link.start()
    assert got.wait(2.0)
    assert chunks == [(b"ok\r\n", 1_000)]
    assert link.close()
    with pytest.raises(RuntimeError, match="write"):
        link.write(b"?")
    assert link.error is None  # a write to a closed link is refused, not latched


def test_a_write_is_stamped_before_its_bytes_go_out() -> None:
    """The send stamp is a lower bound of when the device can act (trigger edges' host times rest on it):
    a write that returns late (this thread descheduled, a slow port) must not move it."""
    clock = ManualClock(5_000)

    class SlowPort(_Port):
        def write(self, data: bytes) -> int:
            clock.advance_ns(3_000_000)  # the device acts now; the write returns 3 ms later
            return super().write(data)

    link = SerialLink(SlowPort(b""), baudrate=115200, clock=clock, error_for=lambda f: RuntimeError(f.kind),
                      on_chunk=lambda data, t_ns: None, read_timeout_s=0.001)
    link.open()
    assert link.write(b"M8\n") == 5_000 and clock.now_ns() == 3_005_000
    link.close()
