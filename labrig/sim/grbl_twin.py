"""A GRBL 1.1h controller twin at the byte level, for :class:`labrig.sim.serial_pty.TwinServer`.

It answers like the firmware on a 328P at 115200 baud, on the host time it is given (no sleeping,
deterministic):

* **Serial.** Bytes from the host arrive one per 10 bit times (86.8 us at 115200 baud). Real-time
  bytes (``?``, ``!``, ``~``, 0x18, 0x85, overrides, 0xA0 flood toggle) act at once and take no
  buffer space; other bytes go into a 128-byte RX ring, and bytes that find it full are dropped
  **silently** (counted in :attr:`GrblTwin.rx_overflow_bytes`). Output is paced at the baud rate.
  While an EEPROM write is in progress (settings, ``G10``, ``G28.1``, ``$N``, ...) received
  bytes are lost, as on the AVR (counted in :attr:`GrblTwin.rx_blackout_bytes`).
* **Main loop.** Lines are taken from the ring one at a time (the ring is drained only while the
  loop is free), pre-parsed like GRBL (spaces, control bytes and comments dropped, upper case,
  79 characters or ``error:11``), then executed after ``parse_us``. Motion lines wait for a free
  block in the 15-block planner, so no ``ok`` comes while the planner is full; ``G4``, ``M3-M5``,
  ``M8``/``M9``, ``M0``/``M2``/``M30`` wait until motion has finished (no ``ok`` during a hold).
  A cycle starts automatically when the ring has no more bytes or the planner is full.
* **Motion.** Trapezoidal profiles with junction-deviation corners and look-ahead replanning
  (:mod:`labrig.devices.motion_profile`), step-quantised targets (``$100-$102``), feed and rapid
  overrides, feed hold and resume, jog cancel, soft limits (``ALARM:2`` locks until reset,
  ``error:15`` for jogs), homing against simulated switches, check mode, sleep.
* **States.** Idle, Run, Hold:0/Hold:1, Jog, Alarm, Check, Home, Sleep. With ``$22=1`` it powers
  up in Alarm. A soft reset in motion gives ``ALARM:3`` (``ALARM:6`` while homing); a reset
  keeps the position.
* **Outputs.** ``M8``/``M9`` (flood), ``M3``/``M4``/``M5`` (spindle) and the 0xA0 toggle call
  ``on_output(t_us, name, level)`` at the host time the output switches (the virtual rig makes
  camera trigger edges of it); edges are also kept in :attr:`GrblTwin.outputs`.

:meth:`GrblTwin.position_mm` gives the machine position (MPos) of the tool reference at any host
times, vectorised, from the executed and planned segments. Physical limit switches sit at the
ends of ``[-max_travel, 0]`` in a frame that differs from MPos by :attr:`GrblTwin.physical_offset_mm`
until homing sets MPos (the tool starts at ``power_on_physical_mm`` with MPos 0).

Known differences from the firmware: arcs (``G2``/``G3``), probing (``G38.x``), safety door,
hard limits, parking and laser mode are not simulated (arcs and probing answer ``error:20``);
homing runs Z, then X, then Y one after the other with the same four phases (seek, back off,
locate, pull off) and no overshoot; the TX buffer never blocks the main loop; a status report
is answered at once (the firmware takes a few ms); ``$N`` lines are checked for syntax only.
"""

from __future__ import annotations

import math
import re
import threading
from collections import deque
from collections.abc import Callable, Generator, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from labrig.devices.grbl_protocol import (
    LINE_END,
    LINE_MAX_CHARS,
    PLANNER_BLOCKS,
    RX_BUFFER_BYTES,
    format_alarm,
    format_error,
    format_help,
    format_message,
    format_ok,
    format_options,
    format_parameter,
    format_parser_state,
    format_probe,
    format_setting,
    format_startup_line,
    format_startup_result,
    format_status,
    format_version,
    format_welcome,
)
from labrig.devices.motion_profile import MachineLimits, MotionTimeline, make_block, quantize_mm

VERSION = "1.1h.20190830"
BANNER = format_welcome("1.1h")
HELP = format_help("$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x")
OK = format_ok()
LINE_BUFFER_CHARS = LINE_MAX_CHARS
MAX_STEP_RATE_HZ = 30_000.0

#: GRBL 1.1h default settings ($$ of a fresh EEPROM).
DEFAULT_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
    20: 0, 21: 0, 22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0,
    100: 250.0, 101: 250.0, 102: 250.0, 110: 500.0, 111: 500.0, 112: 500.0,
    120: 10.0, 121: 10.0, 122: 10.0, 130: 200.0, 131: 200.0, 132: 200.0,
}  # fmt: skip
_INTEGER_SETTINGS = frozenset({0, 1, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 30, 31, 32})
_BOOLEAN_SETTINGS = frozenset({4, 13, 20, 21, 22, 32})
_BUSY_STATES = frozenset({"Run", "Jog", "Hold", "Home", "Door"})

# ("now",) | ("time", t_us) | ("slot",) | ("idle",) | ("rest",)
Wait = tuple
Job = Generator[Wait, None, "str | None"]
OutputHook = Callable[[int, str, int], None]

_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)")

# Modal groups of the G and M words the twin knows: (number, mantissa*100) -> group.
_G_GROUPS: dict[tuple[int, int], str] = {
    (0, 0): "motion", (1, 0): "motion", (2, 0): "motion", (3, 0): "motion", (80, 0): "motion",
    (38, 20): "motion", (38, 30): "motion", (38, 40): "motion", (38, 50): "motion",
    (4, 0): "non_modal", (10, 0): "non_modal", (28, 0): "non_modal", (28, 10): "non_modal",
    (30, 0): "non_modal", (30, 10): "non_modal", (53, 0): "non_modal", (92, 0): "non_modal", (92, 10): "non_modal",
    (17, 0): "plane", (18, 0): "plane", (19, 0): "plane", (90, 0): "distance", (91, 0): "distance",
    (91, 10): "arc_distance", (93, 0): "feed_mode", (94, 0): "feed_mode", (20, 0): "units", (21, 0): "units",
    (40, 0): "cutter", (43, 10): "tlo", (49, 0): "tlo", (61, 0): "path",
    **{(n, 0): "wcs" for n in range(54, 60)},
}  # fmt: skip
_G_NUMBERS = frozenset(n for n, _ in _G_GROUPS)
_M_GROUPS = {
    0: "stopping",
    1: "stopping",
    2: "stopping",
    30: "stopping",
    3: "spindle",
    4: "spindle",
    5: "spindle",
    8: "coolant",
    9: "coolant",
}
_AXIS_COMMANDS = frozenset({(10, 0), (28, 0), (30, 0), (92, 0)})


class _GcodeError(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def _words(text: str) -> list[tuple[str, float]]:
    """Letter/number pairs of a pre-parsed line (``error:1``/``error:2`` on malformed words)."""
    out = []
    i = 0
    while i < len(text):
        letter = text[i]
        if not "A" <= letter <= "Z":
            raise _GcodeError(1)
        m = _NUMBER.match(text, i + 1)
        if m is None:
            raise _GcodeError(2)
        out.append((letter, float(m.group())))
        i = m.end()
    return out


def _g_code(value: float) -> tuple[int, int]:
    number = int(value)
    return number, round((value - number) * 100)


@dataclass
class _Modal:
    """The G-code parser's modal state (feed in mm/min)."""

    motion: tuple[int, int] = (0, 0)
    wcs: int = 0
    plane: int = 17
    inches: bool = False
    incremental: bool = False
    inverse_time: bool = False
    spindle: int = 5
    flood: bool = False
    tool: int = 0
    feed_mm_min: float = 0.0
    spindle_rpm: float = 0.0


@dataclass
class _Plan:
    """A validated G-code block: what to do, in GRBL's execution order."""

    modal: _Modal
    dwell_s: float | None = None
    non_modal: tuple[int, int] | None = None
    axis_values: dict[int, float] | None = None  # axis -> value in mm (non-modal commands)
    target_mm: list[float] | None = None  # machine target of a G0/G1
    feed_mm_min: float | None = None  # None: rapid
    l_value: int = 0
    p_value: int = 0
    tlo_mm: float | None = None
    stopping: int | None = None
    wco_changed: bool = False


class GrblTwin:
    """GRBL 1.1h on a simulated 328P: see the module docstring.

    ``settings``: EEPROM contents on top of the 1.1h defaults (e.g. ``{22: 1, 20: 1}``).
    ``parse_us``: time the main loop spends on a line before answering it.
    ``eeprom_write_us``: how long an EEPROM write keeps the serial receiver deaf.
    ``power_on_physical_mm``: the tool's place in the switch frame at power-up (MPos reads 0).
    ``homed``: start as if homed earlier in the session (MPos reads the switch frame; no Alarm).
    ``link_latency_us``: extra delay each way, as a USB-serial bridge adds (0: a bare UART;
    about 1000 for an Uno's USB chip, 16000 for an FTDI at its default latency timer).
    """

    def __init__(
        self,
        settings: Mapping[int, float] | None = None,
        *,
        baud: int = 115200,
        parse_us: float = 250.0,
        eeprom_write_us: float = 10_000.0,
        power_on_physical_mm: Sequence[float] = (-100.0, -100.0, -40.0),
        on_output: OutputHook | None = None,
        build_info: str = "",
        link_latency_us: float = 0.0,
        homed: bool = False,
    ) -> None:
        self.settings: dict[int, float] = dict(DEFAULT_SETTINGS)
        for number, value in (settings or {}).items():
            if number not in DEFAULT_SETTINGS:
                raise ValueError(f"GRBL has no setting ${number}")
            self.settings[number] = float(value)
        self.byte_us = 10 * 1e6 / baud
        self.parse_us = float(parse_us)
        self.eeprom_write_us = float(eeprom_write_us)
        self.link_latency_us = float(link_latency_us)
        self.on_output = on_output
        self.build_info = build_info
        self.startup_lines = ["", ""]
        self.outputs: list[tuple[int, str, int]] = []
        self.lines_executed = 0
        self.rx_overflow_bytes = 0
        self.rx_blackout_bytes = 0
        self.max_rx_fill_bytes = 0
        self.received: deque[str] = deque(maxlen=4096)
        self._lock = threading.RLock()
        self._power_on_physical = [float(x) for x in power_on_physical_mm]
        self._homed_at_power_on = bool(homed)
        self._t: float | None = None
        # serial
        self._wire: deque[tuple[float, int]] = deque()
        self._wire_free_us = -math.inf
        self._ring: deque[int] = deque()
        self._blackout_until_us = -math.inf
        self._tx: deque[tuple[float, bytes]] = deque()
        self._tx_free_us = -math.inf
        # line assembly
        self._line = bytearray()
        self._in_paren = False
        self._in_comment = False
        self._line_overflow = False
        # main loop
        self._job: Job | None = None
        self._wait: Wait = ("now",)
        self._after_response: Callable[[], None] | None = None
        self._deferred_ok = False
        # machine
        self._tl = MotionTimeline(self._limits())
        self._offset = [0.0, 0.0, 0.0]
        self._state = "Idle"
        self._locked = False
        self._sync_gc_when_idle = False
        self._modal = _Modal()
        self._gc_mm = [0.0, 0.0, 0.0]
        self._wcs = [[0.0, 0.0, 0.0] for _ in range(6)]
        self._g28 = [0.0, 0.0, 0.0]
        self._g30 = [0.0, 0.0, 0.0]
        self._g92 = [0.0, 0.0, 0.0]
        self._tlo = 0.0
        self._probe = ([0.0, 0.0, 0.0], False)
        self._overrides = [100, 100, 100]
        self._wco_counter = 0
        self._ovr_counter = 0

    # -- the SerialTwin protocol -----------------------------------------------------------

    def receive(self, data: bytes, now_us: int) -> None:
        """Bytes the host wrote at ``now_us``: they arrive one per byte time after it."""
        with self._lock:
            self._run_until(now_us)
            start = max(float(now_us) + self.link_latency_us, self._wire_free_us)
            for i, b in enumerate(data):
                self._wire.append((start + (i + 1) * self.byte_us, b))
            if data:
                self._wire_free_us = start + len(data) * self.byte_us

    def transmit(self, now_us: int) -> bytes:
        """Bytes whose last bit has left the UART by ``now_us`` (less the link latency)."""
        with self._lock:
            self._run_until(now_us)
            out = bytearray()
            while self._tx:
                start, data = self._tx[0]
                n = int((now_us - self.link_latency_us - start) / self.byte_us + 1e-9)
                if n <= 0:
                    break
                if n >= len(data):
                    out += data
                    self._tx.popleft()
                    continue
                out += data[:n]
                self._tx[0] = (start + n * self.byte_us, data[n:])
                break
            return bytes(out)

    # -- fault injection ------------------------------------------------------------------

    def trip_hard_limit(self, now_us: int) -> None:
        """A limit switch fires at ``now_us`` (a crash, or noise on its wire), as with ``$21=1``.

        Motion stops dead, ``ALARM:1`` and ``[MSG:Reset to continue]`` go out, and everything
        (even ``?``) is ignored until a soft reset, after which the twin stays in Alarm. The line
        the main loop was busy with is answered only after that reset, as by the firmware.
        """
        with self._lock:
            self._run_until(now_us)
            assert self._t is not None
            self._tl.stop(self._t)
            self._deferred_ok = self._job is not None
            self._alarm(1, critical=True)

    # -- queries -----------------------------------------------------------------------

    def position_mm(self, t_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Machine position (N, 3) mm of the tool reference at host times ``t_us`` (us).

        Past times come from the executed segments; times beyond the twin's clock from the
        current plan (which later commands can still change).
        """
        with self._lock:
            return self._tl.positions_at(t_us)

    @property
    def state(self) -> str:
        """The state as a status report would print it (``Idle``, ``Hold:0``, ...)."""
        with self._lock:
            return self._state_text()

    @property
    def physical_offset_mm(self) -> tuple[float, float, float]:
        """Switch-frame position minus MPos (0 once homed with switches at the travel ends)."""
        return (self._offset[0], self._offset[1], self._offset[2])

    @property
    def planner_blocks(self) -> int:
        return len(self._tl.queue)

    @property
    def rx_fill_bytes(self) -> int:
        return len(self._ring)

    def segments(self) -> list:
        """The executed and planned motion segments (see :class:`~labrig.devices.motion_profile.Segment`)."""
        with self._lock:
            return self._tl.segments()

    # -- time ---------------------------------------------------------------------------

    def _run_until(self, now_us: float) -> None:
        now = float(now_us)
        if self._t is None:
            self._t = now
            if self._homed_at_power_on:  # as if homed before this session: MPos is the switch frame
                self._tl = MotionTimeline(self._limits(), tuple(self._power_on_physical), now)
                self._offset = [0.0, 0.0, 0.0]
            else:
                self._tl = MotionTimeline(self._limits(), (0.0, 0.0, 0.0), now)
                self._offset = list(self._power_on_physical)
            self._boot(power_on=True, alarm=False)
        while True:
            self._step_main_loop()
            t_next = min(
                self._wire[0][0] if self._wire else math.inf,
                self._wait[1]
                if self._job is not None and self._wait[0] == "time" and not self._locked and self._state != "Sleep"
                else math.inf,
                self._tl.next_event_us(),
            )
            if t_next > now:
                break
            self._t = max(self._t, t_next)
            self._advance_motion()
            if self._wire and self._wire[0][0] <= self._t:
                self._on_byte(self._wire.popleft()[1])
        self._t = max(self._t, now)
        self._advance_motion()

    def _advance_motion(self) -> None:
        assert self._t is not None
        self._tl.advance(self._t)
        if self._state in ("Run", "Jog") and self._tl.state == "idle":
            if self._state == "Jog" or self._sync_gc_when_idle:
                self._gc_mm = list(self._tl.position_mm)
                self._sync_gc_when_idle = False
            self._state = "Idle"

    # -- serial in ----------------------------------------------------------------------

    def _on_byte(self, b: int) -> None:
        assert self._t is not None
        if self._t < self._blackout_until_us:
            self.rx_blackout_bytes += 1
            return
        if b == 0x18:
            self._soft_reset()
        elif b == 0x3F:  # ?
            if not self._locked and self._state != "Home":
                self._emit(self._status_report())
        elif b == 0x21:  # !
            self._feed_hold()
        elif b == 0x7E:  # ~
            self._cycle_start()
        elif b >= 0x80:
            self._realtime_extended(b)
        elif len(self._ring) >= RX_BUFFER_BYTES:
            self.rx_overflow_bytes += 1
        else:
            self._ring.append(b)
            self.max_rx_fill_bytes = max(self.max_rx_fill_bytes, len(self._ring))

    def _take_line(self) -> tuple[str, bool] | None:
        """Drain the ring into the line buffer like GRBL's pre-parser; a complete line or None."""
        ring = self._ring
        while ring:
            b = ring.popleft()
            if b in (0x0A, 0x0D):
                line, overflow = self._line.decode("ascii"), self._line_overflow
                self._line.clear()
                self._in_paren = self._in_comment = self._line_overflow = False
                return line, overflow
            if self._in_comment:
                continue
            if self._in_paren:
                self._in_paren = b != 0x29
            elif b == 0x28:
                self._in_paren = True
            elif b == 0x3B:
                self._in_comment = True
            elif b <= 0x20 or b >= 0x7F or b == 0x2F:
                continue
            elif len(self._line) >= LINE_BUFFER_CHARS:
                self._line_overflow = True
            else:
                self._line.append(b - 32 if 0x61 <= b <= 0x7A else b)
        return None

    # -- serial out ---------------------------------------------------------------------

    def _emit(self, text: str) -> None:
        assert self._t is not None
        data = text.encode("ascii") + LINE_END
        start = max(self._t, self._tx_free_us)
        self._tx.append((start, data))
        self._tx_free_us = start + len(data) * self.byte_us

    def _status_report(self) -> str:
        position = self._tl.position_mm
        wco = self._wco()
        mask = int(self.settings[10])
        work = None if mask & 1 else [p - o for p, o in zip(position, wco)]
        busy = self._state in _BUSY_STATES
        wco_due = self._wco_counter == 0
        if wco_due:
            self._wco_counter = 29 if busy else 9
            if self._ovr_counter == 0:
                self._ovr_counter = 1
        else:
            self._wco_counter -= 1
        ovr_due = self._ovr_counter == 0
        if ovr_due:
            self._ovr_counter = 19 if busy else 9
        else:
            self._ovr_counter -= 1
        accessories = {3: "S", 4: "C"}.get(self._modal.spindle, "") + ("F" if self._modal.flood else "")
        return format_status(
            self._state_text(),
            machine_mm=position if work is None else None,
            work_mm=work,
            buffer=(PLANNER_BLOCKS - len(self._tl.queue), RX_BUFFER_BYTES - len(self._ring)) if mask & 2 else None,
            feed_mm_min=self._tl.speed_mm_s * 60.0,
            spindle_rpm=self._modal.spindle_rpm if self._modal.spindle in (3, 4) else 0.0,
            pins=self._pins(),
            wco_mm=wco if wco_due else None,
            overrides_pct=(self._overrides[0], self._overrides[1], self._overrides[2]) if ovr_due else None,
            accessories=accessories if ovr_due else "",
        )

    def _state_text(self) -> str:
        if self._state == "Hold":
            return "Hold:1" if self._tl.state == "hold" else "Hold:0"
        return self._state

    def _pins(self) -> str:
        out = ""
        for axis, letter in enumerate("XYZ"):
            physical = self._tl.position_mm[axis] + self._offset[axis]
            if abs(physical - self._switch_mm(axis)) < 1e-6:
                out += letter
        return out

    # -- real-time commands ----------------------------------------------------------------

    def _feed_hold(self) -> None:
        assert self._t is not None
        if self._locked:
            return
        if self._state == "Run" or self._state == "Idle":
            self._tl.hold(self._t)
            self._state = "Hold"
        elif self._state == "Jog":
            self._tl.cancel(self._t)

    def _cycle_start(self) -> None:
        assert self._t is not None
        if self._locked:
            return
        if self._state == "Hold" and self._tl.state != "hold":
            if self._tl.state == "held":
                self._tl.resume(self._t)
            elif self._tl.state == "queued":
                self._tl.start(self._t)
            self._state = "Run" if self._tl.state == "run" else "Idle"
        elif self._state == "Idle":
            self._auto_start()

    def _realtime_extended(self, b: int) -> None:
        assert self._t is not None
        feed, rapid, spindle = self._overrides
        if b == 0x85:
            if self._state == "Jog":
                self._tl.cancel(self._t)
            return
        if 0x90 <= b <= 0x94:
            feed = {0x90: 100, 0x91: feed + 10, 0x92: feed - 10, 0x93: feed + 1, 0x94: feed - 1}[b]
        elif 0x95 <= b <= 0x97:
            rapid = {0x95: 100, 0x96: 50, 0x97: 25}[b]
        elif 0x99 <= b <= 0x9D:
            spindle = {0x99: 100, 0x9A: spindle + 10, 0x9B: spindle - 10, 0x9C: spindle + 1, 0x9D: spindle - 1}[b]
        elif b == 0xA0:
            if self._state in ("Idle", "Run", "Hold"):
                self._set_flood(not self._modal.flood)
            return
        else:
            return  # 0x84 door, 0x9E spindle stop, 0xA1 mist: not simulated; others are discarded
        new = [min(max(feed, 10), 200), rapid, min(max(spindle, 10), 200)]
        if new != self._overrides:
            self._overrides = new
            self._ovr_counter = 0
            self._tl.feed_scale = new[0] / 100.0
            self._tl.rapid_scale = new[1] / 100.0
            self._tl.rescale(self._t)

    def _soft_reset(self) -> None:
        assert self._t is not None
        alarm = None
        if self._state == "Home":
            alarm = 6
        elif self._state in ("Run", "Jog", "Hold") or self._tl.state in ("run", "hold"):
            alarm = 3
        self._tl.stop(self._t)
        if self._job is not None:
            self._job.close()
        self._job, self._wait, self._after_response = None, ("now",), None
        self._ring.clear()
        self._line.clear()
        self._in_paren = self._in_comment = self._line_overflow = False
        self._set_spindle(5)
        self._set_flood(False)
        if alarm is not None:
            self._emit(format_alarm(alarm))
        if self._deferred_ok:
            self._emit(OK)
        stay_alarm = alarm is not None or self._state in ("Alarm", "Sleep")
        self._boot(power_on=False, alarm=stay_alarm)

    def _boot(self, power_on: bool, alarm: bool) -> None:
        """After power-up or a soft reset: banner, parser defaults, Alarm or the startup lines."""
        self._locked = False
        self._deferred_ok = False
        self._modal = _Modal()
        self._g92 = [0.0, 0.0, 0.0]
        self._tlo = 0.0
        self._overrides = [100, 100, 100]
        self._tl.feed_scale = self._tl.rapid_scale = 1.0
        self._gc_mm = list(self._tl.position_mm)
        self._wco_counter = self._ovr_counter = 0
        self._sync_gc_when_idle = False
        self._emit("")
        self._emit(BANNER)
        if alarm or (power_on and self.settings[22]):
            self._state = "Alarm"
            self._emit(format_message("'$H'|'$X' to unlock"))
        else:
            self._state = "Idle"
            self._start_job(self._startup_lines_job())

    # -- the main loop ---------------------------------------------------------------------

    def _start_job(self, job: Job) -> None:
        self._job, self._wait = job, ("now",)

    def _step_main_loop(self) -> None:
        while not self._locked and self._state != "Sleep":
            if self._job is not None:
                if not self._ready(self._wait):
                    if self._wait[0] in ("slot", "idle"):
                        self._auto_start()
                    return
                try:
                    self._wait = self._job.send(None)
                except StopIteration as stop:
                    self._job = None
                    self._respond(stop.value)
                continue
            taken = self._take_line()
            if taken is None:
                self._auto_start()
                return
            self._start_job(self._line_job(*taken))

    def _ready(self, wait: Wait) -> bool:
        assert self._t is not None
        kind = wait[0]
        if kind == "now":
            return True
        if kind == "time":
            return self._t >= wait[1]
        if kind == "slot":
            return len(self._tl.queue) < PLANNER_BLOCKS
        if kind == "idle":
            return self._tl.state == "idle"
        if kind == "rest":
            return self._tl.state not in ("run", "hold")
        raise AssertionError(wait)

    def _auto_start(self) -> None:
        assert self._t is not None
        if self._tl.state == "queued" and self._state in ("Idle", "Run"):
            self._tl.start(self._t)
            self._state = "Run"

    def _respond(self, response: str | None) -> None:
        if response is not None:
            self._emit(response)
        action, self._after_response = self._after_response, None
        if action is not None:
            action()

    def _line_job(self, line: str, overflow: bool) -> Job:
        assert self._t is not None
        yield ("time", self._t + self.parse_us)
        self.lines_executed += 1
        self.received.append(line)
        if overflow:
            return format_error(11)
        if not line:
            return OK
        if line.startswith("$"):
            return (yield from self._system_command(line[1:]))
        if self._state in ("Alarm", "Jog"):
            return format_error(9)
        return (yield from self._gcode(line))

    def _startup_lines_job(self) -> Job:
        for line in self.startup_lines:
            if line:
                result = yield from self._gcode(line)
                if result is None:  # a soft-limit alarm locked the controller
                    return None
                self._emit(format_startup_result(line, result))
        return None

    # -- $ commands --------------------------------------------------------------------------

    def _system_command(self, body: str) -> Job:
        state = self._state
        if body == "":
            self._emit(HELP)
            return OK
        if body == "$":
            if state in ("Run", "Hold"):
                return format_error(8)
            for number in sorted(self.settings):
                self._emit(format_setting(number, self.settings[number], integer=number in _INTEGER_SETTINGS))
            return OK
        if body == "G":
            self._emit(self._parser_state())
            return OK
        if body == "C":
            if state == "Check":
                self._emit(format_message("Disabled"))
                self._after_response = self._soft_reset
                return OK
            if state != "Idle":
                return format_error(8)
            self._state = "Check"
            self._emit(format_message("Enabled"))
            return OK
        if body == "X":
            if state == "Alarm":
                self._emit(format_message("Caution: Unlocked"))
                self._state = "Idle"
                self._gc_mm = list(self._tl.position_mm)
            return OK
        if body.startswith("J"):
            if state not in ("Idle", "Jog"):
                return format_error(8)
            if body[1:2] != "=":
                return format_error(3)
            return (yield from self._jog(body[2:]))
        if state not in ("Idle", "Alarm"):
            return format_error(8)
        if body == "#":
            for n in range(6):
                self._emit(format_parameter(f"G{54 + n}", self._wcs[n]))
            self._emit(format_parameter("G28", self._g28))
            self._emit(format_parameter("G30", self._g30))
            self._emit(format_parameter("G92", self._g92))
            self._emit(format_parameter("TLO", [self._tlo]))
            self._emit(format_probe(*self._probe))
            return OK
        if body == "H":
            return (yield from self._home())
        if body == "SLP":
            self._after_response = self._sleep
            return OK
        if body == "I":
            self._emit(format_version(VERSION, self.build_info))
            self._emit(format_options("V", PLANNER_BLOCKS, RX_BUFFER_BYTES))
            return OK
        if body.startswith("I="):
            self.build_info = body[2:]
            yield from self._eeprom_write()
            return OK
        if body.startswith("RST="):
            return (yield from self._restore(body[4:]))
        if body == "N":
            for i, line in enumerate(self.startup_lines):
                self._emit(format_startup_line(i, line))
            return OK
        m = re.fullmatch(r"N(\d+)=(.*)", body)
        if m:
            index = int(m.group(1))
            if index >= len(self.startup_lines):
                return format_error(3)
            try:
                _words(m.group(2))
            except _GcodeError as exc:
                return format_error(exc.code)
            self.startup_lines[index] = m.group(2)
            yield from self._eeprom_write()
            return OK
        m = re.fullmatch(r"(\d+)=(.*)", body)
        if m:
            return (yield from self._write_setting(int(m.group(1)), m.group(2)))
        return format_error(3)

    def _write_setting(self, number: int, text: str) -> Job:
        if _NUMBER.fullmatch(text) is None:
            return format_error(2)
        value = float(text)
        if number not in DEFAULT_SETTINGS:
            return format_error(3)
        if value < 0:
            return format_error(4)
        if number in _INTEGER_SETTINGS:
            value = float(int(value))
        if number in _BOOLEAN_SETTINGS:
            value = 1.0 if value else 0.0
        if number == 0 and value < 3:
            return format_error(6)
        if number == 20 and value and not self.settings[22]:
            return format_error(10)
        if 100 <= number <= 102 and value * self.settings[number + 10] / 60.0 > MAX_STEP_RATE_HZ:
            return format_error(12)
        if 110 <= number <= 112 and self.settings[number - 10] * value / 60.0 > MAX_STEP_RATE_HZ:
            return format_error(12)
        self.settings[number] = value
        if number == 22 and not value:
            self.settings[20] = 0.0  # soft limits cannot stay on without homing
        self._tl.limits = self._limits()
        yield from self._eeprom_write()
        return OK

    def _restore(self, which: str) -> Job:
        if which not in ("$", "#", "*"):
            return format_error(3)
        if which in ("$", "*"):
            self.settings = dict(DEFAULT_SETTINGS)
            self._tl.limits = self._limits()
        if which in ("#", "*"):
            self._wcs = [[0.0, 0.0, 0.0] for _ in range(6)]
            self._g28 = [0.0, 0.0, 0.0]
            self._g30 = [0.0, 0.0, 0.0]
        if which == "*":
            self.startup_lines = ["", ""]
            self.build_info = ""
        yield from self._eeprom_write()
        self._emit(format_message("Restoring defaults"))
        self._after_response = self._soft_reset
        return OK

    def _eeprom_write(self) -> Generator[Wait, None, None]:
        assert self._t is not None
        self._blackout_until_us = self._t + self.eeprom_write_us
        yield ("time", self._blackout_until_us)

    def _sleep(self) -> None:
        self._emit(format_message("Sleeping"))
        self._set_spindle(5)
        self._set_flood(False)
        self._state = "Sleep"

    def _parser_state(self) -> str:
        m = self._modal
        motion = {(0, 0): "G0", (1, 0): "G1", (80, 0): "G80"}.get(m.motion, "G0")
        words = [
            motion, f"G{54 + m.wcs}", f"G{m.plane}", "G20" if m.inches else "G21", "G91" if m.incremental else "G90",
            "G93" if m.inverse_time else "G94", f"M{m.spindle}", "M8" if m.flood else "M9", f"T{m.tool}",
            f"F{m.feed_mm_min:.0f}", f"S{m.spindle_rpm:.0f}",
        ]  # fmt: skip
        return format_parser_state(words)

    # -- jogging and homing ------------------------------------------------------------------

    def _jog(self, body: str) -> Job:
        assert self._t is not None
        try:
            words = _words(body)
        except _GcodeError as exc:
            return format_error(exc.code)
        inches, incremental, machine = self._modal.inches, self._modal.incremental, False
        values: dict[int, float] = {}
        feed = None
        for letter, value in words:
            if letter == "G":
                code = _g_code(value)
                if code == (20, 0) or code == (21, 0):
                    inches = code == (20, 0)
                elif code == (90, 0) or code == (91, 0):
                    incremental = code == (91, 0)
                elif code == (53, 0):
                    machine = True
                else:
                    return format_error(16)
            elif letter in "XYZ":
                axis = "XYZ".index(letter)
                if axis in values:
                    return format_error(25)
                values[axis] = value
            elif letter == "F":
                if feed is not None:
                    return format_error(25)
                feed = value
            else:
                return format_error(16)
        if feed is None:
            return format_error(22)
        if not values:
            return format_error(26)
        if feed < 0:
            return format_error(4)
        unit = 25.4 if inches else 1.0
        target = self._target({a: v * unit for a, v in values.items()}, incremental, machine)
        if self.settings[20] and self._beyond_travel(target):
            return format_error(15)
        self._gc_mm = target
        while len(self._tl.queue) >= PLANNER_BLOCKS:
            yield ("slot",)
        block = make_block(self._tl.tail_mm, self._quantize(target), feed * unit, self._tl.limits, tag="jog")
        if block is not None:
            self._tl.append(block, self._t)
            if self._state == "Idle":
                self._tl.start(self._t)
                self._state = "Jog"
        return OK

    def _switch_mm(self, axis: int) -> float:
        """The limit switch's place in the physical frame (travel is ``[-max_travel, 0]``)."""
        negative = (int(self.settings[23]) >> axis) & 1
        return -self.settings[130 + axis] if negative else 0.0

    def _home(self) -> Job:
        assert self._t is not None
        if not self.settings[22]:
            return format_error(5)
        self._state = "Home"
        pull = self.settings[27]
        for axis in (2, 0, 1):
            direction = -1.0 if (int(self.settings[23]) >> axis) & 1 else 1.0
            travel = self.settings[130 + axis]
            physical = self._tl.position_mm[axis] + self._offset[axis]
            distance = max((self._switch_mm(axis) - physical) * direction, 0.0)
            if distance > 1.5 * travel:
                yield from self._home_move(axis, direction * 1.5 * travel, self.settings[25])
                self._alarm(9)
                return OK
            for delta, rate in (
                (distance, self.settings[25]),
                (-pull, self.settings[24]),
                (pull, self.settings[24]),
                (-pull, self.settings[24]),
            ):
                yield from self._home_move(axis, direction * delta, rate)
            homed = list(self._tl.position_mm)
            homed[axis] = -pull if direction > 0 else -travel + pull
            self._offset[axis] += self._tl.position_mm[axis] - homed[axis]
            self._tl.set_position(homed, self._t)
        self._gc_mm = list(self._tl.position_mm)
        self._state = "Idle"
        yield from self._startup_lines_job()
        return OK

    def _home_move(self, axis: int, delta_mm: float, rate_mm_min: float) -> Generator[Wait, None, None]:
        assert self._t is not None
        start = self._tl.position_mm
        end = list(start)
        end[axis] += delta_mm
        block = make_block(start, self._quantize(end), rate_mm_min, self._tl.limits, tag="home")
        if block is not None:
            self._tl.append(block, self._t)
            self._tl.start(self._t)
            while self._tl.state != "idle":
                yield ("idle",)

    def _alarm(self, code: int, critical: bool = False) -> None:
        self._emit(format_alarm(code))
        self._state = "Alarm"
        if critical:
            self._emit(format_message("Reset to continue"))
            self._locked = True

    # -- G-code ------------------------------------------------------------------------

    def _gcode(self, line: str) -> Job:
        assert self._t is not None
        try:
            plan = self._interpret(_words(line))
        except _GcodeError as exc:
            return format_error(exc.code)
        check = self._state == "Check"
        new, old = plan.modal, self._modal
        spindle_change = new.spindle != old.spindle or (new.spindle in (3, 4) and new.spindle_rpm != old.spindle_rpm)
        if (spindle_change or new.flood != old.flood) and not check:
            yield from self._synchronize()  # spindle and coolant switch once queued motion has run
        self._modal = replace(new, spindle=old.spindle, flood=old.flood)
        if check:
            self._modal.spindle, self._modal.flood = new.spindle, new.flood
        else:
            self._set_spindle(new.spindle)
            self._set_flood(new.flood)
        if plan.dwell_s is not None and not check:
            yield from self._synchronize()
            yield ("time", self._t + plan.dwell_s * 1e6)
        if plan.tlo_mm is not None:
            self._tlo = plan.tlo_mm
        if plan.wco_changed:
            self._wco_counter = 0
        nm = plan.non_modal
        values = plan.axis_values or {}
        if nm == (10, 0):
            index = self._modal.wcs if plan.p_value == 0 else plan.p_value - 1
            for axis, v in values.items():
                if plan.l_value == 2:
                    self._wcs[index][axis] = v
                else:
                    self._wcs[index][axis] = self._gc_mm[axis] - v - self._g92[axis] - (self._tlo if axis == 2 else 0.0)
            self._wco_counter = 0
            yield from self._eeprom_write()
        elif nm in ((28, 10), (30, 10)):
            (self._g28 if nm[0] == 28 else self._g30)[:] = self._gc_mm
            yield from self._eeprom_write()
        elif nm == (92, 0):
            for axis, v in values.items():
                self._g92[axis] = self._gc_mm[axis] - self._wcs[self._modal.wcs][axis] - v - (self._tlo if axis == 2 else 0.0)
            self._wco_counter = 0
        elif nm == (92, 10):
            self._g92 = [0.0, 0.0, 0.0]
            self._wco_counter = 0
        elif nm in ((28, 0), (30, 0)):
            if values:
                intermediate = self._target(values, self._modal.incremental, False)
                if not (yield from self._motion(intermediate, None, check)):
                    return None
            stored = list(self._g28 if nm[0] == 28 else self._g30)
            if not (yield from self._motion(stored, None, check)):
                return None
        if plan.target_mm is not None and not (yield from self._motion(plan.target_mm, plan.feed_mm_min, check)):
            return None
        if plan.stopping is not None and not check:
            yield from self._synchronize()
        if plan.stopping == 0:
            if not check:
                self._tl.hold(self._t)
                self._state = "Hold"
        elif plan.stopping in (2, 30):
            self._modal = replace(self._modal, motion=(1, 0), plane=17, incremental=False, inverse_time=False, wcs=0)
            if not check:
                self._set_spindle(5)
                self._set_flood(False)
            self._modal.spindle, self._modal.flood = 5, False
            self._overrides = [100, 100, 100]
            self._emit(format_message("Pgm End"))
        return OK

    def _synchronize(self) -> Generator[Wait, None, None]:
        while self._tl.state != "idle":
            yield ("idle",)

    def _motion(self, target: list[float], feed_mm_min: float | None, check: bool) -> Generator[Wait, None, bool]:
        """Plan a straight move to the machine ``target``; False after a soft-limit alarm."""
        assert self._t is not None
        if self.settings[20] and self._beyond_travel(target):
            if self._tl.state in ("run", "hold"):
                self._tl.hold(self._t)
                while self._tl.state in ("run", "hold"):
                    yield ("rest",)
            self._tl.stop(self._t)
            self._alarm(2, critical=True)
            self._deferred_ok = True
            return False
        self._gc_mm = list(target)
        if check:
            return True
        while len(self._tl.queue) >= PLANNER_BLOCKS:
            yield ("slot",)
        block = make_block(self._tl.tail_mm, self._quantize(target), feed_mm_min, self._tl.limits)
        if block is not None:
            self._tl.append(block, self._t)
        return True

    def _interpret(self, words: list[tuple[str, float]]) -> _Plan:
        """Validate a block against the parser state; what to do, or the GRBL error code."""
        g: dict[str, tuple[int, int]] = {}
        m: dict[str, int] = {}
        vals: dict[str, float] = {}
        for letter, value in words:
            if letter == "G":
                code = _g_code(value)
                group = _G_GROUPS.get(code)
                if group is None:
                    if code[0] == 59:
                        raise _GcodeError(29)
                    raise _GcodeError(23 if code[0] in _G_NUMBERS and code[1] else 20)
                if group in g:
                    raise _GcodeError(21)
                g[group] = code
            elif letter == "M":
                if value != int(value) or int(value) not in _M_GROUPS:
                    raise _GcodeError(20)
                group = _M_GROUPS[int(value)]
                if group in m:
                    raise _GcodeError(21)
                m[group] = int(value)
            elif letter in "FIJKLNPRSTXYZ":
                if letter in vals:
                    raise _GcodeError(25)
                vals[letter] = value
            else:
                raise _GcodeError(20)
        for letter in "FNPST":
            if vals.get(letter, 0.0) < 0:
                raise _GcodeError(4)
        if vals.get("N", 0.0) > 9_999_999:
            raise _GcodeError(27)
        if vals.get("T", 0.0) > 255:
            raise _GcodeError(38)
        used = {"N"}
        modal = replace(self._modal)
        plan = _Plan(modal)
        if "feed_mode" in g:
            modal.inverse_time = g["feed_mode"] == (93, 0)
        if "units" in g:
            modal.inches = g["units"] == (20, 0)
        unit = 25.4 if modal.inches else 1.0
        if "F" in vals:
            used.add("F")
            if not modal.inverse_time:
                modal.feed_mm_min = vals["F"] * unit
        if "S" in vals:
            used.add("S")
            modal.spindle_rpm = vals["S"]
        if "T" in vals:
            used.add("T")
            modal.tool = int(vals["T"])
        if "spindle" in m:
            modal.spindle = m["spindle"]
        if "coolant" in m:
            modal.flood = m["coolant"] == 8
        if "stopping" in m and m["stopping"] != 1:
            plan.stopping = m["stopping"]
        nm = g.get("non_modal")
        plan.non_modal = nm
        if nm == (4, 0):
            if "P" not in vals:
                raise _GcodeError(28)
            used.add("P")
            plan.dwell_s = vals["P"]
        if "plane" in g:
            modal.plane = g["plane"][0]
        if "distance" in g:
            modal.incremental = g["distance"] == (91, 0)
        if "wcs" in g:
            plan.wco_changed = g["wcs"][0] - 54 != modal.wcs
            modal.wcs = g["wcs"][0] - 54
        if "motion" in g:
            modal.motion = g["motion"]
        axes = {i: vals[a] * unit for i, a in enumerate("XYZ") if a in vals}
        axis_command = None
        if nm in _AXIS_COMMANDS and (axes or nm in ((10, 0), (92, 0))):
            axis_command = "non_modal"
        if g.get("tlo") == (43, 10):
            if axis_command is not None:
                raise _GcodeError(24)
            axis_command = "tlo"
        if axis_command is not None and "motion" in g and axes:
            raise _GcodeError(24)
        if axis_command is None and axes:
            axis_command = "motion"
        if nm == (53, 0) and modal.motion not in ((0, 0), (1, 0)):
            raise _GcodeError(30)
        used |= set("XYZ") & set(vals)
        if axis_command == "tlo":
            if set(axes) != {2}:
                raise _GcodeError(37 if axes else 26)
            plan.tlo_mm = axes[2]
            plan.wco_changed = True
        elif g.get("tlo") == (49, 0):
            plan.tlo_mm = 0.0
            plan.wco_changed = True
        if nm == (10, 0):
            if "L" not in vals or "P" not in vals:
                raise _GcodeError(28)
            used |= {"L", "P"}
            if vals["L"] not in (2.0, 20.0):
                raise _GcodeError(20)
            if vals["P"] != int(vals["P"]):
                raise _GcodeError(23)
            if vals["P"] > 6:
                raise _GcodeError(29)
            if not axes:
                raise _GcodeError(26)
            plan.l_value, plan.p_value = int(vals["L"]), int(vals["P"])
            plan.axis_values = axes
        elif nm == (92, 0):
            if not axes:
                raise _GcodeError(26)
            plan.axis_values = axes
        elif nm in ((28, 0), (30, 0)):
            plan.axis_values = axes
        if axis_command == "motion":
            if modal.motion == (80, 0):
                raise _GcodeError(31)
            if modal.motion not in ((0, 0), (1, 0)):
                raise _GcodeError(20)  # arcs and probing are not simulated
            target = self._target(axes, modal.incremental and nm != (53, 0), nm == (53, 0), modal)
            plan.target_mm = target
            if modal.motion == (1, 0):
                if modal.inverse_time:
                    if vals.get("F", 0.0) <= 0:
                        raise _GcodeError(22)
                    length = math.dist(target, self._gc_mm)
                    plan.feed_mm_min = length * vals["F"]
                elif modal.feed_mm_min <= 0:
                    raise _GcodeError(22)
                else:
                    plan.feed_mm_min = modal.feed_mm_min
        if set(vals) - used:
            raise _GcodeError(36)
        return plan

    # -- helpers -----------------------------------------------------------------------

    def _limits(self) -> MachineLimits:
        return MachineLimits.from_settings(self.settings)

    def _quantize(self, target: Sequence[float]) -> tuple[float, float, float]:
        return quantize_mm(target, self._tl.limits.steps_per_mm)

    def _wco(self) -> list[float]:
        return [self._wcs[self._modal.wcs][i] + self._g92[i] + (self._tlo if i == 2 else 0.0) for i in range(3)]

    def _target(self, axes: Mapping[int, float], incremental: bool, machine: bool, modal: _Modal | None = None) -> list[float]:
        """Machine target of axis words (mm) in the given distance mode and frame."""
        wcs = self._wcs[(modal or self._modal).wcs]
        target = list(self._gc_mm)
        for axis, v in axes.items():
            if machine:
                target[axis] = v
            elif incremental:
                target[axis] = self._gc_mm[axis] + v
            else:
                target[axis] = v + wcs[axis] + self._g92[axis] + (self._tlo if axis == 2 else 0.0)
        return target

    def _beyond_travel(self, target: Sequence[float]) -> bool:
        return any(target[i] > 0.0 or target[i] < -self.settings[130 + i] for i in range(3))

    def _set_spindle(self, mode: int) -> None:
        before = self._modal.spindle in (3, 4)
        self._modal.spindle = mode
        if (mode in (3, 4)) != before:
            self._output("spindle", int(not before))

    def _set_flood(self, on: bool) -> None:
        if on != self._modal.flood:
            self._modal.flood = on
            self._output("flood", int(on))

    def _output(self, name: str, level: int) -> None:
        assert self._t is not None
        t_us = round(self._t)
        self.outputs.append((t_us, name, level))
        if self.on_output is not None:
            self.on_output(t_us, name, level)
