"""The virtual rig's imperfect sensor, from the rig file's optional ``sim.*`` sections.

A real gel's markers are printed by hand or through a stencil, a real EVK4 hands its
events to the host in USB bursts, a serial F/T link loses the odd frame. These
sections say how the virtual rig's sensor differs from the ideal one; each may be
left out, and every default is the ideal sensor (the rig then behaves exactly as
without the section).

``[sim.markers]`` (the markers as printed; the nominal lattice is ``[markers]``):

* ``position_error_mm``: a number, the standard deviation (mm, per gel axis x and y)
  of each marker's placement error, drawn once from ``seed``; or an explicit list of
  ``[dx, dy]`` pairs (mm, gel frame), one per marker in the lattice's row-major order.
* ``diameter_variation``: the standard deviation of each marker's diameter relative
  to ``[markers] diameter_mm`` (0.1: 10 %).
* ``contrast_variation``: the standard deviation of each marker's contrast (its
  brightness above the membrane, the ink density) relative to the nominal.
* ``missing``: marker indices (row-major, 0-based) never printed; ``missing_count``:
  that many more, chosen at random from the others (``seed``).

``[sim.camera_delivery]``: ``burst_period_ms`` (0: no bursts) and ``burst_jitter_ms``:
the host receives the camera's data in bursts, released at ``k * period + U(0, jitter)``
ms of world time; ``hot_pixels``: that many pixels of the ROI (chosen from ``seed``)
fire at ``hot_pixel_rate_hz`` on top of their own events.

``[sim.ft]``: ``drop_probability``, the chance that one F/T sample never reaches the host.

``[sim.grbl]``: the virtual CNC's machine limits, written into the GRBL twin's settings at
power-on: ``max_rate_mm_min`` (``$110-$112``, mm/min) and ``acceleration_mm_s2``
(``$120-$122``, mm/s**2), each a number (all axes) or ``[x, y, z]``. Defaults: GRBL 1.1h's
(500 mm/min, 10 mm/s**2), so a protocol faster than 8.3 mm/s needs this section. A rate is
refused if the axis' steps (``GRBL_STEPS_PER_MM``) would pass the stepper's ``GRBL_MAX_STEP_RATE_HZ``.

Random draws are independent per knob (a knob's draws do not change when another
knob is set) and depend only on the section's ``seed``: the same file prints the
same gel.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.errors import ConfigError

Offsets = tuple[tuple[float, float], ...]

#: GRBL's stepper interrupt rate limit (Hz) and the twin's steps/mm ($100-$102): a max rate is capped by them.
GRBL_MAX_STEP_RATE_HZ = 30_000.0
GRBL_STEPS_PER_MM = 250.0
#: GRBL 1.1h's defaults: $110-$112 (mm/min), $120-$122 (mm/s**2).
GRBL_DEFAULT_MAX_RATE_MM_MIN = 500.0
GRBL_DEFAULT_ACCELERATION_MM_S2 = 10.0

#: A marker's diameter and contrast factors are kept at or above this (a variation cannot make them vanish).
MIN_FACTOR = 0.05


@dataclass(frozen=True)
class SimMarkers:
    """``[sim.markers]``: how the markers were printed (see the module docstring)."""

    seed: int = 0
    position_error_mm: float | Offsets = 0.0
    diameter_variation: float = 0.0
    contrast_variation: float = 0.0
    missing: tuple[int, ...] = ()
    missing_count: int = 0

    @property
    def ideal(self) -> bool:
        """Every marker printed where, as large and as dark as nominal."""
        return (self.position_error_mm == 0.0 and self.diameter_variation == 0.0 and self.contrast_variation == 0.0
                and not self.missing and self.missing_count == 0)


@dataclass(frozen=True)
class SimCameraDelivery:
    """``[sim.camera_delivery]``: USB bursts (ms) and hot pixels (see the module docstring)."""

    seed: int = 0
    burst_period_ms: float = 0.0
    burst_jitter_ms: float = 0.0
    hot_pixels: int = 0
    hot_pixel_rate_hz: float = 200.0


@dataclass(frozen=True)
class SimFt:
    """``[sim.ft]``: the F/T link (see the module docstring); drops follow the run's seed."""

    drop_probability: float = 0.0


Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class SimGrbl:
    """``[sim.grbl]``: the virtual CNC's per-axis max rates (mm/min) and accelerations (mm/s**2), x, y, z."""

    max_rate_mm_min: Vec3 = (GRBL_DEFAULT_MAX_RATE_MM_MIN,) * 3
    acceleration_mm_s2: Vec3 = (GRBL_DEFAULT_ACCELERATION_MM_S2,) * 3

    @property
    def max_rate_mm_s(self) -> Vec3:
        """The max rates in mm/s (x, y, z)."""
        x, y, z = (v / 60.0 for v in self.max_rate_mm_min)
        return (x, y, z)

    def settings(self) -> dict[int, float]:
        """The GRBL settings these limits are: ``{110: x, 111: y, 112: z, 120: ..., 122: ...}``."""
        return {**{110 + i: v for i, v in enumerate(self.max_rate_mm_min)},
                **{120 + i: v for i, v in enumerate(self.acceleration_mm_s2)}}


@dataclass(frozen=True)
class PrintedMarkers:
    """The markers as printed, in the lattice's row-major order (N = rows * cols).

    ``rest_mm`` (N, 3): rest centres, gel frame (a missing marker's is where it would have
    been); ``diameter_mm`` (N,); ``contrast`` (N,): brightness above the membrane relative
    to the nominal; ``printed`` (N,): False for a missing marker.
    """

    rest_mm: npt.NDArray[np.float64]
    diameter_mm: npt.NDArray[np.float64]
    contrast: npt.NDArray[np.float64]
    printed: npt.NDArray[np.bool_]

    @property
    def missing(self) -> npt.NDArray[np.int64]:
        """Indices of the markers never printed."""
        return np.flatnonzero(~self.printed)


def printed_markers(spec: SimMarkers, nominal_rest_mm: npt.ArrayLike, diameter_mm: float) -> PrintedMarkers:
    """Realise ``spec`` on the nominal lattice (N, 3 rest centres, gel mm; nominal diameter, mm)."""
    rest = np.array(nominal_rest_mm, dtype=np.float64)
    n = len(rest)
    if isinstance(spec.position_error_mm, tuple):
        rest[:, :2] += np.asarray(spec.position_error_mm, dtype=np.float64)
    elif spec.position_error_mm > 0:
        rest[:, :2] += _rng(spec.seed, 1).normal(0.0, spec.position_error_mm, (n, 2))
    diameter = np.full(n, float(diameter_mm))
    if spec.diameter_variation > 0:
        diameter *= np.maximum(1.0 + _rng(spec.seed, 2).normal(0.0, spec.diameter_variation, n), MIN_FACTOR)
    contrast = np.ones(n)
    if spec.contrast_variation > 0:
        contrast = np.maximum(1.0 + _rng(spec.seed, 3).normal(0.0, spec.contrast_variation, n), MIN_FACTOR)
    printed = np.ones(n, dtype=bool)
    printed[list(spec.missing)] = False
    if spec.missing_count:
        others = np.flatnonzero(printed)
        printed[_rng(spec.seed, 4).choice(others, spec.missing_count, replace=False)] = False
    return PrintedMarkers(rest, diameter, contrast, printed)


def hot_pixel_indices(spec: SimCameraDelivery, roi_pixels: int) -> npt.NDArray[np.int64]:
    """Flat ROI indices (row-major) of the hot pixels, sorted."""
    if spec.hot_pixels == 0:
        return np.zeros(0, np.int64)
    return np.sort(_rng(spec.seed, 5).choice(roi_pixels, spec.hot_pixels, replace=False)).astype(np.int64)


def _rng(seed: int, knob: int) -> np.random.Generator:
    return np.random.default_rng([seed, knob])


# -- parsing ----------------------------------------------------------------------------------------


def parse_imperfections(sim: dict[str, Any], path: Path) -> tuple[SimMarkers, SimCameraDelivery, SimFt]:
    """The optional ``[sim.markers]``, ``[sim.camera_delivery]``, ``[sim.ft]`` sections (defaults where absent)."""
    return (_optional(SimMarkers, sim, "markers", path), _optional(SimCameraDelivery, sim, "camera_delivery", path),
            _optional(SimFt, sim, "ft", path))


def sim_table(sim: dict[str, Any], name: str, cls: type, path: Path) -> tuple[dict[str, Any], str]:
    """The optional ``[sim.NAME]`` table (empty where absent) and the ``where`` of its messages, checked to be a
    table whose keys are fields of the dataclass ``cls``."""
    table = sim.get(name, {})
    where = f"{path}: [sim.{name}]"
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table, e.g. [sim.{name}] on its own line")
    names = [f.name for f in fields(cls)]
    unknown = sorted(set(table) - set(names))
    if unknown:
        raise ConfigError(f"{where} unknown key {unknown[0]!r}; allowed: {', '.join(names)}")
    return table, where


def parse_grbl(sim: dict[str, Any], path: Path) -> SimGrbl:
    """The optional ``[sim.grbl]`` section, checked (defaults where absent: GRBL 1.1h's)."""
    table, where = sim_table(sim, "grbl", SimGrbl, path)
    values = {key: _axes(key, table[key], where) for key in table}
    for key, axes in values.items():
        if min(axes) <= 0:
            raise ConfigError(f"{where} {key} must be positive on every axis, not {_show(table[key])}")
    grbl = SimGrbl(**values)
    cap = GRBL_MAX_STEP_RATE_HZ / GRBL_STEPS_PER_MM * 60.0
    for axis, rate in zip("xyz", grbl.max_rate_mm_min, strict=True):
        if rate > cap:
            raise ConfigError(f"{where} max_rate_mm_min {rate:g} on {axis} is beyond GRBL's step rate "
                              f"({GRBL_MAX_STEP_RATE_HZ:g} Hz at {GRBL_STEPS_PER_MM:g} steps/mm): give at most {cap:g} mm/min")
    return grbl


def _axes(key: str, value: Any, where: str) -> Vec3:
    if _is_number(value):
        return (float(value),) * 3
    if isinstance(value, list) and len(value) == 3 and all(_is_number(v) for v in value):
        return (float(value[0]), float(value[1]), float(value[2]))
    raise ConfigError(f"{where} {key} must be a number (all axes) or [x, y, z], not {_show(value)}")


def _show(value: Any) -> str:
    return repr(value) if not isinstance(value, list) else "[" + ", ".join(str(v) for v in value) + "]"


def _optional(cls: type, sim: dict[str, Any], name: str, path: Path) -> Any:
    table, where = sim_table(sim, name, cls, path)
    values = {key: _value(cls, key, table[key], where) for key in table}
    return cls(**values)


def _value(cls: type, key: str, value: Any, where: str) -> Any:
    default = next(f.default for f in fields(cls) if f.name == key)
    if key == "position_error_mm":
        if isinstance(value, list):
            pairs = []
            for item in value:
                if not (isinstance(item, list) and len(item) == 2 and all(_is_number(v) for v in item)):
                    raise ConfigError(f"{where} position_error_mm: give a number (mm std) or a list of [dx, dy] pairs, "
                                      f"not {item!r} in the list")
                pairs.append((float(item[0]), float(item[1])))
            return tuple(pairs)
        if not _is_number(value):
            raise ConfigError(f"{where} position_error_mm must be a number (mm std) or a list of [dx, dy] pairs")
        return float(value)
    if isinstance(default, tuple):
        if not (isinstance(value, list) and all(isinstance(v, int) and not isinstance(v, bool) for v in value)):
            raise ConfigError(f"{where} {key} must be a list of marker indices, e.g. [0, 17]")
        return tuple(value)
    if isinstance(default, int) and not isinstance(default, bool):
        if not (isinstance(value, int) and not isinstance(value, bool)):
            raise ConfigError(f"{where} {key} must be a whole number, not {value!r}")
        return value
    if not _is_number(value):
        raise ConfigError(f"{where} {key} must be a number, not {value!r}")
    return float(value)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def check_imperfections(
    markers: SimMarkers, delivery: SimCameraDelivery, ft: SimFt, n_markers: int, pitch_mm: float, roi_pixels: int,
    where: str,
) -> None:
    """Range checks; each error names the section and the key and says what is allowed."""
    m = f"{where}: [sim.markers]"
    error = markers.position_error_mm
    if isinstance(error, tuple):
        if len(error) != n_markers:
            raise ConfigError(f"{m} position_error_mm lists {len(error)} [dx, dy] pairs; give one per marker ({n_markers})")
        if max(max(abs(dx), abs(dy)) for dx, dy in error) >= pitch_mm / 2:
            raise ConfigError(f"{m} position_error_mm: every offset must stay under half the pitch ({pitch_mm / 2:g} mm)")
    elif not 0 <= error <= pitch_mm / 4:
        raise ConfigError(f"{m} position_error_mm must be in [0, {pitch_mm / 4:g}] mm (a quarter of the pitch), not {error:g}")
    for key in ("diameter_variation", "contrast_variation"):
        if not 0 <= getattr(markers, key) <= 0.5:
            raise ConfigError(f"{m} {key} must be in [0, 0.5] (a relative standard deviation), not {getattr(markers, key):g}")
    bad = [i for i in markers.missing if not 0 <= i < n_markers]
    if bad:
        raise ConfigError(f"{m} missing: marker index {bad[0]} is outside 0..{n_markers - 1} (row-major)")
    if len(set(markers.missing)) != len(markers.missing):
        raise ConfigError(f"{m} missing lists a marker twice")
    if not 0 <= markers.missing_count <= n_markers - len(markers.missing) - 1:
        raise ConfigError(f"{m} missing_count must be in [0, {n_markers - len(markers.missing) - 1}] "
                          f"(at least one marker printed), not {markers.missing_count}")
    d = f"{where}: [sim.camera_delivery]"
    if delivery.burst_period_ms < 0 or delivery.burst_jitter_ms < 0:
        raise ConfigError(f"{d} burst_period_ms and burst_jitter_ms must be >= 0")
    if delivery.burst_jitter_ms > delivery.burst_period_ms:
        raise ConfigError(f"{d} burst_jitter_ms ({delivery.burst_jitter_ms:g}) must not exceed burst_period_ms "
                          f"({delivery.burst_period_ms:g}); 0 jitter without bursts")
    if not 0 <= delivery.hot_pixels <= roi_pixels:
        raise ConfigError(f"{d} hot_pixels must be in [0, {roi_pixels}] (the ROI's pixels), not {delivery.hot_pixels}")
    if not 0 < delivery.hot_pixel_rate_hz <= 3000:
        raise ConfigError(f"{d} hot_pixel_rate_hz must be in (0, 3000] Hz, not {delivery.hot_pixel_rate_hz:g}")
    if not 0 <= ft.drop_probability < 1:
        raise ConfigError(f"{where}: [sim.ft] drop_probability must be in [0, 1), not {ft.drop_probability:g}")
