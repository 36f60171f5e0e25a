"""Where lines sent to a GRBL 1.1h controller take it, worked out before sending them. Pure, sans-I/O.

:class:`ProgramTracker` follows the G-code parser the way GRBL does (:mod:`labrig.devices.grbl_gcode`),
seeded with the controller's own state (``$G``, ``$#``, its machine position and whether it is in
Alarm): for each line, the straight moves it commands, as start and end of the tool reference
point in machine coordinates (MPos, mm), or why they cannot be known beforehand (arcs, probing,
``G28``/``G30``, anything after homing or a reset, G-code after a jog or a jog after G-code motion
in one program: GRBL refuses a jog while G-code motion runs and G-code while jogging, so whether
they ran depends on timing). A line GRBL rejects (``error:N``, every G-code line and jog in Alarm until ``$X``)
changes nothing, as in the firmware, which validates a whole block before executing any of it.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace

from labrig.devices.grbl_gcode import (
    Coordinates,
    GcodeError,
    ModalState,
    g_code,
    interpret,
    interpret_jog,
    preparse,
    words,
)
from labrig.devices.grbl_protocol import LINE_MAX_CHARS

Point = tuple[float, float, float]

_MIXED = ("jogs mixed with G-code in one program (GRBL refuses a jog while G-code motion runs and G-code while "
          "jogging, so where later lines start depends on timing)")

#: Motion modes whose path is not a straight line the tracker can follow.
_ARC_MODES = frozenset({(2, 0), (3, 0)})
_PROBE_MODES = frozenset({(38, 20), (38, 30), (38, 40), (38, 50)})


@dataclass(frozen=True)
class LineMotion:
    """What one line does to the machine position.

    ``segments``: the straight moves it commands, in order: (start, end) of the tool reference
    point, machine mm. ``unchecked``: why its motion cannot be known before it runs (None when
    ``segments`` is all of it). ``error_code``: GRBL rejects the line with ``error:N`` (nothing moves).
    """

    segments: tuple[tuple[Point, Point], ...] = ()
    unchecked: str | None = None
    error_code: int | None = None


class ProgramTracker:
    """GRBL's parser state through the lines sent to it, from ``modal`` and ``coordinates`` (the
    controller's ``$G`` and ``$#``, the parser at its machine position; both copied); ``alarm``:
    the controller is in Alarm (G-code and jogs are refused until ``$X`` or ``$H``)."""

    def __init__(self, modal: ModalState, coordinates: Coordinates, *, alarm: bool = False) -> None:
        self.modal = replace(modal)
        self.coordinates = copy.deepcopy(coordinates)
        self.alarm = alarm
        self.lost_after: str | None = None  # the line after which the position is no longer known
        self._moved_by: str | None = None  # "jog" or "G-code": what the lines so far moved with

    @property
    def position_mm(self) -> Point:
        """The parser's position: the end of the last move (machine mm)."""
        x, y, z = self.coordinates.position_mm
        return (x, y, z)

    def line(self, text: str) -> LineMotion:
        """The motion of the next line sent (as written: GRBL's pre-parser is applied here)."""
        block = preparse(text)
        if len(block) > LINE_MAX_CHARS:
            return LineMotion(error_code=11)
        if block.startswith("$"):
            return self._system(block[1:], text)
        if not block:
            return LineMotion()
        try:
            block_words = words(block)
        except GcodeError as exc:
            return LineMotion(error_code=exc.code)
        if self.lost_after is not None:
            if _names_motion(block_words):
                return LineMotion(unchecked=f"the position after {self.lost_after} is not known before it runs")
            return LineMotion()
        if self.alarm:
            return LineMotion(error_code=9)
        try:
            plan = interpret(block_words, self.modal, self.coordinates)
        except GcodeError as exc:
            unchecked = self._arc_or_probe(block_words)
            if unchecked is not None and exc.code == 20:
                return LineMotion(unchecked=unchecked)
            return LineMotion(error_code=exc.code)
        if self._moved_by == "jog":
            return LineMotion(unchecked=_MIXED)
        nm = plan.non_modal
        if nm in ((28, 0), (30, 0)):
            return LineMotion(unchecked=f"G{nm[0]} moves through its stored position")
        coords = self.coordinates
        self.modal = replace(plan.modal)
        if plan.tlo_mm is not None:
            coords.tlo_mm = plan.tlo_mm
        values = plan.axis_values or {}
        if nm == (10, 0):
            coords.set_wcs(self.modal.wcs if plan.p_value == 0 else plan.p_value - 1, values, here=plan.l_value == 20)
        elif nm in ((28, 10), (30, 10)):
            (coords.g28_mm if nm[0] == 28 else coords.g30_mm)[:] = coords.position_mm
        elif nm == (92, 0):
            coords.set_g92(values, self.modal.wcs)
        elif nm == (92, 10):
            coords.g92_mm = [0.0, 0.0, 0.0]
        segments: tuple[tuple[Point, Point], ...] = ()
        if plan.target_mm is not None:
            self._moved_by = "G-code"
            start = self.position_mm
            coords.position_mm = list(plan.target_mm)
            segments = ((start, self.position_mm),)
        if plan.stopping in (2, 30):  # program end: GRBL's defaults for these modes
            self.modal = replace(self.modal, motion=(1, 0), plane=17, incremental=False, inverse_time=False, wcs=0,
                                 spindle=5, flood=False)
        return LineMotion(segments)

    def _system(self, body: str, text: str) -> LineMotion:
        """A ``$`` line: a jog moves; homing, resets, check mode and sleep leave the position unknown."""
        if body.startswith("J="):
            if self.lost_after is not None:
                return LineMotion(unchecked=f"the position after {self.lost_after} is not known before it runs")
            if self.alarm:
                return LineMotion(error_code=8)
            try:
                jog = interpret_jog(words(body[2:]), self.modal, self.coordinates)
            except GcodeError as exc:
                return LineMotion(error_code=exc.code)
            if self._moved_by == "G-code":
                return LineMotion(unchecked=_MIXED)
            self._moved_by = "jog"
            start = self.position_mm
            self.coordinates.position_mm = list(jog.target_mm)
            return LineMotion(((start, self.position_mm),))
        if body == "H" or body == "C" or body == "SLP" or body.startswith("RST="):
            self.lost_after = repr(text.strip())
            return LineMotion()
        if body == "X":
            self.alarm = False
            return LineMotion()
        if body[:1] == "N" and "=" in body:
            try:
                stored = words(body[body.index("=") + 1:])
            except GcodeError as exc:
                return LineMotion(error_code=exc.code)
            if _names_motion(stored):
                return LineMotion(unchecked="a startup line that moves runs at every reset and homing")
        return LineMotion()

    def _arc_or_probe(self, block_words: list[tuple[str, float]]) -> str | None:
        """What unfollowable motion the block asks for (an arc, a probing move), or None."""
        modes = {g_code(v) for letter, v in block_words if letter == "G"} & (_ARC_MODES | _PROBE_MODES)
        if not modes and any(letter in "XYZ" for letter, _ in block_words):
            modes = {self.modal.motion} & (_ARC_MODES | _PROBE_MODES)
        if modes & _ARC_MODES:
            return "an arc (G2/G3)"
        if modes:
            return "a probing move (G38.x)"
        return None


def may_move(line: str) -> bool:
    """Whether a line could command motion whatever the parser's state: axis words, ``G28``/``G30``,
    a jog, or a startup line that does (homing, which only goes to the switches, does not count)."""
    block = preparse(line)
    if len(block) > LINE_MAX_CHARS:
        return False  # GRBL answers error:11 (and the driver does not send it)
    if block.startswith("$J="):
        return True
    if block.startswith("$N") and "=" in block:
        block = block[block.index("=") + 1:]
    elif block.startswith("$"):
        return False
    try:
        return _names_motion(words(block))
    except GcodeError:
        return False


def _names_motion(block_words: list[tuple[str, float]]) -> bool:
    """Whether a block could move the machine: axis words, or G28/G30 (which move without any)."""
    return any(letter in "XYZ" or (letter == "G" and g_code(value) in ((28, 0), (30, 0))) for letter, value in block_words)
