"""Indenters as data: geometry, tool offset and limits from protocols/indenters.toml.

An indenter's shape is a **height map**: ``height_mm(x_mm, y_mm)`` is how far the
indenter surface lies above its tip at horizontal offset (x, y) from the tip,
in the indenter frame (aligned with the gel frame at zero yaw); ``inf`` where
the indenter has no surface (outside its footprint). The virtual rig, the
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

DEFAULT_INDENTERS = Path(__file__).resolve().parent.parent / "protocols" / "indenters.toml"

GEOMETRY_KEYS: dict[str, tuple[str, ...]] = {
    "sphere": ("radius_mm",),
    "cylinder": ("diameter_mm", "fillet_mm"),
    "square": ("side_mm", "fillet_mm"),
    "ridge": ("width_mm", "length_mm"),
    "heightmap": ("file", "spacing_mm"),
}
#: A height map given inline (a recording's own copy of its indenter) instead of as a file.
INLINE_HEIGHTMAP_KEY = "heights_mm"
COMMON_KEYS = ("kind", "tool_offset_mm", "max_normal_force_n", "max_shear_force_n", "max_depth_mm")


class IndenterError(LabrigError):
    """A bad indenter definition or an unknown indenter name."""


@dataclass(frozen=True)
class Indenter:
    """One indenter. Lengths in mm, forces in N."""

    name: str
    kind: str
    geometry: dict[str, Any]
    tool_offset_mm: tuple[float, float, float]
    max_normal_force_n: float
    max_shear_force_n: float
    max_depth_mm: float
    _heightmap: npt.NDArray[np.float64] | None = field(default=None, repr=False, compare=False)

    @property
    def axisymmetric(self) -> bool:
        return self.kind in ("sphere", "cylinder")

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
        ny, nx = self._heightmap.shape
        return float(np.hypot(nx, ny) * g["spacing_mm"] / 2)

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
        tip_row, tip_col = np.unravel_index(np.argmin(h), h.shape)
        col = x / spacing + tip_col
        row = y / spacing + tip_row
        inside = (col >= 0) & (col <= nx - 1) & (row >= 0) & (row <= ny - 1)
        c0 = np.clip(np.floor(col).astype(int), 0, nx - 2)
        r0 = np.clip(np.floor(row).astype(int), 0, ny - 2)
        fc, fr = np.clip(col - c0, 0, 1), np.clip(row - r0, 0, 1)
        value = (
            h[r0, c0] * (1 - fc) * (1 - fr) + h[r0, c0 + 1] * fc * (1 - fr)
            + h[r0 + 1, c0] * (1 - fc) * fr + h[r0 + 1, c0 + 1] * fc * fr
        ) - h.min()
        return np.where(inside & np.isfinite(value), value, np.inf)


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


def load_indenters(path: str | Path = DEFAULT_INDENTERS) -> dict[str, Indenter]:
    """All indenters in a TOML file, validated; errors name the file and the field."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise IndenterError(f"{path}: no such indenter file") from None
    except tomllib.TOMLDecodeError as exc:
        raise IndenterError(f"{path}: not valid TOML ({exc})") from None
    return {name: _parse(path, name, entry) for name, entry in data.items()}


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
    kind = entry.get("kind")
    if kind not in GEOMETRY_KEYS:
        raise IndenterError(f"{where} kind must be one of {', '.join(GEOMETRY_KEYS)}, not {kind!r}")
    geometry_keys = GEOMETRY_KEYS[kind]
    if kind == "heightmap" and INLINE_HEIGHTMAP_KEY in entry:
        geometry_keys = ("spacing_mm",)
    allowed = set(COMMON_KEYS) | set(geometry_keys) | ({INLINE_HEIGHTMAP_KEY} if kind == "heightmap" else set())
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
    if heightmap is not None and (heightmap.ndim != 2 or min(heightmap.shape) < 2):
        raise IndenterError(f"{where} height map must be a 2-D array of heights in mm")
    return Indenter(
        name=name,
        kind=kind,
        geometry=geometry,
        tool_offset_mm=(float(offset[0]), float(offset[1]), float(offset[2])),
        max_normal_force_n=float(entry["max_normal_force_n"]),
        max_shear_force_n=float(entry["max_shear_force_n"]),
        max_depth_mm=float(entry["max_depth_mm"]),
        _heightmap=heightmap,
    )
