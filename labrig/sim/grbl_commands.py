"""The commands the GRBL twin's main loop executes, one line at a time: ``$`` system commands,
jogs, homing and G-code blocks, as generators that yield what they wait for (see
:data:`~labrig.sim.grbl_machine.Wait`) and return the line's response.

They act on the firmware state (:class:`~labrig.sim.grbl_machine.GrblMachine`): machine
coordinates in mm, feeds in mm/min, host times in us. G-code is parsed and validated by
:mod:`labrig.devices.grbl_gcode`; motion is planned by :mod:`labrig.devices.motion_profile`.
"""

from __future__ import annotations

import re
from collections.abc import Generator
from dataclasses import replace

from labrig.devices.grbl_gcode import GcodeError, interpret, interpret_jog, parser_state_words
from labrig.devices.grbl_gcode import words as split_words
from labrig.devices.grbl_protocol import (
    PLANNER_BLOCKS,
    RX_BUFFER_BYTES,
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
    format_version,
)
from labrig.devices.motion_profile import make_block
from labrig.sim.grbl_machine import GrblMachine, Job, Wait
from labrig.sim.grbl_settings import DEFAULT_SETTINGS, setting_lines, write_setting

VERSION = "1.1h.20190830"
HELP = format_help("$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x")
OK = format_ok()


class GrblCommands:
    """The line commands of the twin on ``machine``; ``parse_us``: time spent on a line before it runs."""

    def __init__(self, machine: GrblMachine, parse_us: float) -> None:
        self._m = machine
        self.parse_us = parse_us

    def line_job(self, line: str, overflow: bool) -> Job:
        """A line taken from the ring: parsed after ``parse_us``, then executed."""
        assert self._m.t is not None
        yield ("time", self._m.t + self.parse_us)
        self._m.lines_executed += 1
        self._m.received.append(line)
        if overflow:
            return format_error(11)
        if not line:
            return OK
        if line.startswith("$"):
            return (yield from self._system_command(line[1:]))
        if self._m.state in ("Alarm", "Jog"):
            return format_error(9)
        return (yield from self._gcode(line))

    def startup_lines_job(self) -> Job:
        """The stored startup lines (``$N0``, ``$N1``), each reported as ``>line:ok``."""
        for line in self._m.startup_lines:
            if line:
                result = yield from self._gcode(line)
                if result is None:  # a soft-limit alarm locked the controller
                    return None
                self._m.emit(format_startup_result(line, result))
        return None

    # -- $ commands --------------------------------------------------------------------------

    def _system_command(self, body: str) -> Job:
        state = self._m.state
        if body == "":
            self._m.emit(HELP)
            return OK
        if body == "$":
            if state in ("Run", "Hold"):
                return format_error(8)
            for line in setting_lines(self._m.settings):
                self._m.emit(line)
            return OK
        if body == "G":
            self._m.emit(format_parser_state(parser_state_words(self._m.modal)))
            return OK
        if body == "C":
            if state == "Check":
                self._m.emit(format_message("Disabled"))
                self._m.after_response = "reset"
                return OK
            if state != "Idle":
                return format_error(8)
            self._m.state = "Check"
            self._m.emit(format_message("Enabled"))
            return OK
        if body == "X":
            if state == "Alarm":
                self._m.emit(format_message("Caution: Unlocked"))
                self._m.state = "Idle"
                self._m.coords.position_mm = list(self._m.tl.position_mm)
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
                self._m.emit(format_parameter(f"G{54 + n}", self._m.coords.wcs_mm[n]))
            self._m.emit(format_parameter("G28", self._m.coords.g28_mm))
            self._m.emit(format_parameter("G30", self._m.coords.g30_mm))
            self._m.emit(format_parameter("G92", self._m.coords.g92_mm))
            self._m.emit(format_parameter("TLO", [self._m.coords.tlo_mm]))
            self._m.emit(format_probe(*self._m.coords.probe))
            return OK
        if body == "H":
            return (yield from self._home())
        if body == "SLP":
            self._m.after_response = "sleep"
            return OK
        if body == "I":
            self._m.emit(format_version(VERSION, self._m.build_info))
            self._m.emit(format_options("V", PLANNER_BLOCKS, RX_BUFFER_BYTES))
            return OK
        if body.startswith("I="):
            self._m.build_info = body[2:]
            yield from self._m.eeprom_write()
            return OK
        if body.startswith("RST="):
            return (yield from self._restore(body[4:]))
        if body == "N":
            for i, line in enumerate(self._m.startup_lines):
                self._m.emit(format_startup_line(i, line))
            return OK
        m = re.fullmatch(r"N(\d+)=(.*)", body)
        if m:
            index = int(m.group(1))
            if index >= len(self._m.startup_lines):
                return format_error(3)
            try:
                split_words(m.group(2))
            except GcodeError as exc:
                return format_error(exc.code)
            self._m.startup_lines[index] = m.group(2)
            yield from self._m.eeprom_write()
            return OK
        m = re.fullmatch(r"(\d+)=(.*)", body)
        if m:
            error = write_setting(self._m.settings, int(m.group(1)), m.group(2))
            if error is not None:
                return format_error(error)
            self._m.tl.limits = self._m.limits()
            yield from self._m.eeprom_write()
            return OK
        return format_error(3)

    def _restore(self, which: str) -> Job:
        if which not in ("$", "#", "*"):
            return format_error(3)
        if which in ("$", "*"):
            self._m.settings = dict(DEFAULT_SETTINGS)
            self._m.tl.limits = self._m.limits()
        if which in ("#", "*"):
            self._m.coords.clear_stored()
        if which == "*":
            self._m.startup_lines = ["", ""]
            self._m.build_info = ""
        yield from self._m.eeprom_write()
        self._m.emit(format_message("Restoring defaults"))
        self._m.after_response = "reset"
        return OK

    # -- jogging and homing ------------------------------------------------------------------

    def _jog(self, body: str) -> Job:
        assert self._m.t is not None
        try:
            jog = interpret_jog(split_words(body), self._m.modal, self._m.coords)
        except GcodeError as exc:
            return format_error(exc.code)
        target = list(jog.target_mm)
        if self._m.settings[20] and self._m.beyond_travel(target):
            return format_error(15)
        self._m.coords.position_mm = target
        while len(self._m.tl.queue) >= PLANNER_BLOCKS:
            yield ("slot",)
        block = make_block(self._m.tl.tail_mm, self._m.quantize(target), jog.feed_mm_min, self._m.tl.limits, tag="jog")
        if block is not None:
            self._m.tl.append(block, self._m.t)
            if self._m.state == "Idle":
                self._m.tl.start(self._m.t)
                self._m.state = "Jog"
        return OK

    def _home(self) -> Job:
        assert self._m.t is not None
        if not self._m.settings[22]:
            return format_error(5)
        self._m.state = "Home"
        pull = self._m.settings[27]
        for axis in (2, 0, 1):
            direction = -1.0 if (int(self._m.settings[23]) >> axis) & 1 else 1.0
            travel = self._m.settings[130 + axis]
            physical = self._m.tl.position_mm[axis] + self._m.offset[axis]
            distance = max((self._m.switch_mm(axis) - physical) * direction, 0.0)
            if distance > 1.5 * travel:
                yield from self._home_move(axis, direction * 1.5 * travel, self._m.settings[25])
                self._m.alarm(9)
                return OK
            for delta, rate in (
                (distance, self._m.settings[25]),
                (-pull, self._m.settings[24]),
                (pull, self._m.settings[24]),
                (-pull, self._m.settings[24]),
            ):
                yield from self._home_move(axis, direction * delta, rate)
            homed = list(self._m.tl.position_mm)
            homed[axis] = -pull if direction > 0 else -travel + pull
            self._m.offset[axis] += self._m.tl.position_mm[axis] - homed[axis]
            self._m.tl.set_position(homed, self._m.t)
        self._m.coords.position_mm = list(self._m.tl.position_mm)
        self._m.state = "Idle"
        yield from self.startup_lines_job()
        return OK

    def _home_move(self, axis: int, delta_mm: float, rate_mm_min: float) -> Generator[Wait, None, None]:
        assert self._m.t is not None
        start = self._m.tl.position_mm
        end = list(start)
        end[axis] += delta_mm
        block = make_block(start, self._m.quantize(end), rate_mm_min, self._m.tl.limits, tag="home")
        if block is not None:
            self._m.tl.append(block, self._m.t)
            self._m.tl.start(self._m.t)
            while self._m.tl.state != "idle":
                yield ("idle",)

    # -- G-code ------------------------------------------------------------------------

    def _gcode(self, line: str) -> Job:
        assert self._m.t is not None
        try:
            plan = interpret(split_words(line), self._m.modal, self._m.coords)
        except GcodeError as exc:
            return format_error(exc.code)
        check = self._m.state == "Check"
        new, old = plan.modal, self._m.modal
        spindle_change = new.spindle != old.spindle or (new.spindle in (3, 4) and new.spindle_rpm != old.spindle_rpm)
        if (spindle_change or new.flood != old.flood) and not check:
            yield from self._m.synchronize()  # spindle and coolant switch once queued motion has run
        self._m.modal = replace(new, spindle=old.spindle, flood=old.flood)
        if check:
            self._m.modal.spindle, self._m.modal.flood = new.spindle, new.flood
        else:
            self._m.set_spindle(new.spindle)
            self._m.set_flood(new.flood)
        if plan.dwell_s is not None and not check:
            yield from self._m.synchronize()
            yield ("time", self._m.t + plan.dwell_s * 1e6)
        if plan.tlo_mm is not None:
            self._m.coords.tlo_mm = plan.tlo_mm
        if plan.wco_changed:
            self._m.wco_counter = 0
        nm = plan.non_modal
        values = plan.axis_values or {}
        if nm == (10, 0):
            index = self._m.modal.wcs if plan.p_value == 0 else plan.p_value - 1
            self._m.coords.set_wcs(index, values, here=plan.l_value == 20)
            self._m.wco_counter = 0
            yield from self._m.eeprom_write()
        elif nm in ((28, 10), (30, 10)):
            (self._m.coords.g28_mm if nm[0] == 28 else self._m.coords.g30_mm)[:] = self._m.coords.position_mm
            yield from self._m.eeprom_write()
        elif nm == (92, 0):
            self._m.coords.set_g92(values, self._m.modal.wcs)
            self._m.wco_counter = 0
        elif nm == (92, 10):
            self._m.coords.g92_mm = [0.0, 0.0, 0.0]
            self._m.wco_counter = 0
        elif nm in ((28, 0), (30, 0)):
            if values:
                intermediate = self._m.coords.target_mm(values, self._m.modal.incremental, False, self._m.modal.wcs)
                if not (yield from self._motion(intermediate, None, check)):
                    return None
            stored = list(self._m.coords.g28_mm if nm[0] == 28 else self._m.coords.g30_mm)
            if not (yield from self._motion(stored, None, check)):
                return None
        if plan.target_mm is not None and not (yield from self._motion(plan.target_mm, plan.feed_mm_min, check)):
            return None
        if plan.stopping is not None and not check:
            yield from self._m.synchronize()
        if plan.stopping == 0:
            if not check:
                self._m.tl.hold(self._m.t)
                self._m.state = "Hold"
        elif plan.stopping in (2, 30):
            self._m.modal = replace(self._m.modal, motion=(1, 0), plane=17, incremental=False, inverse_time=False, wcs=0)
            if not check:
                self._m.set_spindle(5)
                self._m.set_flood(False)
            self._m.modal.spindle, self._m.modal.flood = 5, False
            self._m.overrides = [100, 100, 100]
            self._m.emit(format_message("Pgm End"))
        return OK

    def _motion(self, target: list[float], feed_mm_min: float | None, check: bool) -> Generator[Wait, None, bool]:
        """Plan a straight move to the machine ``target``; False after a soft-limit alarm."""
        assert self._m.t is not None
        if self._m.settings[20] and self._m.beyond_travel(target):
            if self._m.tl.state in ("run", "hold"):
                self._m.tl.hold(self._m.t)
                while self._m.tl.state in ("run", "hold"):
                    yield ("rest",)
            self._m.tl.stop(self._m.t)
            self._m.stop_outputs()
            self._m.alarm(2, critical=True)
            self._m.deferred_ok = True
            return False
        self._m.coords.position_mm = list(target)
        if check:
            return True
        while len(self._m.tl.queue) >= PLANNER_BLOCKS:
            yield ("slot",)
        block = make_block(self._m.tl.tail_mm, self._m.quantize(target), feed_mm_min, self._m.tl.limits)
        if block is not None:
            self._m.tl.append(block, self._m.t)
        return True
