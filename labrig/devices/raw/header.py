"""Prophesee RAW text header: parse ``% key value`` lines, infer format and geometry, write one.

Parsing follows the rules in the shared notes (events.md section 3): header lines start with
the two bytes ``% ``; the key is the first whitespace-separated token, the value the remaining
tokens joined by single spaces; the header ends after the line ``% end`` or before the first
line that does not start with ``% `` (legacy files have no ``% end``). The payload starts right
after it.

When the header has no ``format`` / ``geometry`` (legacy files), the format comes from the
``evt`` key and the geometry from ``system_ID`` (Prophesee's table of systems), else from the
sensor generation / name keys, else from the plugin name.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field

#: Formats this package decodes, by the name used in the ``format`` key.
FORMATS = ("EVT3", "EVT2")

#: Legacy ``evt`` key value -> format name.
_EVT_KEY = {"3.0": "EVT3", "2.0": "EVT2", "2.1": "EVT21"}

#: Prophesee system_ID -> (format written by that system, width, height).
_SYSTEM_ID = {
    0x15: ("EVT2", 640, 480),  # CCAM3 Gen3.0
    0x1C: ("EVT2", 640, 480),  # CCAM3 Gen3.1
    0x1A: ("EVT2", 1280, 720),  # CCAM3 Gen4.0
    0x17: ("EVT2", 640, 480),  # CCAM4 Gen3.0 (rev A)
    0x97: ("EVT2", 640, 480),  # same, EVK proxy
    0x19: ("EVT2", 640, 480),  # CCAM4 Gen3.0 rev B
    0x99: ("EVT2", 640, 480),  # same, EVK proxy
    0x1D: ("EVT2", 640, 480),  # CCAM4 Gen3.0 rev B bridge
    0x23: ("EVT2", 640, 480),  # CCAM5 / EVK3 Gen3.1
    0x1E: ("EVT3", 1280, 720),  # CCAM5 Gen4.0
    0x2E: ("EVT3", 1280, 720),  # CCAM5 Gen4.0 fixed frame
    0x21: ("EVT2", 640, 480),  # VisionCam Gen3.0
    0xA1: ("EVT2", 640, 480),  # same, EVK proxy
    0x22: ("EVT2", 640, 480),  # VisionCam Gen3.1
    0xA2: ("EVT2", 640, 480),  # same, EVK proxy
    0x29: ("EVT2", 640, 480),  # EVK2 Gen3.1
    0x1F: ("EVT2", 1280, 720),  # EVK2 Gen4.0
    0x27: ("EVT2", 1280, 720),  # EVK2 Gen4.1
    0x28: ("EVT3", 640, 480),  # EVK3 Gen3.1 EVT3
    0x30: ("EVT3", 1280, 720),  # EVK3 Gen4.1
    0x31: ("EVT3", 1280, 720),  # EVK3 IMX636 (EVK4)
    0x32: ("EVT3", 1280, 720),  # EVK2 IMX636
}

#: Sensor generation / name (lower case, as in sensor_generation, generation, sensor_name or a plugin name) -> geometry.
_SENSOR_GEOMETRY = {
    "3.0": (640, 480),
    "3.1": (640, 480),
    "4.0": (1280, 720),
    "4.1": (1280, 720),
    "4.2": (1280, 720),
    "gen3": (640, 480),
    "gen31": (640, 480),
    "gen4": (1280, 720),
    "gen41": (1280, 720),
    "imx636": (1280, 720),
    "imx646": (1280, 720),
    "genx320": (320, 320),
}


@dataclass(frozen=True)
class RawHeader:
    """A parsed header: ``fields`` in file order, the header ``text`` and its size in bytes."""

    fields: dict[str, str] = field(default_factory=dict)
    text: str = ""
    size: int = 0
    has_end: bool = False

    def format_name(self) -> str | None:
        """'EVT3', 'EVT2', ... from ``format``, else the legacy ``evt`` key, else ``system_ID``; None if unknown."""
        fmt = self.fields.get("format", "").strip()
        if fmt:
            return fmt.split(";", 1)[0].strip().upper()
        evt = self.fields.get("evt", "").strip()
        if evt in _EVT_KEY:
            return _EVT_KEY[evt]
        system = _system_entry(self.fields)
        return system[0] if system else None

    def geometry(self) -> tuple[int, int] | None:
        """(width, height) from ``format`` options or ``geometry``, else inferred from the sensor; None if unknown."""
        opts = _format_options(self.fields.get("format", ""))
        if "width" in opts and "height" in opts:
            width, height = _to_int(opts["width"]), _to_int(opts["height"])
            if width and height:
                return width, height
        geo = self.fields.get("geometry", "").lower().split("x")
        if len(geo) == 2:
            width, height = _to_int(geo[0]), _to_int(geo[1])
            if width and height:
                return width, height
        system = _system_entry(self.fields)
        if system:
            return system[1], system[2]
        for key in ("sensor_name", "sensor_generation", "generation"):
            value = self.fields.get(key, "").strip().lower()
            if value in _SENSOR_GEOMETRY:
                return _SENSOR_GEOMETRY[value]
        plugin = self.fields.get("plugin_name", "").lower()
        for part in plugin.replace("-", "_").split("_"):
            if part in _SENSOR_GEOMETRY:
                return _SENSOR_GEOMETRY[part]
        return None


def parse_header(data: bytes | bytearray | memoryview) -> RawHeader:
    """Parse the header at the start of ``data`` (the whole file or at least its header)."""
    buf = bytes(data[:65536]) if len(data) > 65536 else bytes(data)
    fields: dict[str, str] = {}
    pos = 0
    has_end = False
    while buf.startswith(b"% ", pos):
        nl = buf.find(b"\n", pos)
        if nl < 0:
            if len(buf) < len(data):  # a header line longer than the window: stop, treat as payload
                break
            nl = len(buf)  # a last header line without newline, no payload
        line = buf[pos + 2 : nl].decode("latin-1")
        pos = min(nl + 1, len(buf))
        tokens = line.split()
        if not tokens:
            continue
        if tokens[0] == "end":
            has_end = True
            break
        fields[tokens[0]] = " ".join(tokens[1:])
    return RawHeader(fields, buf[:pos].decode("latin-1"), pos, has_end)


def read_header(path: str) -> RawHeader:
    """The header of the RAW file at ``path``."""
    with open(path, "rb") as f:
        head = f.read(65536)
    return parse_header(head)


def make_header(
    format_name: str,
    width: int,
    height: int,
    extra: dict[str, str] | None = None,
    date: _dt.datetime | None = None,
) -> bytes:
    """An EVK4-like header: keys sorted, ``format``/``evt``/``geometry`` for the stream, ending with ``% end``.

    ``extra`` adds or replaces keys (a value of None is not allowed; keys and values must not
    contain newlines). ``date`` defaults to now (local time, as OpenEB writes it).
    """
    name = format_name.upper()
    if name not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, not {format_name!r}")
    stamp = (date or _dt.datetime.now()).strftime("%Y-%m-%d %H:%M:%S")
    fields = {
        "camera_integrator_name": "Prophesee",
        "date": stamp,
        "evt": "3.0" if name == "EVT3" else "2.0",
        "format": f"{name};height={int(height)};width={int(width)}",
        "generation": "4.2",
        "geometry": f"{int(width)}x{int(height)}",
        "integrator_name": "Prophesee",
        "plugin_integrator_name": "Prophesee",
        "plugin_name": "hal_plugin_imx636_evk4",
        "sensor_generation": "4.2",
        "serial_number": "00000000",
        "system_ID": "49",
    }
    for key, value in (extra or {}).items():
        if not key or any(c.isspace() for c in key) or "\n" in str(value) or key == "end":
            raise ValueError(f"bad header key/value: {key!r}: {value!r}")
        fields[key] = str(value)
    lines = [f"% {key} {fields[key]}".rstrip() + "\n" for key in sorted(fields)]
    return ("".join(lines) + "% end\n").encode("latin-1")


def _format_options(fmt: str) -> dict[str, str]:
    opts = {}
    for part in fmt.split(";")[1:]:
        key, _, value = part.partition("=")
        opts[key.strip().lower()] = value.strip()
    return opts


def _system_entry(fields: dict[str, str]) -> tuple[str, int, int] | None:
    text = fields.get("system_ID", "")
    value = _to_int(text)
    if value is None:
        value = _to_int(text, base=0)  # 0x31
    return _SYSTEM_ID.get(value) if value is not None else None


def _to_int(text: str, base: int = 10) -> int | None:
    try:
        return int(text.strip(), base)
    except ValueError:
        return None
