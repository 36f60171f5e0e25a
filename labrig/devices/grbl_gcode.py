"""G-code as GRBL 1.1h parses it: words, modal groups, the parser state, and the validation of a
block into what to execute (or GRBL's ``error:N``). Pure: no time, no motion. The GRBL twin
(:mod:`labrig.sim.grbl_twin`) executes what it returns; the hand tools (``labrig cnc``) follow
the position through the lines they send with it before sending them.

Frames and units: machine coordinates (MPos) in mm, feeds in mm/min, dwell in s; inch words
(G20) are converted on reading. Arcs and probing are recognised but not executable here
(:func:`interpret` answers ``error:20``, as the twin does).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)")

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


class GcodeError(Exception):
    """A block GRBL rejects: ``code`` is its ``error:N``."""

    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def preparse(line: str) -> str:
    """A line as GRBL's pre-parser keeps it: spaces, control bytes, ``/`` and comments (``(...)``,
    ``;`` to the end) dropped, letters upper case (the 79-character limit is the sender's)."""
    out = []
    in_paren = False
    for c in line:
        if in_paren:
            in_paren = c != ")"
        elif c == "(":
            in_paren = True
        elif c == ";":
            break
        elif c > " " and c < "\x7f" and c != "/":
            out.append(c.upper() if "a" <= c <= "z" else c)
    return "".join(out)


def words(text: str) -> list[tuple[str, float]]:
    """Letter/number pairs of a pre-parsed line (``error:1``/``error:2`` on malformed words)."""
    out = []
    i = 0
    while i < len(text):
        letter = text[i]
        if not "A" <= letter <= "Z":
            raise GcodeError(1)
        m = NUMBER.match(text, i + 1)
        if m is None:
            raise GcodeError(2)
        out.append((letter, float(m.group())))
        i = m.end()
    return out


def g_code(value: float) -> tuple[int, int]:
    number = int(value)
    return number, round((value - number) * 100)


@dataclass
class ModalState:
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
class GcodeBlock:
    """A validated G-code block: what to do, in GRBL's execution order (mm, mm/min, s)."""

    modal: ModalState
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


@dataclass
class Coordinates:
    """Where the parser is and the offsets from work to machine coordinates (machine mm).

    ``position_mm``: the parser's position (the end of the last block); ``wcs_mm``: G54-G59;
    ``g28_mm``/``g30_mm``: stored positions; ``g92_mm``: the G92 offset; ``tlo_mm``: the tool
    length offset (Z); ``probe``: the last probe's position and whether it touched.
    """

    position_mm: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    wcs_mm: list[list[float]] = field(default_factory=lambda: [[0.0, 0.0, 0.0] for _ in range(6)])
    g28_mm: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    g30_mm: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    g92_mm: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    tlo_mm: float = 0.0
    probe: tuple[list[float], bool] = field(default_factory=lambda: ([0.0, 0.0, 0.0], False))

    def wco_mm(self, wcs: int) -> list[float]:
        """The work coordinate offset of coordinate system ``wcs`` (0: G54): WCS + G92 + TLO."""
        return [self.wcs_mm[wcs][i] + self.g92_mm[i] + (self.tlo_mm if i == 2 else 0.0) for i in range(3)]

    def target_mm(self, axes: Mapping[int, float], incremental: bool, machine: bool, wcs: int) -> list[float]:
        """Machine target of axis words (mm) in the given distance mode and frame."""
        offsets = self.wcs_mm[wcs]
        target = list(self.position_mm)
        for axis, v in axes.items():
            if machine:
                target[axis] = v
            elif incremental:
                target[axis] = self.position_mm[axis] + v
            else:
                target[axis] = v + offsets[axis] + self.g92_mm[axis] + (self.tlo_mm if axis == 2 else 0.0)
        return target

    def clear_stored(self) -> None:
        """``$RST=#``: the coordinate systems and the stored G28/G30 positions back to zero."""
        self.wcs_mm = [[0.0, 0.0, 0.0] for _ in range(6)]
        self.g28_mm = [0.0, 0.0, 0.0]
        self.g30_mm = [0.0, 0.0, 0.0]

    def set_wcs(self, index: int, values: Mapping[int, float], *, here: bool) -> None:
        """``G10 L2`` (the offsets themselves) or, with ``here``, ``G10 L20`` (offsets that make the
        current position read ``values``) for coordinate system ``index`` (0: G54)."""
        for axis, v in values.items():
            if here:
                tlo = self.tlo_mm if axis == 2 else 0.0
                self.wcs_mm[index][axis] = self.position_mm[axis] - v - self.g92_mm[axis] - tlo
            else:
                self.wcs_mm[index][axis] = v

    def set_g92(self, values: Mapping[int, float], wcs: int) -> None:
        """``G92``: offsets that make the current position read ``values`` in coordinate system ``wcs``."""
        for axis, v in values.items():
            tlo = self.tlo_mm if axis == 2 else 0.0
            self.g92_mm[axis] = self.position_mm[axis] - self.wcs_mm[wcs][axis] - v - tlo


def interpret(words: list[tuple[str, float]], modal_state: ModalState, coordinates: Coordinates) -> GcodeBlock:
    """Validate a block against the parser state (``modal_state``, ``coordinates``: left unchanged);
    what to do, or :class:`GcodeError` with the GRBL error code."""
    g: dict[str, tuple[int, int]] = {}
    m: dict[str, int] = {}
    vals: dict[str, float] = {}
    for letter, value in words:
        if letter == "G":
            code = g_code(value)
            group = _G_GROUPS.get(code)
            if group is None:
                if code[0] == 59:
                    raise GcodeError(29)
                raise GcodeError(23 if code[0] in _G_NUMBERS and code[1] else 20)
            if group in g:
                raise GcodeError(21)
            g[group] = code
        elif letter == "M":
            if value != int(value) or int(value) not in _M_GROUPS:
                raise GcodeError(20)
            group = _M_GROUPS[int(value)]
            if group in m:
                raise GcodeError(21)
            m[group] = int(value)
        elif letter in "FIJKLNPRSTXYZ":
            if letter in vals:
                raise GcodeError(25)
            vals[letter] = value
        else:
            raise GcodeError(20)
    for letter in "FNPST":
        if vals.get(letter, 0.0) < 0:
            raise GcodeError(4)
    if vals.get("N", 0.0) > 9_999_999:
        raise GcodeError(27)
    if vals.get("T", 0.0) > 255:
        raise GcodeError(38)
    used = {"N"}
    modal = replace(modal_state)
    plan = GcodeBlock(modal)
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
            raise GcodeError(28)
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
            raise GcodeError(24)
        axis_command = "tlo"
    if axis_command is not None and "motion" in g and axes:
        raise GcodeError(24)
    if axis_command is None and axes:
        axis_command = "motion"
    if nm == (53, 0) and modal.motion not in ((0, 0), (1, 0)):
        raise GcodeError(30)
    used |= set("XYZ") & set(vals)
    if axis_command == "tlo":
        if set(axes) != {2}:
            raise GcodeError(37 if axes else 26)
        plan.tlo_mm = axes[2]
        plan.wco_changed = True
    elif g.get("tlo") == (49, 0):
        plan.tlo_mm = 0.0
        plan.wco_changed = True
    if nm == (10, 0):
        if "L" not in vals or "P" not in vals:
            raise GcodeError(28)
        used |= {"L", "P"}
        if vals["L"] not in (2.0, 20.0):
            raise GcodeError(20)
        if vals["P"] != int(vals["P"]):
            raise GcodeError(23)
        if vals["P"] > 6:
            raise GcodeError(29)
        if not axes:
            raise GcodeError(26)
        plan.l_value, plan.p_value = int(vals["L"]), int(vals["P"])
        plan.axis_values = axes
    elif nm == (92, 0):
        if not axes:
            raise GcodeError(26)
        plan.axis_values = axes
    elif nm in ((28, 0), (30, 0)):
        plan.axis_values = axes
    if axis_command == "motion":
        if modal.motion == (80, 0):
            raise GcodeError(31)
        if modal.motion not in ((0, 0), (1, 0)):
            raise GcodeError(20)  # arcs and probing are not simulated
        target = coordinates.target_mm(axes, modal.incremental and nm != (53, 0), nm == (53, 0), modal.wcs)
        plan.target_mm = target
        if modal.motion == (1, 0):
            if modal.inverse_time:
                if vals.get("F", 0.0) <= 0:
                    raise GcodeError(22)
                length = math.dist(target, coordinates.position_mm)
                plan.feed_mm_min = length * vals["F"]
            elif modal.feed_mm_min <= 0:
                raise GcodeError(22)
            else:
                plan.feed_mm_min = modal.feed_mm_min
    if set(vals) - used:
        raise GcodeError(36)
    return plan


@dataclass(frozen=True)
class JogBlock:
    """A validated ``$J=`` jog: its machine target (mm) and feed (mm/min)."""

    target_mm: tuple[float, float, float]
    feed_mm_min: float


def interpret_jog(words: list[tuple[str, float]], modal_state: ModalState, coordinates: Coordinates) -> JogBlock:
    """Validate the words after ``$J=`` against the parser state (left unchanged): the jog, or
    :class:`GcodeError` with the GRBL error code. ``G20``/``G21`` and ``G90``/``G91`` apply to this jog
    only (the modal ones otherwise), ``G53`` makes the axis words machine coordinates; ``F`` is
    required, ``N`` allowed."""
    inches, incremental, machine = modal_state.inches, modal_state.incremental, False
    values: dict[int, float] = {}
    feed = None
    line_number = None
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
                raise GcodeError(16)
        elif letter in "XYZ":
            axis = "XYZ".index(letter)
            if axis in values:
                raise GcodeError(25)
            values[axis] = value
        elif letter == "F":
            if feed is not None:
                raise GcodeError(25)
            feed = value
        elif letter == "N":
            if line_number is not None:
                raise GcodeError(25)
            line_number = value
        else:
            raise GcodeError(16)
    if line_number is not None and line_number < 0:
        raise GcodeError(4)
    if line_number is not None and line_number > 9_999_999:
        raise GcodeError(27)
    if feed is None:
        raise GcodeError(22)
    if not values:
        raise GcodeError(26)
    if feed < 0:
        raise GcodeError(4)
    unit = 25.4 if inches else 1.0
    x, y, z = coordinates.target_mm({a: v * unit for a, v in values.items()}, incremental, machine, modal_state.wcs)
    return JogBlock((x, y, z), feed * unit)


def modal_state_from_report(report: Sequence[str]) -> ModalState:
    """The modal state of a ``$G`` report's words (``G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0``; F in mm/min).

    ValueError naming the word for a word that is not a modal state GRBL reports, or when one of
    the motion, coordinate system, units and distance modes is missing.
    """
    modal = ModalState()
    seen: set[str] = set()
    for word in report:
        if len(word) < 2 or NUMBER.fullmatch(word, 1) is None:
            raise ValueError(f"{word!r} is not a G-code word")
        letter, value = word[0], float(word[1:])
        if not math.isfinite(value):
            raise ValueError(f"{word!r} is not a G-code word")
        if letter == "G":
            code = g_code(value)
            group = _G_GROUPS.get(code)
            if group == "motion":
                modal.motion = code
            elif group == "wcs":
                modal.wcs = code[0] - 54
            elif group == "plane":
                modal.plane = code[0]
            elif group == "units":
                modal.inches = code == (20, 0)
            elif group == "distance":
                modal.incremental = code == (91, 0)
            elif group == "feed_mode":
                modal.inverse_time = code == (93, 0)
            elif group not in ("arc_distance", "cutter", "tlo", "path"):
                raise ValueError(f"{word!r} is not a modal state")
            if group is not None:
                seen.add(group)
        elif letter == "M" and value in (3, 4, 5):
            modal.spindle = int(value)
        elif letter == "M" and value in (8, 9):
            modal.flood = value == 8
        elif letter == "M" and value in (0, 1, 2, 7, 30, 56):
            pass  # program flow, mist, parking override: nothing the parser's motion depends on
        elif letter == "T" and value == int(value) and 0 <= value <= 255:
            modal.tool = int(value)
        elif letter == "F" and value >= 0:
            modal.feed_mm_min = value
        elif letter == "S" and value >= 0:
            modal.spindle_rpm = value
        else:
            raise ValueError(f"{word!r} is not a modal state")
    missing = [name for name, group in (("motion", "motion"), ("coordinate system", "wcs"), ("units", "units"),
                                        ("distance", "distance")) if group not in seen]
    if missing:
        raise ValueError(f"no {' or '.join(missing)} mode among {' '.join(report)!r}")
    return modal


#: The ``$#`` parameters a GRBL 1.1 controller reports with three values (mm); ``TLO`` has one.
COORDINATE_PARAMETERS = ("G54", "G55", "G56", "G57", "G58", "G59", "G28", "G30", "G92")


def coordinates_from_parameters(parameters: Mapping[str, Sequence[float]], position_mm: Sequence[float]) -> Coordinates:
    """The offsets of a ``$#`` report (name -> values, machine mm) with the parser at ``position_mm``.

    ValueError naming the parameter when one is missing or is not finite numbers (three, one for ``TLO``).
    """
    def values(name: str, count: int) -> list[float]:
        found = parameters.get(name)
        if found is None or len(found) != count or not all(math.isfinite(v) for v in found):
            raise ValueError(f"no {name} with {count} finite value{'s' if count > 1 else ''} in the $# report")
        return [float(v) for v in found]

    stored = {name: values(name, 3) for name in COORDINATE_PARAMETERS}
    if len(position_mm) != 3 or not all(math.isfinite(v) for v in position_mm):
        raise ValueError(f"the position {tuple(position_mm)} is not three finite values")
    return Coordinates(
        position_mm=[float(v) for v in position_mm],
        wcs_mm=[stored[f"G{54 + n}"] for n in range(6)],
        g28_mm=stored["G28"],
        g30_mm=stored["G30"],
        g92_mm=stored["G92"],
        tlo_mm=values("TLO", 1)[0],
    )


def parser_state_words(m: ModalState) -> list[str]:
    """The modal words ``$G`` reports (``[GC:...]``)."""
    motion = {(0, 0): "G0", (1, 0): "G1", (80, 0): "G80"}.get(m.motion, "G0")
    words = [
        motion, f"G{54 + m.wcs}", f"G{m.plane}", "G20" if m.inches else "G21", "G91" if m.incremental else "G90",
        "G93" if m.inverse_time else "G94", f"M{m.spindle}", "M8" if m.flood else "M9", f"T{m.tool}",
        f"F{m.feed_mm_min:.0f}", f"S{m.spindle_rpm:.0f}",
    ]  # fmt: skip
    return words
