"""The health of a Bota sensor's frame stream, sans I/O: counters, losses, clock jumps, status bits, stalls.

:class:`StreamHealth` is fed what the reader sees while the sensor streams (frames with their host
receive time in ns, sync events, boot text, quiet reads) and answers with the warnings to give,
as ``(key, text)``; :class:`WarningLimiter` keeps each key to one message per interval. Frames
lost are found from the device timestamps (us, a wrapping uint32 counter) against the nominal
period.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from labrig.devices.bota_protocol import (
    STATUS_ADVICE,
    TIMESTAMP_MODULUS,
    CrcError,
    Event,
    Frame,
    Status,
    SyncAcquired,
    SyncLost,
)

Warning = tuple[str, str]


@dataclass(frozen=True)
class BotaStats:
    """Streaming counters since the last :meth:`~labrig.devices.bota.BotaSensor.start`."""

    frames: int = 0
    frames_lost: int = 0  # from device timestamp steps longer than the nominal period
    gaps: int = 0  # places where frames were lost
    crc_errors: int = 0
    sync_losses: int = 0
    resyncs: int = 0
    skipped_bytes: int = 0
    clock_jumps: int = 0  # device timestamp steps that are zero or backwards
    stalls: int = 0  # no frame for stall_timeout_s while running
    restarts: int = 0  # boot text seen while connected (power dip, watchdog)
    status_frames: dict[str, int] = field(default_factory=dict)  # frames with each status bit set


class StreamHealth:
    """Counters and warnings of one streaming run.

    ``period_us``: the nominal frame period (None: unknown, no loss detection); ``t_ns``: when the
    run started (host ns; None: not started, no stall detection); ``raw_gauges``: the sensor was
    asked for raw gauge values, so the raw-measurement status bit is expected.
    """

    def __init__(self, period_us: float | None = None, t_ns: int | None = None, *, raw_gauges: bool = False) -> None:
        self.period_us = period_us
        self.raw_gauges = raw_gauges
        self._counts = {f.name: 0 for f in fields(BotaStats) if f.name != "status_frames"}
        self._status_frames: dict[str, int] = {}
        self._last_t_device: int | None = None
        self._last_frame_ns = t_ns
        self._stalled = False

    def snapshot(self) -> BotaStats:
        return BotaStats(**self._counts, status_frames=dict(self._status_frames))

    def frame(self, frame: Frame, t_ns: int) -> list[Warning]:
        """A frame received at ``t_ns`` while streaming."""
        self._last_frame_ns = t_ns
        self._stalled = False
        c = self._counts
        c["frames"] += 1
        lost = self._lost_before(frame.t_device_us)
        warnings: list[Warning] = []
        if lost > 0:
            c["frames_lost"] += lost
            c["gaps"] += 1
            warnings.append(("gap", f"{lost} frame(s) lost before device time {frame.t_device_us} us"))
        elif lost < 0:
            c["clock_jumps"] += 1
            warnings.append(("clock", f"device timestamp stepped back or stood still at {frame.t_device_us} us"))
        for bit, advice in STATUS_ADVICE.items():
            if frame.status & bit:
                name = str(bit.name).lower()
                self._status_frames[name] = self._status_frames.get(name, 0) + 1
                if not (bit is Status.RAW_MEASUREMENTS and self.raw_gauges):
                    warnings.append((f"status:{bit.name}", advice))
        return warnings

    def sync_event(self, event: Event) -> list[Warning]:
        """A CRC error, a sync loss or a resync while streaming."""
        c = self._counts
        if isinstance(event, CrcError):
            c["crc_errors"] += 1
            return [("crc", "frame with a bad CRC dropped (noise on the line?)")]
        if isinstance(event, SyncLost):
            c["sync_losses"] += 1
        elif isinstance(event, SyncAcquired) and event.resync:
            c["skipped_bytes"] += event.skipped_bytes
            c["resyncs"] += 1
            return [("resync", f"frame sync lost and found again ({event.skipped_bytes} bytes skipped)")]
        return []

    def restarted(self) -> list[Warning]:
        """Boot text while connected: the sensor restarted by itself and streams its saved configuration."""
        self._counts["restarts"] += 1
        self.period_us = None  # the saved configuration's period may differ
        return [("restart", "the sensor restarted by itself (power dip?) and runs its saved configuration; "
                 "stop, configure and start again")]

    def quiet(self, now_ns: int, stall_timeout_s: float) -> list[Warning]:
        """No bytes came for a read: a stall once no frame came for ``stall_timeout_s`` (counted once per stall)."""
        if self._last_frame_ns is None or self._stalled or now_ns - self._last_frame_ns <= stall_timeout_s * 1e9:
            return []
        self._stalled = True
        self._counts["stalls"] += 1
        return [("stall", f"no frame for {stall_timeout_s:g} s while streaming; check the sensor")]

    def _lost_before(self, t_device_us: int) -> int:
        """Frames lost before this one (from the device timestamps); -1 for a backwards step."""
        last, self._last_t_device = self._last_t_device, t_device_us
        if last is None or self.period_us is None:
            return 0
        delta = (t_device_us - last) % TIMESTAMP_MODULUS
        if delta == 0 or delta > TIMESTAMP_MODULUS // 2:
            return -1
        return max(0, round(delta / self.period_us) - 1)


class WarningLimiter:
    """At most one message per key per interval; counts what it held back."""

    def __init__(self, interval_ns: int) -> None:
        self.interval_ns = interval_ns
        self._last: dict[str, int] = {}
        self._held: dict[str, int] = {}

    def allow(self, key: str, now_ns: int) -> int | None:
        """None: stay quiet; else the number of occurrences held back since the last message."""
        last = self._last.get(key)
        if last is not None and now_ns - last < self.interval_ns:
            self._held[key] = self._held.get(key, 0) + 1
            return None
        self._last[key] = now_ns
        return self._held.pop(key, 0)
