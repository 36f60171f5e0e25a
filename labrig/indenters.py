"""Indenters as data: geometry, tool offset and limits from protocols/indenters.toml.

An indenter's shape is a **height map**: ``height_mm(x_mm, y_mm)`` is how far the
indenter surface lies above its tip at horizontal offset (x, y) from the tip,
in the indenter frame; ``inf`` where the indenter has no surface (outside its
footprint). The indenter frame is turned by ``yaw_deg`` about the CNC's z axis
from the machine axes (a file key, default 0): relative to a gel yawed by
``gel_yaw_deg`` in the machine it is turned by ``yaw_deg - gel_yaw_deg``, and
:meth:`Indenter.height_in_gel_mm` gives its surface at gel-frame offsets. A
height map's tool axis is ``axis_mm`` (mm from its first sample, x along its
columns, y along its rows; default: its lowest sample). The virtual rig, the
protocol runner and the ground-truth generator all read indenters from here.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.errors import LabrigError
from labrig.indenter_shapes import FAMILIES, draw_shape

DEFAULT_INDENTERS = Path(__file__).resolve().parent.parent / "protocols" / "indenters.toml"

GEOMETRY_KEYS: dict[str, tuple[str, ...]] = {
    "sphere": ("radius_mm",),
    "cylinder": ("diameter_mm", "fillet_mm"),
    "square": ("side_mm", "fillet_mm"),
    "ridge": ("width_mm", "length_mm"),
    "heightmap": ("file", "spacing_mm"),
}
#: The top-level key of an indenters file that names the file it adds to.
EXTENDS_KEY = "extends"
#: A height map drawn from a shape family and a seed (:mod:`labrig.indenter_shapes`): keys ``family``, ``seed``.
PROCEDURAL_KIND = "procedural"
#: A height map given inline (a recording's own copy of its indenter) instead of as a file.
INLINE_HEIGHTMAP_KEY = "heights_mm"
COMMON_KEYS = ("kind", "tool_offset_mm", "max_normal_force_n", "max_shear_force_n", "max_depth_mm")
#: Keys that may be left out (their defaults: no yaw in the CNC frame; a height map's lowest sample as its axis).
OPTIONAL_KEYS: dict[str, tuple[str, ...]] = {"common": ("yaw_deg",), "heightmap": ("axis_mm",)}
#: The turn (deg) that maps each non-axisymmetric shape onto itself.
SYMMETRY_DEG = {"square": 90.0, "ridge": 180.0, "heightmap": 360.0}


class IndenterError(LabrigError):
    """A bad indenter definition or an unknown indenter name."""


@dataclass(frozen=True)
class Indenter:
    """One indenter. Lengths in mm, forces in N, angles in deg.

    ``yaw_deg``: the indenter frame's turn about the CNC's z axis from the machine
    axes. ``axis_mm``: a height map's tool axis (mm from its first sample, x along
    columns, y along rows); None = its lowest sample.
    """

    name: str
    kind: str
    geometry: dict[str, Any]
    tool_offset_mm: tuple[float, float, float]
    max_normal_force_n: float
    max_shear_force_n: float
    max_depth_mm: float
    _heightmap: npt.NDArray[np.float64] | None = field(default=None, repr=False, compare=False)
    yaw_deg: float = 0.0
    axis_mm: tuple[float, float] | None = None

    @property
    def axisymmetric(self) -> bool:
        return self.kind in ("sphere", "cylinder")

    def footprint_yaw_deg(self, gel_yaw_deg: float) -> float:
        """The footprint's turn relative to a gel yawed by ``gel_yaw_deg`` in the machine, deg
        (``yaw_deg - gel_yaw_deg``, see :meth:`reduced_turn_deg`)."""
        return self.reduced_turn_deg(self.yaw_deg - gel_yaw_deg)

    def reduced_turn_deg(self, turn_deg: float) -> float:
        """A turn of this indenter reduced by its symmetry, deg: in (-s/2, s/2] for a shape that maps
        onto itself when turned by s (square 90, ridge 180, height map 360); 0 when axisymmetric."""
        if self.axisymmetric:
            return 0.0
        period = SYMMETRY_DEG[self.kind]
        turn = period / 2 - (period / 2 - float(turn_deg)) % period
        return 0.0 if abs(turn) < 1e-9 else float(round(turn, 9))

    def height_in_gel_mm(self, x_mm: npt.ArrayLike, y_mm: npt.ArrayLike, yaw_deg: float = 0.0) -> npt.NDArray[np.float64]:
        """:meth:`height_mm` at gel-frame offsets (x, y) from the tip, the indenter turned by ``yaw_deg``
        relative to the gel (see :meth:`footprint_yaw_deg`); inf outside."""
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        if yaw_deg == 0.0 or self.axisymmetric:
            return self.height_mm(x, y)
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        return self.height_mm(c * x + s * y, -s * x + c * y)

    def axis_sample(self) -> tuple[float, float]:
        """A height map's tool axis as (column, row) sample coordinates (fractional)."""
        assert self._heightmap is not None
        if self.axis_mm is None:
            row, col = np.unravel_index(np.argmin(self._heightmap), self._heightmap.shape)
            return float(col), float(row)
        spacing = float(self.geometry["spacing_mm"])
        return self.axis_mm[0] / spacing, self.axis_mm[1] / spacing

    @property
    def footprint_radius_mm(self) -> float:
        """Radius of a circle around the tip that holds the whole footprint."""
        g = self.geometry
        if self.kind == "sphere":
            return float(g["radius_mm"])
        if self.kind == "cylinder":
            return float(g["diameter_mm"]) / 2
        if self.kind == "square":
            return float(g["side_mm"]) / np.sqrt(2)
        if self.kind == "ridge":
            return float(g["length_mm"]) / 2
        assert self._heightmap is not None
        rows, cols = np.nonzero(np.isfinite(self._heightmap))  # the samples with a surface
        col, row = self.axis_sample()
        return float(np.hypot(cols - col, rows - row).max() * g["spacing_mm"])

    def height_mm(self, x_mm: npt.ArrayLike, y_mm: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Height of the indenter surface above its tip at (x, y) from the tip; inf outside."""
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        g = self.geometry
        if self.kind == "sphere":
            return _round_cap(np.hypot(x, y), float(g["radius_mm"]))
        if self.kind == "cylinder":
            a, f = float(g["diameter_mm"]) / 2, float(g["fillet_mm"])
            return _filleted(np.hypot(x, y) - (a - f), f)
        if self.kind == "square":
            half, f = float(g["side_mm"]) / 2, float(g["fillet_mm"])
            dx = np.clip(np.abs(x) - (half - f), 0, None)
            dy = np.clip(np.abs(y) - (half - f), 0, None)
            return _filleted(np.hypot(dx, dy), f, inside=(np.abs(x) <= half - f) & (np.abs(y) <= half - f))
        if self.kind == "ridge":
            r, half = float(g["width_mm"]) / 2, float(g["length_mm"]) / 2
            dx = np.clip(np.abs(x) - (half - r), 0, None)
            return _round_cap(np.hypot(dx, y), r)
        return self._sample_heightmap(x, y)

    def _sample_heightmap(self, x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        assert self._heightmap is not None
        h = self._heightmap
        spacing = float(self.geometry["spacing_mm"])
        ny, nx = h.shape
        tip_col, tip_row = self.axis_sample()
        col = x / spacing + tip_col
        row = y / spacing + tip_row
        inside = (col >= 0) & (col <= nx - 1) & (row >= 0) & (row <= ny - 1)
        c0 = np.clip(np.floor(col).astype(int), 0, nx - 2)
        r0 = np.clip(np.floor(row).astype(int), 0, ny - 2)
        fc, fr = np.clip(col - c0, 0, 1), np.clip(row - r0, 0, 1)
        value = np.zeros(np.broadcast(x, y).shape)
        for dr, dc, weight in ((0, 0, (1 - fc) * (1 - fr)), (0, 1, fc * (1 - fr)), (1, 0, (1 - fc) * fr), (1, 1, fc * fr)):
            value += np.where(weight > 0, h[r0 + dr, c0 + dc], 0.0) * weight  # inf (no surface) only where it weighs
        return np.where(inside & np.isfinite(value), value - h.min(), np.inf)


def _round_cap(r: npt.NDArray[np.float64], radius: float) -> npt.NDArray[np.float64]:
    """Height of a sphere (or cylinder) cap of ``radius`` at distance ``r`` from its axis."""
    with np.errstate(invalid="ignore"):
        h = radius - np.sqrt(radius**2 - r**2)
    return np.where(r < radius, h, np.inf)


def _filleted(d: npt.NDArray[np.float64], fillet: float, inside: npt.NDArray[np.bool_] | None = None) -> npt.NDArray[np.float64]:
    """Flat face (d <= 0) rounded over a quarter circle of radius ``fillet``."""
    with np.errstate(invalid="ignore"):
        edge = fillet - np.sqrt(np.clip(fillet**2 - d**2, 0, None))
    h = np.where(d <= 0, 0.0, np.where(d < fillet, edge, np.inf))
    if inside is not None:
        h = np.where(inside, 0.0, h)
    return h


def load_indenters(path: str | Path = DEFAULT_INDENTERS, *, _seen: tuple[Path, ...] = ()) -> dict[str, Indenter]:
    """All indenters in a TOML file, validated; errors name the file and the field.

    A file may begin with ``extends = "other.toml"`` (relative to it): the other file's indenters
    come first, and this file adds to them (a name defined twice is an error)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise IndenterError(f"{path}: no such indenter file") from None
    except tomllib.TOMLDecodeError as exc:
        raise IndenterError(f"{path}: not valid TOML ({exc})") from None
    indenters: dict[str, Indenter] = {}
    base = data.pop(EXTENDS_KEY, None)
    if base is not None:
        if not isinstance(base, str):
            raise IndenterError(f'{path}: {EXTENDS_KEY} must name another indenters file in quotes, e.g. "indenters.toml"')
        base_path = (path.parent / base).resolve()
        if base_path in _seen or base_path == path.resolve():
            raise IndenterError(f"{path}: {EXTENDS_KEY} = {base!r} leads back to itself")
        indenters = load_indenters(base_path, _seen=(*_seen, path.resolve()))
    for name, entry in data.items():
        if name in indenters:
            raise IndenterError(f"{path}: [{name}] is already defined in {base}; give it another name")
        indenters[name] = _parse(path, name, entry)
    return indenters


def indenter_toml(indenter: Indenter) -> str:
    """One indenter as a self-contained TOML document (``[name]`` and its keys): a recording
    carries it, so later steps need no indenters file. A height map is written inline
    (``heights_mm``, rows of mm) instead of naming its ``.npy`` file."""
    lines = [f"[{indenter.name}]", f'kind = "{indenter.kind}"']
    for key, value in indenter.geometry.items():
        if key != "file":
            lines.append(f"{key} = {float(value)!r}")
    if indenter._heightmap is not None:
        rows = ", ".join("[" + ", ".join(repr(float(v)) for v in row) + "]" for row in indenter._heightmap)
        lines.append(f"{INLINE_HEIGHTMAP_KEY} = [{rows}]")
    lines += [f"tool_offset_mm = [{', '.join(repr(v) for v in indenter.tool_offset_mm)}]",
              f"max_normal_force_n = {indenter.max_normal_force_n!r}", f"max_shear_force_n = {indenter.max_shear_force_n!r}",
              f"max_depth_mm = {indenter.max_depth_mm!r}"]
    if indenter.yaw_deg != 0.0:
        lines.append(f"yaw_deg = {float(indenter.yaw_deg)!r}")
    if indenter.axis_mm is not None:
        lines.append(f"axis_mm = [{float(indenter.axis_mm[0])!r}, {float(indenter.axis_mm[1])!r}]")
    return "\n".join(lines) + "\n"


def indenter_from_toml(text: str, source: str) -> Indenter:
    """The one indenter of a document written by :func:`indenter_toml`; ``source`` names where it
    came from in errors (e.g. the recording's path)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise IndenterError(f"{source}: the indenter definition is not valid TOML ({exc})") from None
    if len(data) != 1:
        raise IndenterError(f"{source}: an indenter definition holds one indenter, not {len(data)}")
    (name, entry), = data.items()
    return _parse(Path(source), name, entry)


def load_indenter(name: str, path: str | Path = DEFAULT_INDENTERS) -> Indenter:
    indenters = load_indenters(path)
    if name not in indenters:
        raise IndenterError(f"unknown indenter {name!r}; {Path(path).name} defines: {', '.join(indenters)}")
    return indenters[name]


def _parse(path: Path, name: str, entry: Any) -> Indenter:
    where = f"{path}: [{name}]"
    if not isinstance(entry, dict):
        raise IndenterError(f"{where} must be a table")
    if entry.get("kind") == PROCEDURAL_KIND:
        entry = _procedural_entry(where, entry)
    kind = entry.get("kind")
    if kind not in GEOMETRY_KEYS:
        raise IndenterError(f"{where} kind must be one of {', '.join((*GEOMETRY_KEYS, PROCEDURAL_KIND))}, not {kind!r}")
    geometry_keys = GEOMETRY_KEYS[kind]
    if kind == "heightmap" and INLINE_HEIGHTMAP_KEY in entry:
        geometry_keys = ("spacing_mm",)
    allowed = (set(COMMON_KEYS) | set(geometry_keys) | set(OPTIONAL_KEYS["common"]) | set(OPTIONAL_KEYS.get(kind, ()))
               | ({INLINE_HEIGHTMAP_KEY} if kind == "heightmap" else set()))
    unknown = sorted(set(entry) - allowed)
    if unknown:
        raise IndenterError(f"{where} unknown key {unknown[0]!r}; allowed: {', '.join(sorted(allowed))}")
    missing = [k for k in (*COMMON_KEYS, *geometry_keys) if k not in entry]
    if missing:
        raise IndenterError(f"{where} missing {missing[0]!r}")
    geometry = {k: entry[k] for k in geometry_keys}
    for key, value in geometry.items():
        if key != "file" and (not isinstance(value, int | float) or value < 0 or (value == 0 and key != "fillet_mm")):
            raise IndenterError(f"{where} {key} must be a positive number of mm, not {value!r}")
    offset = entry["tool_offset_mm"]
    if not (isinstance(offset, list) and len(offset) == 3 and all(isinstance(v, int | float) for v in offset)):
        raise IndenterError(f"{where} tool_offset_mm must be [x, y, z] in mm")
    heightmap = None
    if kind == "heightmap" and INLINE_HEIGHTMAP_KEY in entry:
        try:
            heightmap = np.asarray(entry[INLINE_HEIGHTMAP_KEY], dtype=np.float64)
        except (TypeError, ValueError):
            raise IndenterError(f"{where} {INLINE_HEIGHTMAP_KEY} must be rows of heights in mm") from None
    elif kind == "heightmap":
        file = (path.parent / geometry["file"]).resolve()
        try:
            heightmap = np.load(file).astype(np.float64)
        except (OSError, ValueError) as exc:
            raise IndenterError(f"{where} cannot read height map {file}: {exc}") from None
    if heightmap is not None:
        if heightmap.ndim != 2 or min(heightmap.shape) < 2:
            raise IndenterError(f"{where} height map must be a 2-D array of heights in mm")
        heightmap = np.where(np.isnan(heightmap), np.inf, heightmap)  # NaN or inf: no surface there
        if not np.isfinite(heightmap).any():
            raise IndenterError(f"{where} height map has no finite height")
    yaw = entry.get("yaw_deg", 0.0)
    if not isinstance(yaw, int | float) or isinstance(yaw, bool) or not np.isfinite(yaw):
        raise IndenterError(f"{where} yaw_deg must be a number of degrees (the turn about the CNC z axis), not {yaw!r}")
    axis = _axis_mm(where, entry.get("axis_mm"), heightmap, float(geometry.get("spacing_mm", 0.0)))
    return Indenter(
        name=name,
        kind=kind,
        geometry=geometry,
        tool_offset_mm=(float(offset[0]), float(offset[1]), float(offset[2])),
        max_normal_force_n=float(entry["max_normal_force_n"]),
        max_shear_force_n=float(entry["max_shear_force_n"]),
        max_depth_mm=float(entry["max_depth_mm"]),
        _heightmap=heightmap,
        yaw_deg=float(yaw),
        axis_mm=axis,
    )


def _procedural_entry(where: str, entry: dict[str, Any]) -> dict[str, Any]:
    """A ``kind = "procedural"`` entry as the inline height map it draws (:mod:`labrig.indenter_shapes`)."""
    family, seed = entry.get("family"), entry.get("seed")
    if family not in FAMILIES:
        raise IndenterError(f"{where} family must be one of {', '.join(FAMILIES)}, not {family!r}")
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise IndenterError(f"{where} seed must be a whole number >= 0, not {seed!r}")
    shape = draw_shape(family, seed)
    rest = {k: v for k, v in entry.items() if k not in ("kind", "family", "seed")}
    if "axis_mm" in rest:
        raise IndenterError(f"{where} a procedural shape's tool axis is the centre of its map: leave out axis_mm")
    centre = shape.half_width_mm
    return {**rest, "kind": "heightmap", "spacing_mm": shape.spacing_mm, INLINE_HEIGHTMAP_KEY: shape.heights_mm,
            "axis_mm": [centre, centre]}


def _axis_mm(
    where: str, value: object, heightmap: npt.NDArray[np.float64] | None, spacing_mm: float
) -> tuple[float, float] | None:
    """A height map's ``axis_mm`` = [x, y] (mm from its first sample), checked to lie inside the map."""
    if value is None:
        return None
    assert heightmap is not None
    if not (isinstance(value, list) and len(value) == 2
            and all(isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v) for v in value)):
        raise IndenterError(f"{where} axis_mm must be [x, y] in mm from the height map's first sample, not {value!r}")
    ny, nx = heightmap.shape
    x, y = float(value[0]), float(value[1])
    if not (0 <= x <= (nx - 1) * spacing_mm and 0 <= y <= (ny - 1) * spacing_mm):
        raise IndenterError(
            f"{where} axis_mm {value!r} lies outside the height map (x 0 to {(nx - 1) * spacing_mm:g} mm, "
            f"y 0 to {(ny - 1) * spacing_mm:g} mm)"
        )
    return x, y
