"""Precomputed contact tables for real-time use, cached on disk.

One :class:`ContactTable` holds, for one indenter, gel, mode and grid:

* normal solutions over the indentation depth (0 to the indenter's
  ``max_depth_mm`` in ``depth_step_mm`` steps): the surface ``depth_mm`` field
  (uz, into the gel, whole grid) and the pressure (on a box around the contact);
* monotonic tangential solutions at every ``shear_depth_stride``-th depth
  (default: every depth), over the shift along one direction. The shift is
  normalised per depth by the gross-slip shift s_gs (the shift at which the
  last stick point vanishes under the full-slip traction mu p). The fractions
  s / s_gs are spaced so that Mindlin's Q / (mu P) = 1 - (1 - s / s_gs)^(3/2)
  steps uniformly (k / K), and lookups interpolate linearly in that
  coordinate: a Hertzian contact's force is linear in it and other shapes are
  close (linear steps in s would make the initial stiffness a secant, ~5 %
  low). Beyond s_gs the traction is taken as mu p along the shift (the solver
  gives |Q| 0.1-0.3 % below mu P there: the local slip directions fan out
  slightly), the gel surface stays put and only the rigid slip grows, so
  nothing more is stored.

Lookups (:meth:`ContactTable.fields`, ~1-3 ms at 0.1 mm) interpolate
linearly in depth and in that shift coordinate, superpose monotonic terms
for a shear history (Masing, see :mod:`history`), clip the traction to mu p,
rotate it for axisymmetric indenters (forces rotate exactly), and get the
in-plane surface displacement by one FFT convolution of the traction with the
stored tangential kernel window (so it is consistent with the returned
traction). Stiffening (:mod:`stiffening`) is applied at lookup: it is not
part of the cached data. Interpolating between depths blurs the contact edge
by the edge's motion over one depth step (fields there are a blend of two
contact sizes); forces match direct solves to < 1 %.

The grid is local: centred on the indenter tip, aligned with the gel axes,
``size_mm`` wide; a non-axisymmetric footprint is solved turned by its yaw
relative to the gel (``yaw_deg``; the virtual rig's :func:`labrig.sim.truth_config.true_contact_table`
takes it from the indenter's ``yaw_deg`` and the true gel yaw); the gel is treated as laterally infinite
(its edges are not modelled). Fields are float32; forces are from float64
sums. Tables are cached on disk, keyed by a hash of every input
(:mod:`table_cache`).
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.config import GelConfig
from labrig.indenters import Indenter
from labrig.physics.mechanics.convolution import SurfaceConvolver
from labrig.physics.mechanics.grid import Grid
from labrig.physics.mechanics.history import ShearHistory, Term
from labrig.physics.mechanics.influence import check_mode
from labrig.physics.mechanics.kernels import Box
from labrig.physics.mechanics.rotation import clip_to_friction_disc, rotate_contact_traction
from labrig.physics.mechanics.stiffening import stiffening_factor
from labrig.physics.mechanics.table_build import compute_table, to_mindlin
from labrig.physics.mechanics.table_cache import (
    TABLE_ARRAYS,
    read_table_file,
    table_key,
    table_path,
    table_spec,
    write_table_file,
)
from labrig.physics.mechanics.tangential import STICK_MARGIN

#: A non-axisymmetric indenter's table serves shifts within this angle of its direction (their
#: component along it); tables are built every DIRECTION_STEP_DEG (see :func:`table_direction_deg`).
DIRECTION_STEP_DEG = 15.0
DIRECTION_TOLERANCE_DEG = DIRECTION_STEP_DEG / 2 + 0.5
#: Table files a process keeps loaded (each tens of MB): a campaign's worker records recording after
#: recording with the same few tables, and a load is about 0.06 s.
LOADED_TABLES = 8

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ContactFields:
    """Contact state at one (depth, shift), on the table's grid (float32 fields).

    Gel frame directions; x_mm, y_mm are the cell-centre axes relative to the
    indenter tip. ``depth_mm`` is uz (positive into the gel, negative where the
    surface bulges out); ``ux_mm``, ``uy_mm`` the in-plane surface
    displacement; ``traction_mpa`` (2, ny, nx) and ``force_n`` = (Fx, Fy, Fz)
    are what the indenter applies to the gel (Fz > 0 pressing).
    """

    x_mm: F64
    y_mm: F64
    depth_mm: F32
    ux_mm: F32
    uy_mm: F32
    pressure_mpa: F32
    traction_mpa: F32
    contact_mask: npt.NDArray[np.bool_]
    stick_mask: npt.NDArray[np.bool_]
    force_n: F64


class ContactTable:
    """Tabulated normal and tangential contact of one indenter; build with :meth:`build`."""

    def __init__(self, meta: dict[str, Any], arrays: dict[str, np.ndarray], stiffening: float = 0.0) -> None:
        self.meta = meta
        self.stiffening = float(stiffening)
        self.depths_mm: F64 = arrays["depths_mm"]
        self.depth_fields: F32 = arrays["depth_fields"]  # (nd, ny, nx)
        self.pressure: F32 = arrays["pressure"]  # (nd, by, bx) on self.box
        self.normal_force_n: F64 = arrays["normal_force_n"]  # (nd,)
        self.shear_rows: npt.NDArray[np.int64] = arrays["shear_rows"]  # (nt,) indices into depths_mm
        self.slip_shift_mm: F64 = arrays["slip_shift_mm"]  # (nt,) gross-slip shift per shear depth
        self.fractions: F64 = arrays["fractions"]  # (nk,) shift / slip shift
        self.traction: F32 = arrays["traction"]  # (nt, nk, 2, by, bx) along the table direction
        self.shear_force_n: F64 = arrays["shear_force_n"]  # (nt, nk, 2)
        self.window: F64 = arrays["window"]  # tangential coefficients, box -> whole grid
        self.grid = Grid(meta["spacing_mm"], *meta["grid_shape"])
        self.box = Box(*meta["box"])
        self.shear_depths_mm = self.depths_mm[self.shear_rows]
        self._mindlin = to_mindlin(self.fractions)
        angle = np.deg2rad(meta["direction_deg"])
        self.direction = np.array([np.cos(angle), np.sin(angle)])
        self._convolver: SurfaceConvolver | None = None
        self._pressure_centres_mm = _pressure_centres(self.pressure, self.grid, self.box)
        self._scalar_lookup: _ScalarLookup | None = None

    # ------------------------------------------------------------------ building

    @classmethod
    def build(
        cls,
        indenter: Indenter,
        gel: GelConfig,
        *,
        mode: str = "layer",
        spacing_mm: float = 0.1,
        size_mm: float = 24.0,
        direction_deg: float = 0.0,
        yaw_deg: float = 0.0,
        depth_step_mm: float = 0.05,
        max_depth_mm: float | None = None,
        shear_depth_stride: int = 1,
        shear_steps: int = 10,
        stiffening: float = 0.0,
        cache_dir: str | Path | None = None,
        use_cache: bool = True,
    ) -> ContactTable:
        """The table for ``indenter`` on ``gel``: from the disk cache, or computed and cached.

        ``direction_deg`` is the shear direction in the gel frame (ignored for
        axisymmetric indenters, whose tables are rotated at lookup).
        ``yaw_deg`` is the footprint's turn relative to the gel
        (:meth:`~labrig.indenters.Indenter.footprint_yaw_deg`; ignored for axisymmetric indenters).
        ``stiffening`` is applied at lookup and is not part of the cache key.
        """
        check_mode(mode)
        max_depth = indenter.max_depth_mm if max_depth_mm is None else float(max_depth_mm)
        spec = table_spec(indenter, gel, mode=mode, spacing_mm=spacing_mm, size_mm=size_mm, direction_deg=direction_deg,
                          yaw_deg=indenter.reduced_turn_deg(yaw_deg),
                          depth_step_mm=depth_step_mm, max_depth_mm=max_depth, shear_depth_stride=shear_depth_stride,
                          shear_steps=shear_steps)
        key = table_key(spec)
        path = table_path(indenter, mode, key, cache_dir)
        if use_cache and path.exists():
            try:
                return _loaded(cls, path, stiffening)
            except (OSError, ValueError, KeyError):
                pass  # a damaged cache file: rebuild it
        start = time.perf_counter()
        meta, arrays = compute_table(indenter, gel, spec)
        meta.update(spec=spec, key=key, build_seconds=time.perf_counter() - start)
        table = cls(meta, arrays, stiffening)
        if use_cache:
            table.save(path)
        return table

    def save(self, path: str | Path) -> Path:
        """Write the table as an uncompressed ``.npz`` (atomically)."""
        return write_table_file(path, self.meta, {name: getattr(self, name) for name in TABLE_ARRAYS})

    @classmethod
    def load(cls, path: str | Path, stiffening: float = 0.0) -> ContactTable:
        """A table from its file; ValueError when the file is of another :data:`TABLE_VERSION`."""
        meta, arrays = read_table_file(path)
        return cls(meta, arrays, stiffening)

    @property
    def nbytes(self) -> int:
        return sum(getattr(self, name).nbytes for name in TABLE_ARRAYS)

    # ------------------------------------------------------------------ lookups

    @property
    def axisymmetric(self) -> bool:
        return bool(self.meta["spec"]["indenter"]["axisymmetric"])

    @property
    def yaw_deg(self) -> float:
        """The footprint's turn relative to the gel, deg (0 for axisymmetric indenters)."""
        return float(self.meta["spec"].get("yaw_deg", 0.0))

    @property
    def friction(self) -> float:
        return float(self.meta["spec"]["gel"]["friction"])

    def fields(
        self, depth_mm: float, shift_mm: float | npt.ArrayLike = 0.0, history: ShearHistory | None = None
    ) -> ContactFields:
        """Contact state at indentation ``depth_mm`` and indenter shift ``shift_mm``.

        ``shift_mm``: a scalar along the table direction (negative = opposite),
        or a gel-frame 2-vector (any direction for axisymmetric indenters, else
        parallel to the table direction). With ``history`` the shift path is
        tracked (feed every step in order) and Masing superposition applies;
        without it the loading is monotonic from zero. Depths <= 0 give an
        unloaded gel; depths beyond the table raise ValueError.
        """
        self._check_depth(depth_mm)
        terms, angle = self.shear_terms(shift_mm, history)
        return self.fields_for_terms(depth_mm, terms, angle)

    def shear_terms(
        self, shift_mm: float | npt.ArrayLike, history: ShearHistory | None = None
    ) -> tuple[tuple[Term, ...], float]:
        """(Masing terms along the table direction, rotation angle in rad) for a shift.

        Advances ``history`` (feed every step in order); without one the
        loading is monotonic from zero.
        """
        along, angle = self._resolve_shift(shift_mm, history)
        terms = history.advance(along) if history is not None else ((1.0, along),)
        return terms, angle

    def force_for_terms(self, depth_mm: float, terms: tuple[Term, ...], angle: float = 0.0) -> F64:
        """Net force (Fx, Fy, Fz) N the indenter applies to the gel (Fz > 0 pressing), cheaply.

        The Masing sum of the tabulated net shear forces, rotated by ``angle``,
        and the tabulated normal force, stiffened: microseconds instead of the
        fields' milliseconds, for force sensors sampled at kHz. Equal to
        :meth:`fields_for_terms`'s force.
        """
        return np.array(self.force_xyz_for_terms(depth_mm, terms, angle))

    def force_xyz_for_terms(self, depth_mm: float, terms: tuple[Term, ...], angle: float = 0.0) -> tuple[float, float, float]:
        """:meth:`force_for_terms` as Python floats (the kHz samplers' path: no small arrays)."""
        depth = self._check_depth(depth_mm)
        if depth <= 0:
            return 0.0, 0.0, 0.0
        lookup = self._lookup()
        row, weight = _bracket_list(lookup.depths_mm, depth)
        shear_x = shear_y = 0.0
        for w, s in terms:
            if s != 0 and w != 0:
                fx, fy = self._monotonic_force_xy(depth, s)
                shear_x += w * fx
                shear_y += w * fy
        if angle:
            c, s_ = math.cos(angle), math.sin(angle)
            shear_x, shear_y = c * shear_x - s_ * shear_y, s_ * shear_x + c * shear_y
        factor = stiffening_factor(depth, lookup.thickness_mm, self.stiffening)
        normal = _lerp_list(lookup.normal_force_n, row, weight)
        return shear_x * factor, shear_y * factor, normal * factor

    def pressure_centre_mm(self, depth_mm: float) -> F64:
        """Centre of pressure (x, y) mm relative to the tip at ``depth_mm`` (normal contact only, Goodman)."""
        return np.array(self.pressure_centre_xy(depth_mm))

    def pressure_centre_xy(self, depth_mm: float) -> tuple[float, float]:
        """:meth:`pressure_centre_mm` as Python floats."""
        depth = float(depth_mm)
        if depth <= 0:
            return 0.0, 0.0
        lookup = self._lookup()
        row, weight = _bracket_list(lookup.depths_mm, depth)
        return _lerp_list(lookup.centres_x_mm, row, weight), _lerp_list(lookup.centres_y_mm, row, weight)

    def slip_shift_at(self, depth_mm: float) -> float:
        """Gross-slip shift (mm) at ``depth_mm``, linear between the shear depths, held beyond them (0 without)."""
        lookup = self._lookup()
        depths, slips = lookup.shear_depths_mm, lookup.slip_shift_mm
        if not slips:
            return 0.0
        depth = float(depth_mm)
        if depth <= depths[0]:
            return slips[0]
        if depth >= depths[-1]:
            return slips[-1]
        i = bisect.bisect_right(depths, depth) - 1
        return (slips[i + 1] - slips[i]) / (depths[i + 1] - depths[i]) * (depth - depths[i]) + slips[i]

    def fields_for_terms(self, depth_mm: float, terms: tuple[Term, ...], angle: float = 0.0) -> ContactFields:
        """Contact fields at ``depth_mm`` for Masing ``terms`` (see :meth:`shear_terms`).

        The traction field is the superposition clipped to the Coulomb disc;
        the net force is :meth:`force_for_terms` (the clipped part, if any,
        is a fraction of a percent).
        """
        depth = self._check_depth(depth_mm)
        row, weight = _bracket(self.depths_mm, depth)
        depth_field = _lerp(self.depth_fields, row, weight)
        pressure = _lerp(self.pressure, row, weight)
        bound = (self.friction * pressure).astype(np.float32)
        traction = np.zeros((2, *self.box.shape), dtype=np.float32)
        if depth > 0:
            for w, s in terms:
                if s != 0 and w != 0:
                    traction += np.float32(w) * self._monotonic_traction(depth, s)
            traction = clip_to_friction_disc(traction, bound)
        area = self.grid.cell_area_mm2
        shear_force = traction.sum(axis=(1, 2), dtype=np.float64) * area
        if angle:
            traction, shear_force = rotate_contact_traction(traction, bound, angle, shear_force, area)
        # A zero traction (normal contact) displaces nothing: its convolution is skipped.
        u = self._tangential_convolver()(traction) if traction.any() else np.zeros((2, *self.grid.shape), np.float32)
        factor = stiffening_factor(depth, self.meta["spec"]["gel"]["thickness_mm"], self.stiffening)
        magnitude = np.hypot(traction[0], traction[1])
        in_contact = pressure > 0
        return ContactFields(
            x_mm=self.grid.x_mm,
            y_mm=self.grid.y_mm,
            depth_mm=depth_field,
            ux_mm=u[0],
            uy_mm=u[1],
            pressure_mpa=self._on_grid(pressure * np.float32(factor)),
            traction_mpa=self._on_grid(traction * np.float32(factor)),
            contact_mask=self._on_grid(in_contact),
            stick_mask=self._on_grid(in_contact & (magnitude < (1 - STICK_MARGIN) * bound)),
            force_n=self.force_for_terms(depth, terms, angle),
        )

    def _check_depth(self, depth_mm: float) -> float:
        depth = float(depth_mm)
        if depth > self.depths_mm[-1] + 1e-9:
            raise ValueError(f"depth {depth:.3f} mm is beyond this table's {self.depths_mm[-1]:.3f} mm")
        return depth

    def _monotonic_force_xy(self, depth: float, shift: float) -> tuple[float, float]:
        """Monotonic net shear force (x, y) N, unstiffened, for a signed shift along the table direction."""
        lookup = self._lookup()
        j, v = _bracket_list(lookup.shear_depths_mm, depth)
        out_x = out_y = 0.0
        sign = float((shift > 0) - (shift < 0))
        for row, w in ((j, 1 - v), (j + 1, v)):
            if w == 0 or row >= len(lookup.slip_shift_mm) or lookup.slip_shift_mm[row] <= 0:
                continue
            fraction = min(abs(shift) / lookup.slip_shift_mm[row], 1.0)
            k, f = _bracket_list(lookup.mindlin, 1.0 - (1.0 - fraction) ** 1.5)  # to_mindlin, on a float
            c = w * sign
            out_x += c * _lerp_list(lookup.shear_force_x_n[row], k, f)
            out_y += c * _lerp_list(lookup.shear_force_y_n[row], k, f)
        return out_x, out_y

    def _lookup(self) -> _ScalarLookup:
        if self._scalar_lookup is None:
            self._scalar_lookup = _ScalarLookup.of(self)
        return self._scalar_lookup

    def _monotonic_traction(self, depth: float, shift: float) -> F32:
        """Monotonic traction (box, float32) at ``depth`` for a signed shift along the table direction."""
        j, v = _bracket(self.shear_depths_mm, depth)
        out = np.zeros((2, *self.box.shape), dtype=np.float32)
        for row, w in ((j, 1 - v), (j + 1, v)):
            if w == 0 or row >= len(self.shear_rows) or self.slip_shift_mm[row] <= 0:
                continue
            k, f = _bracket(self._mindlin, float(to_mindlin(min(abs(shift) / self.slip_shift_mm[row], 1.0))))
            out += np.float32(w * np.sign(shift)) * _lerp(self.traction[row], k, f)
        return out

    def _resolve_shift(self, shift_mm: float | npt.ArrayLike, history: ShearHistory | None) -> tuple[float, float]:
        """(signed shift along the table direction, rotation angle in rad) for a scalar or vector shift."""
        if isinstance(shift_mm, (int, float)):
            return float(shift_mm), 0.0
        shift = np.asarray(shift_mm, dtype=np.float64)
        if shift.ndim == 0:
            return float(shift), 0.0
        sx, sy = shift.reshape(2).tolist()
        size = math.hypot(sx, sy)
        if history is not None:
            if history.axis is None and size > 0:
                history.axis = (sx / size, sy / size)
            ax, ay = history.axis if history.axis is not None else self._lookup().direction
            along = sx * ax + sy * ay
            if math.hypot(sx - along * ax, sy - along * ay) > 1e-9 + 1e-6 * size:
                raise ValueError("a shear history needs shifts along one axis (the first non-zero shift's)")
        elif size == 0:
            return 0.0, 0.0
        else:
            ax, ay, along = sx / size, sy / size, size
        turn = math.atan2(ay, ax) - self._lookup().direction_rad
        turn = (turn + math.pi) % (2 * math.pi) - math.pi
        if abs(turn) > math.pi / 2 + 1e-12:  # opposite half-plane: F is odd in the shift
            turn -= math.copysign(math.pi, turn)
            along = -along
        if abs(turn) > 1e-9 and not self.axisymmetric:
            if abs(turn) > math.radians(DIRECTION_TOLERANCE_DEG):
                raise ValueError(
                    f"this table shears along {self.meta['direction_deg']:.1f} deg; build one for this direction"
                )
            return along * math.cos(turn), 0.0  # a few degrees off: the component along the table's direction
        return along, (turn if abs(turn) > 1e-9 else 0.0)

    def _tangential_convolver(self) -> SurfaceConvolver:
        if self._convolver is None:
            self._convolver = SurfaceConvolver(self.window, self.box.shape, self.grid.shape, dtype=np.float32)
        return self._convolver

    def _on_grid(self, box_field: np.ndarray) -> np.ndarray:
        out = np.zeros((*box_field.shape[:-2], *self.grid.shape), dtype=box_field.dtype)
        out[(..., *self.box.slices)] = box_field
        return out


_loaded_tables: OrderedDict[tuple[str, int, int, float], ContactTable] = OrderedDict()
_loaded_lock = threading.Lock()


def _loaded(cls: type[ContactTable], path: Path, stiffening: float) -> ContactTable:
    """The table in ``path``, loaded once per process while the file stays as it is (its arrays
    read-only: every rig of the process shares them, with their lazily built lookups)."""
    stat = path.stat()
    key = (str(path.resolve()), stat.st_mtime_ns, stat.st_size, float(stiffening))
    with _loaded_lock:
        table = _loaded_tables.get(key)
        if table is not None:
            _loaded_tables.move_to_end(key)
            return table
    table = cls.load(path, stiffening=stiffening)
    for name in TABLE_ARRAYS:
        getattr(table, name).flags.writeable = False
    with _loaded_lock:
        _loaded_tables[key] = table
        while len(_loaded_tables) > LOADED_TABLES:
            _loaded_tables.popitem(last=False)
    return table


def table_direction_deg(shear_direction_deg: float) -> float:
    """The table direction (deg, in [0, 180)) serving a shear direction for a non-axisymmetric indenter.

    Forces are odd in the shift, so a direction and its opposite share a table."""
    return float(round((shear_direction_deg % 180.0) / DIRECTION_STEP_DEG) * DIRECTION_STEP_DEG % 180.0)


def _pressure_centres(pressure: F32, grid: Grid, box: Box) -> F64:
    """Centre of pressure (nd, 2) mm relative to the tip for each tabulated depth (0 where unloaded)."""
    x_mm = grid.x_mm[box.slices[1]]
    y_mm = grid.y_mm[box.slices[0]]
    total = pressure.sum(axis=(1, 2), dtype=np.float64)
    safe = np.where(total > 0, total, 1.0)
    cx = (pressure.sum(axis=1, dtype=np.float64) * x_mm).sum(axis=1) / safe
    cy = (pressure.sum(axis=2, dtype=np.float64) * y_mm).sum(axis=1) / safe
    return np.stack([np.where(total > 0, cx, 0.0), np.where(total > 0, cy, 0.0)], axis=1)


def _bracket(axis: npt.NDArray[np.floating], value: float) -> tuple[int, float]:
    """(i, w) with value = (1 - w) axis[i] + w axis[i + 1], clamped to the axis."""
    if value <= axis[0]:
        return 0, 0.0
    if value >= axis[-1]:
        return len(axis) - 1, 0.0
    i = int(axis.searchsorted(value, side="right")) - 1
    return i, float((value - axis[i]) / (axis[i + 1] - axis[i]))


def _lerp(stack: np.ndarray, i: int, w: float) -> np.ndarray:
    if w == 0.0:
        return stack[i].copy()
    a = stack.dtype.type
    return stack[i] * a(1 - w) + stack[i + 1] * a(w)


@dataclass(frozen=True)
class _ScalarLookup:
    """A table's small arrays as Python floats, for the per-sample lookups of kHz samplers."""

    depths_mm: list[float]
    normal_force_n: list[float]
    centres_x_mm: list[float]
    centres_y_mm: list[float]
    shear_depths_mm: list[float]
    slip_shift_mm: list[float]
    mindlin: list[float]
    shear_force_x_n: list[list[float]]
    shear_force_y_n: list[list[float]]
    thickness_mm: float
    direction: tuple[float, float]
    direction_rad: float

    @classmethod
    def of(cls, table: ContactTable) -> _ScalarLookup:
        dx, dy = (float(v) for v in table.direction)
        return cls(
            table.depths_mm.tolist(), table.normal_force_n.tolist(), table._pressure_centres_mm[:, 0].tolist(),
            table._pressure_centres_mm[:, 1].tolist(), table.shear_depths_mm.tolist(), table.slip_shift_mm.tolist(),
            table._mindlin.tolist(), table.shear_force_n[..., 0].tolist(), table.shear_force_n[..., 1].tolist(),
            float(table.meta["spec"]["gel"]["thickness_mm"]), (dx, dy), math.atan2(dy, dx),
        )


def _bracket_list(axis: list[float], value: float) -> tuple[int, float]:
    """:func:`_bracket` on a Python list."""
    if value <= axis[0]:
        return 0, 0.0
    if value >= axis[-1]:
        return len(axis) - 1, 0.0
    i = bisect.bisect_right(axis, value) - 1
    return i, (value - axis[i]) / (axis[i + 1] - axis[i])


def _lerp_list(values: list[float], i: int, w: float) -> float:
    if w == 0.0:
        return values[i]
    return values[i] * (1 - w) + values[i + 1] * w
