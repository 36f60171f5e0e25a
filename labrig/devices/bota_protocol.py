"""Bota serial F/T sensor protocol (Rokubi / SensONE serial, "gen0"), sans-I/O.

Nothing here touches a port or a clock: bytes go in, frozen event objects come
out, and commands are turned into the bytes to write. The driver
(:mod:`labrig.devices.bota`) and the twin (:mod:`labrig.sim.bota_twin`) share it.

Host -> sensor: ASCII config commands (:class:`Command`). Single-letter commands
(``C``, ``R``, ``s``, ``l``, ``w``, ``I``, ``#``) are sent as the bare letter;
commands with arguments end with a terminator (``\\n`` by default). Every
command but ``#`` is acknowledged with ``r,<n>,<cmd>,<rc>`` (``rc`` 0 = accepted).

Sensor -> host: ASCII text (boot text, acknowledgements) and, in RUN mode, 37-byte
binary frames (little-endian)::

    0  u8      header 0xAA
    1  u16     status bits (:class:`Status`)
    3  6 x f32 Fx Fy Fz [N], Mx My Mz [N m], sensor frame
    27 u32     device timestamp [us], free-running, wraps every 2**32 us
    31 f32     temperature [degC]
    35 u16     CRC-16/X-25 over bytes 1..34 (header excluded)

:class:`BotaReceiver` splits one byte stream into frames and text lines. It
locks onto frames only on header 0xAA *and* a good CRC; while locked it takes
37 bytes at a time, and a wrong header or a bad CRC drops it back to searching,
one byte further on. So garbage, truncated frames and bit errors cost frames
but never yield a frame whose CRC does not match.
"""

from __future__ import annotations

import binascii
import enum
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass, replace

# -- link constants ---------------------------------------------------------

FRAME_HEADER = 0xAA
FRAME_SIZE = 37
#: Bytes covered by the CRC: frame bytes 1..34.
CRC_SPAN = slice(1, 35)
#: header, status, Fx Fy Fz Mx My Mz, timestamp, temperature, crc
FRAME_STRUCT = struct.Struct("<BH6fIfH")
assert FRAME_STRUCT.size == FRAME_SIZE

#: Baud code (the ``B`` of ``c,T,K,D,B``) -> baud rate [bit/s].
BAUD_RATES = {0: 9600, 1: 57600, 2: 115200, 3: 230400, 4: 460800}
DEFAULT_BAUD_CODE = 4
#: Bits on the wire per byte (8N1).
BITS_PER_BYTE = 10

#: Sample rate = ADC_BASE_RATE_HZ / sinc_length.
ADC_BASE_RATE_HZ = 51_200
SINC_LENGTH_MIN = 64
SINC_LENGTH_MAX = 2048
#: The device's command input buffer [bytes].
MAX_COMMAND_CHARS = 64

TIMESTAMP_MODULUS = 1 << 32

# Acknowledgement return codes. Only 0 is documented (accepted); the twin uses
# the others, and the driver treats any non-zero code as a rejection.
RC_OK = 0
RC_UNKNOWN_COMMAND = 1
RC_BAD_ARGUMENTS = 2
RC_WRONG_MODE = 3


class Status(enum.IntFlag):
    """Frame status bits (bits 4..15 are reserved)."""

    APP_TOOK_TOO_LONG = 0x1  # bota-driver: "throttled"; the sinc length is too short
    OVERRANGE = 0x2
    INVALID_MEASUREMENTS = 0x4  # saturation, short or open circuit
    RAW_MEASUREMENTS = 0x8  # values are gauge readings, not forces

    THROTTLED = APP_TOOK_TOO_LONG


#: What each status bit means for the user, and what to do.
STATUS_ADVICE = {
    Status.APP_TOOK_TOO_LONG: "app_took_too_long (throttled): the sinc length is too short for the load; increase it",
    Status.OVERRANGE: "overrange: a force or torque exceeds the sensor's range",
    Status.INVALID_MEASUREMENTS: "invalid_measurements: gauge saturation, short or open circuit; the data is invalid",
    Status.RAW_MEASUREMENTS: "raw_measurements: values are raw gauge readings, not forces (calibration disabled)",
}


def status_names(status: int) -> list[str]:
    """Names of the known bits set in ``status`` (lower case, bit order)."""
    return [str(bit.name).lower() for bit in STATUS_ADVICE if status & bit]


# -- CRC-16/X-25 ----------------------------------------------------------------


#: Each byte with its bits reversed (a ``bytes.translate`` table).
_REVERSED_BITS = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))


def crc16_x25(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/X-25: poly 0x1021 reflected, init 0xFFFF, xorout 0xFFFF (check("123456789") = 0x906E).

    The reflected CRC is the plain CRC-CCITT (``binascii.crc_hqx``, in C) of the bit-reversed bytes,
    bit-reversed: ``reverse16(crc_hqx(reverse8(data), 0xFFFF)) ^ 0xFFFF`` (init 0xFFFF is its own reverse).
    """
    crc = binascii.crc_hqx(bytes(data).translate(_REVERSED_BITS), 0xFFFF)
    return ((_REVERSED_BITS[crc & 0xFF] << 8) | _REVERSED_BITS[crc >> 8]) ^ 0xFFFF


# -- configuration values ------------------------------------------------------


@dataclass(frozen=True)
class CommSetup:
    """Comm setup ``c,T,K,D,B``. A new baud code takes effect after ``s`` (save) and a reset."""

    temperature_compensation: bool = False
    calibrated: bool = True  # K: 1 = calibration matrix applied (forces), 0 = raw gauges
    data_format: int = 0  # D: 0 binary frames, 1 CSV text
    baud_code: int = DEFAULT_BAUD_CODE

    def __post_init__(self) -> None:
        if self.data_format not in (0, 1):
            raise ValueError(f"data format must be 0 (binary) or 1 (CSV), got {self.data_format}")
        if self.baud_code not in BAUD_RATES:
            raise ValueError(f"baud code must be one of {sorted(BAUD_RATES)}, got {self.baud_code}")

    @property
    def baud_rate(self) -> int:
        return BAUD_RATES[self.baud_code]

    def text(self) -> str:
        return f"c,{int(self.temperature_compensation)},{int(self.calibrated)},{self.data_format},{self.baud_code}"


@dataclass(frozen=True)
class FilterSetup:
    """Filter setup ``f,S,C,F,D``: sinc length S (64..2048) sets the sample rate 51200/S Hz."""

    sinc_length: int = 512
    chop: bool = False
    fast: bool = False
    fir_disable: bool = True

    def __post_init__(self) -> None:
        if not SINC_LENGTH_MIN <= self.sinc_length <= SINC_LENGTH_MAX:
            raise ValueError(
                f"sinc length must be in [{SINC_LENGTH_MIN}, {SINC_LENGTH_MAX}] (rate 800..25 Hz), got {self.sinc_length}"
            )

    @property
    def sample_rate_hz(self) -> float:
        return ADC_BASE_RATE_HZ / self.sinc_length

    @property
    def period_us(self) -> float:
        """Nominal sample period in device microseconds (1250 for sinc length 64)."""
        return self.sinc_length * 1e6 / ADC_BASE_RATE_HZ

    def text(self) -> str:
        return f"f,{self.sinc_length},{int(self.chop)},{int(self.fast)},{int(self.fir_disable)}"


Vector3 = tuple[float, float, float]


@dataclass(frozen=True)
class Offsets:
    """Hardware F/T offsets ``b,fx,fy,fz,mx,my,mz`` [N, N m], added by the sensor to its output.

    A hardware tare sends the *negated* measured offset.
    """

    force_n: Vector3 = (0.0, 0.0, 0.0)
    torque_nm: Vector3 = (0.0, 0.0, 0.0)


# -- commands (host -> sensor) -------------------------------------------------

#: Commands without arguments: sent as the single letter, executed at once.
BARE_COMMANDS = frozenset("CRslwI#")
#: Commands with comma-separated arguments: sent with a terminator.
ARGUMENT_COMMANDS = frozenset("cfbm")


@dataclass(frozen=True)
class Command:
    """One config command. ``text`` excludes the terminator."""

    text: str

    def __post_init__(self) -> None:
        if not self.text or not self.text.isascii() or not self.text.isprintable():
            raise ValueError(f"a command must be printable ASCII, got {self.text!r}")
        if len(self.text) > MAX_COMMAND_CHARS:
            raise ValueError(f"command {self.text[:20]!r}... is {len(self.text)} chars; the sensor takes {MAX_COMMAND_CHARS}")

    @property
    def code(self) -> str:
        """The command letter; the acknowledgement names it."""
        return self.text[0]

    @property
    def expects_ack(self) -> bool:
        return self.code != "#"

    def encode(self, terminator: bytes = b"\n") -> bytes:
        """The bytes to write: bare letters as they are, argument commands plus ``terminator``."""
        raw = self.text.encode("ascii")
        return raw if self.code in BARE_COMMANDS else raw + terminator


def cmd_config_mode() -> Command:
    """``C``: go to CONFIG mode (streaming stops)."""
    return Command("C")


def cmd_run_mode() -> Command:
    """``R``: go to RUN mode (binary frames start)."""
    return Command("R")


def cmd_comm_setup(setup: CommSetup) -> Command:
    return Command(setup.text())


def cmd_filter(setup: FilterSetup) -> Command:
    return Command(setup.text())


def _fmt(value: float, decimals: int) -> str:
    text = f"{float(value):.{decimals}f}"
    return f"{0.0:.{decimals}f}" if float(text) == 0.0 else text  # no "-0.000"


def cmd_offsets(offsets: Offsets, decimals: int = 3) -> Command:
    """``b,fx,fy,fz,mx,my,mz`` with ``decimals`` digits (ROS uses 3)."""
    values = (*offsets.force_n, *offsets.torque_nm)
    return Command("b," + ",".join(_fmt(v, decimals) for v in values))


def cmd_matrix_row(row: int, values: Sequence[float], decimals: int = 6) -> Command:
    """``m<row>,a1,...,a6``: one row (0..5) of the calibration matrix."""
    if not 0 <= row <= 5 or len(values) != 6:
        raise ValueError(f"a calibration matrix row is a row index 0..5 and 6 values, got {row} and {len(values)}")
    return Command(f"m{row}," + ",".join(_fmt(v, decimals) for v in values))


def cmd_save() -> Command:
    """``s``: save the configuration to non-volatile memory."""
    return Command("s")


def cmd_load() -> Command:
    """``l``: load the saved configuration."""
    return Command("l")


def cmd_print_config() -> Command:
    """``w``: print the user configuration."""
    return Command("w")


def cmd_software_reset() -> Command:
    """``I``: software reset to INIT mode."""
    return Command("I")


def cmd_hardware_reset() -> Command:
    """``#``: hardware reset; no acknowledgement, the boot text follows."""
    return Command("#")


@dataclass(frozen=True)
class MatrixRow:
    row: int
    values: tuple[float, ...]


CommandArgs = CommSetup | FilterSetup | Offsets | MatrixRow | None


class CommandError(ValueError):
    """A command the sensor would reject; ``rc`` is the code to acknowledge it with."""

    def __init__(self, code: str, rc: int, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.rc = rc


def parse_command(text: str) -> tuple[str, CommandArgs]:
    """Parse one command as the sensor does: (letter, arguments). Raises :class:`CommandError`.

    Spaces around arguments are ignored (ROS pads matrix values with ``%9.6f``).
    """
    text = text.strip()
    if not text:
        raise CommandError("?", RC_UNKNOWN_COMMAND, "empty command")
    code = text[0]
    if code in BARE_COMMANDS:
        if len(text) > 1:
            raise CommandError(code, RC_BAD_ARGUMENTS, f"{code!r} takes no arguments, got {text!r}")
        return code, None
    if code not in ARGUMENT_COMMANDS:
        raise CommandError(code, RC_UNKNOWN_COMMAND, f"unknown command {text!r}")
    head, _, rest = text.partition(",")
    fields = [f.strip() for f in rest.split(",")] if rest else []
    try:
        if code == "m":
            row = int(head[1:])
            values = tuple(float(f) for f in fields)
            if not 0 <= row <= 5 or len(values) != 6:
                raise ValueError("m needs a row 0..5 and 6 values")
            return code, MatrixRow(row, values)
        if head != code:
            raise ValueError(f"unexpected {head!r}")
        if code == "c":
            t, k, d, b = (int(f) for f in fields)
            if t not in (0, 1) or k not in (0, 1):
                raise ValueError("T and K must be 0 or 1")
            return code, CommSetup(bool(t), bool(k), d, b)
        if code == "f":
            s, c, f, d = (int(x) for x in fields)
            if not {c, f, d} <= {0, 1}:
                raise ValueError("C, F and D must be 0 or 1")
            return code, FilterSetup(s, bool(c), bool(f), bool(d))
        values = tuple(float(f) for f in fields)  # "b"
        if len(values) != 6:
            raise ValueError("b needs 6 values")
        return code, Offsets(values[:3], values[3:])  # type: ignore[arg-type]
    except ValueError as exc:
        raise CommandError(code, RC_BAD_ARGUMENTS, f"bad arguments in {text!r}: {exc}") from None


def encode_ack(code: str, rc: int = RC_OK, index: int = 0) -> bytes:
    """The acknowledgement line ``r,<index>,<code>,<rc>\\r\\n``."""
    return f"r,{index},{code},{rc}\r\n".encode("ascii")


# -- frames ----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded RUN-mode frame. Forces and torques in the sensor frame."""

    status: int
    force_n: Vector3
    torque_nm: Vector3
    t_device_us: int  # raw uint32 device counter [us]
    temperature_c: float

    @property
    def flags(self) -> Status:
        return Status(self.status & 0xF)


def encode_frame(frame: Frame) -> bytes:
    """The 37 bytes of ``frame`` with its CRC (timestamp taken modulo 2**32)."""
    body = bytearray(
        FRAME_STRUCT.pack(
            FRAME_HEADER,
            frame.status & 0xFFFF,
            *frame.force_n,
            *frame.torque_nm,
            frame.t_device_us % TIMESTAMP_MODULUS,
            frame.temperature_c,
            0,
        )
    )
    struct.pack_into("<H", body, 35, crc16_x25(body[CRC_SPAN]))
    return bytes(body)


# -- boot text -------------------------------------------------------------------


@dataclass(frozen=True)
class BootInfo:
    """What the boot text told: product name, S/N, firmware version, comm setup."""

    app_init: bool = False
    name: str = ""
    serial_number: str = ""
    firmware_version: str = ""
    comm_setup: CommSetup | None = None

    def updated(self, event: object) -> BootInfo:
        """This info with one receiver event applied (other events leave it as is)."""
        if isinstance(event, AppInit):
            return BootInfo(app_init=True)  # a new boot starts afresh
        if isinstance(event, InfoLine):
            return replace(self, **{event.key: event.value})  # type: ignore[arg-type]
        if isinstance(event, CommSetupLine):
            return replace(self, comm_setup=event.setup)
        return self


def encode_boot_text(info: BootInfo, comm: CommSetup) -> bytes:
    """Boot text as the twin prints it; :class:`BotaReceiver` parses it back."""
    lines = [
        "",
        "App Init",
        f"name: {info.name}",
        f"S/N: {info.serial_number}",
        f"FW version: {info.firmware_version}",
        comm.text(),
    ]
    return "\r\n".join(lines).encode("ascii") + b"\r\n"


# -- receiver events -------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class CrcError:
    """A frame-sized window at a frame boundary whose CRC did not match (sync is dropped)."""

    received_crc: int
    computed_crc: int


@dataclass(frozen=True, slots=True)
class SyncLost:
    """The frame lock was lost: ``reason`` is ``bad_header`` or ``bad_crc``."""

    reason: str


@dataclass(frozen=True, slots=True)
class SyncAcquired:
    """Locked onto frames. ``resync``: after a loss (not the first lock since a restart).

    ``skipped_bytes``: bytes between losing the lock (or the start, or a restart)
    and this frame, whatever they were (a bad frame, garbage, text).
    """

    skipped_bytes: int
    resync: bool


@dataclass(frozen=True, slots=True)
class Ack:
    """Acknowledgement ``r,<index>,<command>,<rc>``; ``rc`` 0 means accepted."""

    index: int
    command: str
    rc: int

    @property
    def ok(self) -> bool:
        return self.rc == RC_OK


@dataclass(frozen=True, slots=True)
class AppInit:
    """The boot text's ``App Init`` line: the sensor (re)started."""


@dataclass(frozen=True, slots=True)
class InfoLine:
    """A boot info line; ``key`` is ``name``, ``serial_number`` or ``firmware_version``."""

    key: str
    value: str


@dataclass(frozen=True, slots=True)
class CommSetupLine:
    """A ``c,T,K,D,B`` line (boot text or ``w`` output)."""

    setup: CommSetup


@dataclass(frozen=True, slots=True)
class TextLine:
    """Any other printable line."""

    text: str


Event = Frame | CrcError | SyncLost | SyncAcquired | Ack | AppInit | InfoLine | CommSetupLine | TextLine

_ACK_RE = re.compile(r"r,(\d+),(.),(-?\d+)")
_COMM_RE = re.compile(r"c,([01]),([01]),(\d),(\d)")
_INFO_RE = re.compile(r"(name|S/N|FW version)\s*:\s*(.*)", re.IGNORECASE)
_INFO_KEYS = {"name": "name", "s/n": "serial_number", "fw version": "firmware_version"}
_LINE_BREAK = re.compile(rb"[\r\n]")
_PRINTABLE = re.compile(rb"[\x20-\x7e\t]+")
_NON_PRINTABLE = re.compile(rb"[^\x20-\x7e\t\r\n]")


def classify_line(text: str) -> Event:
    """The event for one text line (without its terminator)."""
    text = text.strip()
    if m := _ACK_RE.fullmatch(text):
        return Ack(int(m[1]), m[2], int(m[3]))
    if "App Init" in text:
        return AppInit()
    if m := _INFO_RE.fullmatch(text):
        return InfoLine(_INFO_KEYS[m[1].lower()], m[2].strip())
    if m := _COMM_RE.fullmatch(text):
        try:
            return CommSetupLine(CommSetup(m[1] == "1", m[2] == "1", int(m[3]), int(m[4])))
        except ValueError:
            pass
    return TextLine(text)


@dataclass(frozen=True)
class ReceiverCounters:
    """Totals since the receiver was made."""

    bytes_in: int = 0
    frames: int = 0
    text_lines: int = 0
    crc_errors: int = 0
    sync_losses: int = 0
    resyncs: int = 0
    skipped_bytes: int = 0


class BotaReceiver:
    """Sensor -> host byte stream to events: frames, text lines, sync and CRC events.

    Call :meth:`feed` with whatever bytes arrived (any split); it returns the
    events completed by them, in stream order. While not locked, printable
    lines ending in ``\\r`` or ``\\n`` become text events and other bytes are
    skipped (counted), up to the next 0xAA whose 37-byte window has a good CRC.
    """

    def __init__(self, max_line_chars: int = 256) -> None:
        self.max_line_chars = max_line_chars
        self._buf = bytearray()
        self._locked = False
        self._lost = False  # lock lost since the last restart: the next lock is a resync
        self._base = 0  # stream offset of self._buf[0]
        self._unlocked_at = 0  # stream offset where the lock was lost (or the search began)
        self._bytes_in = 0
        self._frames = 0
        self._text_lines = 0
        self._crc_errors = 0
        self._sync_losses = 0
        self._resyncs = 0
        self._skipped = 0

    @property
    def locked(self) -> bool:
        return self._locked

    @property
    def buffered_bytes(self) -> int:
        return len(self._buf)

    def counters(self) -> ReceiverCounters:
        return ReceiverCounters(
            self._bytes_in, self._frames, self._text_lines, self._crc_errors, self._sync_losses, self._resyncs, self._skipped
        )

    def restart_sync(self) -> None:
        """Forget that the lock was lost: the next lock is a first lock, not a resync.

        For the host to call when streaming (re)starts after a mode change.
        """
        self._lost = False
        self._unlocked_at = self._base

    def feed(self, data: bytes | bytearray | memoryview) -> list[Event]:
        """Take newly received bytes; return the events they complete."""
        buf = self._buf
        buf += data
        self._bytes_in += len(data)
        events: list[Event] = []
        pos = 0
        n = len(buf)
        unpack = FRAME_STRUCT.unpack_from
        while pos < n:
            if self._locked:
                if buf[pos] != FRAME_HEADER:
                    self._lose_sync("bad_header", pos, events)
                    continue
                if n - pos < FRAME_SIZE:
                    break
                fields = unpack(buf, pos)
                computed = crc16_x25(buf[pos + 1 : pos + 35])
                if fields[-1] != computed:
                    self._crc_errors += 1
                    events.append(CrcError(fields[-1], computed))
                    self._lose_sync("bad_crc", pos, events)
                    pos += 1  # search again from the next byte
                    self._skip(1)
                    continue
                events.append(Frame(fields[1], fields[2:5], fields[5:8], fields[8], fields[9]))
                self._frames += 1
                pos += FRAME_SIZE
                continue
            header = buf.find(FRAME_HEADER, pos)
            end = n if header < 0 else header
            if end > pos:
                pos = self._scan_text(buf, pos, end, header >= 0, events)
            if header < 0 or n - header < FRAME_SIZE:
                break
            if crc16_x25(buf[header + 1 : header + 35]) == struct.unpack_from("<H", buf, header + 35)[0]:
                self._locked = True
                if self._lost:
                    self._resyncs += 1
                events.append(SyncAcquired(self._base + header - self._unlocked_at, self._lost))
                self._lost = False
            else:
                pos = header + 1
                self._skip(1)
        del buf[:pos]
        self._base += pos
        return events

    def _lose_sync(self, reason: str, pos: int, events: list[Event]) -> None:
        self._locked = False
        self._lost = True
        self._unlocked_at = self._base + pos
        self._sync_losses += 1
        events.append(SyncLost(reason))

    def _skip(self, count: int) -> None:
        self._skipped += count

    def _scan_text(self, buf: bytearray, pos: int, end: int, header_follows: bool, events: list[Event]) -> int:
        """Consume text lines and garbage in buf[pos:end]; return where to go on from.

        A trailing piece without a line break is kept (returned pos < end) unless
        a header follows it or it cannot become a text line.
        """
        while pos < end:
            m = _LINE_BREAK.search(buf, pos, end)
            if m is None:
                break
            stop = m.start()
            if stop > pos:
                if _PRINTABLE.fullmatch(buf, pos, stop):
                    events.append(classify_line(buf[pos:stop].decode("ascii")))
                    self._text_lines += 1
                else:
                    self._skip(stop - pos + 1)
            pos = stop + 1
        if pos < end:
            if header_follows:
                self._skip(end - pos)  # a piece cut short by a frame header
                return end
            bad = None
            for bad in _NON_PRINTABLE.finditer(buf, pos, end):  # noqa: B007 - keep the last match
                pass
            cut = bad.end() if bad is not None else pos
            if end - cut > self.max_line_chars:
                cut = end
            self._skip(cut - pos)
            pos = cut
        return pos


def decode_all(data: bytes) -> list[Event]:
    """All events in ``data`` (a fresh receiver); for tests and offline files."""
    return BotaReceiver().feed(data)
