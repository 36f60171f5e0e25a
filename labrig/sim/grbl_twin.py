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
from dataclasses import replace

import numpy as np
import numpy.typing as npt

from labrig.devices.grbl_protocol import (
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
    format_startup_line,
    format_startup_result,
    format_status,
    format_version,
    format_welcome,
)
from labrig.devices.motion_profile import MachineLimits, MotionTimeline, make_block, quantize_mm
from labrig.sim.grbl_gcode import Coordinates, GcodeError, ModalState, g_code, interpret, parser_state_words
from labrig.sim.grbl_gcode import words as split_words
from labrig.sim.grbl_settings import DEFAULT_SETTINGS, initial_settings, setting_lines, write_setting
from labrig.sim.grbl_uart import TwinUart

VERSION = "1.1h.20190830"
BANNER = format_welcome("1.1h")
HELP = format_help("$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x")
OK = format_ok()
_BUSY_STATES = frozenset({"Run", "Jog", "Hold", "Home", "Door"})

# ("now",) | ("time", t_us) | ("slot",) | ("idle",) | ("rest",)
Wait = tuple
Job = Generator[Wait, None, "str | None"]
OutputHook = Callable[[int, str, int], None]

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
        self.settings = initial_settings(settings)
        self.byte_us = 10 * 1e6 / baud
        self.parse_us = float(parse_us)
        self.eeprom_write_us = float(eeprom_write_us)
        self.link_latency_us = float(link_latency_us)
        self.on_output = on_output
        self.build_info = build_info
        self.startup_lines = ["", ""]
        self.outputs: list[tuple[int, str, int]] = []
        self.lines_executed = 0
        self.received: deque[str] = deque(maxlen=4096)
        self._lock = threading.RLock()
        self._power_on_physical = [float(x) for x in power_on_physical_mm]
        self._homed_at_power_on = bool(homed)
        self._t: float | None = None
        self._uart = TwinUart(self.byte_us, self.link_latency_us)
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
        self._modal = ModalState()
        self._coords = Coordinates()
        self._overrides = [100, 100, 100]
        self._wco_counter = 0
        self._ovr_counter = 0

    # -- the SerialTwin protocol -----------------------------------------------------------

    def receive(self, data: bytes, now_us: int) -> None:
        """Bytes the host wrote at ``now_us``: they arrive one per byte time after it."""
        with self._lock:
            self._run_until(now_us)
            self._uart.host_wrote(data, now_us)

    def transmit(self, now_us: int) -> bytes:
        """Bytes whose last bit has left the UART by ``now_us`` (less the link latency)."""
        with self._lock:
            self._run_until(now_us)
            return self._uart.transmit(now_us)

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
        return self._uart.rx_fill_bytes

    @property
    def rx_overflow_bytes(self) -> int:
        """Bytes dropped because the RX ring was full (GRBL drops them silently)."""
        return self._uart.rx_overflow_bytes

    @property
    def rx_blackout_bytes(self) -> int:
        """Bytes lost while an EEPROM write kept the receiver deaf."""
        return self._uart.rx_blackout_bytes

    @property
    def max_rx_fill_bytes(self) -> int:
        return self._uart.max_rx_fill_bytes

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
                self._uart.next_arrival_us(),
                self._wait[1]
                if self._job is not None and self._wait[0] == "time" and not self._locked and self._state != "Sleep"
                else math.inf,
                self._tl.next_event_us(),
            )
            if t_next > now:
                break
            self._t = max(self._t, t_next)
            self._advance_motion()
            b = self._uart.arrived(self._t)
            if b is not None:
                self._on_byte(b)
        self._t = max(self._t, now)
        self._advance_motion()

    def _advance_motion(self) -> None:
        assert self._t is not None
        self._tl.advance(self._t)
        if self._state in ("Run", "Jog") and self._tl.state == "idle":
            if self._state == "Jog" or self._sync_gc_when_idle:
                self._coords.position_mm = list(self._tl.position_mm)
                self._sync_gc_when_idle = False
            self._state = "Idle"

    # -- serial in ----------------------------------------------------------------------

    def _on_byte(self, b: int) -> None:
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
        else:
            self._uart.store(b)

    # -- serial out ---------------------------------------------------------------------

    def _emit(self, text: str) -> None:
        assert self._t is not None
        self._uart.send(text, self._t)

    def _status_report(self) -> str:
        position = self._tl.position_mm
        wco = self._coords.wco_mm(self._modal.wcs)
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
            buffer=(PLANNER_BLOCKS - len(self._tl.queue), RX_BUFFER_BYTES - self._uart.rx_fill_bytes) if mask & 2 else None,
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
        self._uart.clear_input()
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
        self._modal = ModalState()
        self._coords.g92_mm = [0.0, 0.0, 0.0]
        self._coords.tlo_mm = 0.0
        self._overrides = [100, 100, 100]
        self._tl.feed_scale = self._tl.rapid_scale = 1.0
        self._coords.position_mm = list(self._tl.position_mm)
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
            taken = self._uart.take_line()
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
            for line in setting_lines(self.settings):
                self._emit(line)
            return OK
        if body == "G":
            self._emit(format_parser_state(parser_state_words(self._modal)))
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
                self._coords.position_mm = list(self._tl.position_mm)
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
                self._emit(format_parameter(f"G{54 + n}", self._coords.wcs_mm[n]))
            self._emit(format_parameter("G28", self._coords.g28_mm))
            self._emit(format_parameter("G30", self._coords.g30_mm))
            self._emit(format_parameter("G92", self._coords.g92_mm))
            self._emit(format_parameter("TLO", [self._coords.tlo_mm]))
            self._emit(format_probe(*self._coords.probe))
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
                split_words(m.group(2))
            except GcodeError as exc:
                return format_error(exc.code)
            self.startup_lines[index] = m.group(2)
            yield from self._eeprom_write()
            return OK
        m = re.fullmatch(r"(\d+)=(.*)", body)
        if m:
            error = write_setting(self.settings, int(m.group(1)), m.group(2))
            if error is not None:
                return format_error(error)
            self._tl.limits = self._limits()
            yield from self._eeprom_write()
            return OK
        return format_error(3)

    def _restore(self, which: str) -> Job:
        if which not in ("$", "#", "*"):
            return format_error(3)
        if which in ("$", "*"):
            self.settings = dict(DEFAULT_SETTINGS)
            self._tl.limits = self._limits()
        if which in ("#", "*"):
            self._coords.clear_stored()
        if which == "*":
            self.startup_lines = ["", ""]
            self.build_info = ""
        yield from self._eeprom_write()
        self._emit(format_message("Restoring defaults"))
        self._after_response = self._soft_reset
        return OK

    def _eeprom_write(self) -> Generator[Wait, None, None]:
        assert self._t is not None
        self._uart.deaf_until(self._t + self.eeprom_write_us)
        yield ("time", self._t + self.eeprom_write_us)

    def _sleep(self) -> None:
        self._emit(format_message("Sleeping"))
        self._set_spindle(5)
        self._set_flood(False)
        self._state = "Sleep"

    # -- jogging and homing ------------------------------------------------------------------

    def _jog(self, body: str) -> Job:
        assert self._t is not None
        try:
            words = split_words(body)
        except GcodeError as exc:
            return format_error(exc.code)
        inches, incremental, machine = self._modal.inches, self._modal.incremental, False
        values: dict[int, float] = {}
        feed = None
        for letter, value in words:
            if letter == "G":
                code = g_code(value)
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
        target = self._coords.target_mm({a: v * unit for a, v in values.items()}, incremental, machine, self._modal.wcs)
        if self.settings[20] and self._beyond_travel(target):
            return format_error(15)
        self._coords.position_mm = target
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
        self._coords.position_mm = list(self._tl.position_mm)
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
            plan = interpret(split_words(line), self._modal, self._coords)
        except GcodeError as exc:
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
            self._coords.tlo_mm = plan.tlo_mm
        if plan.wco_changed:
            self._wco_counter = 0
        nm = plan.non_modal
        values = plan.axis_values or {}
        if nm == (10, 0):
            index = self._modal.wcs if plan.p_value == 0 else plan.p_value - 1
            self._coords.set_wcs(index, values, here=plan.l_value == 20)
            self._wco_counter = 0
            yield from self._eeprom_write()
        elif nm in ((28, 10), (30, 10)):
            (self._coords.g28_mm if nm[0] == 28 else self._coords.g30_mm)[:] = self._coords.position_mm
            yield from self._eeprom_write()
        elif nm == (92, 0):
            self._coords.set_g92(values, self._modal.wcs)
            self._wco_counter = 0
        elif nm == (92, 10):
            self._coords.g92_mm = [0.0, 0.0, 0.0]
            self._wco_counter = 0
        elif nm in ((28, 0), (30, 0)):
            if values:
                intermediate = self._coords.target_mm(values, self._modal.incremental, False, self._modal.wcs)
                if not (yield from self._motion(intermediate, None, check)):
                    return None
            stored = list(self._coords.g28_mm if nm[0] == 28 else self._coords.g30_mm)
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
        self._coords.position_mm = list(target)
        if check:
            return True
        while len(self._tl.queue) >= PLANNER_BLOCKS:
            yield ("slot",)
        block = make_block(self._tl.tail_mm, self._quantize(target), feed_mm_min, self._tl.limits)
        if block is not None:
            self._tl.append(block, self._t)
        return True

    # -- helpers -----------------------------------------------------------------------

    def _limits(self) -> MachineLimits:
        return MachineLimits.from_settings(self.settings)

    def _quantize(self, target: Sequence[float]) -> tuple[float, float, float]:
        return quantize_mm(target, self._tl.limits.steps_per_mm)

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
