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
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from labrig.clock import HostClock, MonotonicClock
from labrig.devices.bota_health import BotaStats
from labrig.devices.bota_protocol import (
    BAUD_RATES,
    Ack,
    BootInfo,
    Command,
    CommSetup,
    FilterSetup,
    Offsets,
    ReceiverCounters,
    Status,
    cmd_comm_setup,
    cmd_config_mode,
    cmd_filter,
    cmd_hardware_reset,
    cmd_offsets,
    cmd_run_mode,
    cmd_save,
)
from labrig.devices.bota_stream import BotaStream, Collector, FtSample, SensorState
from labrig.devices.serial_link import LinkFailure, SerialLink, SerialPort, port_name
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
        self.baudrate = baudrate
        self.clock = clock or MonotonicClock()
        self.on_error = on_error
        self.terminator = terminator
        self.char_gap_s = char_gap_s
        self.ack_timeout_s = ack_timeout_s
        self.read_timeout_s = read_timeout_s
        self.write_timeout_s = write_timeout_s
        self.port_name = port_name(port)
        self._stream = BotaStream(
            self.port_name, on_sample=on_sample, on_warning=on_warning, stall_timeout_s=stall_timeout_s,
            warn_interval_s=warn_interval_s,
        )  # fmt: skip
        self._link = SerialLink(
            port,
            baudrate=baudrate,
            clock=self.clock,
            error_for=self._error_for,
            on_chunk=self._stream.on_chunk,
            on_idle=self._stream.on_idle,
            on_failure=self._on_failure,
            read_timeout_s=read_timeout_s,
            write_timeout_s=write_timeout_s,
            low_latency=True,
            thread_name=f"labrig-bota:{port if isinstance(port, str) else 'port'}",
        )
        self._connected = False
        self._settings: BotaSettings | None = None

    # -- properties ------------------------------------------------------------

    @property
    def state(self) -> SensorState:
        return self._stream.state

    @property
    def on_sample(self) -> Callable[[FtSample], None]:
        """Called from the reader thread with every sample in RUN mode (tare subtracted)."""
        return self._stream.on_sample

    @on_sample.setter
    def on_sample(self, callback: Callable[[FtSample], None]) -> None:
        self._stream.on_sample = callback

    @property
    def on_warning(self) -> Callable[[str], None] | None:
        return self._stream.on_warning

    @on_warning.setter
    def on_warning(self, callback: Callable[[str], None] | None) -> None:
        self._stream.on_warning = callback

    @property
    def stall_timeout_s(self) -> float:
        return self._stream.stall_timeout_s

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
        return self._stream.boot

    @property
    def settings(self) -> BotaSettings | None:
        return self._settings

    @property
    def tare_offset(self) -> Offsets:
        """The software tare subtracted from every sample [N, N m]."""
        t = self._stream.tare
        return Offsets((t[0], t[1], t[2]), (t[3], t[4], t[5]))

    def stats(self) -> BotaStats:
        with self._stream.cond:
            return self._stream.health.snapshot()

    def receiver_counters(self) -> ReceiverCounters:
        """The byte-level totals since connect (all modes)."""
        return self._stream.receiver.counters()

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
        if self._stream.state is not SensorState.CLOSED:
            raise BotaError(f"F/T sensor on {self.port_name} is already connected; close() it first")
        self._link.open()
        self._connected = True
        self._stream.set_state(SensorState.BOOTING if reset else SensorState.CONFIG)
        self._link.start()
        try:
            if reset:
                self._reboot(boot_timeout_s, boot_settle_s)
            self.command(cmd_config_mode())
        except BaseException:
            self.close()  # a later connect() starts afresh
            raise
        self._stream.set_state(SensorState.CONFIG)
        return self._stream.boot

    def configure(self, settings: BotaSettings) -> None:
        """Send the comm setup, filter and offsets (CONFIG mode).

        A new baud code is saved and the sensor reset (it only takes effect
        then); the port follows to the new rate and the boot is waited out again.
        """
        self._require(SensorState.CONFIG, "configure")
        comm = settings.comm_setup
        boot_comm = self._stream.boot.comm_setup
        current = boot_comm.baud_code if boot_comm else _baud_code(self._port_baudrate())
        self.command(cmd_comm_setup(comm))
        self.command(cmd_filter(settings.filter_setup))
        if settings.offsets is not None:
            self.command(cmd_offsets(settings.offsets))
        if settings.save or comm.baud_code != current:
            self.command(cmd_save(), timeout_s=max(self.ack_timeout_s, 2.0))
        if comm.baud_code != current:
            self._stream.set_state(SensorState.BOOTING)
            self._reboot(10.0, 0.5, new_baud=comm.baud_rate)
            self.command(cmd_config_mode())
            self._stream.set_state(SensorState.CONFIG)
        self._settings = settings

    def start(self) -> None:
        """RUN mode: frames stream and reach ``on_sample``. Counters restart."""
        self._require(SensorState.CONFIG, "start")
        settings = self._settings
        raw_gauges = settings is not None and not settings.calibrated
        self._stream.begin_run(settings.period_us if settings else None, self.clock.now_ns(), raw_gauges=raw_gauges)
        try:
            self.command(cmd_run_mode())  # the reader switches to RUNNING on the ack, before the frames
        except BotaError:
            with self._stream.cond:
                if self._stream.state is SensorState.STARTING:
                    self._stream.state = SensorState.CONFIG
            raise

    def stop(self) -> None:
        """Back to CONFIG mode: streaming stops. Frames before the acknowledgement are still delivered."""
        self._raise_if_failed()
        if self._stream.state not in (SensorState.RUNNING, SensorState.STARTING):
            return
        self._stream.set_state(SensorState.STOPPING)
        try:
            self.command(cmd_config_mode())
        finally:
            with self._stream.cond:
                if self._stream.state is SensorState.STOPPING:
                    self._stream.state = SensorState.CONFIG

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop streaming (if the port still works), end the reader, close the port if we opened it."""
        if self._stream.state is SensorState.CLOSED and not self._connected:
            return
        in_reader = self._link.in_reader_thread()  # close() from a callback: no waiting on acks
        if self.error is None and not in_reader and self._stream.state in (SensorState.RUNNING, SensorState.STARTING):
            try:
                self.stop()
            except BotaError as exc:
                log.warning("F/T sensor on %s: could not stop streaming cleanly: %s", self.port_name, exc)
        self._link.close(timeout_s)
        self._connected = False
        with self._stream.cond:
            self._stream.state = SensorState.CLOSED
            self._stream.cond.notify_all()

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
        with self._stream.cond:
            self._stream.acks.clear()
        self._write(command.encode(self.terminator))
        if not command.expects_ack:
            return None
        timeout = self.ack_timeout_s if timeout_s is None else timeout_s
        ack = self._wait(
            lambda: next((a for a in self._stream.acks if a.command == command.code), None),
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
        if self._stream.state not in (SensorState.RUNNING, SensorState.STARTING):
            raise BotaError(f"F/T sensor on {self.port_name} is not streaming; call start() first")
        if timeout_s is None:
            period_s = (self._settings.period_us if self._settings else 20_000.0) * 1e-6
            timeout_s = 2 * n * period_s + 1.0
        bad = Status.OVERRANGE | Status.INVALID_MEASUREMENTS
        collector = Collector(n, (lambda f: not f.status & bad) if valid_only else (lambda f: True))
        with self._stream.cond:
            self._stream.collectors.append(collector)
        try:
            self._wait(lambda: len(collector.samples) >= n, timeout_s, f"{n} samples", "is the sensor streaming?")
        finally:
            with self._stream.cond:
                self._stream.collectors.remove(collector)
        samples = collector.samples[:n]
        return samples if raw else [self._stream.tared(s) for s in samples]

    def tare(self, n_samples: int = 256, timeout_s: float | None = None) -> Offsets:
        """Average the next ``n_samples`` valid samples and subtract that from every later sample."""
        samples = self.wait_samples(n_samples, timeout_s, raw=True, valid_only=True)
        sums = [0.0] * 6
        for s in samples:
            for i, v in enumerate((*s.force_n, *s.torque_nm)):
                sums[i] += v
        self._stream.tare = tuple(v / len(samples) for v in sums)
        log.info("F/T sensor on %s tared over %d samples: %s", self.port_name, len(samples), self.tare_offset)
        return self.tare_offset

    def clear_tare(self) -> None:
        self._stream.tare = (0.0,) * 6

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
        self._stream.expect_boot()
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
            lambda: self._stream.boot.app_init,
            boot_timeout_s,
            f"'App Init' after a reset by {how}",
            f"check power and cable, and that the sensor talks at {self._port_baudrate()} baud",
        )
        with contextlib.suppress(BotaTimeout):  # name, S/N, FW and comm lines follow, then frames
            self._wait(lambda: self._stream.frames_idle > 0, settle_s, "", "")

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
        with self._stream.cond:
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
                self._stream.cond.wait(left)

    def _set_state(self, state: SensorState) -> None:
        with self._stream.cond:
            if self._stream.state is not SensorState.FAILED:
                self._stream.state = state
            self._stream.cond.notify_all()

    def _require(self, state: SensorState, action: str) -> None:
        self._raise_if_failed()
        if self._stream.state is not state:
            raise BotaError(f"cannot {action} the F/T sensor on {self.port_name} while it is {self._stream.state.value}")

    def _raise_if_failed(self) -> None:
        self._link.raise_if_failed()

    def _fail(self, error: BotaError) -> Exception:
        """Latch the failure (the first one wins); returns the error to raise."""
        return self._link.fail(error)

    def _on_failure(self, error: Exception) -> None:
        """The link latched its first failure: wake every waiter, tell on_error."""
        with self._stream.cond:
            self._stream.state = SensorState.FAILED
            self._stream.cond.notify_all()
        log.error("%s", error)
        if self.on_error is not None and isinstance(error, BotaError):
            try:
                self.on_error(error)
            except Exception:
                log.exception("F/T sensor on_error callback raised")


def _baud_code(baud_rate: int) -> int:
    for code, rate in BAUD_RATES.items():
        if rate == baud_rate:
            return code
    return -1
