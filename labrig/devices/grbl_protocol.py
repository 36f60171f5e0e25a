"""GRBL 1.1 serial protocol, sans I/O: bytes in, events out; lines out, bytes to write.

Both sides of the wire live here: :func:`classify_line` reads what GRBL sends and the
``format_*`` functions write it (the twin, :mod:`labrig.sim.grbl_twin`, answers with them;
:func:`classify_line` reads every one of them back); :func:`motion_line` and :func:`jog_line`
write the G-code lines the driver sends.

Theory of operation
-------------------
:class:`GrblProtocol` never touches a port. The caller writes what :meth:`GrblProtocol.send_line`
and :meth:`GrblProtocol.realtime` return, and feeds what it reads to
:meth:`GrblProtocol.receive_data`, which returns :mod:`events <Event>` (frozen dataclasses).

Everything that affects the protocol state lives in the :class:`GrblProtocol` instance:

* **In-flight lines** (character counting). GRBL's RX ring holds 128 bytes and overflows
  silently. Every line sent is recorded with the exact number of bytes written (the line plus
  exactly one ``\\n``). Each response, ``ok`` or ``error:N``, answers the oldest unanswered line
  (GRBL answers lines in order, once each), so the pair is popped and returned in the event.
  :meth:`can_send` admits a line only while the unanswered bytes stay within ``rx_limit_bytes``
  (127 by default, one byte of margin, as the reference streamer keeps). Real-time bytes
  (``?``, ``!``, ``~``, 0x18, 0x85, overrides) are picked out by GRBL's receive interrupt and
  take no buffer space, so they are not counted. Push messages (status reports, ``ALARM:N``,
  ``[MSG:...]``, settings, ...) never answer a line.
* **Resets.** The welcome banner (``Grbl 1.1h ['$' for help]``) means the controller has reset:
  every line still unanswered was discarded without a response, so the accounting is cleared
  and the lost lines are returned in :class:`Welcome`. A soft reset we request with
  :meth:`realtime` (0x18) blocks new lines until that banner arrives.
* **Controller condition**: the last status report, the last alarm, and whether a critical
  alarm (1 hard limit, 2 soft limit) locks the controller until a reset (GRBL then ignores every
  line and even ``?``; the offending line's own ``ok`` arrives only after the reset).

Received lines end in ``\\r\\n``; either byte ends a line and empty lines are skipped (the banner
is preceded by one). Bytes outside printable ASCII are removed before a line is classified
(noise on the wire), and counted. A line that matches nothing GRBL sends becomes
:class:`Unrecognized`; it never answers an in-flight line.

Errors are split by blame: :class:`GrblUsageError` is our misuse (a line with a terminator in
it, too long, a real-time character inside a line); :class:`GrblCommandError` and
:class:`GrblAlarm` carry what the controller said, with what it means and what to do.
"""

from __future__ import annotations

import math
import re
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

from labrig.errors import LabrigError

#: GRBL's serial receive ring (``RX_BUFFER_SIZE``): bytes that fit.
RX_BUFFER_BYTES = 128
#: Unanswered bytes we allow in flight (one below the ring, as the reference streamer).
DEFAULT_RX_LIMIT_BYTES = 127
#: GRBL's line buffer holds 79 characters after its pre-parser (spaces and comments removed).
LINE_MAX_CHARS = 79
#: Usable planner blocks in a stock 328P build.
PLANNER_BLOCKS = 15
#: Line terminator we send: exactly one ``\n`` per line.
EOL = b"\n"


class Realtime:
    """Single-byte real-time commands (no terminator, no response, no buffer space)."""

    STATUS = b"?"
    FEED_HOLD = b"!"
    CYCLE_START = b"~"
    SOFT_RESET = b"\x18"
    SAFETY_DOOR = b"\x84"
    JOG_CANCEL = b"\x85"
    FEED_OVR_RESET = b"\x90"
    FEED_OVR_PLUS_10 = b"\x91"
    FEED_OVR_MINUS_10 = b"\x92"
    FEED_OVR_PLUS_1 = b"\x93"
    FEED_OVR_MINUS_1 = b"\x94"
    RAPID_OVR_100 = b"\x95"
    RAPID_OVR_50 = b"\x96"
    RAPID_OVR_25 = b"\x97"
    SPINDLE_OVR_RESET = b"\x99"
    SPINDLE_OVR_PLUS_10 = b"\x9a"
    SPINDLE_OVR_MINUS_10 = b"\x9b"
    SPINDLE_OVR_PLUS_1 = b"\x9c"
    SPINDLE_OVR_MINUS_1 = b"\x9d"
    SPINDLE_STOP = b"\x9e"
    FLOOD_TOGGLE = b"\xa0"
    MIST_TOGGLE = b"\xa1"

    ALL = frozenset(
        [b"?", b"!", b"~", b"\x18", b"\x84", b"\x85", *(bytes([c]) for c in range(0x90, 0xA2) if c not in (0x98, 0x9F))]
    )


#: Characters GRBL's interrupt takes as real-time commands even inside a line.
_REALTIME_IN_LINE = frozenset(b"?!~")

# -- code tables (meanings in our words; the numbering is GRBL 1.1's) ------------------------

ERROR_MEANINGS: dict[int, str] = {
    1: "a G-code word has no letter",
    2: "a number is missing or malformed",
    3: "unknown or malformed '$' command",
    4: "negative value where only positive ones are allowed",
    5: "homing is not enabled ($22=0)",
    6: "step pulse must be at least 3 us",
    7: "settings could not be read from EEPROM; defaults restored",
    8: "'$' command needs the controller Idle",
    9: "G-code locked out in Alarm or Jog state",
    10: "soft limits need homing enabled ($22=1)",
    11: "line too long (more than 79 characters), not executed",
    12: "setting would exceed the maximum step rate (30 kHz)",
    13: "safety door is open",
    14: "startup or build-info line too long for EEPROM",
    15: "jog target beyond machine travel",
    16: "jog command has no '=' or a word jogging does not allow",
    17: "laser mode needs a PWM spindle output",
    20: "unsupported or invalid G-code command",
    21: "two commands of one modal group in a block",
    22: "feed rate not set",
    23: "command needs an integer value",
    24: "two commands in a block both need axis words",
    25: "a word is repeated in the block",
    26: "no axis words where the command needs some",
    27: "line number out of range (1-9,999,999)",
    28: "a required P or L value is missing",
    29: "G59.1, G59.2 and G59.3 are not supported",
    30: "G53 needs G0 or G1 motion mode",
    31: "axis words left unused (G80 is active)",
    32: "arc has no axis word in the selected plane",
    33: "invalid motion target (impossible arc, or probe target at the current position)",
    34: "arc radius error",
    35: "arc has no I, J or K offset word in the plane",
    36: "words left over that no command uses",
    37: "tool length offset on an axis other than the configured one",
    38: "tool number too large",
}

#: What to do about an error, where more than "fix the line" helps.
ERROR_HINTS: dict[int, str] = {
    5: "enable homing with $22=1 or do not home",
    7: "check the settings ($$) and write them again",
    8: "wait for Idle (or send '!'/0x85 to stop) and send it again",
    9: "unlock ($X) or home ($H) first, or wait for the jog to end",
    10: "set $22=1 first",
    11: "shorten the line (remove spaces and comments)",
    13: "close the door and resume",
    15: "choose a jog target inside the travel",
    22: "give an F word (jogs need F on every command)",
}

ALARM_MEANINGS: dict[int, str] = {
    1: "hard limit triggered",
    2: "soft limit: target beyond travel",
    3: "reset while in motion",
    4: "probe not in the expected state before probing",
    5: "probe made no contact within travel",
    6: "homing failed: reset during homing",
    7: "homing failed: safety door opened during homing",
    8: "homing failed: pull-off did not clear the limit switch",
    9: "homing failed: limit switch not found within search distance",
    10: "homing failed: second switch of a dual axis not found",
}

ALARM_ACTIONS: dict[int, str] = {
    1: "position likely lost; check the switches, reset and re-home",
    2: "reset and re-home",
    3: "position may be lost; re-home ($H) or unlock ($X)",
    4: "check the probe wiring and $6, then unlock ($X)",
    5: "move the probe closer to the work, then unlock ($X)",
    6: "home again ($H)",
    7: "close the door and home again ($H)",
    8: "increase the pull-off $27 or check the switches, then home again",
    9: "check the switches, $23 homing direction and $130-$132 travel, then home again",
    10: "check the second switch, then home again",
}

#: Alarms that lock GRBL until a soft reset (it then ignores lines and '?').
CRITICAL_ALARMS = frozenset({1, 2})

STATES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")


def error_meaning(code: int) -> str:
    return ERROR_MEANINGS.get(code, f"unknown error code {code}")


def alarm_meaning(code: int) -> str:
    return ALARM_MEANINGS.get(code, f"unknown alarm code {code}")


# -- exceptions ----------------------------------------------------------------------------


class GrblError(LabrigError):
    """Anything that went wrong talking to a GRBL controller."""


class GrblUsageError(GrblError, ValueError):
    """Our misuse of the protocol or the driver (the controller said nothing wrong)."""


class GrblCommandError(GrblError):
    """The controller answered a line with ``error:N``."""

    def __init__(self, code: int, line: bytes | None, index: int | None = None) -> None:
        self.code = code
        self.line = line
        self.index = index
        what = f" in {line.decode('ascii', 'replace')!r}" if line is not None else ""
        where = f" (line {index + 1})" if index is not None else ""
        hint = ERROR_HINTS.get(code, "fix the line and send it again")
        super().__init__(f"GRBL error:{code} {error_meaning(code)}{what}{where}; {hint}")


class GrblAlarm(GrblError):
    """The controller raised ``ALARM:N`` (G-code is locked out until reset/unlock/home)."""

    def __init__(self, code: int, context: str = "") -> None:
        self.code = code
        self.critical = code in CRITICAL_ALARMS
        extra = f" ({context})" if context else ""
        super().__init__(f"ALARM:{code} {alarm_meaning(code)}; {ALARM_ACTIONS.get(code, 'reset and unlock ($X)')}{extra}")


class GrblTimeout(GrblError):
    """An expected answer did not come in time (lost response, unresponsive controller)."""


class GrblConnectionError(GrblError):
    """The serial port failed or went away (unplugged, closed, no device)."""


class GrblResetError(GrblError):
    """The controller reset and discarded lines before answering them."""


# -- events --------------------------------------------------------------------------------


@dataclass(frozen=True)
class SentLine:
    """A line we wrote: its bytes without terminator, the bytes it occupies in GRBL's ring, our tag."""

    line: bytes
    n_bytes: int
    tag: object = field(default=None, compare=False)


@dataclass(frozen=True)
class Event:
    """Base of everything :meth:`GrblProtocol.receive_data` returns."""


@dataclass(frozen=True)
class Ok(Event):
    """``ok``: ``sent`` was parsed and executed or queued (None if no line was in flight)."""

    sent: SentLine | None


@dataclass(frozen=True)
class ErrorReply(Event):
    """``error:N`` answering ``sent``."""

    code: int
    sent: SentLine | None

    @property
    def meaning(self) -> str:
        return error_meaning(self.code)


@dataclass(frozen=True)
class Alarm(Event):
    """``ALARM:N`` pushed; ``critical`` ones lock the controller until a soft reset."""

    code: int

    @property
    def meaning(self) -> str:
        return alarm_meaning(self.code)

    @property
    def critical(self) -> bool:
        return self.code in CRITICAL_ALARMS


@dataclass(frozen=True)
class Status(Event):
    """A status report ``<...>``. Positions in mm (machine/work), feed in mm/min.

    ``position_mm`` is the machine position (MPos, or WPos + the last known WCO); ``wco_mm`` is
    the last known work offset (``wco_in_report`` tells whether this report carried it).
    Optional fields are None when the report (and, for WCO, every earlier one) lacked them.
    """

    state: str
    substate: int | None
    position_mm: tuple[float, ...] | None
    work_position_mm: tuple[float, ...] | None
    wco_mm: tuple[float, ...] | None
    wco_in_report: bool
    planner_free_blocks: int | None
    rx_free_bytes: int | None
    line_number: int | None
    feed_mm_min: float | None
    spindle_rpm: float | None
    pins: str
    overrides_pct: tuple[int, int, int] | None
    accessories: str | None
    raw: bytes

    @property
    def state_text(self) -> str:
        """The state as GRBL prints it (``Hold:0``)."""
        return self.state if self.substate is None else f"{self.state}:{self.substate}"


@dataclass(frozen=True)
class Welcome(Event):
    """The banner: the controller (re)started. ``dropped``: lines it discarded unanswered."""

    version: str
    dropped: tuple[SentLine, ...]


@dataclass(frozen=True)
class Message(Event):
    """``[MSG:text]``."""

    text: str


@dataclass(frozen=True)
class ParserState(Event):
    """``[GC:...]``: the modal words, e.g. ``('G0', 'G54', 'G17', 'G21', 'G90', 'G94', 'M5', 'M9', 'T0', 'F0', 'S0')``."""

    words: tuple[str, ...]


@dataclass(frozen=True)
class Probe(Event):
    """``[PRB:x,y,z:s]``: machine position of the last probe and whether it touched."""

    position_mm: tuple[float, ...]
    success: bool


@dataclass(frozen=True)
class Parameter(Event):
    """``[G54:x,y,z]`` ... ``[G92:...]``, ``[TLO:z]``: a coordinate parameter (mm)."""

    name: str
    values: tuple[float, ...]


@dataclass(frozen=True)
class Help(Event):
    """``[HLP:...]``."""

    text: str


@dataclass(frozen=True)
class Version(Event):
    """``[VER:1.1h.20190830:info]``."""

    version: str
    info: str


@dataclass(frozen=True)
class Options(Event):
    """``[OPT:V,15,128]``: build option codes, planner blocks, RX buffer bytes."""

    codes: str
    planner_blocks: int | None
    rx_buffer_bytes: int | None


@dataclass(frozen=True)
class Echo(Event):
    """``[echo:...]`` (builds with line echo)."""

    text: str


@dataclass(frozen=True)
class Setting(Event):
    """``$N=value`` from ``$$``."""

    number: int
    text: str

    @property
    def value(self) -> float:
        return float(self.text)


@dataclass(frozen=True)
class StartupLine(Event):
    """``$N0=line`` from ``$N``."""

    index: int
    line: str


@dataclass(frozen=True)
class StartupResult(Event):
    """``>line:ok`` or ``>line:error:N``: a stored startup line ran (not a response)."""

    line: str
    error_code: int | None


@dataclass(frozen=True)
class Unrecognized(Event):
    """A line that is nothing GRBL sends (noise, a foreign device)."""

    raw: bytes


# -- classification ------------------------------------------------------------------------

_BANNER = re.compile(r"^Grbl\w*\s+(\S+)\s*\[.*\]\s*$")
_SETTING = re.compile(r"^\$(\d+)=(.*)$")
_STARTUP = re.compile(r"^\$N(\d)=(.*)$")
_STARTUP_RESULT = re.compile(r"^>(.*):(ok|error:(\d+))$")
_PARAM_NAMES = frozenset({"G54", "G55", "G56", "G57", "G58", "G59", "G28", "G30", "G92", "TLO"})


def _floats(text: str) -> tuple[float, ...]:
    values = tuple(float(v) for v in text.split(","))
    if not values:
        raise ValueError(text)
    return values


def _parse_status(body: str, raw: bytes, last_wco: tuple[float, ...] | None) -> Status:
    fields = body.split("|")
    head = fields[0]
    state, _, sub = head.partition(":")
    if not state or not state.isalpha():
        raise ValueError(head)
    substate = int(sub) if sub else None
    mpos = wpos = wco = None
    values: dict[str, object] = {}
    for f in fields[1:]:
        key, sep, val = f.partition(":")
        if not sep:
            raise ValueError(f)
        if key == "MPos":
            mpos = _floats(val)
        elif key == "WPos":
            wpos = _floats(val)
        elif key == "WCO":
            wco = _floats(val)
        elif key in ("Bf", "Buf"):
            blocks, rx = val.split(",")
            values["bf"] = (int(blocks), int(rx))
        elif key == "Ln":
            values["ln"] = int(val)
        elif key == "FS":
            feed, rpm = _floats(val)
            values["fs"] = (feed, rpm)
        elif key == "F":
            values["fs"] = (float(val), None)
        elif key == "Pn":
            values["pn"] = val
        elif key == "Ov":
            ov = tuple(int(v) for v in val.split(","))
            if len(ov) != 3:
                raise ValueError(f)
            values["ov"] = ov
        elif key == "A":
            values["a"] = val
        # Unknown fields (other builds) are ignored.
    known_wco = wco if wco is not None else last_wco
    if mpos is None and wpos is None:
        raise ValueError("status report without a position")
    if mpos is not None and wpos is None and known_wco is not None and len(known_wco) == len(mpos):
        wpos = tuple(m - o for m, o in zip(mpos, known_wco))
    if wpos is not None and mpos is None and known_wco is not None and len(known_wco) == len(wpos):
        mpos = tuple(w + o for w, o in zip(wpos, known_wco))
    bf = values.get("bf")
    fs = values.get("fs")
    return Status(
        state=state,
        substate=substate,
        position_mm=mpos,
        work_position_mm=wpos,
        wco_mm=known_wco,
        wco_in_report=wco is not None,
        planner_free_blocks=bf[0] if bf else None,  # type: ignore[index]
        rx_free_bytes=bf[1] if bf else None,  # type: ignore[index]
        line_number=values.get("ln"),  # type: ignore[arg-type]
        feed_mm_min=fs[0] if fs else None,  # type: ignore[index]
        spindle_rpm=fs[1] if fs else None,  # type: ignore[index]
        pins=str(values.get("pn", "")),
        overrides_pct=values.get("ov"),  # type: ignore[arg-type]
        accessories=values.get("a"),  # type: ignore[arg-type]
        raw=raw,
    )


def _parse_bracket(body: str) -> Event:
    key, sep, val = body.partition(":")
    if not sep:
        raise ValueError(body)
    if key == "MSG":
        return Message(val)
    if key == "GC":
        return ParserState(tuple(val.split()))
    if key == "PRB":
        pos, _, ok = val.rpartition(":")
        return Probe(_floats(pos), ok == "1")
    if key == "HLP":
        return Help(val)
    if key == "VER":
        version, _, info = val.partition(":")
        return Version(version, info)
    if key == "OPT":
        parts = val.split(",")
        blocks = int(parts[1]) if len(parts) > 1 and parts[1] else None
        rx = int(parts[2]) if len(parts) > 2 and parts[2] else None
        return Options(parts[0], blocks, rx)
    if key == "echo":
        return Echo(val)
    if key in _PARAM_NAMES:
        return Parameter(key, _floats(val))
    raise ValueError(body)


def classify_line(text: str, raw: bytes, last_wco: tuple[float, ...] | None = None) -> Event:
    """The event a line from GRBL stands for, ignoring in-flight pairing (``Ok``/``ErrorReply`` carry no line)."""
    try:
        if text == "ok":
            return Ok(None)
        if text.startswith("error:"):
            return ErrorReply(int(text[6:]), None)
        if text.startswith("ALARM:"):
            return Alarm(int(text[6:]))
        if text.startswith("<") and text.endswith(">"):
            return _parse_status(text[1:-1], raw, last_wco)
        if text.startswith("[") and text.endswith("]"):
            return _parse_bracket(text[1:-1])
        if text.startswith("$"):
            m = _STARTUP.match(text)
            if m:
                return StartupLine(int(m.group(1)), m.group(2))
            m = _SETTING.match(text)
            if m:
                float(m.group(2))
                return Setting(int(m.group(1)), m.group(2))
        if text.startswith(">"):
            m = _STARTUP_RESULT.match(text)
            if m:
                return StartupResult(m.group(1), int(m.group(3)) if m.group(3) else None)
        m = _BANNER.match(text)
        if m:
            return Welcome(m.group(1), ())
    except ValueError:
        pass
    return Unrecognized(raw)


def preparsed_length(line: bytes) -> int:
    """Characters GRBL's line buffer keeps of ``line``: spaces, control bytes and comments removed."""
    n = 0
    in_paren = False
    for c in line:
        if in_paren:
            in_paren = c != ord(")")
        elif c == ord("("):
            in_paren = True
        elif c == ord(";"):
            break
        elif c > 0x20 and c < 0x7F:
            n += 1
    return n


# -- formatting: the lines GRBL sends (the twin's side), read back by classify_line -----------

#: What ends every line GRBL sends.
LINE_END = b"\r\n"


def format_mm(values: Sequence[float], decimals: int = 3) -> str:
    """Comma-separated values as GRBL prints positions (mm mode: 3 decimals)."""
    return ",".join(f"{v:.{decimals}f}" for v in values)


def format_ok() -> str:
    return "ok"


def format_error(code: int) -> str:
    return f"error:{code}"


def format_alarm(code: int) -> str:
    return f"ALARM:{code}"


def format_welcome(version: str) -> str:
    """The banner after power-up or a reset, e.g. ``Grbl 1.1h ['$' for help]``."""
    return f"Grbl {version} ['$' for help]"


def format_message(text: str) -> str:
    return f"[MSG:{text}]"


def format_help(text: str) -> str:
    return f"[HLP:{text}]"


def format_parser_state(words: Sequence[str]) -> str:
    """``[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]`` from the modal words."""
    return "[GC:" + " ".join(words) + "]"


def format_parameter(name: str, values: Sequence[float]) -> str:
    """``[G54:x,y,z]`` ... ``[G92:...]``, ``[TLO:z]`` (mm)."""
    return f"[{name}:{format_mm(values)}]"


def format_probe(position_mm: Sequence[float], success: bool) -> str:
    return f"[PRB:{format_mm(position_mm)}:{int(success)}]"


def format_version(version: str, info: str) -> str:
    return f"[VER:{version}:{info}]"


def format_options(codes: str, planner_blocks: int, rx_buffer_bytes: int) -> str:
    return f"[OPT:{codes},{planner_blocks},{rx_buffer_bytes}]"


def format_echo(text: str) -> str:
    return f"[echo:{text}]"


def format_setting(number: int, value: float, *, integer: bool) -> str:
    """``$N=value`` as ``$$`` lists it: integer settings without decimals, the others with 3."""
    return f"${number}={value:.0f}" if integer else f"${number}={value:.3f}"


def format_startup_line(index: int, line: str) -> str:
    return f"$N{index}={line}"


def format_startup_result(line: str, response: str) -> str:
    """``>line:ok`` or ``>line:error:N`` after a stored startup line ran; ``response``: the
    line's own answer (:func:`format_ok` or :func:`format_error`)."""
    return f">{line}:{response}"


def format_status(
    state: str,
    *,
    machine_mm: Sequence[float] | None = None,
    work_mm: Sequence[float] | None = None,
    buffer: tuple[int, int] | None = None,
    line_number: int | None = None,
    feed_mm_min: float | None = None,
    spindle_rpm: float | None = None,
    pins: str = "",
    wco_mm: Sequence[float] | None = None,
    overrides_pct: tuple[int, int, int] | None = None,
    accessories: str = "",
) -> str:
    """A status report ``<state|MPos:...|Bf:...|Ln:...|FS:...|Pn:...|WCO:...|Ov:...|A:...>``.

    ``state`` as printed (``Hold:0``); one of ``machine_mm`` (MPos) or ``work_mm`` (WPos), mm;
    ``buffer``: free planner blocks and RX bytes; ``feed_mm_min`` with ``spindle_rpm`` gives
    ``FS``, alone ``F`` (builds without a variable spindle). Fields left out are not printed.
    """
    if (machine_mm is None) == (work_mm is None):
        raise ValueError("a status report has exactly one of MPos (machine_mm) and WPos (work_mm)")
    parts = [state, "MPos:" + format_mm(machine_mm) if machine_mm is not None else "WPos:" + format_mm(work_mm or ())]
    if buffer is not None:
        parts.append(f"Bf:{buffer[0]},{buffer[1]}")
    if line_number is not None:
        parts.append(f"Ln:{line_number}")
    if feed_mm_min is not None:
        parts.append(f"F:{feed_mm_min:.0f}" if spindle_rpm is None else f"FS:{feed_mm_min:.0f},{spindle_rpm:.0f}")
    if pins:
        parts.append("Pn:" + pins)
    if wco_mm is not None:
        parts.append("WCO:" + format_mm(wco_mm))
    if overrides_pct is not None:
        parts.append("Ov:{},{},{}".format(*overrides_pct))
    if accessories:
        parts.append("A:" + accessories)
    return "<" + "|".join(parts) + ">"


# -- formatting: the lines we send ---------------------------------------------------------------


def format_number(value: float) -> str:
    """A G-code number: at most 4 decimals, no trailing zeros, no ``-0``."""
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _axis_words(x: float | None, y: float | None, z: float | None) -> str:
    words = "".join(f"{a}{format_number(v)}" for a, v in zip("XYZ", (x, y, z)) if v is not None)
    if not words:
        raise GrblUsageError("give at least one of x, y, z")
    for v in (x, y, z):
        if v is not None and not math.isfinite(v):
            raise GrblUsageError(f"axis values must be finite, got {v!r}")
    return words


def motion_line(x: float | None, y: float | None, z: float | None, feed_mm_min: float | None) -> str:
    """``G1X..Y..Z..F..`` (only the axes given), or a rapid ``G0X..`` when ``feed_mm_min`` is None."""
    words = _axis_words(x, y, z)
    if feed_mm_min is None:
        return "G0" + words
    if not feed_mm_min > 0 or not math.isfinite(feed_mm_min):
        raise GrblUsageError(f"feed_mm_min must be positive (or None for a rapid), got {feed_mm_min!r}")
    return "G1" + words + f"F{format_number(feed_mm_min)}"


def jog_line(
    x: float | None, y: float | None, z: float | None, *, feed_mm_min: float, relative: bool = True, machine: bool = False
) -> str:
    """``$J=G91X..F..``: a jog, relative or absolute, in work or machine (G53) coordinates (mm, mm/min)."""
    if feed_mm_min is None or not feed_mm_min > 0:
        raise GrblUsageError("a jog needs a positive feed_mm_min (F is not modal for jogs)")
    head = "$J=" + ("G91" if relative else "G90") + ("G53" if machine else "")
    return head + _axis_words(x, y, z) + f"F{format_number(feed_mm_min)}"


# -- the state machine ---------------------------------------------------------------------


class GrblProtocol:
    """The GRBL 1.1 link state: in-flight lines, resets, the controller's last condition.

    ``rx_limit_bytes``: unanswered bytes allowed in GRBL's ring (127 keeps one byte of margin).
    ``max_line_bytes``: the longest partial line kept while waiting for its terminator.
    """

    def __init__(self, rx_limit_bytes: int = DEFAULT_RX_LIMIT_BYTES, max_line_bytes: int = 1024) -> None:
        if not 2 <= rx_limit_bytes <= RX_BUFFER_BYTES:
            raise GrblUsageError(f"rx_limit_bytes must be 2..{RX_BUFFER_BYTES}, got {rx_limit_bytes}")
        self.rx_limit_bytes = rx_limit_bytes
        self.max_line_bytes = max_line_bytes
        self._in_flight: deque[SentLine] = deque()
        self._in_flight_bytes = 0
        self._partial = bytearray()
        self.reset_pending = False
        self.version: str | None = None
        self.status: Status | None = None
        self.alarm: int | None = None
        self.locked = False
        self.wco_mm: tuple[float, ...] | None = None
        # Statistics (for tests and diagnostics).
        self.max_in_flight_bytes = 0
        self.lines_sent = 0
        self.unmatched_responses = 0
        self.noise_bytes = 0
        self.unrecognized_lines = 0

    # -- outgoing --------------------------------------------------------------------

    @property
    def in_flight(self) -> tuple[SentLine, ...]:
        return tuple(self._in_flight)

    @property
    def in_flight_bytes(self) -> int:
        return self._in_flight_bytes

    @staticmethod
    def check_line(line: bytes | str) -> bytes:
        """The line as bytes, or :class:`GrblUsageError` if GRBL could not take it as one line."""
        data = line.encode("ascii") if isinstance(line, str) else bytes(line)
        if b"\n" in data or b"\r" in data:
            raise GrblUsageError(f"line {data!r} contains a terminator; send one line at a time without '\\n'")
        bad = [c for c in data if c >= 0x80 or (c < 0x20 and c != 0x09)]
        if bad:
            raise GrblUsageError(f"line {data!r} contains byte 0x{bad[0]:02x}; GRBL lines are printable ASCII")
        rt = [chr(c) for c in data if c in _REALTIME_IN_LINE]
        if rt:
            raise GrblUsageError(f"line {data!r} contains {rt[0]!r}, which GRBL executes as a real-time command; remove it")
        if preparsed_length(data) > LINE_MAX_CHARS:
            raise GrblUsageError(f"line {data!r} is longer than GRBL's {LINE_MAX_CHARS}-character line buffer; shorten it")
        return data

    def can_send(self, line: bytes | str) -> bool:
        """Whether ``line`` (plus its ``\\n``) fits in GRBL's ring next to the unanswered lines."""
        return self._in_flight_bytes + len(line) + len(EOL) <= self.rx_limit_bytes

    def send_line(self, line: bytes | str, tag: object = None) -> bytes:
        """Record ``line`` as in flight and return the exact bytes to write (line + ``\\n``)."""
        data = self.check_line(line)
        if self.reset_pending:
            raise GrblUsageError("a soft reset is in progress; wait for the welcome banner before sending lines")
        n = len(data) + len(EOL)
        if n > self.rx_limit_bytes:
            raise GrblUsageError(f"line {data!r} needs {n} bytes, more than the {self.rx_limit_bytes}-byte RX limit")
        if not self.can_send(data):
            raise GrblUsageError(
                f"line {data!r} would overflow GRBL's RX buffer ({self._in_flight_bytes} + {n} > {self.rx_limit_bytes} bytes); "
                "wait for responses first (can_send)"
            )
        self._in_flight.append(SentLine(data, n, tag))
        self._in_flight_bytes += n
        self.max_in_flight_bytes = max(self.max_in_flight_bytes, self._in_flight_bytes)
        self.lines_sent += 1
        return data + EOL

    def realtime(self, command: bytes) -> bytes:
        """The byte to write for a real-time command (see :class:`Realtime`)."""
        if command not in Realtime.ALL:
            raise GrblUsageError(f"{command!r} is not a GRBL real-time command")
        if command == Realtime.SOFT_RESET:
            self.reset_pending = True
        return command

    def forget_in_flight(self) -> tuple[SentLine, ...]:
        """Drop the accounting without a banner (the port was reopened, the device replaced)."""
        lost = tuple(self._in_flight)
        self._in_flight.clear()
        self._in_flight_bytes = 0
        self._partial.clear()
        return lost

    # -- incoming --------------------------------------------------------------------

    def receive_data(self, data: bytes) -> list[Event]:
        """Feed bytes read from the port; returns the events of the complete lines among them."""
        return [event for _, event in self.receive_lines(data)]

    def receive_lines(self, data: bytes) -> list[tuple[bytes, Event]]:
        """Like :meth:`receive_data`, with each event's line as received (no terminator)."""
        out: list[tuple[bytes, Event]] = []
        partial = self._partial
        for b in data:
            if b == 0x0A or b == 0x0D:
                if partial:
                    raw = bytes(partial)
                    partial.clear()
                    out.append((raw, self._line(raw)))
            else:
                if len(partial) >= self.max_line_bytes:
                    raw = bytes(partial)
                    partial.clear()
                    out.append((raw, self._line(raw)))
                partial.append(b)
        return out

    def _line(self, raw: bytes) -> Event:
        clean = bytes(c for c in raw if 0x20 <= c < 0x7F)
        self.noise_bytes += len(raw) - len(clean)
        text = clean.decode("ascii").strip()
        if not text:
            return Unrecognized(raw)
        event = classify_line(text, raw, self.wco_mm)
        if isinstance(event, Ok):
            return Ok(self._answer())
        if isinstance(event, ErrorReply):
            return ErrorReply(event.code, self._answer())
        if isinstance(event, Status):
            self.status = event
            if event.wco_in_report:
                self.wco_mm = event.wco_mm
            if event.state != "Alarm":
                self.alarm = None
            return event
        if isinstance(event, Alarm):
            self.alarm = event.code
            self.locked = self.locked or event.critical
            return event
        if isinstance(event, Message) and event.text == "Reset to continue":
            self.locked = True
        if isinstance(event, Welcome):
            dropped = tuple(self._in_flight)
            self._in_flight.clear()
            self._in_flight_bytes = 0
            self.reset_pending = False
            self.locked = False
            self.version = event.version
            self.wco_mm = None
            return Welcome(event.version, dropped)
        if isinstance(event, Unrecognized):
            self.unrecognized_lines += 1
        return event

    def _answer(self) -> SentLine | None:
        if not self._in_flight:
            self.unmatched_responses += 1
            return None
        sent = self._in_flight.popleft()
        self._in_flight_bytes -= sent.n_bytes
        return sent
