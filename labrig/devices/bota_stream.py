"""The reader side of a Bota F/T sensor: what the link's reader thread makes of the sensor's bytes.

:class:`BotaStream` feeds each stamped chunk (host ns) to the sans-I/O
:class:`~labrig.devices.bota_protocol.BotaReceiver`, collects the boot text and the
acknowledgements the caller's commands wait for, moves the sensor's state on the ``R``/``C``
acknowledgements, and in RUN mode turns each frame into an :class:`FtSample` (sensor frame, tare
subtracted) for ``on_sample``, counted by :class:`~labrig.devices.bota_health.StreamHealth`,
whose warnings it logs (rate-limited) and hands to ``on_warning``. Everything here is guarded by
:attr:`BotaStream.cond`, on which :class:`~labrig.devices.bota.BotaSensor` waits.
"""

from __future__ import annotations

import enum
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

from labrig.devices.bota_health import StreamHealth, WarningLimiter
from labrig.devices.bota_protocol import (
    Ack,
    AppInit,
    BootInfo,
    BotaReceiver,
    CommSetupLine,
    Event,
    Frame,
    InfoLine,
    TextLine,
    Vector3,
)

log = logging.getLogger("labrig.devices.bota")


class SensorState(enum.Enum):
    CLOSED = "closed"
    BOOTING = "booting"
    CONFIG = "config"
    STARTING = "starting"
    RUNNING = "running"
    STOPPING = "stopping"
    FAILED = "failed"


@dataclass(frozen=True, slots=True)
class FtSample:
    """One sample as handed to ``on_sample``. Sensor frame; tare subtracted."""

    t_device_us: int  # raw uint32 device counter [us]
    t_host_ns: int  # host clock [ns] when the frame's last byte was read
    force_n: Vector3
    torque_nm: Vector3
    status: int
    temperature_c: float


class Collector:
    """Raw samples gathered for :meth:`~labrig.devices.bota.BotaSensor.wait_samples`."""

    def __init__(self, n: int, accept: Callable[[Frame], bool]) -> None:
        self.n = n
        self.accept = accept
        self.samples: list[FtSample] = []


def _no_sample(sample: FtSample) -> None:
    pass


class BotaStream:
    """The sensor's incoming side (see the module docstring); ``port_name`` names it in messages."""

    def __init__(
        self,
        port_name: str,
        *,
        on_sample: Callable[[FtSample], None] | None,
        on_warning: Callable[[str], None] | None,
        stall_timeout_s: float,
        warn_interval_s: float,
    ) -> None:
        self.port_name = port_name
        self.on_sample = on_sample or _no_sample
        self.on_warning = on_warning
        self.stall_timeout_s = stall_timeout_s
        self.cond = threading.Condition()
        self.state = SensorState.CLOSED
        self.receiver = BotaReceiver()
        self.restart_sync = False
        self.acks: list[Ack] = []
        self.boot = BootInfo()
        self.frames_idle = 0  # frames seen outside RUN (boot streaming)
        self.collectors: list[Collector] = []
        self.health = StreamHealth()
        self.tare: tuple[float, ...] = (0.0,) * 6
        self._warnings = WarningLimiter(round(warn_interval_s * 1e9))

    def begin_run(self, period_us: float | None, t_ns: int, *, raw_gauges: bool) -> None:
        """RUN mode was asked for at ``t_ns``: counters restart (``period_us``: the nominal frame
        period, None if unknown), the receiver resynchronises on the first frames."""
        with self.cond:
            self.state = SensorState.STARTING
            self.health = StreamHealth(period_us, t_ns, raw_gauges=raw_gauges)
            self.restart_sync = True

    def expect_boot(self) -> None:
        """A reset was asked for: forget the boot text seen so far."""
        with self.cond:
            self.boot = BootInfo()
            self.frames_idle = 0

    def set_state(self, state: SensorState) -> None:
        """Move to ``state`` (never out of FAILED) and wake the waiters."""
        with self.cond:
            if self.state is not SensorState.FAILED:
                self.state = state
            self.cond.notify_all()

    def warn_all(self, warnings: list[tuple[str, str]], now_ns: int) -> None:
        """Log each warning and tell ``on_warning``, each key at most once per interval."""
        for key, message in warnings:
            self._warn(key, message, now_ns)

    def _warn(self, key: str, message: str, now_ns: int) -> None:
        held = self._warnings.allow(key, now_ns)
        if held is None:
            return
        text = f"F/T sensor on {self.port_name}: {message}" + (f" ({held} more since the last report)" if held else "")
        log.warning("%s", text)
        if self.on_warning is not None:
            self.on_warning(text)

    # -- the reader thread ----------------------------------------------------------------------

    def on_chunk(self, data: bytes, t_ns: int) -> None:
        """A chunk of bytes read at ``t_ns`` (the link's reader thread)."""
        if self.restart_sync:
            self.restart_sync = False
            self.receiver.restart_sync()
        self._handle(self.receiver.feed(data), t_ns)

    def on_idle(self, t_ns: int) -> None:
        """A read that timed out empty at ``t_ns``: a stall while streaming is counted and told."""
        if self.state is not SensorState.RUNNING:
            return
        with self.cond:
            warnings = self.health.quiet(t_ns, self.stall_timeout_s)
        self.warn_all(warnings, t_ns)

    def _handle(self, events: list[Event], t_ns: int) -> None:
        for ev in events:
            if isinstance(ev, Frame):
                self._on_frame(ev, t_ns)
            elif isinstance(ev, Ack):
                self._on_ack(ev)
            elif isinstance(ev, AppInit | InfoLine | CommSetupLine):
                with self.cond:
                    self.boot = self.boot.updated(ev)
                    self.cond.notify_all()
                if isinstance(ev, AppInit) and self.state is not SensorState.BOOTING:
                    self._on_unexpected_boot(t_ns)
            elif isinstance(ev, TextLine):
                log.debug("F/T sensor on %s says %r", self.port_name, ev.text)
            elif self.state is SensorState.RUNNING:
                self._on_sync_event(ev, t_ns)

    def _on_unexpected_boot(self, t_ns: int) -> None:
        with self.cond:
            warnings = self.health.restarted()
        self.warn_all(warnings, t_ns)

    def _on_ack(self, ack: Ack) -> None:
        with self.cond:
            self.acks.append(ack)
            if ack.ok and ack.command == "R" and self.state is SensorState.STARTING:
                self.state = SensorState.RUNNING
            elif ack.ok and ack.command == "C" and self.state is SensorState.STOPPING:
                self.state = SensorState.CONFIG
            self.cond.notify_all()

    def _on_sync_event(self, ev: Event, t_ns: int) -> None:
        with self.cond:
            warnings = self.health.sync_event(ev)
        self.warn_all(warnings, t_ns)

    def _on_frame(self, frame: Frame, t_ns: int) -> None:
        state = self.state
        if state not in (SensorState.RUNNING, SensorState.STOPPING):
            with self.cond:
                self.frames_idle += 1
                if self.frames_idle == 1:
                    self.cond.notify_all()
            return
        raw = FtSample(frame.t_device_us, t_ns, frame.force_n, frame.torque_nm, frame.status, frame.temperature_c)
        with self.cond:
            warnings = self.health.frame(frame, t_ns)
            if self.collectors:
                for collector in self.collectors:
                    if len(collector.samples) < collector.n and collector.accept(frame):
                        collector.samples.append(raw)
                self.cond.notify_all()
        self.warn_all(warnings, t_ns)
        self.on_sample(self.tared(raw))

    def tared(self, s: FtSample) -> FtSample:
        """``s`` less the software tare."""
        t = self.tare
        if not any(t):
            return s
        f, m = s.force_n, s.torque_nm
        return FtSample(
            s.t_device_us,
            s.t_host_ns,
            (f[0] - t[0], f[1] - t[1], f[2] - t[2]),
            (m[0] - t[3], m[1] - t[4], m[2] - t[5]),
            s.status,
            s.temperature_c,
        )
