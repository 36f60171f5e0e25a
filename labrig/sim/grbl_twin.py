"""A GRBL 1.1h controller twin at the byte level, for :class:`labrig.sim.serial_pty.TwinServer`.

It answers like the firmware on a 328P at 115200 baud, on the host time it is given (no sleeping,
deterministic). Its parts mirror the firmware's: the UART and RX ring (:mod:`labrig.sim.grbl_uart`),
the G-code parser (:mod:`labrig.devices.grbl_gcode`), the EEPROM settings (:mod:`labrig.sim.grbl_settings`),
the planner (:mod:`labrig.devices.motion_profile`) and the reports, written with the formatters
beside the driver's parser (:mod:`labrig.devices.grbl_protocol`); this module is the main loop:

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
  overrides, feed hold and resume, jog cancel, soft limits (``$20=1``, travel ``[-$13x, 0]``: a
  target beyond it stops the cycle with a feed hold, switches spindle and coolant off and gives
  ``ALARM:2``, locked until reset; a jog beyond it is refused with ``error:15``), homing against
  simulated switches, check mode, sleep.
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
import threading
from collections import deque
from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt

from labrig.devices.grbl_gcode import ModalState
from labrig.devices.grbl_protocol import (
    PLANNER_BLOCKS,
    RX_BUFFER_BYTES,
    format_alarm,
    format_message,
    format_ok,
    format_status,
    format_welcome,
)
from labrig.devices.motion_profile import MotionTimeline, Segment
from labrig.sim.grbl_commands import GrblCommands
from labrig.sim.grbl_machine import GrblMachine, Job, OutputHook, Wait
from labrig.sim.grbl_uart import TwinUart

BANNER = format_welcome("1.1h")
OK = format_ok()
_BUSY_STATES = frozenset({"Run", "Jog", "Hold", "Home", "Door"})


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
        self.byte_us = 10 * 1e6 / baud
        self.link_latency_us = float(link_latency_us)
        self._lock = threading.RLock()
        self._power_on_physical = [float(x) for x in power_on_physical_mm]
        self._homed_at_power_on = bool(homed)
        self._uart = TwinUart(self.byte_us, self.link_latency_us)
        self._m = GrblMachine(
            settings, self._uart, eeprom_write_us=float(eeprom_write_us), on_output=on_output, build_info=build_info
        )
        self._commands = GrblCommands(self._m, float(parse_us))
        self._job: Job | None = None
        self._wait: Wait = ("now",)

    # -- the firmware's memory -------------------------------------------------------------

    @property
    def parse_us(self) -> float:
        """Time the main loop spends on a line before answering it (us)."""
        return self._commands.parse_us

    @parse_us.setter
    def parse_us(self, value: float) -> None:
        self._commands.parse_us = float(value)

    @property
    def eeprom_write_us(self) -> float:
        """How long an EEPROM write keeps the serial receiver deaf (us)."""
        return self._m.eeprom_write_us

    @eeprom_write_us.setter
    def eeprom_write_us(self, value: float) -> None:
        self._m.eeprom_write_us = float(value)

    @property
    def settings(self) -> dict[int, float]:
        """The EEPROM settings (``$N`` -> value)."""
        return self._m.settings

    @property
    def startup_lines(self) -> list[str]:
        return self._m.startup_lines

    @startup_lines.setter
    def startup_lines(self, lines: list[str]) -> None:
        self._m.startup_lines = lines

    @property
    def build_info(self) -> str:
        return self._m.build_info

    @property
    def on_output(self) -> OutputHook | None:
        return self._m.on_output

    @on_output.setter
    def on_output(self, hook: OutputHook | None) -> None:
        self._m.on_output = hook

    @property
    def outputs(self) -> list[tuple[int, str, int]]:
        """Output edges so far: (host us, ``flood``/``spindle``, level)."""
        return self._m.outputs

    @property
    def lines_executed(self) -> int:
        return self._m.lines_executed

    @property
    def received(self) -> deque[str]:
        """The last lines executed, as the pre-parser kept them."""
        return self._m.received

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

        Motion stops dead, spindle and coolant switch off, ``ALARM:1`` and ``[MSG:Reset to continue]``
        go out, and everything (even ``?``) is ignored until a soft reset, after which the twin stays
        in Alarm. The line the main loop was busy with is answered only after that reset, as by the
        firmware.
        """
        with self._lock:
            self._run_until(now_us)
            assert self._m.t is not None
            self._m.tl.stop(self._m.t)
            self._m.stop_outputs()
            self._m.deferred_ok = self._job is not None
            self._m.alarm(1, critical=True)

    # -- queries -----------------------------------------------------------------------

    def position_mm(self, t_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Machine position (N, 3) mm of the tool reference at host times ``t_us`` (us).

        Past times come from the executed segments; times beyond the twin's clock from the
        current plan (which later commands can still change).
        """
        with self._lock:
            return self._m.tl.positions_at(t_us)

    @property
    def state(self) -> str:
        """The state as a status report would print it (``Idle``, ``Hold:0``, ...)."""
        with self._lock:
            return self._m.state_text()

    @property
    def physical_offset_mm(self) -> tuple[float, float, float]:
        """Switch-frame position minus MPos (0 once homed with switches at the travel ends)."""
        return (self._m.offset[0], self._m.offset[1], self._m.offset[2])

    @property
    def planner_blocks(self) -> int:
        return len(self._m.tl.queue)

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

    def segments(self) -> list[Segment]:
        """The executed and planned motion segments (see :class:`~labrig.devices.motion_profile.Segment`)."""
        with self._lock:
            return self._m.tl.segments()

    # -- time ---------------------------------------------------------------------------

    def _run_until(self, now_us: float) -> None:
        now = float(now_us)
        if self._m.t is None:
            self._m.t = now
            if self._homed_at_power_on:  # as if homed before this session: MPos is the switch frame
                self._m.tl = MotionTimeline(self._m.limits(), tuple(self._power_on_physical), now)
                self._m.offset = [0.0, 0.0, 0.0]
            else:
                self._m.tl = MotionTimeline(self._m.limits(), (0.0, 0.0, 0.0), now)
                self._m.offset = list(self._power_on_physical)
            self._boot(power_on=True, alarm=False)
        while True:
            self._step_main_loop()
            t_next = min(
                self._uart.next_arrival_us(),
                self._wait[1]
                if self._job is not None and self._wait[0] == "time" and not self._m.locked and self._m.state != "Sleep"
                else math.inf,
                self._m.tl.next_event_us(),
            )
            if t_next > now:
                break
            self._m.t = max(self._m.t, t_next)
            self._advance_motion()
            b = self._uart.arrived(self._m.t)
            if b is not None:
                self._on_byte(b)
        self._m.t = max(self._m.t, now)
        self._advance_motion()

    def _advance_motion(self) -> None:
        assert self._m.t is not None
        self._m.tl.advance(self._m.t)
        if self._m.state in ("Run", "Jog") and self._m.tl.state == "idle":
            if self._m.state == "Jog" or self._m.sync_gc_when_idle:
                self._m.coords.position_mm = list(self._m.tl.position_mm)
                self._m.sync_gc_when_idle = False
            self._m.state = "Idle"

    # -- serial in ----------------------------------------------------------------------

    def _on_byte(self, b: int) -> None:
        if b == 0x18:
            self._soft_reset()
        elif b == 0x3F:  # ?
            if not self._m.locked and self._m.state != "Home":
                self._m.emit(self._status_report())
        elif b == 0x21:  # !
            self._feed_hold()
        elif b == 0x7E:  # ~
            self._cycle_start()
        elif b >= 0x80:
            self._realtime_extended(b)
        else:
            self._uart.store(b)

    # -- serial out ---------------------------------------------------------------------

    def _status_report(self) -> str:
        position = self._m.tl.position_mm
        wco = self._m.coords.wco_mm(self._m.modal.wcs)
        mask = int(self._m.settings[10])
        work = None if mask & 1 else [p - o for p, o in zip(position, wco)]
        busy = self._m.state in _BUSY_STATES
        wco_due = self._m.wco_counter == 0
        if wco_due:
            self._m.wco_counter = 29 if busy else 9
            if self._m.ovr_counter == 0:
                self._m.ovr_counter = 1
        else:
            self._m.wco_counter -= 1
        ovr_due = self._m.ovr_counter == 0
        if ovr_due:
            self._m.ovr_counter = 19 if busy else 9
        else:
            self._m.ovr_counter -= 1
        accessories = {3: "S", 4: "C"}.get(self._m.modal.spindle, "") + ("F" if self._m.modal.flood else "")
        return format_status(
            self._m.state_text(),
            machine_mm=position if work is None else None,
            work_mm=work,
            buffer=(PLANNER_BLOCKS - len(self._m.tl.queue), RX_BUFFER_BYTES - self._uart.rx_fill_bytes) if mask & 2 else None,
            feed_mm_min=self._m.tl.speed_mm_s * 60.0,
            spindle_rpm=self._m.modal.spindle_rpm if self._m.modal.spindle in (3, 4) else 0.0,
            pins=self._m.pins(),
            wco_mm=wco if wco_due else None,
            overrides_pct=(self._m.overrides[0], self._m.overrides[1], self._m.overrides[2]) if ovr_due else None,
            accessories=accessories if ovr_due else "",
        )

    # -- real-time commands ----------------------------------------------------------------

    def _feed_hold(self) -> None:
        assert self._m.t is not None
        if self._m.locked:
            return
        if self._m.state == "Run" or self._m.state == "Idle":
            self._m.tl.hold(self._m.t)
            self._m.state = "Hold"
        elif self._m.state == "Jog":
            self._m.tl.cancel(self._m.t)

    def _cycle_start(self) -> None:
        assert self._m.t is not None
        if self._m.locked:
            return
        if self._m.state == "Hold" and self._m.tl.state != "hold":
            if self._m.tl.state == "held":
                self._m.tl.resume(self._m.t)
            elif self._m.tl.state == "queued":
                self._m.tl.start(self._m.t)
            self._m.state = "Run" if self._m.tl.state == "run" else "Idle"
        elif self._m.state == "Idle":
            self._auto_start()

    def _realtime_extended(self, b: int) -> None:
        assert self._m.t is not None
        feed, rapid, spindle = self._m.overrides
        if b == 0x85:
            if self._m.state == "Jog":
                self._m.tl.cancel(self._m.t)
            return
        if 0x90 <= b <= 0x94:
            feed = {0x90: 100, 0x91: feed + 10, 0x92: feed - 10, 0x93: feed + 1, 0x94: feed - 1}[b]
        elif 0x95 <= b <= 0x97:
            rapid = {0x95: 100, 0x96: 50, 0x97: 25}[b]
        elif 0x99 <= b <= 0x9D:
            spindle = {0x99: 100, 0x9A: spindle + 10, 0x9B: spindle - 10, 0x9C: spindle + 1, 0x9D: spindle - 1}[b]
        elif b == 0xA0:
            if self._m.state in ("Idle", "Run", "Hold"):
                self._m.set_flood(not self._m.modal.flood)
            return
        else:
            return  # 0x84 door, 0x9E spindle stop, 0xA1 mist: not simulated; others are discarded
        new = [min(max(feed, 10), 200), rapid, min(max(spindle, 10), 200)]
        if new != self._m.overrides:
            self._m.overrides = new
            self._m.ovr_counter = 0
            self._m.tl.feed_scale = new[0] / 100.0
            self._m.tl.rapid_scale = new[1] / 100.0
            self._m.tl.rescale(self._m.t)

    def _soft_reset(self) -> None:
        assert self._m.t is not None
        alarm = None
        if self._m.state == "Home":
            alarm = 6
        elif self._m.state in ("Run", "Jog", "Hold") or self._m.tl.state in ("run", "hold"):
            alarm = 3
        self._m.tl.stop(self._m.t)
        if self._job is not None:
            self._job.close()
        self._job, self._wait, self._m.after_response = None, ("now",), None
        self._uart.clear_input()
        self._m.set_spindle(5)
        self._m.set_flood(False)
        if alarm is not None:
            self._m.emit(format_alarm(alarm))
        if self._m.deferred_ok:
            self._m.emit(OK)
        stay_alarm = alarm is not None or self._m.state in ("Alarm", "Sleep")
        self._boot(power_on=False, alarm=stay_alarm)

    def _boot(self, power_on: bool, alarm: bool) -> None:
        """After power-up or a soft reset: banner, parser defaults, Alarm or the startup lines."""
        self._m.locked = False
        self._m.deferred_ok = False
        self._m.modal = ModalState()
        self._m.coords.g92_mm = [0.0, 0.0, 0.0]
        self._m.coords.tlo_mm = 0.0
        self._m.overrides = [100, 100, 100]
        self._m.tl.feed_scale = self._m.tl.rapid_scale = 1.0
        self._m.coords.position_mm = list(self._m.tl.position_mm)
        self._m.wco_counter = self._m.ovr_counter = 0
        self._m.sync_gc_when_idle = False
        self._m.emit("")
        self._m.emit(BANNER)
        if alarm or (power_on and self._m.settings[22]):
            self._m.state = "Alarm"
            self._m.emit(format_message("'$H'|'$X' to unlock"))
        else:
            self._m.state = "Idle"
            self._start_job(self._commands.startup_lines_job())

    # -- the main loop ---------------------------------------------------------------------

    def _start_job(self, job: Job) -> None:
        self._job, self._wait = job, ("now",)

    def _step_main_loop(self) -> None:
        while not self._m.locked and self._m.state != "Sleep":
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
            self._start_job(self._commands.line_job(*taken))

    def _ready(self, wait: Wait) -> bool:
        assert self._m.t is not None
        kind = wait[0]
        if kind == "now":
            return True
        if kind == "time":
            return self._m.t >= wait[1]
        if kind == "slot":
            return len(self._m.tl.queue) < PLANNER_BLOCKS
        if kind == "idle":
            return self._m.tl.state == "idle"
        if kind == "rest":
            return self._m.tl.state not in ("run", "hold")
        raise AssertionError(wait)

    def _auto_start(self) -> None:
        assert self._m.t is not None
        if self._m.tl.state == "queued" and self._m.state in ("Idle", "Run"):
            self._m.tl.start(self._m.t)
            self._m.state = "Run"

    def _respond(self, response: str | None) -> None:
        if response is not None:
            self._m.emit(response)
        action, self._m.after_response = self._m.after_response, None
        if action == "reset":
            self._soft_reset()
        elif action == "sleep":
            self._m.sleep()

