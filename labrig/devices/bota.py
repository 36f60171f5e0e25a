"""Driver for Bota serial F/T sensors (Rokubi / SensONE serial) on a pyserial port.

Life cycle::

    sensor = BotaSensor("/dev/ttyUSB0", clock=clock, on_sample=samples.append)
    sensor.connect()                       # reset, wait for "App Init", CONFIG mode
    sensor.configure(BotaSettings(sinc_length=64))   # 800 Hz
    sensor.start()                         # RUN mode: samples reach on_sample
    sensor.tare(256)                       # software tare from here on
    ...
    sensor.close()                         # CONFIG mode, reader stopped, port closed

One reader thread (a :class:`~labrig.devices.serial_link.SerialLink`) owns the
input side from :meth:`BotaSensor.connect` on. It stamps every chunk of bytes on
the host clock (an injectable :class:`labrig.clock.HostClock`, integer ns) the
moment the read returns; the sensor feeds the chunk to the sans-I/O
:class:`~labrig.devices.bota_protocol.BotaReceiver`, and for each frame in RUN
mode calls ``on_sample`` with an :class:`FtSample` (from the reader thread: keep
it short). Acknowledgements and boot text wake the caller's command methods.
Every wait has a timeout. When the port fails (unplugged), the reader ends,
:attr:`BotaSensor.error` says why, ``on_error`` is called, and every later call
raises that error at once.

Counters (:meth:`BotaSensor.stats`, since :meth:`BotaSensor.start`, kept by
:class:`~labrig.devices.bota_health.StreamHealth`): frames, CRC errors, sync
losses and resyncs, skipped bytes, and frames lost, found from the device
timestamps against the nominal period. Status bits are counted and logged as
warnings (``labrig.devices.bota`` logger, and ``on_warning``), at most once per
``warn_interval_s`` per kind.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from labrig.clock import HostClock, MonotonicClock
from labrig.devices.bota_health import BotaStats, StreamHealth, WarningLimiter
from labrig.devices.bota_protocol import (
    BAUD_RATES,
    Ack,
    AppInit,
    BootInfo,
    BotaReceiver,
    Command,
    CommSetup,
    CommSetupLine,
    Event,
    FilterSetup,
    Frame,
    InfoLine,
    Offsets,
    ReceiverCounters,
    Status,
    TextLine,
    Vector3,
    cmd_comm_setup,
    cmd_config_mode,
    cmd_filter,
    cmd_hardware_reset,
    cmd_offsets,
    cmd_run_mode,
    cmd_save,
)
from labrig.devices.serial_link import LinkFailure, SerialLink, SerialPort
from labrig.errors import LabrigError

log = logging.getLogger(__name__)

DEFAULT_BAUD_RATE = 460_800


class BotaError(LabrigError):
    """The F/T sensor cannot be used as asked; the message says what to do."""


class BotaTimeout(BotaError):
    """The sensor did not answer in time."""


class BotaDisconnected(BotaError):
    """The port failed (unplugged, powered off); reconnect."""


class BotaCommandError(BotaError):
    """The sensor rejected a command (non-zero return code)."""


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


@dataclass(frozen=True)
class BotaSettings:
    """What :meth:`BotaSensor.configure` sets. Sample rate = 51200 / sinc_length Hz.

    ``offsets``: hardware offsets (``b``) to send, or None to leave them.
    ``save``: also store the configuration in the sensor (``s``); a baud code
    other than the current one is always saved, since it only takes effect
    after a save and a reset.
    """

    sinc_length: int = 64
    chop: bool = False
    fast: bool = False
    fir_disable: bool = True
    temperature_compensation: bool = False
    calibrated: bool = True
    baud_code: int = 4
    offsets: Offsets | None = None
    save: bool = False

    def __post_init__(self) -> None:
        self.filter_setup  # noqa: B018 - validates the ranges
        self.comm_setup  # noqa: B018

    @property
    def filter_setup(self) -> FilterSetup:
        return FilterSetup(self.sinc_length, self.chop, self.fast, self.fir_disable)

    @property
    def comm_setup(self) -> CommSetup:
        return CommSetup(self.temperature_compensation, self.calibrated, 0, self.baud_code)

    @property
    def sample_rate_hz(self) -> float:
        return self.filter_setup.sample_rate_hz

    @property
    def period_us(self) -> float:
        return self.filter_setup.period_us


class _Collector:
    """Raw samples gathered for :meth:`BotaSensor.wait_samples`."""

    def __init__(self, n: int, accept: Callable[[Frame], bool]) -> None:
        self.n = n
        self.accept = accept
        self.samples: list[FtSample] = []


def _no_sample(sample: FtSample) -> None:
    pass


class BotaSensor:
    """A Bota serial F/T sensor on a pyserial port (an open port object, or a port name / URL).

    ``clock``: the host clock samples are stamped with (share it with the recording).
    ``on_sample``: called from the reader thread for every frame in RUN mode.
    ``on_error``: called once from the reader thread when it ends on a failure.
    ``on_warning``: called with each (rate-limited) warning text.
    ``terminator``: ends commands with arguments (single-letter commands go bare).
    ``char_gap_s``: pause between the characters of a command (the sensor's
    input buffer is small; Bota's ROS driver uses 5 ms); 0 writes at once.
    ``stall_timeout_s``: no frame for this long while running is reported.
    """

    def __init__(
        self,
        port: SerialPort | str,
        *,
        baudrate: int = DEFAULT_BAUD_RATE,
        clock: HostClock | None = None,
        on_sample: Callable[[FtSample], None] | None = None,
        on_error: Callable[[BotaError], None] | None = None,
        on_warning: Callable[[str], None] | None = None,
        terminator: bytes = b"\n",
        char_gap_s: float = 0.005,
        ack_timeout_s: float = 1.0,
        read_timeout_s: float = 0.05,
        write_timeout_s: float = 1.0,
        stall_timeout_s: float = 0.5,
        warn_interval_s: float = 5.0,
    ) -> None:
        self._port_arg = port
        self.baudrate = baudrate
        self.clock = clock or MonotonicClock()
        self.on_sample = on_sample or _no_sample
        self.on_error = on_error
        self.on_warning = on_warning
        self.terminator = terminator
        self.char_gap_s = char_gap_s
        self.ack_timeout_s = ack_timeout_s
        self.read_timeout_s = read_timeout_s
        self.write_timeout_s = write_timeout_s
        self.stall_timeout_s = stall_timeout_s

        self._link = SerialLink(
            port,
            baudrate=baudrate,
            clock=self.clock,
            error_for=self._error_for,
            on_chunk=self._on_chunk,
            on_idle=self._on_idle,
            on_failure=self._on_failure,
            read_timeout_s=read_timeout_s,
            write_timeout_s=write_timeout_s,
            low_latency=True,
            thread_name=f"labrig-bota:{port if isinstance(port, str) else 'port'}",
        )
        self.port_name = self._link.name
        self._receiver = BotaReceiver()
        self._cond = threading.Condition()
        self._state = SensorState.CLOSED
        self._connected = False
        self._restart_sync = False
        self._acks: list[Ack] = []
        self._boot = BootInfo()
        self._frames_idle = 0  # frames seen outside RUN (boot streaming)
        self._collectors: list[_Collector] = []
        self._settings: BotaSettings | None = None
        self._health = StreamHealth()
        self._tare: tuple[float, ...] = (0.0,) * 6
        self._warnings = WarningLimiter(round(warn_interval_s * 1e9))

    # -- properties ------------------------------------------------------------

    @property
    def state(self) -> SensorState:
        return self._state

    @property
    def error(self) -> BotaError | None:
        """The failure that ended the reader thread, if any."""
        error = self._link.error
        assert error is None or isinstance(error, BotaError)
        return error

    @property
    def reader_exit_reason(self) -> str:
        """Why the reader thread ended ("" while it runs or before it starts)."""
        return self._link.exit_reason

    @property
    def boot_info(self) -> BootInfo:
        return self._boot

    @property
    def settings(self) -> BotaSettings | None:
        return self._settings

    @property
    def tare_offset(self) -> Offsets:
        """The software tare subtracted from every sample [N, N m]."""
        t = self._tare
        return Offsets((t[0], t[1], t[2]), (t[3], t[4], t[5]))

    def stats(self) -> BotaStats:
        with self._cond:
            return self._health.snapshot()

    def receiver_counters(self) -> ReceiverCounters:
        """The byte-level totals since connect (all modes)."""
        return self._receiver.counters()

    # -- life cycle ------------------------------------------------------------------

    def connect(self, *, reset: bool = True, boot_timeout_s: float = 10.0, boot_settle_s: float = 0.5) -> BootInfo:
        """Open the port, reset the sensor and wait out its boot, then enter CONFIG mode.

        Opening a real port pulses DTR, which reboots the sensor (Arduino
        bootloader). The reset pulses DTR again; a port without modem lines (a
        pty) refuses that with ENOTTY, and ``#`` is sent instead. Then the boot
        text must bring ``App Init`` within ``boot_timeout_s``; the rest of it is
        collected until frames stream or ``boot_settle_s`` passes.
        ``reset=False`` attaches to a sensor that is already up.
        """
        if self._state is not SensorState.CLOSED:
            raise BotaError(f"F/T sensor on {self.port_name} is already connected; close() it first")
        self._link.open()
        self._connected = True
        self._set_state(SensorState.BOOTING if reset else SensorState.CONFIG)
        self._link.start()
        try:
            if reset:
                self._reboot(boot_timeout_s, boot_settle_s)
            self.command(cmd_config_mode())
        except BaseException:
            self.close()  # a later connect() starts afresh
            raise
        self._set_state(SensorState.CONFIG)
        return self._boot

    def configure(self, settings: BotaSettings) -> None:
        """Send the comm setup, filter and offsets (CONFIG mode).

        A new baud code is saved and the sensor reset (it only takes effect
        then); the port follows to the new rate and the boot is waited out again.
        """
        self._require(SensorState.CONFIG, "configure")
        comm = settings.comm_setup
        current = self._boot.comm_setup.baud_code if self._boot.comm_setup else _baud_code(self._port_baudrate())
        self.command(cmd_comm_setup(comm))
        self.command(cmd_filter(settings.filter_setup))
        if settings.offsets is not None:
            self.command(cmd_offsets(settings.offsets))
        if settings.save or comm.baud_code != current:
            self.command(cmd_save(), timeout_s=max(self.ack_timeout_s, 2.0))
        if comm.baud_code != current:
            self._set_state(SensorState.BOOTING)
            self._reboot(10.0, 0.5, new_baud=comm.baud_rate)
            self.command(cmd_config_mode())
            self._set_state(SensorState.CONFIG)
        self._settings = settings

    def start(self) -> None:
        """RUN mode: frames stream and reach ``on_sample``. Counters restart."""
        self._require(SensorState.CONFIG, "start")
        with self._cond:
            self._state = SensorState.STARTING
            settings = self._settings
            raw_gauges = settings is not None and not settings.calibrated
            self._health = StreamHealth(settings.period_us if settings else None, self.clock.now_ns(), raw_gauges=raw_gauges)
            self._restart_sync = True
        try:
            self.command(cmd_run_mode())  # the reader switches to RUNNING on the ack, before the frames
        except BotaError:
            with self._cond:
                if self._state is SensorState.STARTING:
                    self._state = SensorState.CONFIG
            raise

    def stop(self) -> None:
        """Back to CONFIG mode: streaming stops. Frames before the acknowledgement are still delivered."""
        self._raise_if_failed()
        if self._state not in (SensorState.RUNNING, SensorState.STARTING):
            return
        self._set_state(SensorState.STOPPING)
        try:
            self.command(cmd_config_mode())
        finally:
            with self._cond:
                if self._state is SensorState.STOPPING:
                    self._state = SensorState.CONFIG

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop streaming (if the port still works), end the reader, close the port if we opened it."""
        if self._state is SensorState.CLOSED and not self._connected:
            return
        in_reader = self._link.in_reader_thread()  # close() from a callback: no waiting on acks
        if self.error is None and not in_reader and self._state in (SensorState.RUNNING, SensorState.STARTING):
            try:
                self.stop()
            except BotaError as exc:
                log.warning("F/T sensor on %s: could not stop streaming cleanly: %s", self.port_name, exc)
        self._link.close(timeout_s)
        self._connected = False
        with self._cond:
            self._state = SensorState.CLOSED
            self._cond.notify_all()

    def __enter__(self) -> BotaSensor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- commands and samples ----------------------------------------------------------

    def command(self, command: Command, timeout_s: float | None = None) -> Ack | None:
        """Send one command and wait for its acknowledgement (none for ``#``).

        Raises :class:`BotaCommandError` on a non-zero return code,
        :class:`BotaTimeout` when no acknowledgement comes in time.
        """
        self._raise_if_failed()
        if not self._link.is_open:
            raise BotaError(f"F/T sensor on {self.port_name} is not connected; call connect() first")
        with self._cond:
            self._acks.clear()
        self._write(command.encode(self.terminator))
        if not command.expects_ack:
            return None
        timeout = self.ack_timeout_s if timeout_s is None else timeout_s
        ack = self._wait(
            lambda: next((a for a in self._acks if a.command == command.code), None),
            timeout,
            f"acknowledgement of {command.text!r}",
            "check that the sensor is powered and the port's baud rate matches the sensor",
        )
        if not ack.ok:
            raise BotaCommandError(
                f"F/T sensor on {self.port_name} rejected {command.text!r} (r,{ack.index},{ack.command},{ack.rc}); "
                "check the command and its value ranges"
            )
        return ack

    def wait_samples(
        self, n: int, timeout_s: float | None = None, *, raw: bool = False, valid_only: bool = False
    ) -> list[FtSample]:
        """The next ``n`` samples (RUN mode). ``raw``: without the tare; ``valid_only``: skip
        frames flagged overrange or invalid. Default timeout: twice their duration + 1 s."""
        self._raise_if_failed()
        if self._state not in (SensorState.RUNNING, SensorState.STARTING):
            raise BotaError(f"F/T sensor on {self.port_name} is not streaming; call start() first")
        if timeout_s is None:
            period_s = (self._settings.period_us if self._settings else 20_000.0) * 1e-6
            timeout_s = 2 * n * period_s + 1.0
        bad = Status.OVERRANGE | Status.INVALID_MEASUREMENTS
        collector = _Collector(n, (lambda f: not f.status & bad) if valid_only else (lambda f: True))
        with self._cond:
            self._collectors.append(collector)
        try:
            self._wait(lambda: len(collector.samples) >= n, timeout_s, f"{n} samples", "is the sensor streaming?")
        finally:
            with self._cond:
                self._collectors.remove(collector)
        samples = collector.samples[:n]
        return samples if raw else [self._tared(s) for s in samples]

    def tare(self, n_samples: int = 256, timeout_s: float | None = None) -> Offsets:
        """Average the next ``n_samples`` valid samples and subtract that from every later sample."""
        samples = self.wait_samples(n_samples, timeout_s, raw=True, valid_only=True)
        sums = [0.0] * 6
        for s in samples:
            for i, v in enumerate((*s.force_n, *s.torque_nm)):
                sums[i] += v
        self._tare = tuple(v / len(samples) for v in sums)
        log.info("F/T sensor on %s tared over %d samples: %s", self.port_name, len(samples), self.tare_offset)
        return self.tare_offset

    def clear_tare(self) -> None:
        self._tare = (0.0,) * 6

    # -- internals: port --------------------------------------------------------------

    def _error_for(self, failure: LinkFailure) -> BotaError:
        """The sensor's error for a failure of its serial link."""
        exc = failure.cause
        if failure.kind == "open":
            return BotaError(
                f"cannot open the F/T sensor port {self.port_name}: {exc}; check the name (ls /dev/serial/by-id) "
                "and that you may use it (group dialout)"
            )
        if failure.kind == "write":
            return BotaDisconnected(
                f"cannot write to the F/T sensor on {self.port_name} ({exc}); check the cable, then reconnect"
            )
        if failure.kind == "read":
            return BotaDisconnected(
                f"F/T sensor on {self.port_name} disconnected ({exc}); the reader stopped: "
                "check the cable and power, then reconnect"
            )
        error = BotaError(f"F/T sample callback raised {type(exc).__name__}: {exc}; the reader stopped")
        error.__cause__ = exc
        return error

    def _port_baudrate(self) -> int:
        return int(getattr(self._link.port, "baudrate", self.baudrate))

    def _write(self, data: bytes) -> None:
        self._link.write(data, char_gap_s=self.char_gap_s)

    def _reboot(self, boot_timeout_s: float, settle_s: float, new_baud: int | None = None) -> None:
        with self._cond:
            self._boot = BootInfo()
            self._frames_idle = 0
        how = "'#'"
        if new_baud is None:
            how = self._reset_line()
        else:
            self._write(cmd_hardware_reset().encode())
            port: Any = self._link.port
            with contextlib.suppress(Exception):
                port.flush()  # let '#' leave at the old rate
            port.baudrate = new_baud
        self._wait(
            lambda: self._boot.app_init,
            boot_timeout_s,
            f"'App Init' after a reset by {how}",
            f"check power and cable, and that the sensor talks at {self._port_baudrate()} baud",
        )
        with contextlib.suppress(BotaTimeout):  # name, S/N, FW and comm lines follow, then frames
            self._wait(lambda: self._frames_idle > 0, settle_s, "", "")

    def _reset_line(self) -> str:
        """Reset the sensor: a DTR pulse, or ``#`` when the port has no modem lines."""
        try:
            if self._link.pulse_dtr():
                return "a DTR pulse"
        except OSError as exc:
            raise self._fail(BotaDisconnected(f"cannot reset the F/T sensor on {self.port_name}: {exc}")) from None
        self._write(cmd_hardware_reset().encode())
        return "'#' (the port has no DTR line)"

    # -- internals: waiting and state ---------------------------------------------------------

    def _wait(self, predicate: Callable[[], Any], timeout_s: float, what: str, hint: str) -> Any:
        """Wait for ``predicate()`` to be truthy and return it; raise the reader's failure or a timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                value = predicate()
                if value:
                    return value
                error = self.error
                if error is not None:
                    raise error
                left = deadline - time.monotonic()
                if left <= 0:
                    raise BotaTimeout(f"no {what} from the F/T sensor on {self.port_name} within {timeout_s:g} s; {hint}")
                self._cond.wait(left)

    def _set_state(self, state: SensorState) -> None:
        with self._cond:
            if self._state is not SensorState.FAILED:
                self._state = state
            self._cond.notify_all()

    def _require(self, state: SensorState, action: str) -> None:
        self._raise_if_failed()
        if self._state is not state:
            raise BotaError(f"cannot {action} the F/T sensor on {self.port_name} while it is {self._state.value}")

    def _raise_if_failed(self) -> None:
        self._link.raise_if_failed()

    def _fail(self, error: BotaError) -> Exception:
        """Latch the failure (the first one wins); returns the error to raise."""
        return self._link.fail(error)

    def _on_failure(self, error: Exception) -> None:
        """The link latched its first failure: wake every waiter, tell on_error."""
        with self._cond:
            self._state = SensorState.FAILED
            self._cond.notify_all()
        log.error("%s", error)
        if self.on_error is not None and isinstance(error, BotaError):
            try:
                self.on_error(error)
            except Exception:
                log.exception("F/T sensor on_error callback raised")
        return error

    def _warn_all(self, warnings: list[tuple[str, str]], now_ns: int) -> None:
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

    # -- internals: the reader thread ------------------------------------------------------------

    def _on_chunk(self, data: bytes, t_ns: int) -> None:
        if self._restart_sync:
            self._restart_sync = False
            self._receiver.restart_sync()
        self._handle(self._receiver.feed(data), t_ns)

    def _on_idle(self, t_ns: int) -> None:
        if self._state is not SensorState.RUNNING:
            return
        with self._cond:
            warnings = self._health.quiet(t_ns, self.stall_timeout_s)
        self._warn_all(warnings, t_ns)

    def _handle(self, events: list[Event], t_ns: int) -> None:
        for ev in events:
            if isinstance(ev, Frame):
                self._on_frame(ev, t_ns)
            elif isinstance(ev, Ack):
                self._on_ack(ev)
            elif isinstance(ev, AppInit | InfoLine | CommSetupLine):
                with self._cond:
                    self._boot = self._boot.updated(ev)
                    self._cond.notify_all()
                if isinstance(ev, AppInit) and self._state is not SensorState.BOOTING:
                    self._on_unexpected_boot(t_ns)
            elif isinstance(ev, TextLine):
                log.debug("F/T sensor on %s says %r", self.port_name, ev.text)
            elif self._state is SensorState.RUNNING:
                self._on_sync_event(ev, t_ns)

    def _on_unexpected_boot(self, t_ns: int) -> None:
        with self._cond:
            warnings = self._health.restarted()
        self._warn_all(warnings, t_ns)

    def _on_ack(self, ack: Ack) -> None:
        with self._cond:
            self._acks.append(ack)
            if ack.ok and ack.command == "R" and self._state is SensorState.STARTING:
                self._state = SensorState.RUNNING
            elif ack.ok and ack.command == "C" and self._state is SensorState.STOPPING:
                self._state = SensorState.CONFIG
            self._cond.notify_all()

    def _on_sync_event(self, ev: Event, t_ns: int) -> None:
        with self._cond:
            warnings = self._health.sync_event(ev)
        self._warn_all(warnings, t_ns)

    def _on_frame(self, frame: Frame, t_ns: int) -> None:
        state = self._state
        if state not in (SensorState.RUNNING, SensorState.STOPPING):
            with self._cond:
                self._frames_idle += 1
                if self._frames_idle == 1:
                    self._cond.notify_all()
            return
        raw = FtSample(frame.t_device_us, t_ns, frame.force_n, frame.torque_nm, frame.status, frame.temperature_c)
        with self._cond:
            warnings = self._health.frame(frame, t_ns)
            if self._collectors:
                for collector in self._collectors:
                    if len(collector.samples) < collector.n and collector.accept(frame):
                        collector.samples.append(raw)
                self._cond.notify_all()
        self._warn_all(warnings, t_ns)
        self.on_sample(self._tared(raw))

    def _tared(self, s: FtSample) -> FtSample:
        t = self._tare
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


def _baud_code(baud_rate: int) -> int:
    for code, rate in BAUD_RATES.items():
        if rate == baud_rate:
            return code
    return -1
