"""The GRBL twin's firmware state, shared by its main loop (:mod:`labrig.sim.grbl_twin`) and the
commands it executes (:mod:`labrig.sim.grbl_commands`).

Frames, units, times: machine coordinates (MPos) in mm; the physical (switch) frame differs by
``offset`` until homing; host times in us (float ``t``, the twin's clock). Line output goes
through the UART (:mod:`labrig.sim.grbl_uart`), paced from ``t`` on.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Generator, Mapping, Sequence
from typing import Literal

from labrig.devices.grbl_gcode import Coordinates, ModalState
from labrig.devices.grbl_protocol import format_alarm, format_message
from labrig.devices.motion_profile import MachineLimits, MotionTimeline, quantize_mm
from labrig.sim.grbl_settings import initial_settings
from labrig.sim.grbl_uart import TwinUart

#: What a job waits for: ("now",) | ("time", t_us) | ("slot",) a free planner block |
#: ("idle",) motion finished | ("rest",) motion stopped or held.
Wait = tuple
#: A line's execution: yields waits, returns the response line (None: no response now).
Job = Generator[Wait, None, "str | None"]
#: ``on_output(t_us, name, level)``: an output edge (``flood``, ``spindle``) at host time ``t_us``.
OutputHook = Callable[[int, str, int], None]


class GrblMachine:
    """Everything the firmware keeps: settings, parser state, planner, outputs, controller state.

    ``state``: Idle, Run, Hold, Jog, Alarm, Check, Home or Sleep; ``locked``: a critical alarm
    ignores everything until a reset; ``deferred_ok``: the line being executed is answered only
    after that reset; ``after_response``: what follows the current line's response (``"reset"``
    after ``$C`` off or ``$RST``, ``"sleep"`` after ``$SLP``); ``wco_counter``/``ovr_counter``:
    status reports until the next one carrying ``WCO``/``Ov`` (0: the next).
    """

    def __init__(
        self,
        settings: Mapping[int, float] | None,
        uart: TwinUart,
        *,
        eeprom_write_us: float,
        on_output: OutputHook | None,
        build_info: str,
    ) -> None:
        self.settings = initial_settings(settings)
        self.uart = uart
        self.eeprom_write_us = eeprom_write_us
        self.on_output = on_output
        self.build_info = build_info
        self.startup_lines = ["", ""]
        self.outputs: list[tuple[int, str, int]] = []
        self.lines_executed = 0
        self.received: deque[str] = deque(maxlen=4096)
        self.t: float | None = None
        self.tl = MotionTimeline(self.limits())
        self.offset = [0.0, 0.0, 0.0]
        self.state = "Idle"
        self.locked = False
        self.deferred_ok = False
        self.after_response: Literal["reset", "sleep"] | None = None
        self.sync_gc_when_idle = False
        self.modal = ModalState()
        self.coords = Coordinates()
        self.overrides = [100, 100, 100]
        self.wco_counter = 0
        self.ovr_counter = 0

    def emit(self, text: str) -> None:
        """Send a line (from now, after what is queued)."""
        assert self.t is not None
        self.uart.send(text, self.t)

    def state_text(self) -> str:
        """The state as a status report prints it (``Hold:0`` while decelerating, ``Hold:1`` held)."""
        if self.state == "Hold":
            return "Hold:1" if self.tl.state == "hold" else "Hold:0"
        return self.state

    def pins(self) -> str:
        """The limit switches pressed (``Pn:`` letters)."""
        out = ""
        for axis, letter in enumerate("XYZ"):
            physical = self.tl.position_mm[axis] + self.offset[axis]
            if abs(physical - self.switch_mm(axis)) < 1e-6:
                out += letter
        return out

    def eeprom_write(self) -> Generator[Wait, None, None]:
        """An EEPROM write: the receiver is deaf and the main loop busy for ``eeprom_write_us``."""
        assert self.t is not None
        self.uart.deaf_until(self.t + self.eeprom_write_us)
        yield ("time", self.t + self.eeprom_write_us)

    def sleep(self) -> None:
        """``$SLP`` after its ``ok``: outputs off, asleep until a reset."""
        self.emit(format_message("Sleeping"))
        self.set_spindle(5)
        self.set_flood(False)
        self.state = "Sleep"

    def switch_mm(self, axis: int) -> float:
        """The limit switch's place in the physical frame (travel is ``[-max_travel, 0]``)."""
        negative = (int(self.settings[23]) >> axis) & 1
        return -self.settings[130 + axis] if negative else 0.0

    def alarm(self, code: int, critical: bool = False) -> None:
        """``ALARM:code``; a critical one locks everything (even ``?``) until a soft reset."""
        self.emit(format_alarm(code))
        self.state = "Alarm"
        if critical:
            self.emit(format_message("Reset to continue"))
            self.locked = True

    def synchronize(self) -> Generator[Wait, None, None]:
        """Wait until the planned motion has finished."""
        while self.tl.state != "idle":
            yield ("idle",)

    def limits(self) -> MachineLimits:
        """The planner limits of the current settings."""
        return MachineLimits.from_settings(self.settings)

    def quantize(self, target: Sequence[float]) -> tuple[float, float, float]:
        """``target`` (mm) on the steps grid."""
        return quantize_mm(target, self.tl.limits.steps_per_mm)

    def beyond_travel(self, target: Sequence[float]) -> bool:
        """Whether a machine target (mm) leaves the travel ``[-$13x, 0]`` (soft limits)."""
        return any(target[i] > 0.0 or target[i] < -self.settings[130 + i] for i in range(3))

    def stop_outputs(self) -> None:
        """Spindle, then coolant, off now, as GRBL's ``mc_reset`` does when a soft or hard limit trips:
        the outputs switch at the alarm, not at the reset that follows it. Not in check mode, where
        the parser's M3/M8 never reached the outputs."""
        if self.state != "Check":
            self.set_spindle(5)
            self.set_flood(False)

    def set_spindle(self, mode: int) -> None:
        """M3/M4/M5 now; an edge on the spindle output when it turns on or off."""
        before = self.modal.spindle in (3, 4)
        self.modal.spindle = mode
        if (mode in (3, 4)) != before:
            self.output("spindle", int(not before))

    def set_flood(self, on: bool) -> None:
        """M8/M9 now; an edge on the flood output when it changes."""
        if on != self.modal.flood:
            self.modal.flood = on
            self.output("flood", int(on))

    def output(self, name: str, level: int) -> None:
        """An output edge at the twin's time, kept and handed to ``on_output``."""
        assert self.t is not None
        t_us = round(self.t)
        self.outputs.append((t_us, name, level))
        if self.on_output is not None:
            self.on_output(t_us, name, level)
