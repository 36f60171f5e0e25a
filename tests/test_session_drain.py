"""RigSession.end drains a lagging camera: it waits while events keep coming, reports a stalled one."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from types import SimpleNamespace

from labrig.clock import ClockModel
from labrig.config import RigConfig
from labrig.protocol.rigfile import DeviceConfig
from labrig.protocol.safety import SafetyLimits
from labrig.protocol.session import RigSession

NS_PER_US = 1000


@dataclass
class _Writer:
    """What end() asks of a recording writer: its host origin and live camera clock model (camera = host time)."""

    t0_host_ns: int = 0

    def clock_model(self, device: str) -> ClockModel:
        return ClockModel(method="envelope", n_pairs=2)


def _session(rig: RigConfig) -> RigSession:
    session = RigSession(rig, DeviceConfig(), SafetyLimits())
    session.camera = SimpleNamespace(error=None)  # type: ignore[assignment]  # a camera is attached, streaming fine
    session._writer = _Writer()  # type: ignore[assignment]
    return session


def _deliver(session: RigSession, upto_us: int, step_us: int, every_s: float) -> threading.Thread:
    """Events arriving late: a chunk every ``every_s`` advancing the camera's time by ``step_us``."""

    def run() -> None:
        t = session.last_camera_device_us
        while t < upto_us:
            time.sleep(every_s)
            t = min(t + step_us, upto_us)
            session.last_camera_device_us = t
            session.last_camera_ns = time.monotonic_ns()  # arrival: always after the run's end

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_a_camera_that_lags_but_keeps_delivering_is_drained_to_the_end(rig: RigConfig) -> None:
    session = _session(rig)
    session.last_camera_device_us = 1_000_000
    end_ns = 2_000_000 * NS_PER_US  # the camera is a full second behind, catching up at 1/4 real time
    thread = _deliver(session, 2_000_000, 25_000, 0.1)
    start = time.monotonic()
    behind_us = session.end(end_ns, stall_s=0.5, limit_s=30.0)
    thread.join()
    assert behind_us == 0 and session.last_camera_device_us == 2_000_000
    assert time.monotonic() - start > 3.0  # longer than any stall: the wait follows progress


def test_a_stalled_camera_is_given_up_after_the_stall_time_and_the_shortfall_is_reported(rig: RigConfig) -> None:
    session = _session(rig)
    session.last_camera_device_us = 1_200_000
    session.last_camera_ns = 10**15  # a chunk that arrived late: its arrival time says nothing about its events
    start = time.monotonic()
    behind_us = session.end(2_000_000 * NS_PER_US, stall_s=0.3, limit_s=30.0)
    assert 0.3 <= time.monotonic() - start < 2.0
    assert behind_us == 800_000
