"""Evetac's published dot tracker (Funk et al., IEEE T-RO 2024), re-implemented from its description.

The facts come from Evetac's public source (``nifunk/evetac_software``: the tracker model in
``utils/dot_tracking_utils.py``, the 1 kHz slicing and noise filter in
``ebcam-readout/track_dots_ros.py``, the dot calibration in ``calibration/calibrate.py``);
no code is taken from it. Per slice of events (1 ms: Evetac's 1 kHz; the ROS node allows up
to 5 ms):

1. **Background-activity filter first.** An event passes if one of its 8 neighbouring
   pixels had an event less than ``ba_window_us`` (Evetac: 100 ms) before it; every event,
   passed or not, stamps its own pixel (dv-processing's ``BackgroundActivityNoiseFilter``).
2. **Ring band.** A passed event acts on every dot whose centre is at a distance ``d`` in
   the band ``(D - w, D]``: ``D`` is the calibrated dot size (the OpenCV blob size, a
   diameter, of the dot's accumulated events), ``w`` the band width (12.5 px x 1.1).
3. **Falloff.** The event pulls the dot's centre toward itself by ``2 (1.25 D - d)``
   (px units) along the line between them (the gradient, with respect to the event, of a
   circle fit of radius 1.25 D): an event at the band's inner edge pulls hardest.
4. **Clip.** Each dot's pulls are summed per axis, each sum clipped to ``+-C`` (400
   units), and scaled by the step (0.003 px per unit).
5. **Activity threshold.** A dot moves only if the band saw at least ``10 + 3 (slice ms
   - 1)`` non-zero pull components (two per event, one for an event straight above, below,
   left or right of the centre): longer slices need more activity.
6. **Springs on moving dots only.** A moving dot is also pulled along each link to its
   neighbours (rest distance below 105 px: the 8-neighbourhood) by
   ``step * g * 8 / n * 4 (c_j - c_i) (|c_j - c_i|^2 - d0^2)`` (``g`` = 7.5e-5 px^-2,
   ``n`` its neighbour count, ``d0`` the rest distance): a stretched link contracts, a
   squeezed one pushes. A dot below the threshold feels no spring.

Pulls and springs are evaluated at the slice's starting positions and applied together.

**Transfer to this rig.** Evetac images a GelSight Mini gel with a 640 x 480 DVXplorer
Mini; its pixel constants belong to that geometry. Two scales carry them over:

* dot constants (band width, clip) scale by ``k = D / 25 px``: ``D`` here is the
  marker's image diameter (:func:`labrig.pipeline.tracking.marker_diameter_px`, the blob
  Evetac's calibration would find) and 25 px is Evetac's dot size, inferred from its band:
  the inner edge ``D - 12.5`` px sits on the dot's rim (``D / 2``) for a 25 px dot, which is
  what makes the pull track (a lagging centre sees the leading rim in the band and the
  trailing rim inside the hole). So the band here is ``(0.45 D, D]``, the clip ``400 k``
  (at most ``1.2 k`` px per axis per slice). The step, the 1.25 D pull radius and the
  activity counts are unitless and kept.
* grid constants scale by the pitch ``P`` (the median rest distance to the nearest
  neighbour) over Evetac's 61.5 px, inferred from its 105 px neighbour cut-off, which must
  take the diagonal neighbours (1.41 P) and not the next ring (2 P): midway, 1.71 P. The
  cut-off is ``1.71 P`` and the spring gain ``g (61.5 / P)^2`` (the spring's move per unit
  strain then scales with the pitch, like every other length).

Other differences: event offsets from a centre are exact (Evetac truncates them to whole
pixels for its lookup table); slices are whole multiples of ``slice_us`` of the event
clock, so a window that ends inside a slice processes that slice's events so far and the
next window processes the rest as a second, shorter slice (time windows that are whole
multiples of the slice never split one). Positions are sensor pixels (x, y), in the rig's
marker order; events must come in time order.

**Missing markers** (``observed`` False: never printed, as the extrinsic calibration found)
are skipped as :class:`~labrig.pipeline.tracking.CircleFitTracker` skips them: they have no
band (their events pull nobody), no spring links to them (the pitch and the neighbour links
come from the observed dots' rest positions, so a neighbour of a hole keeps its other
links, reweighted by ``8 / n``), and their reported position follows the mean displacement
of their observed grid neighbours (never ``moved``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from numba import njit

from labrig.pipeline.tracking import follow_neighbours, grid_markers, grid_neighbours

Array = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

# Evetac's published constants, in its own pixels.
EVETAC_DOT_PX = 25.0  # its dot size (inferred, see the module docstring)
EVETAC_PITCH_PX = 61.5  # its dot pitch (inferred from the neighbour cut-off)
BAND_WIDTH_PX = 12.5 * 1.1  # the band's width, with its 1.1 factor for smaller dots
PULL_RADIUS = 1.25  # x D: where the pull falls to zero
STEP = 200 * 0.000015  # px of move per unit of clipped pull
CLIP = 400.0  # per-axis clip of a dot's summed pull
SPRING_GAIN = 1.5 * 200 * 0.00000025  # px^-2
NEIGHBOUR_CUTOFF_PX = 105.0
ACTIVITY_BASE = 10  # non-zero pull components a dot needs in a 1 ms slice ...
ACTIVITY_PER_MS = 3  # ... and this many more per further ms of slice
BA_WINDOW_US = 100_000
MAX_SLICE_US = 5_000  # Evetac's longest slice ("to keep the hyperparameters")
_CELL_CAPACITY = 16  # dots whose band may reach one lookup cell


@dataclass(frozen=True)
class EvetacParams:
    """Evetac's tracker on this rig; ``marker_diameter_px`` is the dot size D, ``pitch_px`` None: from the rest grid."""

    marker_diameter_px: float = 14.0
    pitch_px: float | None = None
    slice_us: int = 1_000  # 1 ms: Evetac's 1 kHz; up to 5 ms in whole ms
    springs: bool = True  # Evetac's ``regularize_tracking``
    ba_window_us: int | None = BA_WINDOW_US  # None: no background-activity filter
    grid_rows: int = 12
    grid_cols: int = 13
    width_px: int = 1280
    height_px: int = 720

    def __post_init__(self) -> None:
        if self.marker_diameter_px <= 0:
            raise ValueError(f"marker_diameter_px must be positive, not {self.marker_diameter_px}")
        if not (1_000 <= self.slice_us <= MAX_SLICE_US and self.slice_us % 1_000 == 0):
            raise ValueError(f"slice_us must be 1000-{MAX_SLICE_US} in whole ms (Evetac's slices), not {self.slice_us}")

    @property
    def activity_threshold(self) -> int:
        """Non-zero pull components a dot needs in one slice to move: 10 at 1 ms, 3 more per further ms."""
        return ACTIVITY_BASE + ACTIVITY_PER_MS * (self.slice_us // 1_000 - 1)


@dataclass(frozen=True)
class Geometry:
    """The published constants carried over to this rig (px); see the module docstring."""

    inner_px: float  # band (inner, outer]
    outer_px: float
    pull_radius_px: float  # where the pull falls to zero
    clip: float  # per-axis clip of the summed pull (px units)
    spring_gain: float  # px^-2
    neighbour_cutoff_px: float

    @classmethod
    def for_rig(cls, diameter_px: float, pitch_px: float) -> Geometry:
        k = diameter_px / EVETAC_DOT_PX
        return cls(inner_px=diameter_px - BAND_WIDTH_PX * k, outer_px=diameter_px, pull_radius_px=PULL_RADIUS * diameter_px,
                   clip=CLIP * k, spring_gain=SPRING_GAIN * (EVETAC_PITCH_PX / pitch_px) ** 2,
                   neighbour_cutoff_px=NEIGHBOUR_CUTOFF_PX / EVETAC_PITCH_PX * pitch_px)


@njit(cache=True, nogil=True)
def background_activity(x, y, t, surface, window_us, keep):  # pragma: no cover - compiled
    """keep[i]: an 8-neighbour of event i fired less than ``window_us`` before it; every event stamps ``surface``."""
    h, w = surface.shape
    for i in range(x.shape[0]):
        xi, yi, ti = int(x[i]), int(y[i]), t[i]
        ok = False
        for dy in range(-1, 2):
            yy = yi + dy
            if yy < 0 or yy >= h:
                continue
            for dx in range(-1, 2):
                xx = xi + dx
                if (dx == 0 and dy == 0) or xx < 0 or xx >= w:
                    continue
                if ti - surface[yy, xx] < window_us:
                    ok = True
        keep[i] = ok
        if xi < w and yi < h:
            surface[yi, xi] = ti


@njit(cache=True, nogil=True)
def band_pulls(x, y, keep, pos, inner, outer, pull_radius, cell, cells, counts, pull, activity):  # pragma: no cover
    """pull[m] += each band event's pull on dot m (toward the event, 2 (pull_radius - d)); activity[m] += its
    non-zero components. ``cells``/``counts``: per lookup cell (``cell`` px square), the dots whose band reaches it."""
    gh, gw = counts.shape
    counts[:, :] = 0
    for m in range(pos.shape[0]):
        cx0, cx1 = math.floor((pos[m, 0] - outer) / cell), math.floor((pos[m, 0] + outer) / cell)
        cy0, cy1 = math.floor((pos[m, 1] - outer) / cell), math.floor((pos[m, 1] + outer) / cell)
        for cy in range(max(cy0, 0), min(cy1, gh - 1) + 1):
            for cx in range(max(cx0, 0), min(cx1, gw - 1) + 1):
                if counts[cy, cx] < cells.shape[2]:
                    cells[cy, cx, counts[cy, cx]] = m
                    counts[cy, cx] += 1
    inner2, outer2 = inner * inner, outer * outer
    for i in range(x.shape[0]):
        if not keep[i]:
            continue
        xi, yi = float(x[i]), float(y[i])
        cy, cx = int(yi // cell), int(xi // cell)
        if cy >= gh or cx >= gw:
            continue
        for k in range(counts[cy, cx]):
            m = cells[cy, cx, k]
            dx, dy = xi - pos[m, 0], yi - pos[m, 1]
            d2 = dx * dx + dy * dy
            if d2 <= inner2 or d2 > outer2:
                continue
            d = max(math.sqrt(d2), 1.0)
            g = 2.0 * (pull_radius - d) / d
            pull[m, 0] += g * dx
            pull[m, 1] += g * dy
            activity[m] += (dx != 0.0) + (dy != 0.0)


@njit(cache=True, nogil=True)
def spring_pulls(pos, neigh, rest_d2, correction, active, gain, out):  # pragma: no cover - compiled
    """out[m] = gain * 8/n * sum_j 4 (c_j - c_m)(|c_j - c_m|^2 - d0^2) for active dots, 0 for the others."""
    for m in range(pos.shape[0]):
        out[m, 0], out[m, 1] = 0.0, 0.0
        if not active[m]:
            continue
        for k in range(neigh.shape[1]):
            j = neigh[m, k]
            if j < 0:
                continue
            dx, dy = pos[j, 0] - pos[m, 0], pos[j, 1] - pos[m, 1]
            stretch = dx * dx + dy * dy - rest_d2[m, k]
            out[m, 0] += 4.0 * dx * stretch
            out[m, 1] += 4.0 * dy * stretch
        out[m, 0] *= gain * correction[m]
        out[m, 1] *= gain * correction[m]


def neighbour_links(rest_px: Array, cutoff_px: float) -> tuple[npt.NDArray[np.int64], Array, Array]:
    """(neighbours (M, K) padded with -1, their squared rest distances (M, K) px^2, 8 / count (M,)) within ``cutoff_px``."""
    d = np.linalg.norm(rest_px[:, None, :] - rest_px[None, :, :], axis=2)
    linked = (d < cutoff_px) & ~np.eye(len(rest_px), dtype=bool)
    count = linked.sum(axis=1)
    neigh = np.full((len(rest_px), max(int(count.max()), 1)), -1, np.int64)
    rest_d2 = np.ones(neigh.shape)
    for m in range(len(rest_px)):
        js = np.flatnonzero(linked[m])
        neigh[m, :len(js)] = js
        rest_d2[m, :len(js)] = d[m, js] ** 2
    return neigh, rest_d2, 8.0 / np.maximum(count, 1)


def grid_pitch_px(rest_px: Array) -> float:
    """The median distance from each rest position to its nearest neighbour (px)."""
    d = np.linalg.norm(rest_px[:, None, :] - rest_px[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


class EvetacTracker:
    """Evetac's tracker: ``update(events)`` per window -> (positions_px (M, 2), moved (M,): active in a slice).

    ``observed`` (M,): False for missing markers, which are skipped (module docstring); None: all observed.
    """

    def __init__(self, rest_px: npt.ArrayLike, params: EvetacParams = EvetacParams(),
                 observed: npt.ArrayLike | None = None) -> None:
        self.params = params
        self.rest_px, self.observed = grid_markers(rest_px, observed, params.grid_rows, params.grid_cols)
        if not self.observed.any():
            raise ValueError("no observed marker to track")
        self._dots = np.flatnonzero(self.observed)  # the dots Evetac tracks, in marker order
        self._follow = grid_neighbours(params.grid_rows, params.grid_cols, 8)
        dots_rest = self.rest_px[self._dots]
        pitch = params.pitch_px if params.pitch_px is not None else grid_pitch_px(dots_rest)
        self.geometry = Geometry.for_rig(params.marker_diameter_px, pitch)
        self._neigh, self._rest_d2, self._correction = neighbour_links(dots_rest, self.geometry.neighbour_cutoff_px)
        self._cell = float(math.ceil(self.geometry.outer_px))
        shape = (int(params.height_px // self._cell) + 1, int(params.width_px // self._cell) + 1)
        self._cells = np.zeros((*shape, _CELL_CAPACITY), np.int32)
        self._counts = np.zeros(shape, np.int32)
        self.reset()

    def reset(self, positions_px: npt.ArrayLike | None = None) -> None:
        """Start again from the rest positions (or ``positions_px``), with an empty noise-filter history."""
        self.positions_px = self.rest_px.copy() if positions_px is None else np.array(positions_px, np.float64)
        self._surface = np.full((self.params.height_px, self.params.width_px), np.iinfo(np.int64).min // 2, np.int64)

    def update(self, events: npt.NDArray, t_end_us: float | None = None) -> tuple[Array, BoolArray]:
        """Advance by one window of events (EVENT_DTYPE, time order), slice by slice (by the events' own times:
        ``t_end_us`` is not used); copies of positions and moved mask."""
        p, geo = self.params, self.geometry
        moved = np.zeros(len(self._dots), np.bool_)
        if len(events) == 0:
            return self.positions_px.copy(), np.zeros(len(self.positions_px), np.bool_)
        x, y, t = events["x"], events["y"], np.ascontiguousarray(events["t"], np.int64)
        keep = np.ones(len(events), np.bool_)
        if p.ba_window_us is not None:
            background_activity(x, y, t, self._surface, np.int64(p.ba_window_us), keep)
        slice_index = t // p.slice_us
        bounds = np.flatnonzero(np.diff(slice_index)) + 1
        pos = self.positions_px[self._dots]
        pull, activity, springs = np.zeros_like(pos), np.zeros(len(pos), np.int64), np.zeros_like(pos)
        for lo, hi in zip(np.r_[0, bounds], np.r_[bounds, len(events)]):
            pull[...] = 0.0
            activity[...] = 0
            band_pulls(x[lo:hi], y[lo:hi], keep[lo:hi], pos, geo.inner_px, geo.outer_px, geo.pull_radius_px, self._cell,
                       self._cells, self._counts, pull, activity)
            active = activity >= p.activity_threshold
            move = STEP * np.clip(pull, -geo.clip, geo.clip)
            if p.springs:
                spring_pulls(pos, self._neigh, self._rest_d2, self._correction, active, geo.spring_gain, springs)
                move += STEP * springs
            pos = pos + np.where(active[:, None], move, 0.0)
            moved |= active
        out = self.positions_px.copy()
        out[self._dots] = pos
        moved_all = np.zeros(len(out), np.bool_)
        moved_all[self._dots] = moved
        if len(self._dots) < len(out):
            follow_neighbours(out, self.rest_px, self.observed, self._follow)
        self.positions_px = out
        return out.copy(), moved_all
