"""Protocol and campaign files (TOML): load, validate, expand.

A **protocol** file describes one probing run (sections [probe], [approach],
[normal], [wait], [shear], [retract]); keys it leaves out take the defaults of
:class:`~labrig.protocol.spec.ProbeSpec`. A **campaign** file names a base
protocol, a seed, a split and one or more [[group]] tables, each the cartesian
product of its lists. See docs/protocols.md.

Validation collects every problem before raising one :class:`ProtocolError`,
one line per problem: ``file:line: field: what is wrong; what to do``.
"""

from __future__ import annotations

import dataclasses
import difflib
import itertools
import math
import re
import tomllib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from labrig.config import RigConfig
from labrig.dataset import SPLITS
from labrig.indenters import Indenter
from labrig.protocol.feedback import (
    EVENTS_LOOP_DEFAULTS,
    EVENTS_STALE_AFTER_S,
    FEEDBACKS,
    VIRTUAL_RIG_EVENTS_STALE_AFTER_S,
)
from labrig.protocol.force_loop import ForceLoopParams
from labrig.protocol.rigfile import device_config
from labrig.protocol.safety import SpeedLimits, depth_problem
from labrig.protocol.slip import SLIP_ACTIONS, SlipParams
from labrig.protocol.spec import ApproachSpec, Campaign, ProbeSpec, Problem, ProtocolError, RecordingPlan
from labrig.protocol.split import PAPER_SPLIT, assign_splits, split_counts
from labrig.protocol.variation import parse_variation, slowest_machine

PROTOCOLS_DIR = Path(__file__).resolve().parent.parent.parent / "protocols"
DEFAULT_PROTOCOL = PROTOCOLS_DIR / "probe.toml"

Where = Callable[[str], tuple[str, int]]  # field name -> (file, line)

# ----------------------------------------------------------------------------- locating keys


class TomlLocator:
    """Line numbers (1-based) of table headers and keys in TOML text.

    tomllib reports no positions for values, so this scans the text: headers
    ``[name]`` / ``[[name]]`` (the n-th ``[[name]]`` is index n), and ``key =``
    lines outside multi-line arrays, inline tables and strings. Good enough for
    error messages; not a TOML parser.
    """

    _HEADER = re.compile(r"^\s*(\[\[?)\s*([^\[\]]+?)\s*\]\]?")
    _KEY = re.compile(r"""^\s*("[^"]*"|'[^']*'|[A-Za-z0-9_-]+)\s*(?:\.[^=]*)?=""")

    def __init__(self, text: str) -> None:
        self.headers: dict[tuple[str, int], int] = {}
        self.keys: dict[tuple[str, int, str], int] = {}
        counts: dict[str, int] = {}
        section: tuple[str, int] = ("", 0)
        depth = 0
        in_multiline: str | None = None
        for number, raw in enumerate(text.splitlines(), start=1):
            line = raw
            if in_multiline is not None:
                if in_multiline not in line:
                    continue
                line = line.split(in_multiline, 1)[1]
                in_multiline = None
            code, in_multiline = _strip_strings_and_comment(line)
            if depth == 0:
                header = self._HEADER.match(code)
                if header:
                    name = header.group(2)
                    index = counts.get(name, 0) if header.group(1) == "[[" else 0
                    counts[name] = index + 1 if header.group(1) == "[[" else counts.get(name, 0)
                    section = (name, index)
                    self.headers.setdefault(section, number)
                    continue
                key = self._KEY.match(line)
                if key:
                    self.keys.setdefault((*section, key.group(1).strip("\"'")), number)
            depth = max(0, depth + code.count("[") + code.count("{") - code.count("]") - code.count("}"))

    def line(self, section: str = "", key: str | None = None, index: int = 0) -> int:
        """Line of ``key`` in ``[section]`` (the index-th ``[[section]]``); falls back to the
        header's line, then to line 1."""
        if key is not None and (section, index, key) in self.keys:
            return self.keys[(section, index, key)]
        return self.headers.get((section, index), 1)


def _strip_strings_and_comment(line: str) -> tuple[str, str | None]:
    """The line with string contents and the comment removed; and the open multi-line
    string delimiter if one starts here and does not end."""
    out: list[str] = []
    i = 0
    while i < len(line):
        ch = line[i]
        if ch == "#":
            break
        if line.startswith('"""', i) or line.startswith("'''", i):
            delim = line[i : i + 3]
            end = line.find(delim, i + 3)
            if end < 0:
                return "".join(out), delim
            i = end + 3
            out.append('""')
            continue
        if ch in "\"'":
            end = i + 1
            while end < len(line) and line[end] != ch:
                end += 2 if ch == '"' and line[end] == "\\" else 1
            i = end + 1
            out.append('""')
            continue
        out.append(ch)
        i += 1
    return "".join(out), None


# ----------------------------------------------------------------------------- problems


class _Problems:
    """Collects problems (deduplicated, in order) and raises them together."""

    def __init__(self) -> None:
        self.items: dict[tuple[str, int, str, str], Problem] = {}

    def add(self, where: tuple[str, int], field: str, message: str) -> None:
        problem = Problem(where[0], where[1], field, message)
        self.items.setdefault((problem.file, problem.line, field, message), problem)

    def extend(self, problems: Iterable[Problem]) -> None:
        for p in problems:
            self.items.setdefault((p.file, p.line, p.field, p.message), p)

    def __bool__(self) -> bool:
        return bool(self.items)

    def raise_if_any(self) -> None:
        if self.items:
            problems = tuple(sorted(self.items.values(), key=lambda p: (p.file, p.line)))
            raise ProtocolError("\n".join(str(p) for p in problems), problems)


def _read_toml(path: Path, kind: str) -> tuple[str, dict[str, Any]]:
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ProtocolError(f"{path}: no such {kind} file; check the path") from None
    except OSError as exc:
        raise ProtocolError(f"{path}: cannot read the {kind} file ({exc.strerror})") from None
    try:
        return text, tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        message = str(exc)
        at = re.search(r"\(at line (\d+), column (\d+)\)", message)
        if at:
            what = message[: at.start()].strip()
            line, column = at.groups()
            raise ProtocolError(f"{path}:{line}:{column}: not valid TOML: {what}; fix the syntax there") from None
        raise ProtocolError(f"{path}: not valid TOML: {message}; fix the syntax") from None


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


_UNIT_SUFFIXES = ("_mm_s", "_mm", "_n", "_s", "_deg")


def _stem(key: str) -> str:
    for suffix in _UNIT_SUFFIXES:
        if key.endswith(suffix):
            return key[: -len(suffix)]
    return key


def _unknown_key_message(key: str, known: Iterable[str], what: str = "key") -> str:
    known = list(known)
    stems = [k for k in known if _stem(k) == key.lower() and k != key]
    if stems:
        if any(k in ("depth_mm", "force_n") for k in stems):
            stems = [k for k in ("depth_mm", "force_n") if k in known]
        return f"no unit; give a unit: {' or '.join(stems)}"
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
    if close:
        return f"unknown {what}; did you mean {close[0]!r}?"
    return f"unknown {what}; known: {', '.join(known)}"


# ----------------------------------------------------------------------------- protocol files

# (section, key) -> ProbeSpec field ("approach.<name>" for ApproachSpec fields).
PROTOCOL_KEYS: dict[str, dict[str, str]] = {
    "probe": {"indenter": "indenter", "location_mm": "location_mm"},
    "approach": {
        "start_height_mm": "approach.start_height_mm",
        "speed_mm_s": "approach.speed_mm_s",
        "contact_force_n": "approach.contact_force_n",
        "max_travel_mm": "approach.max_travel_mm",
    },
    "normal": {"depth_mm": "depth_mm", "force_n": "force_n", "speed_mm_s": "normal_speed_mm_s", "max_depth_mm": "max_depth_mm",
               "hold_s": "press_hold_s"},
    "wait": {"duration_s": "wait_s"},
    "shear": {"direction_deg": "shear_direction_deg", "distance_mm": "shear_mm", "speed_mm_s": "shear_speed_mm_s",
              "hold_force_n": "shear_hold_force_n", "force_n": "shear_force_n"},
    "slip": {"action": "slip_action", "share": "slip.share", "at_friction": "slip.at_friction",
             "net_ratio": "slip.net_ratio", "persist": "slip.persist", "press_ratio": "slip.press_ratio",
             "friction": "slip.friction", "stall_ratio": "slip.stall_ratio", "stall_span_mm": "slip.stall_span_mm",
             "stall_friction_ratio": "slip.stall_friction_ratio", "follow_ratio": "slip.follow_ratio",
             "follow_span_mm": "slip.follow_span_mm"},
    "release": {"force_n": "release_force_n", "hold_s": "release_hold_s"},
    "retract": {"height_mm": "retract_height_mm", "speed_mm_s": "retract_speed_mm_s"},
    "control": {
        "feedback": "feedback",
        "stiffness_n_per_mm": "control.stiffness_n_per_mm",
        "max_speed_mm_s": "control.max_speed_mm_s",
        "segment_s": "control.segment_s",
        "stale_after_s": "control.stale_after_s",
        "saturation_s": "control.saturation_s",
        "reading_noise_n": "control.reading_noise_n",
    },
}
# How each numeric field may be: "positive", "nonneg" or "any".
_FIELD_SIGN: dict[str, str] = {
    "depth_mm": "positive",
    "force_n": "positive",
    "max_depth_mm": "positive",
    "normal_speed_mm_s": "positive",
    "wait_s": "nonneg",
    "shear_direction_deg": "any",
    "shear_mm": "nonneg",
    "shear_speed_mm_s": "positive",
    "retract_height_mm": "positive",
    "retract_speed_mm_s": "positive",
    "shear_hold_force_n": "positive",
    "shear_force_n": "positive",
    "release_force_n": "positive",
    "release_hold_s": "positive",
    "slip.share": "fraction",
    "slip.at_friction": "fraction",
    "slip.net_ratio": "fraction",
    "slip.press_ratio": "fraction",
    "slip.persist": "count",
    "slip.friction": "positive",
    "slip.stall_ratio": "fraction",
    "slip.stall_span_mm": "positive",
    "slip.stall_friction_ratio": "fraction",
    "slip.follow_ratio": "fraction",
    "slip.follow_span_mm": "positive",
    "press_hold_s": "positive",
    "control.stiffness_n_per_mm": "positive",
    "control.max_speed_mm_s": "positive",
    "control.segment_s": "positive",
    "control.stale_after_s": "positive",
    "control.saturation_s": "positive",
    "control.reading_noise_n": "nonneg",
    "approach.start_height_mm": "nonneg",
    "approach.speed_mm_s": "positive",
    "approach.contact_force_n": "positive",
    "approach.max_travel_mm": "positive",
}
_UNIT_WORDS = {"_mm_s": "mm/s", "_mm": "mm", "_n": "N", "_s": "s", "_deg": "degrees"}


def _unit_of(key: str) -> str:
    return next((word for suffix, word in _UNIT_WORDS.items() if key.endswith(suffix)), "")


def _check_number(value: object, key: str, sign: str) -> str | None:
    """Problem text for a bad number, or None."""
    unit = _unit_of(key)
    if not _is_number(value):
        return f"must be a number ({unit}), not {value!r}; write e.g. {key} = 1.0"
    assert isinstance(value, int | float)
    if sign == "positive" and value <= 0:
        return f"must be positive, not {value}; give a value > 0 {unit}"
    if sign == "nonneg" and value < 0:
        return f"must not be negative, not {value}; give a value >= 0 {unit}"
    if sign == "fraction" and not 0 < value <= 1:
        return f"must be a share in (0, 1], not {value}; e.g. {key} = 0.9"
    if sign == "count" and (value != int(value) or value < 1):
        return f"must be a whole number of readings, at least 1, not {value}; e.g. {key} = 2"
    return None


def _check_xy(value: object) -> str | None:
    if isinstance(value, list | tuple) and len(value) == 2 and all(_is_number(v) for v in value):
        return None
    return f"must be [x, y] in mm (gel frame, from the gel centre), not {value!r}"


@dataclass
class _ProtocolFile:
    """A parsed protocol file: field values found, and where each came from."""

    path: str
    locator: TomlLocator
    values: dict[str, Any]

    def where(self, field: str) -> tuple[str, int]:
        for section, keys in PROTOCOL_KEYS.items():
            for key, name in keys.items():
                if name == field:
                    return self.path, self.locator.line(section, key)
        return self.path, 1

    def key_of(self, field: str) -> str:
        for section, keys in PROTOCOL_KEYS.items():
            for key, name in keys.items():
                if name == field:
                    return f"{section}.{key}"
        return field


def _parse_protocol(path: Path, problems: _Problems) -> _ProtocolFile:
    text, data = _read_toml(path, "protocol")
    locator = TomlLocator(text)
    pf = _ProtocolFile(str(path), locator, {})
    for section, table in data.items():
        if section not in PROTOCOL_KEYS and not isinstance(table, dict):
            homes = [f"[{name}]" for name, keys in PROTOCOL_KEYS.items() if section in keys] or ["its section"]
            problems.add((pf.path, locator.line("", section)), section, f"is outside any section; move it under {homes[0]}")
            continue
        if section not in PROTOCOL_KEYS:
            message = _unknown_key_message(section, PROTOCOL_KEYS, "section")
            problems.add((pf.path, locator.line(section)), f"[{section}]", message)
            continue
        if not isinstance(table, dict):
            problems.add((pf.path, locator.line("", section)), section, f"must be a table; write it as [{section}]")
            continue
        known = PROTOCOL_KEYS[section]
        for key, value in table.items():
            where = (pf.path, locator.line(section, key))
            name = f"{section}.{key}"
            if key not in known:
                problems.add(where, name, _unknown_key_message(key, known))
                continue
            field = known[key]
            if field == "indenter":
                if not isinstance(value, str) or not value:
                    problems.add(where, name, f"must be an indenter name in quotes, not {value!r}")
                    continue
            elif field == "feedback":
                if value not in FEEDBACKS:
                    problems.add(where, name, f"must be \"ft\" (the F/T sensor) or \"events\" (the event sensor's "
                                              f"estimate), not {value!r}")
                    continue
            elif field == "slip_action":
                if value not in SLIP_ACTIONS:
                    problems.add(where, name, f"must be \"report\" (record when the contact slips), \"stop\" (end the "
                                              f"shear there) or \"press\" (raise the held force), not {value!r}")
                    continue
            elif field == "location_mm":
                bad = _check_xy(value)
                if bad:
                    problems.add(where, name, bad)
                    continue
                value = (float(value[0]), float(value[1]))
            else:
                bad = _check_number(value, key, _FIELD_SIGN[field])
                if bad:
                    problems.add(where, name, bad)
                    continue
                value = int(value) if _FIELD_SIGN[field] == "count" else float(value)
            pf.values[field] = value
    normal_table = data.get("normal")
    normal = normal_table if isinstance(normal_table, dict) else {}
    if "depth_mm" in normal and "force_n" in normal:
        problems.add((pf.path, locator.line("normal", "force_n")), "normal", "both depth_mm and force_n; keep one of them")
        pf.values.pop("force_n", None)
    if "indenter" not in pf.values and not (isinstance(data.get("probe"), dict) and "indenter" in data["probe"]):
        problems.add((pf.path, locator.line("probe")), "probe.indenter", 'missing; name the indenter, e.g. indenter = "sphere"')
    return pf


def on_virtual_camera(spec: ProbeSpec, protocol_text: str) -> tuple[ProbeSpec, str | None]:
    """``spec`` as run against the embedded virtual rig's camera: an events loop whose protocol does not set
    ``[control] stale_after_s`` waits :data:`~labrig.protocol.feedback.VIRTUAL_RIG_EVENTS_STALE_AFTER_S` for a
    reading instead of the real camera's default; and the line that says so (None: unchanged)."""
    if spec.feedback != "events" or "stale_after_s" in tomllib.loads(protocol_text).get("control", {}):
        return spec, None
    control = dataclasses.replace(spec.control, stale_after_s=VIRTUAL_RIG_EVENTS_STALE_AFTER_S)
    return dataclasses.replace(spec, control=control), (
        f"the virtual rig renders its camera on this host and falls behind real time where the scene is dear: the "
        f"events loop waits {VIRTUAL_RIG_EVENTS_STALE_AFTER_S:g} s for a reading before it stops as stalled (a real "
        f"camera: {EVENTS_STALE_AFTER_S:g} s; [control] stale_after_s sets it)")


def _build_spec(values: Mapping[str, Any]) -> ProbeSpec:
    """A ProbeSpec from field values (missing ones take the dataclass defaults)."""
    approach = {k.split(".", 1)[1]: v for k, v in values.items() if k.startswith("approach.")}
    control = {k.split(".", 1)[1]: v for k, v in values.items() if k.startswith("control.")}
    slip = {k.split(".", 1)[1]: v for k, v in values.items() if k.startswith("slip.")}
    top = {k: v for k, v in values.items() if not k.startswith(("approach.", "control.", "slip."))}
    if slip:
        top["slip"] = SlipParams(**slip)
    if top.get("feedback") == "events":
        control = {**EVENTS_LOOP_DEFAULTS, **control}
    if control:
        top["control"] = ForceLoopParams(**control)
    if top.get("depth_mm") is None and top.get("force_n") is None:
        top["depth_mm"] = 1.5
    top.setdefault("indenter", "?")
    return ProbeSpec(approach=ApproachSpec(**approach), **top)


def check_spec(
    spec: ProbeSpec,
    rig: RigConfig | None,
    indenters: Mapping[str, Indenter] | None,
) -> list[tuple[str, str]]:
    """Problems of one run against the rig and the indenters: (field, message) pairs.

    Fields are ProbeSpec field names (``location_mm``, ``depth_mm``, ...).
    """
    out: list[tuple[str, str]] = []
    a = spec.approach
    if a.max_travel_mm <= a.start_height_mm:
        out.append((
            "approach.max_travel_mm",
            f"{a.max_travel_mm} mm does not reach below the nominal surface (start height {a.start_height_mm} mm);"
            " make it larger than start_height_mm",
        ))
    if spec.press_hold_s is not None and spec.force_n is None:
        out.append(("press_hold_s", "presses to a force target and holds it, and this run has a depth target; "
                                    "give [normal] force_n instead of depth_mm, or drop hold_s"))
    if spec.shear_hold_force_n is not None and not spec.has_shear:
        out.append(("shear_hold_force_n", "holds the normal force during the shears, and distance_mm = 0 has none; "
                                          "give a shear distance or drop hold_force_n"))
    held_shear = "needs the normal force held during the shears: give [shear] hold_force_n, or [normal] force_n with hold_s"
    if spec.shear_force_n is not None and spec.shear_held_n is None:
        out.append(("shear_force_n", f"shears until a tangential force and {held_shear}"))
    if spec.slip_action is not None and spec.shear_held_n is None:
        out.append(("slip_action", f"is the held shear's reflex and {held_shear}"))
    if spec.release_force_n is not None and spec.force_n is not None and spec.release_force_n >= spec.force_n:
        out.append(("release_force_n", f"{spec.release_force_n} N is not below the pressed force {spec.force_n} N; "
                                       "a release holds less than the press"))
    target = spec.force_n if spec.force_n is not None else None
    if target is not None and a.contact_force_n >= target:
        out.append(("approach.contact_force_n", f"{a.contact_force_n} N is not below the force target {target} N; lower it"))
    indenter = None
    if indenters is not None:
        indenter = indenters.get(spec.indenter)
        if indenter is None:
            out.append(("indenter", f"unknown indenter {spec.indenter!r}; known: {', '.join(indenters)}"))
    if indenter is not None:
        for key, value in (("depth_mm", spec.depth_mm), ("max_depth_mm", spec.max_depth_mm)):
            problem = None if value is None else depth_problem(value, indenter.name, indenter.max_depth_mm)
            if problem is not None:
                out.append((key, problem))
        if spec.shear_hold_force_n is not None and spec.shear_hold_force_n > indenter.max_normal_force_n:
            out.append((
                "shear_hold_force_n",
                f"{spec.shear_hold_force_n} N is beyond the {indenter.name}'s max_normal_force_n "
                f"{indenter.max_normal_force_n}; use at most {indenter.max_normal_force_n} N",
            ))
        if spec.force_n is not None and spec.force_n > indenter.max_normal_force_n:
            out.append((
                "force_n",
                f"{spec.force_n} N is beyond the {indenter.name}'s max_normal_force_n {indenter.max_normal_force_n};"
                f" use at most {indenter.max_normal_force_n} N",
            ))
    if rig is not None and device_config(rig).virtual:  # hardware: the runner checks the controller's $$
        out.extend(SpeedLimits.of_rig(rig).problems(spec))
    if rig is not None:
        radius = indenter.footprint_radius_mm if indenter is not None else 0.0
        half_x = rig.gel.size_x_mm / 2 - radius
        half_y = rig.gel.size_y_mm / 2 - radius
        x, y = spec.location_mm
        angle = math.radians(spec.shear_direction_deg)
        sx, sy = x + spec.shear_mm * math.cos(angle), y + spec.shear_mm * math.sin(angle)
        gel = f"gel {rig.gel.size_x_mm:g} x {rig.gel.size_y_mm:g} mm"
        footprint = f"{spec.indenter} footprint radius {radius:g} mm" if indenter is not None else "the tip"
        limit = f"|x| <= {half_x:g}, |y| <= {half_y:g} mm"
        if abs(x) > half_x + 1e-9 or abs(y) > half_y + 1e-9:
            out.append(("location_mm", f"({x:g}, {y:g}) is off the gel ({gel}, {footprint}); keep {limit}"))
        elif spec.has_shear and (abs(sx) > half_x + 1e-9 or abs(sy) > half_y + 1e-9):
            out.append((
                "location_mm",
                f"({x:g}, {y:g}) sheared {spec.shear_mm:g} mm at {spec.shear_direction_deg:g} deg ends off the gel at"
                f" ({sx:.2f}, {sy:.2f}) ({gel}, {footprint}); keep {limit} or shear less",
            ))
    return out


def load_protocol(
    path: str | Path,
    rig: RigConfig | None = None,
    indenters: Mapping[str, Indenter] | None = None,
) -> ProbeSpec:
    """One probing run from a protocol file; with ``rig`` / ``indenters`` also checks the
    location against the gel and the targets against the indenter's limits."""
    path = Path(path)
    problems = _Problems()
    pf = _parse_protocol(path, problems)
    spec = _build_spec(pf.values)  # from the values that parsed, to report their problems too
    for field, message in check_spec(spec, rig, indenters):
        problems.add(pf.where(field), pf.key_of(field), message)
    problems.raise_if_any()
    return spec


def apply_overrides(
    spec: ProbeSpec,
    *,
    at: str | tuple[float, float] | None = None,
    depth: float | None = None,
    force: float | None = None,
    rig: RigConfig | None = None,
    indenters: Mapping[str, Indenter] | None = None,
    **fields: Any,
) -> ProbeSpec:
    """``spec`` with command-line overrides: ``at`` ("X,Y" mm or a pair), ``depth`` (mm) or
    ``force`` (N), and any ProbeSpec field by name (``wait_s=0.2``; ``None`` values are
    ignored, so unset CLI options can be passed straight through). A new normal target
    replaces the old one. Checked against ``rig`` / ``indenters`` when given."""
    problems: list[str] = []
    flag = {"location_mm": "--at", "depth_mm": "--depth", "force_n": "--force"}
    # The field names work too: location_mm= is at=, depth_mm= is depth=, force_n= is force=.
    at = fields.pop("location_mm", at)
    depth = fields.pop("depth_mm", depth)
    force = fields.pop("force_n", force)
    changes: dict[str, Any] = {}
    known = {f.name for f in dataclasses.fields(ProbeSpec)}
    for name, value in fields.items():
        if value is None:
            continue
        if name not in known:
            problems.append(f"{name}: {_unknown_key_message(name, sorted(known), 'field')}")
        else:
            changes[name] = value
    if at is not None:
        location: tuple[float, float] | None = None
        if isinstance(at, str):
            parts = at.replace(" ", "").split(",")
            try:
                if len(parts) == 2:
                    location = (float(parts[0]), float(parts[1]))
            except ValueError:
                location = None
        elif len(at) == 2 and all(_is_number(v) for v in at):
            location = (float(at[0]), float(at[1]))
        if location is None:
            problems.append(f"--at: {at!r} is not a location; give X,Y in mm from the gel centre, e.g. --at 2.5,-1")
        else:
            changes["location_mm"] = location
    if depth is not None and force is not None:
        problems.append("--depth/--force: both given; give one normal target")
    elif depth is not None or force is not None:
        key, value = ("depth_mm", depth) if depth is not None else ("force_n", force)
        bad = _check_number(value, key, "positive")
        if bad:
            problems.append(f"{flag[key]}: {bad}")
        else:
            changes["depth_mm"] = float(depth) if depth is not None else None
            changes["force_n"] = float(force) if force is not None else None
    if problems:
        raise ProtocolError("\n".join(problems))
    new = dataclasses.replace(spec, **changes)
    found = check_spec(new, rig, indenters)
    if found:
        raise ProtocolError("\n".join(f"{flag.get(field, field)}: {message}" for field, message in found))
    return new


# ----------------------------------------------------------------------------- campaign files

CAMPAIGN_KEYS: dict[str, tuple[str, ...]] = {
    "campaign": ("name", "seed", "protocol", "indenters", "repetitions", "description"),
    "split": SPLITS,
    "vary": (),  # any sim.* rig key (labrig.protocol.variation)
    "group": (
        "name",
        "indenters",
        "locations_mm",
        "grid",
        "depth_mm",
        "force_n",
        "max_depth_mm",
        "normal_speed_mm_s",
        "shear_direction_deg",
        "shear_mm",
        "shear_speed_mm_s",
        "wait_s",
        "shear_hold_force_n",
        "press_hold_s",
        "repetitions",
    ),
}
GRID_KEYS = ("x_mm", "y_mm", "nx", "ny")
# Group keys that are lists of numbers, each giving one ProbeSpec field.
_GROUP_NUMBERS = ("depth_mm", "force_n", "max_depth_mm", "normal_speed_mm_s", "shear_direction_deg", "shear_mm",
                  "shear_speed_mm_s", "wait_s", "shear_hold_force_n", "press_hold_s")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def _as_list(value: Any) -> list[Any]:
    return list(value) if isinstance(value, list) else [value]


def _grid_locations(grid: Any, where: tuple[str, int], label: str, problems: _Problems) -> list[tuple[float, float]]:
    if not isinstance(grid, dict):
        problems.add(where, f"{label}.grid", "must be a table: grid = {x_mm = [min, max], y_mm = [min, max], nx = 3, ny = 3}")
        return []
    ok = True
    for key in grid:
        if key not in GRID_KEYS:
            problems.add(where, f"{label}.grid.{key}", _unknown_key_message(key, GRID_KEYS))
            ok = False
    for key in ("x_mm", "y_mm"):
        value = grid.get(key)
        if not (isinstance(value, list) and len(value) == 2 and all(_is_number(v) for v in value)):
            problems.add(where, f"{label}.grid.{key}", f"must be [min, max] in mm, not {value!r}")
            ok = False
    for key in ("nx", "ny"):
        value = grid.get(key)
        if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
            problems.add(where, f"{label}.grid.{key}", f"must be a whole number >= 1 (points along {key[1]}), not {value!r}")
            ok = False
    if not ok:
        return []

    def axis(bounds: list[float], n: int) -> list[float]:
        lo, hi = float(bounds[0]), float(bounds[1])
        return [lo + (hi - lo) * i / (n - 1) for i in range(n)] if n > 1 else [(lo + hi) / 2]

    xs, ys = axis(grid["x_mm"], grid["nx"]), axis(grid["y_mm"], grid["ny"])
    return [(round(x, 9), round(y, 9)) for y in ys for x in xs]


def campaign_indenters_file(path: str | Path) -> Path | None:
    """The indenters file a campaign names (``[campaign] indenters``, relative to the campaign file), or None
    (the default file, or the one given on the command line). An unreadable campaign gives None: loading it
    reports the problem."""
    path = Path(path)
    try:
        value = tomllib.loads(path.read_text()).get("campaign", {}).get("indenters")
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, AttributeError):
        return None
    return path.parent / value if isinstance(value, str) else None


def load_campaign(
    path: str | Path,
    rig: RigConfig | None,
    indenters: Mapping[str, Indenter] | None,
) -> Campaign:
    """A campaign file expanded into its recordings, each checked and assigned a split.

    Group lists multiply: each group gives ``len(indenters) x len(locations) x len(depths) x ...``
    runs, each ``repetitions`` times, in that nesting order (indenters outermost, so
    indenter changes stay few). Values a group leaves out come from the base protocol.
    """
    path = Path(path)
    problems = _Problems()
    text, data = _read_toml(path, "campaign")
    loc = TomlLocator(text)
    file = str(path)

    for section in data:
        if section not in CAMPAIGN_KEYS:
            problems.add((file, loc.line(section)), f"[{section}]", _unknown_key_message(section, CAMPAIGN_KEYS, "section"))
    head = data.get("campaign")
    if not isinstance(head, dict):
        problems.add((file, 1), "[campaign]", 'missing; start the file with [campaign] and name = "..."')
        head = {}
    for key in head:
        if key not in CAMPAIGN_KEYS["campaign"]:
            message = _unknown_key_message(key, CAMPAIGN_KEYS["campaign"])
            problems.add((file, loc.line("campaign", key)), f"campaign.{key}", message)

    def at(key: str, section: str = "campaign", index: int = 0) -> tuple[str, int]:
        return file, loc.line(section, key, index)

    name = head.get("name", path.stem)
    if not isinstance(name, str) or not _NAME.match(name):
        problems.add(at("name"), "campaign.name", f"{name!r} is not a usable name; use letters, digits, '-', '_' or '.'")
        name = path.stem
    seed = head.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        problems.add(at("seed"), "campaign.seed", f"must be a whole number >= 0, not {seed!r}")
        seed = 0
    repetitions = head.get("repetitions", 1)
    if not isinstance(repetitions, int) or isinstance(repetitions, bool) or repetitions < 1:
        problems.add(at("repetitions"), "campaign.repetitions", f"must be a whole number >= 1, not {repetitions!r}")
        repetitions = 1

    indenters_value = head.get("indenters")
    if indenters_value is not None and not (isinstance(indenters_value, str) and (path.parent / indenters_value).is_file()):
        problems.add(at("indenters"), "campaign.indenters",
                     f"must name an indenters file relative to {path.name} in quotes, e.g. \"shapes.toml\", "
                     f"not {indenters_value!r}")

    # The base protocol: its values are every group's defaults.
    protocol_value = head.get("protocol")
    base: _ProtocolFile | None = None
    protocol_path: Path | None = None
    if protocol_value is None:
        protocol_path = DEFAULT_PROTOCOL
    elif not isinstance(protocol_value, str):
        message = f'must be a file name in quotes, e.g. "probe.toml", not {protocol_value!r}'
        problems.add(at("protocol"), "campaign.protocol", message)
    else:
        protocol_path = path.parent / protocol_value
        if not protocol_path.is_file():
            message = f"{protocol_path} does not exist; give a path relative to {path.name}"
            problems.add(at("protocol"), "campaign.protocol", message)
            protocol_path = None
    if protocol_path is not None:
        try:
            base = _parse_protocol(protocol_path, problems)
        except ProtocolError as exc:  # unreadable or not TOML: report with the rest
            problems.add(at("protocol"), "campaign.protocol", str(exc))

    # Sensor variation: read first, so the groups' speeds are checked against the slowest virtual CNC it gives.
    variation = None
    vary = data.get("vary")
    if vary is not None:
        if not isinstance(vary, dict):
            problems.add((file, loc.line("vary")), "[vary]", 'must be a table of "sim.key" = [low, high]')
        else:
            variation, refused = parse_variation(vary, rig)
            for key, message in refused:
                problems.add((file, loc.line("vary")), f"vary.{key}", message)
    if rig is not None and variation is not None:
        rig = slowest_machine(rig, variation)

    # Groups.
    groups = data.get("group")
    if isinstance(groups, dict):
        problems.add((file, loc.line("group")), "[group]", "write [[group]] (double brackets): each group is one table of a list")
        groups = []
    elif groups is None:
        problems.add((file, len(text.splitlines()) or 1), "[[group]]", "no groups; add at least one [[group]] table")
        groups = []
    expanded: list[tuple[int, int, ProbeSpec]] = []  # (group, repetition, spec)
    complete = base is not None  # every group expanded: the recording count is known
    for g, group in enumerate(groups):
        runs = _expand_group(g, group, loc, file, base, repetitions, rig, indenters, problems)
        complete = complete and runs is not None
        expanded.extend(runs or [])

    # Split.
    split = data.get("split", {})
    n = len(expanded)
    counts = dict.fromkeys(SPLITS, 0)
    if not isinstance(split, dict):
        problems.add((file, loc.line("", "split")), "split", "must be a table [split] with train, val, test")
        split = {}
    for key in split:
        if key not in SPLITS:
            problems.add(at(key, "split"), f"split.{key}", _unknown_key_message(key, SPLITS))
    values = {k: split[k] for k in SPLITS if k in split}
    bad = [k for k, v in values.items() if not _is_number(v) or v < 0]
    for k in bad:
        problems.add(at(k, "split"), f"split.{k}", f"must be a count or a fraction >= 0, not {values[k]!r}")
    if not values:
        counts = split_counts(n, PAPER_SPLIT)
    elif not bad:
        if all(isinstance(v, int) for v in values.values()):
            counts = {k: int(values.get(k, 0)) for k in SPLITS}
            if sum(counts.values()) != n and complete:
                total = " + ".join(k for k in SPLITS)
                problems.add(
                    (file, loc.line("split")), "split",
                    f"{total} = {sum(counts.values())} but the campaign has {n} recordings;"
                    f" make the counts add up to {n} or give fractions (e.g. train = 0.7)",
                )
        else:
            fractions = {k: float(values.get(k, 0.0)) for k in SPLITS}
            if abs(sum(fractions.values()) - 1) > 1e-6:
                problems.add(
                    (file, loc.line("split")), "split",
                    f"fractions add up to {sum(fractions.values()):g}, not 1; make train + val + test = 1",
                )
            else:
                counts = split_counts(n, fractions)
    problems.raise_if_any()

    splits = assign_splits([spec.indenter for _, _, spec in expanded], counts, seed)
    width = max(3, len(str(max(n - 1, 0))))
    plans = tuple(
        RecordingPlan(id=f"{name}-{i:0{width}d}", index=i, spec=spec, repetition=rep, split=splits[i], group=g)
        for i, (g, rep, spec) in enumerate(expanded)
    )
    return Campaign(name=name, seed=seed, plans=plans, source=path, protocol=protocol_path, variation=variation)


def _expand_group(
    g: int,
    group: Any,
    loc: TomlLocator,
    file: str,
    base: _ProtocolFile | None,
    repetitions: int,
    rig: RigConfig | None,
    indenters: Mapping[str, Indenter] | None,
    problems: _Problems,
) -> list[tuple[int, int, ProbeSpec]] | None:
    """The runs of group ``g``; None if the group is too broken to expand."""
    label = f"group[{g + 1}]"

    def at(key: str | None = None) -> tuple[str, int]:
        return file, loc.line("group", key, g)

    if not isinstance(group, dict):
        problems.add(at(), label, "must be a table")
        return None
    ok = True
    for key in group:
        if key not in CAMPAIGN_KEYS["group"]:
            problems.add(at(key), f"{label}.{key}", _unknown_key_message(key, CAMPAIGN_KEYS["group"]))
            ok = False
    axes: dict[str, list[Any]] = {}
    names = _as_list(group.get("indenters", []))
    if "indenters" in group:
        if not names or not all(isinstance(v, str) and v for v in names):
            message = f'must be a list of indenter names, e.g. ["sphere"], not {group["indenters"]!r}'
            problems.add(at("indenters"), f"{label}.indenters", message)
            ok = False
        elif indenters is not None:
            for v in names:
                if v not in indenters:
                    problems.add(at("indenters"), f"{label}.indenters", f"unknown indenter {v!r}; known: {', '.join(indenters)}")
                    ok = False
        axes["indenter"] = names
    if "locations_mm" in group and "grid" in group:
        problems.add(at("grid"), f"{label}.grid", "both locations_mm and grid; keep one of them")
        ok = False
    if "locations_mm" in group:
        raw = group["locations_mm"]
        points = raw if isinstance(raw, list) and raw and isinstance(raw[0], list) else [raw]
        for p in points:
            bad = _check_xy(p)
            if bad:
                problems.add(at("locations_mm"), f"{label}.locations_mm", f"each location {bad}; write [[x, y], ...]")
                ok = False
        if ok:
            axes["location_mm"] = [(float(p[0]), float(p[1])) for p in points]
    elif "grid" in group:
        grid = _grid_locations(group["grid"], at("grid"), label, problems)
        ok = ok and bool(grid)
        axes["location_mm"] = grid
    if "depth_mm" in group and "force_n" in group:
        problems.add(at("force_n"), f"{label}", "both depth_mm and force_n; give one normal target per group")
        ok = False
    for key in _GROUP_NUMBERS:
        if key not in group:
            continue
        values = _as_list(group[key])
        if not values:
            problems.add(at(key), f"{label}.{key}", "is an empty list; give at least one value or leave the key out")
            ok = False
        for v in values:
            bad = _check_number(v, key, _FIELD_SIGN[key])
            if bad:
                problems.add(at(key), f"{label}.{key}", bad)
                ok = False
        axes[key] = [float(v) if _is_number(v) else v for v in values]
    reps = group.get("repetitions", repetitions)
    if not isinstance(reps, int) or isinstance(reps, bool) or reps < 1:
        problems.add(at("repetitions"), f"{label}.repetitions", f"must be a whole number >= 1, not {reps!r}")
        ok = False
    if not ok or base is None:
        return None

    key_for = {"indenter": "indenters", "location_mm": "grid" if "grid" in group else "locations_mm"}
    defaults = dict(base.values)
    if "depth_mm" in axes or "force_n" in axes:  # the group's target replaces the base's
        defaults.pop("depth_mm", None)
        defaults.pop("force_n", None)

    def where(field: str) -> tuple[str, int]:
        if field in axes:
            return at(key_for.get(field, field))
        return base.where(field)

    def field_label(field: str) -> str:
        return f"{label}.{key_for.get(field, field)}" if field in axes else base.key_of(field)

    out: list[tuple[int, int, ProbeSpec]] = []
    names_axes = list(axes)
    for combo in itertools.product(*(axes[k] for k in names_axes)):
        combo_values = {**defaults, **dict(zip(names_axes, combo))}
        spec = _build_spec(combo_values)
        for field, message in check_spec(spec, rig, indenters):
            problems.add(where(field), field_label(field), message)
        out.extend((g, rep, spec) for rep in range(reps))
    return out
