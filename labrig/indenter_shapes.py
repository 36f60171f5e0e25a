"""Procedural indenter shapes: height maps drawn from a family and a seed.

Labs press with more than spheres and punches. Each family below draws its
parameters from ``numpy.random.default_rng(seed)`` and renders a height map
(mm above the tip, ``inf`` where the indenter has no surface) on a square grid
of ``spacing_mm`` samples centred on the tool axis, in the indenter frame
(x along columns, y along rows); its lowest point is the tip (height 0). The same family and seed always give the same
map, so an indenters file names a shape in two keys
(``kind = "procedural"``, ``family``, ``seed``; see :mod:`labrig.indenters`).

Families (lengths in mm):

* ``annulus``: a ring (a torus of tube radius 0.4-1.0 on a centre circle of
  radius 1.6-3.0), open in the middle;
* ``pins``: 2-4 hemispherical pins (radius 0.6-1.4), spread over 3.5 mm, tips
  up to 0.25 mm apart in height;
* ``edge``: a straight edge: a wedge (flank angle 15-40 deg from the face) with
  a rounded tip (radius 0.2-1.0), 6-9 mm long with rounded ends;
* ``flat``: a flat face (round, or a rectangle of aspect up to 2) of width
  3-6, rounded over a fillet of 0.1-1.5;
* ``textured``: a sphere cap (radius 4-10) carrying a texture of
  0.03-0.12 amplitude: a grating (period 0.8-2.0) or a field of bumps.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Sample spacing of a procedural height map (mm).
SHAPE_SPACING_MM = 0.1
#: Half width of a procedural height map (mm): every footprint fits in 2 x this.
SHAPE_HALF_WIDTH_MM = 5.0
#: Heights above this (mm) are left out of a map (``inf``): deeper than any press reaches.
MAX_RELIEF_MM = 3.0


@dataclass(frozen=True)
class ShapeDraw:
    """One procedural shape: its family, seed, drawn parameters (mm, deg) and height map
    (mm above the tip, ``inf`` outside; rows along y, columns along x, the tip's axis at the centre sample)."""

    family: str
    seed: int
    parameters: dict[str, Any]
    heights_mm: FloatArray
    spacing_mm: float

    @property
    def half_width_mm(self) -> float:
        """From the map's first sample to its centre (the tool axis), mm, along x and y alike."""
        return (self.heights_mm.shape[1] - 1) / 2 * self.spacing_mm


def draw_shape(family: str, seed: int) -> ShapeDraw:
    """The shape of ``family`` drawn with ``seed`` (see the module docstring for the families)."""
    if family not in FAMILIES:
        raise ValueError(f"unknown shape family {family!r}; known: {', '.join(FAMILIES)}")
    rng = np.random.default_rng([seed, FAMILY_SALT[family]])
    n = round(SHAPE_HALF_WIDTH_MM / SHAPE_SPACING_MM)
    axis = np.arange(-n, n + 1) * SHAPE_SPACING_MM
    x, y = np.meshgrid(axis, axis)
    parameters, height = FAMILIES[family](rng, x, y)
    height = np.where(np.isfinite(height) & (height <= MAX_RELIEF_MM), height, np.inf)
    finite = np.isfinite(height)
    height = np.where(finite, height - height[finite].min(), np.inf)  # the lowest point is the tip
    return ShapeDraw(family, int(seed), parameters, height, SHAPE_SPACING_MM)


def _cap(r: FloatArray, radius: float) -> FloatArray:
    """Height of a sphere cap of ``radius`` at distance ``r`` from its axis (inf beyond it)."""
    with np.errstate(invalid="ignore"):
        return np.where(r < radius, radius - np.sqrt(np.clip(radius**2 - r**2, 0, None)), np.inf)


def _fillet(d: FloatArray, radius: float) -> FloatArray:
    """A flat face (d <= 0: distance inside its edge) rounded over a quarter circle of ``radius``."""
    with np.errstate(invalid="ignore"):
        edge = radius - np.sqrt(np.clip(radius**2 - d**2, 0, None))
    return np.where(d <= 0, 0.0, np.where(d < radius, edge, np.inf))


def _turn(x: FloatArray, y: FloatArray, angle_deg: float) -> tuple[FloatArray, FloatArray]:
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    return c * x + s * y, -s * x + c * y


def _annulus(rng: np.random.Generator, x: FloatArray, y: FloatArray) -> tuple[dict[str, Any], FloatArray]:
    tube = float(rng.uniform(0.4, 1.0))
    centre = float(rng.uniform(max(1.6, tube + 0.6), 3.0))
    return {"centre_radius_mm": centre, "tube_radius_mm": tube}, _cap(np.abs(np.hypot(x, y) - centre), tube)


def _pins(rng: np.random.Generator, x: FloatArray, y: FloatArray) -> tuple[dict[str, Any], FloatArray]:
    count = int(rng.integers(2, 5))
    pins: list[tuple[float, float, float, float]] = []
    while len(pins) < count:
        radius = float(rng.uniform(0.6, 1.4))
        px, py = (float(v) for v in rng.uniform(-1.75, 1.75, 2))
        if all(np.hypot(px - qx, py - qy) > radius + qr + 0.3 for qx, qy, qr, _ in pins):
            pins.append((px, py, radius, float(rng.uniform(0.0, 0.25))))
    height = np.full(x.shape, np.inf)
    for px, py, radius, lift in pins:
        height = np.minimum(height, _cap(np.hypot(x - px, y - py), radius) + lift)
    return {"pins_xy_radius_lift_mm": [list(p) for p in pins]}, height


def _edge(rng: np.random.Generator, x: FloatArray, y: FloatArray) -> tuple[dict[str, Any], FloatArray]:
    tip = float(rng.uniform(0.2, 1.0))
    flank = float(rng.uniform(15.0, 40.0))
    length = float(rng.uniform(6.0, 9.0))
    yaw = float(rng.uniform(0.0, 180.0))
    u, v = _turn(x, y, yaw)
    across = np.hypot(np.clip(np.abs(u) - (length / 2 - tip), 0, None), v)  # distance from the edge's line
    slope = np.tan(np.radians(flank))
    touch = tip * np.sin(np.radians(flank))  # where the flank meets the tip circle tangentially
    with np.errstate(invalid="ignore"):
        round_tip = tip - np.sqrt(np.clip(tip**2 - across**2, 0, None))
    flank_height = tip - np.sqrt(tip**2 - touch**2) + (across - touch) * slope
    height = np.where(across <= touch, round_tip, flank_height)
    return {"tip_radius_mm": tip, "flank_deg": flank, "length_mm": length, "yaw_deg": yaw}, height


def _flat(rng: np.random.Generator, x: FloatArray, y: FloatArray) -> tuple[dict[str, Any], FloatArray]:
    width = float(rng.uniform(3.0, 6.0))
    fillet = float(rng.uniform(0.1, min(1.5, width / 3)))
    round_face = bool(rng.random() < 0.5)
    if round_face:
        return ({"diameter_mm": width, "fillet_mm": fillet},
                _fillet(np.hypot(x, y) - (width / 2 - fillet), fillet))
    aspect = float(rng.uniform(1.0, 2.0))
    yaw = float(rng.uniform(0.0, 90.0))
    u, v = _turn(x, y, yaw)
    half_u, half_v = width / 2, min(width * aspect, 9.0) / 2
    du = np.clip(np.abs(u) - (half_u - fillet), 0, None)
    dv = np.clip(np.abs(v) - (half_v - fillet), 0, None)
    return ({"width_mm": width, "length_mm": 2 * half_v, "fillet_mm": fillet, "yaw_deg": yaw},
            _fillet(np.hypot(du, dv), fillet))


def _textured(rng: np.random.Generator, x: FloatArray, y: FloatArray) -> tuple[dict[str, Any], FloatArray]:
    radius = float(rng.uniform(4.0, 10.0))
    amplitude = float(rng.uniform(0.03, 0.12))
    base = _cap(np.hypot(x, y), radius)
    if rng.random() < 0.5:
        period = float(rng.uniform(0.8, 2.0))
        angle = float(rng.uniform(0.0, 180.0))
        u, _ = _turn(x, y, angle)
        texture = amplitude * 0.5 * (1 - np.cos(2 * np.pi * u / period))
        parameters = {"radius_mm": radius, "grating_period_mm": period, "grating_deg": angle, "amplitude_mm": amplitude}
    else:
        count = int(rng.integers(8, 20))
        centres = rng.uniform(-4.0, 4.0, (count, 2))
        width = float(rng.uniform(0.3, 0.7))
        bumps = np.zeros(x.shape)
        for cx, cy in centres:
            bumps = np.maximum(bumps, np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * width**2)))
        texture = amplitude * (1 - bumps)  # bumps stand out from the cap by up to ``amplitude``
        parameters = {"radius_mm": radius, "bumps": count, "bump_width_mm": width, "amplitude_mm": amplitude}
    return parameters, base + texture


Family = Callable[[np.random.Generator, FloatArray, FloatArray], tuple[dict[str, Any], FloatArray]]

#: The shape families, by name.
FAMILIES: dict[str, Family] = {
    "annulus": _annulus,
    "pins": _pins,
    "edge": _edge,
    "flat": _flat,
    "textured": _textured,
}
#: Mixed into each family's random stream, so that one seed draws unrelated shapes in two families.
FAMILY_SALT = {name: i + 1 for i, name in enumerate(FAMILIES)}
