"""Event-based marker tracking: the paper's patch-centroid tracker and a circle-fit baseline.

:class:`Tracker` (the paper's, section III-A): per window, each marker's square
patch (``patch_scale`` x the marker diameter) around its last position, clipped
to its non-overlapping region (the midpoints to its four grid neighbours); the
centroid of the patch's events (of each polarity, averaged, so that a moving
bright dot's leading ON and trailing OFF crescents balance; where one polarity
outnumbers the other by more than ``polarity_guard``, only as many of it as the
other has count, the nearest the marker: the membrane's slope shading under a
pressing edge is one polarity, bands of it that would drag the dot); markers with fewer
than ``min_events`` events keep their position; then the grid-aware refinement
p = lambda * prior + (1 - lambda) * centroid, the prior being the mean of the
neighbours' positions each shifted by its rest offset to the marker.

Missing markers (never printed, found by the extrinsic calibration: ``observed`` False)
are skipped: they get no patch, no neighbour prior counts them, and their reported
position follows the mean displacement of their observed neighbours (never ``updated``),
so downstream stages see finite positions and know from the mask which are estimates.

Events reach markers through a label image (sensor pixel -> marker, -1 for
none) of the clipped patches, repainted only where a patch moved; a compiled
loop then sums each marker's events. Positions are sensor pixels (x, y), in
the rig's marker order (row-major from -y, -x of the gel frame).

:class:`CircleFitTracker` is a circle-fit baseline (formerly called "Evetac-style"; it
is not Evetac's published algorithm, which is :mod:`labrig.pipeline.evetac`): events on
an annulus around each dot pull its centre toward a circle fit of the dot's radius (the
mean gradient, a few iterations, each move clipped); normalised springs on the squared
distances to the (up to 8) neighbours hold the grid together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from numba import njit

from labrig.calibration.files import load_extrinsics, uncalibrated_camera
from labrig.config import RigConfig
from labrig.physics.camera import CameraModel

Array = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def rest_positions_px(rig: RigConfig, extrinsics_path: str | Path | None = None) -> Array:
    """Markers' rest positions (M, 2) px: measured by the extrinsic calibration (its file's marker map:
    the nominal projection only where a marker is missing), else the nominal lattice through the rig
    file's nominal camera (:func:`labrig.calibration.files.uncalibrated_camera`)."""
    if extrinsics_path is not None:
        return np.asarray(load_extrinsics(extrinsics_path).marker_map.rest_px, np.float64)
    camera, _ = uncalibrated_camera(rig)
    return camera.project(rig.markers.rest_positions_mm())


def marker_diameter_px(rig: RigConfig, camera: CameraModel | None = None) -> float:
    """The markers' mean image diameter (px) at rest through ``camera`` (None: the rig file's nominal camera)."""
    camera = camera or CameraModel.nominal(rig)
    jac = camera.jacobian_px_per_mm(rig.markers.rest_positions_mm())[:, :, :2]
    scale = np.sqrt(np.abs(np.linalg.det(jac)))  # px per mm, area-equivalent
    return float(rig.markers.diameter_mm * scale.mean())


def grid_markers(rest_px: npt.ArrayLike, observed: npt.ArrayLike | None, rows: int,
                 cols: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_]]:
    """A tracker's markers checked: rest positions (M, 2) px for a ``rows`` x ``cols`` grid and the
    observed mask (M,) (None: all observed)."""
    rest = np.array(rest_px, np.float64).reshape(-1, 2)
    if len(rest) != rows * cols:
        raise ValueError(f"{len(rest)} rest positions for a {rows}x{cols} grid")
    seen = np.ones(len(rest), bool) if observed is None else np.array(observed, bool).reshape(-1)
    if seen.shape != (len(rest),):
        raise ValueError(f"observed mask of {seen.size} for {len(rest)} markers")
    return rest, seen


def grid_neighbours(rows: int, cols: int, connectivity: int = 4) -> npt.NDArray[np.int64]:
    """(M, 4 or 8) neighbour indices in a row-major grid, -1 where there is none."""
    if connectivity not in (4, 8):
        raise ValueError("connectivity must be 4 or 8")
    steps = [(0, -1), (0, 1), (-1, 0), (1, 0)]
    if connectivity == 8:
        steps += [(-1, -1), (-1, 1), (1, -1), (1, 1)]
    r, c = np.divmod(np.arange(rows * cols), cols)
    out = np.full((rows * cols, len(steps)), -1, np.int64)
    for k, (dr, dc) in enumerate(steps):
        rr, cc = r + dr, c + dc
        ok = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
        out[ok, k] = rr[ok] * cols + cc[ok]
    return out


#: A flooded patch holds ON and OFF events alike, within this ratio: an edge translating across it makes both, a
#: pressing edge's slope shading one.
FLOOD_POLARITY_RATIO = 3.0


@dataclass(frozen=True)
class TrackerParams:
    """The paper's tracker: defaults as published (3x diameter patches, lambda = 0.2)."""

    marker_diameter_px: float = 14.0
    patch_scale: float = 3.0  # patch side / marker diameter
    refine_lambda: float = 0.2  # weight of the neighbour prior
    prior_connectivity: int = 4  # neighbours in the prior: 4 or 8
    min_events: int = 8  # fewer events in a patch: the marker is not updated
    min_each_polarity: int = 4  # ... nor with fewer ON or fewer OFF events than this (a moving dot makes both)
    polarity_balance: bool = True  # average the ON and OFF centroids when both are present
    gate_diameters: float | None = 1.0  # keep only events this close (in diameters) to the centre; None: whole patch
    gate_passes: int = 1  # re-centre the gate on the centroid and sum again (mean shift)
    noise_subtraction: bool = True  # with a gate: take the expected background events out of each gate's sums
    # A gate whose ON (or OFF) events outnumber the other polarity's by more than this keeps only as many of them
    # as the other has, the nearest its centre (a moving dot makes both alike; slope shading makes one); None: off
    polarity_guard: float | None = 2.0
    # A gate whose one polarity outnumbers the other more than this cannot place its dot: the dot makes the mean
    # move of its updated 4-neighbours instead; None: off
    lopsided_ratio: float | None = 10.0
    # A gate whose patch around it holds ON and OFF events alike (within FLOOD_POLARITY_RATIO) at least this densely
    # as the gate itself cannot place its dot either: a dot's own events lie in its gate, an edge translating across the patch (a
    # sliding flat punch's rim) makes both polarities everywhere (a pressing edge's shading makes one); None: off
    flood_ratio: float | None = 0.3
    # Report each dot at the window's end, not at its events' mean time: moved on by its velocity (its last two
    # centroids, averaged with its neighbours'), the step shrunk where the centroids moved less than this; None: off
    lag_noise_px: float | None = 1.0
    grid_rows: int = 12
    grid_cols: int = 13
    width_px: int = 1280
    height_px: int = 720


@njit(cache=True, nogil=True)
def _clipped_rects(pos, neigh4, half, width, height, rects):  # pragma: no cover - compiled
    """Integer pixel bounds [x0, x1) x [y0, y1) of each marker's patch clipped at the neighbour midpoints."""
    for i in range(pos.shape[0]):
        px, py = pos[i, 0], pos[i, 1]
        xmin, xmax, ymin, ymax = px - half, px + half, py - half, py + half
        for k in range(neigh4.shape[1]):
            j = neigh4[i, k]
            if j < 0:
                continue
            dx, dy = pos[j, 0] - px, pos[j, 1] - py
            if abs(dx) >= abs(dy):
                mid = px + 0.5 * dx
                if dx > 0:
                    xmax = min(xmax, mid)
                else:
                    xmin = max(xmin, mid)
            else:
                mid = py + 0.5 * dy
                if dy > 0:
                    ymax = min(ymax, mid)
                else:
                    ymin = max(ymin, mid)
        rects[i, 0] = min(max(int(np.ceil(xmin)), 0), width)
        rects[i, 1] = min(max(int(np.ceil(xmax)), 0), width)
        rects[i, 2] = min(max(int(np.ceil(ymin)), 0), height)
        rects[i, 3] = min(max(int(np.ceil(ymax)), 0), height)


@njit(cache=True, nogil=True)
def _repaint(label, old, new):  # pragma: no cover - compiled
    """Move each changed patch in the label image: clear its old pixels, then paint all changed ones."""
    m = old.shape[0]
    changed = np.zeros(m, np.bool_)
    for i in range(m):
        for k in range(4):
            if old[i, k] != new[i, k]:
                changed[i] = True
        if changed[i]:
            for y in range(old[i, 2], old[i, 3]):
                for x in range(old[i, 0], old[i, 1]):
                    if label[y, x] == i:
                        label[y, x] = -1
    for i in range(m):
        if changed[i]:
            for y in range(new[i, 2], new[i, 3]):
                for x in range(new[i, 0], new[i, 1]):
                    label[y, x] = i
            for k in range(4):
                old[i, k] = new[i, k]


@njit(cache=True, nogil=True)
def _sum_events(x, y, p, label, centre, gate2, sums, outside, owner):  # pragma: no cover - compiled
    """sums[m, polarity] += (count, sum x, sum y) over the events in marker m's patch (and gate, if gate2 > 0);
    outside[m, polarity] += 1 for the patch's events outside the gate; owner[i]: the marker whose sums took
    event i, else -1."""
    h, w = label.shape
    for i in range(x.shape[0]):
        owner[i] = -1
        xi, yi = int(x[i]), int(y[i])
        if xi >= w or yi >= h:
            continue
        m = label[yi, xi]
        if m >= 0:
            ch = 1 if p[i] else 0
            if gate2 > 0.0:
                dx, dy = xi - centre[m, 0], yi - centre[m, 1]
                if dx * dx + dy * dy > gate2:
                    outside[m, ch] += 1.0
                    continue
            sums[m, ch, 0] += 1.0
            sums[m, ch, 1] += xi
            sums[m, ch, 2] += yi
            owner[i] = m


@njit(cache=True, nogil=True)
def _guard_polarity(x, y, p, owner, centre, sums, ratio):  # pragma: no cover - compiled
    """In place: where one polarity's count in a marker's gate exceeds ``ratio`` x the other's (both present),
    its sums become those of its events nearest the gate's centre, as many as the other polarity has.
    ``owner``: each event's marker from :func:`_sum_events` (-1: none)."""
    m_count = sums.shape[0]
    trim = np.full(m_count, -1, np.int64)  # the polarity to trim, -1: none
    keep = np.zeros(m_count, np.int64)
    for m in range(m_count):
        n_off, n_on = sums[m, 0, 0], sums[m, 1, 0]
        if n_off >= 1.0 and n_on >= 1.0:
            if n_on > ratio * n_off:
                trim[m], keep[m] = 1, int(n_off)
            elif n_off > ratio * n_on:
                trim[m], keep[m] = 0, int(n_on)
    start = np.zeros(m_count + 1, np.int64)
    for m in range(m_count):
        start[m + 1] = start[m] + (int(sums[m, trim[m], 0]) if trim[m] >= 0 else 0)
    if start[m_count] == 0:
        return
    d2 = np.empty(start[m_count])
    ex = np.empty(start[m_count])
    ey = np.empty(start[m_count])
    fill = start[:-1].copy()
    for i in range(x.shape[0]):
        m = owner[i]
        if m < 0 or trim[m] < 0 or (1 if p[i] else 0) != trim[m] or fill[m] >= start[m + 1]:
            continue
        xi, yi = float(x[i]), float(y[i])
        dx, dy = xi - centre[m, 0], yi - centre[m, 1]
        k = fill[m]
        d2[k], ex[k], ey[k] = dx * dx + dy * dy, xi, yi
        fill[m] = k + 1
    for m in range(m_count):
        if trim[m] < 0:
            continue
        a, b = start[m], fill[m]
        nearest = np.argsort(d2[a:b])[: keep[m]]
        sx, sy = 0.0, 0.0
        for j in nearest:
            sx += ex[a + j]
            sy += ey[a + j]
        sums[m, trim[m], 0], sums[m, trim[m], 1], sums[m, trim[m], 2] = len(nearest), sx, sy


@njit(cache=True, nogil=True)
def _mean_times(owner, t, t_ref, count, mean):  # pragma: no cover - compiled
    """count[m], mean[m]: how many events marker m's sums took (``owner``) and their mean time - t_ref (0 if none)."""
    count[:] = 0.0
    mean[:] = 0.0
    for i in range(owner.shape[0]):
        m = owner[i]
        if m >= 0:
            count[m] += 1.0
            mean[m] += float(t[i] - t_ref)
    for m in range(count.shape[0]):
        if count[m] > 0.0:
            mean[m] /= count[m]


@njit(cache=True, nogil=True)
def _lag_steps(centroid, last_px, last_t, t_mean, count, updated, neigh, t_end, noise_px, limit_px, out):  # pragma: no cover
    """out[m] = centroid[m] + the step to ``t_end`` (see :meth:`Tracker._at_window_end`)."""
    m_count = centroid.shape[0]
    velocity = np.zeros((m_count, 2))
    dt = np.zeros(m_count)
    moving = np.zeros(m_count, np.bool_)
    for m in range(m_count):
        d = t_mean[m] - last_t[m]
        if updated[m] and count[m] > 0.0 and d > 0.0:  # NaN (no previous centroid) compares False
            moving[m], dt[m] = True, d
            velocity[m, 0] = (centroid[m, 0] - last_px[m, 0]) / d
            velocity[m, 1] = (centroid[m, 1] - last_px[m, 1]) / d
    for m in range(m_count):
        out[m, 0], out[m, 1] = centroid[m, 0], centroid[m, 1]
        if not moving[m]:
            continue
        vx, vy, n = velocity[m, 0], velocity[m, 1], 1.0
        for k in range(neigh.shape[1]):
            j = neigh[m, k]
            if j >= 0 and moving[j]:
                vx += velocity[j, 0]
                vy += velocity[j, 1]
                n += 1.0
        vx, vy = vx / n, vy / n
        moved = np.sqrt(vx * vx + vy * vy) * dt[m]
        if moved <= noise_px:
            continue
        keep = 1.0 - (noise_px / moved) ** 2
        lead = t_end - t_mean[m]
        sx, sy = keep * vx * lead, keep * vy * lead
        size = np.sqrt(sx * sx + sy * sy)
        if size > limit_px:
            sx, sy = sx * limit_px / size, sy * limit_px / size
        out[m, 0] += sx
        out[m, 1] += sy


@njit(cache=True, nogil=True)
def _centroids_and_prior(pos, sums, neigh, rest, min_events, min_each, balance, lam, out, updated):  # pragma: no cover
    m = pos.shape[0]
    centroid = pos.copy()
    for i in range(m):
        n_off, n_on = sums[i, 0, 0], sums[i, 1, 0]
        if n_off <= 0.0 and n_on <= 0.0:
            updated[i] = False
            continue
        updated[i] = n_off + n_on >= min_events and n_off >= min_each and n_on >= min_each
        if not updated[i]:
            continue
        if balance and n_off >= 1 and n_on >= 1:
            centroid[i, 0] = 0.5 * (sums[i, 0, 1] / n_off + sums[i, 1, 1] / n_on)
            centroid[i, 1] = 0.5 * (sums[i, 0, 2] / n_off + sums[i, 1, 2] / n_on)
        else:
            centroid[i, 0] = (sums[i, 0, 1] + sums[i, 1, 1]) / (n_off + n_on)
            centroid[i, 1] = (sums[i, 0, 2] + sums[i, 1, 2]) / (n_off + n_on)
    for i in range(m):
        out[i, 0], out[i, 1] = centroid[i, 0], centroid[i, 1]
        if not updated[i] or lam == 0.0:
            continue
        sx, sy, n = 0.0, 0.0, 0
        for k in range(neigh.shape[1]):
            j = neigh[i, k]
            if j >= 0:
                sx += centroid[j, 0] + rest[i, 0] - rest[j, 0]
                sy += centroid[j, 1] + rest[i, 1] - rest[j, 1]
                n += 1
        if n:
            out[i, 0] = lam * sx / n + (1.0 - lam) * centroid[i, 0]
            out[i, 1] = lam * sy / n + (1.0 - lam) * centroid[i, 1]


#: Standard deviations of the expected noise a gate's events must exceed (per polarity).
NOISE_SIGMAS = 3.0


def subtract_background(sums: npt.NDArray[np.float64], outside: npt.NDArray[np.float64],
                        patches: npt.NDArray[np.int64], gate2_px2: float, centre_px: Array) -> None:
    """Take the expected background (noise) events out of each gate's sums, in place.

    Noise events are spread evenly, so inside a gate of area ``pi gate2`` they are expected
    ``rho pi gate2`` times per polarity, centred on the gate's centre: left in, they pull a
    moving marker's centroid back to its last position, and at 1-2 Hz per pixel (6-12 events
    a gate per 10 ms) they alone pass the event minimums and the track random-walks. ``rho``
    (events / px per polarity) is the median over markers of the events in each patch outside
    its gate over that area: a moving marker's own events outside its gate move few markers.
    A polarity whose excess over the expected noise is under three of the noise's standard
    deviations is dropped (that marker is not updated): at 5-10 Hz per pixel the excess of a
    slow marker is itself noise, and a centroid of noise minus its mean random-walks.
    """
    _subtract_background(sums, outside, patches, float(gate2_px2), np.ascontiguousarray(centre_px, np.float64),
                         NOISE_SIGMAS)


@njit(cache=True, nogil=True)
def _subtract_background(sums, outside, patches, gate2_px2, centre_px, sigmas):  # type: ignore[no-untyped-def]
    """:func:`subtract_background`, compiled (every window, every marker)."""
    m = patches.shape[0]
    ring = np.empty(m)
    usable = np.zeros(m, np.bool_)
    n_usable = 0
    for i in range(m):
        side = (patches[i, 1] - patches[i, 0]) * (patches[i, 3] - patches[i, 2])
        ring[i] = side - np.pi * gate2_px2
        usable[i] = ring[i] > 0.25 * max(side, 1)
        n_usable += usable[i]
    if n_usable == 0:
        return
    density = np.empty(n_usable)
    for pol in range(2):
        k = 0
        for i in range(m):
            if usable[i]:
                density[k] = outside[i, pol] / ring[i]
                k += 1
        expected = np.median(density) * np.pi * gate2_px2
        floor = sigmas * np.sqrt(expected)
        for i in range(m):
            sums[i, pol, 0] -= expected
            sums[i, pol, 1] -= expected * centre_px[i, 0]
            sums[i, pol, 2] -= expected * centre_px[i, 1]
            if sums[i, pol, 0] < floor:
                sums[i, pol, 0] = 0.0
                sums[i, pol, 1] = 0.0
                sums[i, pol, 2] = 0.0


def drop_unobserved(neighbours: npt.NDArray[np.int64], observed: BoolArray) -> npt.NDArray[np.int64]:
    """``neighbours`` (M, K) with every unobserved marker's row and every entry naming one set to -1."""
    out = np.where((neighbours >= 0) & observed[np.maximum(neighbours, 0)], neighbours, -1)
    out[~observed] = -1
    return out


def follow_neighbours(positions_px: Array, rest_px: Array, observed: BoolArray, neighbours: npt.NDArray[np.int64]) -> None:
    """In place: each unobserved marker at its rest plus the mean displacement of its observed
    ``neighbours`` (M, K; -1 for none); at rest when none is observed."""
    for i in np.flatnonzero(~observed):
        j = neighbours[i][neighbours[i] >= 0]
        j = j[observed[j]]
        shift = (positions_px[j] - rest_px[j]).mean(axis=0) if j.size else np.zeros(2)
        positions_px[i] = rest_px[i] + shift


class _PatchTracker:
    """What both trackers share: rest positions on the marker grid, and each marker's square patch
    (half side ``_half`` px) clipped at the midpoints to its neighbours, painted into a label image;
    unobserved (missing) markers get no patch and follow their observed neighbours."""

    _half: float

    def __init__(self, rest_px: npt.ArrayLike, params: TrackerParams | CircleFitParams,
                 observed: npt.ArrayLike | None = None) -> None:
        self.params = params
        self.rest_px, self.observed = grid_markers(rest_px, observed, params.grid_rows, params.grid_cols)
        self._neigh4 = grid_neighbours(params.grid_rows, params.grid_cols, 4)
        self._follow = grid_neighbours(params.grid_rows, params.grid_cols, 8)

    def reset(self, positions_px: npt.ArrayLike | None = None) -> None:
        """Start again from the rest positions (or from ``positions_px``)."""
        p = self.params
        self.positions_px = self.rest_px.copy() if positions_px is None else np.array(positions_px, np.float64)
        self._label = np.full((p.height_px, p.width_px), -1, np.int16)
        self._painted = np.zeros((len(self.rest_px), 4), np.int64)
        self._rects = np.zeros_like(self._painted)
        self._sync_patches()

    def _sync_patches(self) -> None:
        p = self.params
        _clipped_rects(self.positions_px, self._neigh4, self._half, p.width_px, p.height_px, self._rects)
        self._rects[~self.observed] = 0  # no patch: a missing marker's events are nobody's
        _repaint(self._label, self._painted, self._rects)


class Tracker(_PatchTracker):
    """The paper's marker tracker. ``update(events)`` per window -> (positions_px (M, 2), updated (M,))."""

    params: TrackerParams

    def __init__(self, rest_px: npt.ArrayLike, params: TrackerParams = TrackerParams(),
                 observed: npt.ArrayLike | None = None) -> None:
        super().__init__(rest_px, params, observed)
        self._prior = drop_unobserved(grid_neighbours(params.grid_rows, params.grid_cols, params.prior_connectivity),
                                      self.observed)
        self._half = params.patch_scale * params.marker_diameter_px / 2
        self._sums = np.zeros((len(self.rest_px), 2, 3))
        self._outside = np.zeros((len(self.rest_px), 2))
        self.reset()

    def reset(self, positions_px: npt.ArrayLike | None = None) -> None:
        super().reset(positions_px)
        self._centroid_px = self.positions_px.copy()  # (M, 2) each dot's last centroid, before the lag correction
        self._centroid_t_us = np.full(len(self.positions_px), np.nan)  # (M,) when it was there (its events' mean)

    def _at_window_end(self, centroid: Array, updated: BoolArray, events: npt.NDArray,
                       owner: npt.NDArray[np.int32], t_end_us: float, noise_px: float) -> Array:
        """The centroids (M, 2) px moved on from their events' mean times to ``t_end_us`` by each dot's velocity.

        A moving dot's centroid is where it was at its events' mean time, about half a window before
        the window's end (at 1.5 mm/s and 20,000-event windows, 1-2 px behind). The velocity: from the
        dot's centroids and their times in this window and the one before, where both updated it,
        averaged over the dot and its such 4-neighbours (the gel moves smoothly; the average cuts
        the centroids' noise). The step is shrunk by max(0, 1 - (noise_px / moved)^2), ``moved`` the
        averaged centroid step, so still dots stay still, and is at most a dot's radius.
        """
        m = len(centroid)
        count, t_mean = np.empty(m), np.empty(m)
        t_ref = int(t_end_us)
        _mean_times(owner, events["t"], t_ref, count, t_mean)
        t_mean += t_ref  # us
        reported = np.empty_like(centroid)
        _lag_steps(centroid, self._centroid_px, self._centroid_t_us, t_mean, count, updated, self._neigh4,
                   float(t_end_us), float(noise_px), 0.5 * self.params.marker_diameter_px, reported)
        self._centroid_px = np.where(updated[:, None], centroid, self.positions_px)
        self._centroid_t_us = np.where(updated & (count > 0), t_mean, np.nan)  # no update: no velocity next time
        return reported

    def _lopsided(self, counts: Array) -> BoolArray:
        """The dots whose gates are lopsided (``counts`` (M, 2) OFF / ON events before the polarity guard: one
        polarity more than ``lopsided_ratio`` x the other). A moving dot makes ON and OFF events alike; a gate flooded
        with one polarity is seeing the membrane's slope shading (a flat punch's or a ridge's edge passing), whose
        trimmed remainder still drags the dot."""
        ratio = self.params.lopsided_ratio
        if ratio is None:
            return np.zeros(len(counts), np.bool_)
        n_off, n_on = counts[:, 0], counts[:, 1]
        return ((np.maximum(n_on, n_off) > ratio * np.maximum(np.minimum(n_on, n_off), 1.0))
                & (n_off + n_on >= self.params.min_events) & self.observed)

    def _flooded(self, counts: Array, gate2: float) -> BoolArray:
        """The dots whose patches, outside their gates, hold ON and OFF events alike (within FLOOD_POLARITY_RATIO)
        at least ``flood_ratio`` x as densely as the gates (``counts`` (M, 2): the gates' events). A dot's own events lie in
        its gate (outside it a moving dot's patch sees the sensor's noise, a hundredth of the gate's density); an
        edge translating across the patch (a sliding flat punch's rim) makes both polarities everywhere, which
        neither the guard nor the lopsided test sees, and the gate follows the edge. A pressing edge's shading makes
        one polarity: not this."""
        ratio = self.params.flood_ratio
        if ratio is None or not gate2:
            return np.zeros(len(counts), np.bool_)
        gate_px2 = math.pi * gate2
        rects = self._painted
        outside_px2 = np.maximum((rects[:, 1] - rects[:, 0]) * (rects[:, 3] - rects[:, 2]) - gate_px2, 1.0)
        off, on = self._outside[:, 0], self._outside[:, 1]
        balanced = np.minimum(off, on) * FLOOD_POLARITY_RATIO >= np.maximum(off, on)
        inside = counts.sum(axis=1)
        return (balanced & ((off + on) / outside_px2 >= ratio * inside / gate_px2)
                & (inside >= self.params.min_events) & self.observed)

    def _follow_neighbours_moves(self, out: Array, updated: BoolArray, blind: BoolArray) -> None:
        """In place: the dots whose gates cannot place them (``blind``: :meth:`_lopsided`, :meth:`_flooded`) make
        this window's mean move of their 4-neighbours that updated (at least two; else they stay), and are not
        updated. Without its own say, the gel's smooth motion is the best guess; following the neighbours' moves,
        not their displacement, keeps the dot's own history (a dot under a slipping contact has moved differently
        from its neighbours)."""
        good = updated & ~blind
        step = out - self.positions_px  # this window's moves
        acc = np.zeros_like(out)
        n = np.zeros(len(out))
        for k in range(self._neigh4.shape[1]):
            j = self._neigh4[:, k]
            ok = (j >= 0) & good[np.maximum(j, 0)]
            acc[ok] += step[j[ok]]
            n[ok] += 1
        move = blind & (n >= 2)
        out[move] = self.positions_px[move] + acc[move] / n[move, None]
        stay = blind & ~move
        out[stay] = self.positions_px[stay]
        updated[blind] = False

    @property
    def patches_px(self) -> npt.NDArray[np.int64]:
        """(M, 4) current patches as pixel bounds x0, x1, y0, y1 (x1, y1 exclusive)."""
        return self._painted.copy()

    def update(self, events: npt.NDArray, t_end_us: float | None = None) -> tuple[Array, BoolArray]:
        """Advance by one window of events (EVENT_DTYPE) ending at ``t_end_us`` (default: its last event's time);
        returns copies of the positions (at the window's end) and the update mask."""
        p = self.params
        owner = np.empty(len(events), np.int32)
        out = np.empty_like(self.positions_px)
        updated = np.zeros(len(out), np.bool_)
        gate2 = 0.0 if p.gate_diameters is None else (p.gate_diameters * p.marker_diameter_px) ** 2
        centre = self.positions_px
        for k in range(p.gate_passes if gate2 else 1):
            self._sums[...] = 0.0
            self._outside[...] = 0.0
            if len(events):
                _sum_events(events["x"], events["y"], events["p"], self._label, centre, gate2, self._sums, self._outside,
                            owner)
                polarity_counts = self._sums[:, :, 0].copy()  # before the guard trims
                if p.polarity_guard is not None:
                    _guard_polarity(events["x"], events["y"], events["p"], owner, centre, self._sums,
                                    float(p.polarity_guard))
            if gate2 and p.noise_subtraction:
                subtract_background(self._sums, self._outside, self._painted, gate2, centre)
            lam = float(p.refine_lambda) if k == (p.gate_passes if gate2 else 1) - 1 else 0.0
            _centroids_and_prior(centre, self._sums, self._prior, self.rest_px, float(p.min_events),
                                 float(p.min_each_polarity), p.polarity_balance, lam, out, updated)
            centre = out.copy()
        if len(events):
            blind = self._lopsided(polarity_counts) | self._flooded(polarity_counts, gate2)
            if blind.any():
                self._follow_neighbours_moves(out, updated, blind)
        reported = out  # the tracker keeps its centroids (a dot that stops is where its events put it)
        if p.lag_noise_px is not None:
            end = float(events["t"][-1]) if t_end_us is None and len(events) else t_end_us
            if end is not None:
                reported = self._at_window_end(out, updated, events, owner, float(end), float(p.lag_noise_px))
        if not self.observed.all():
            follow_neighbours(out, self.rest_px, self.observed, self._follow)
            if reported is not out:
                follow_neighbours(reported, self.rest_px, self.observed, self._follow)
            updated &= self.observed
        self.positions_px = out
        self._sync_patches()
        return reported.copy(), updated


# -- circle-fit baseline -------------------------------------------------------------------------------


@dataclass(frozen=True)
class CircleFitParams:
    """Circle-fit + normalised neighbour-spring tracker; radii in marker radii."""

    marker_diameter_px: float = 14.0
    fit_radius: float = 1.0  # events are pulled onto a circle of this many marker radii
    inner_radius: float = 0.3  # annulus of events used, in marker radii
    outer_radius: float = 2.0
    step: float = 1.0  # fraction of the mean circle-fit gradient applied per iteration
    max_step_px: float = 2.0  # clip of one iteration's move
    iterations: int = 3
    min_events: int = 10
    spring: float = 0.1  # neighbour-spring gain (per iteration)
    spring_connectivity: int = 8
    grid_rows: int = 12
    grid_cols: int = 13
    width_px: int = 1280
    height_px: int = 720


@njit(cache=True, nogil=True)
def _circle_gradients(x, y, label, pos, r_in2, r_out2, r_fit, sums):  # pragma: no cover - compiled
    h, w = label.shape
    for i in range(x.shape[0]):
        xi, yi = int(x[i]), int(y[i])
        if xi >= w or yi >= h:
            continue
        m = label[yi, xi]
        if m < 0:
            continue
        dx, dy = xi - pos[m, 0], yi - pos[m, 1]
        d2 = dx * dx + dy * dy
        if d2 < r_in2 or d2 > r_out2:
            continue
        d = np.sqrt(d2)
        g = (d - r_fit) / d
        sums[m, 0] += 1.0
        sums[m, 1] += g * dx
        sums[m, 2] += g * dy


@njit(cache=True, nogil=True)
def _springs(pos, neigh, rest_d2, gain):  # pragma: no cover - compiled
    """One gradient step on sum_j (|p_i - p_j|^2 - d0^2)^2 / d0^4, normalised per marker."""
    m = pos.shape[0]
    move = np.zeros((m, 2))
    for i in range(m):
        n = 0
        for k in range(neigh.shape[1]):
            j = neigh[i, k]
            if j < 0:
                continue
            dx, dy = pos[i, 0] - pos[j, 0], pos[i, 1] - pos[j, 1]
            e = (dx * dx + dy * dy - rest_d2[i, k]) / rest_d2[i, k]
            move[i, 0] -= e * dx
            move[i, 1] -= e * dy
            n += 1
        if n:
            move[i, 0] *= gain / n
            move[i, 1] *= gain / n
    for i in range(m):
        pos[i, 0] += move[i, 0]
        pos[i, 1] += move[i, 1]


class CircleFitTracker(_PatchTracker):
    """The circle-fit baseline: ``update(events)`` -> (positions_px (M, 2), updated (M,))."""

    params: CircleFitParams

    def __init__(self, rest_px: npt.ArrayLike, params: CircleFitParams = CircleFitParams(),
                 observed: npt.ArrayLike | None = None) -> None:
        super().__init__(rest_px, params, observed)
        self._neigh = drop_unobserved(grid_neighbours(params.grid_rows, params.grid_cols, params.spring_connectivity),
                                      self.observed)
        diff = self.rest_px[:, None, :] - self.rest_px[np.maximum(self._neigh, 0)]
        self._rest_d2 = np.where(self._neigh >= 0, (diff**2).sum(-1), 1.0)
        r = params.marker_diameter_px / 2
        self._half = params.outer_radius * r
        self._sums = np.zeros((len(self.rest_px), 3))
        self.reset()

    def update(self, events: npt.NDArray, t_end_us: float | None = None) -> tuple[Array, BoolArray]:
        """Advance by one window of events (EVENT_DTYPE); ``t_end_us`` is not used (a circle fit has no
        time in it). Copies of the positions and the update mask."""
        p = self.params
        r = p.marker_diameter_px / 2
        pos = self.positions_px.copy()
        updated = np.zeros(len(pos), np.bool_)
        for _ in range(p.iterations):
            self._sums[...] = 0.0
            if len(events):
                _circle_gradients(events["x"], events["y"], self._label, pos, (p.inner_radius * r) ** 2,
                                  (p.outer_radius * r) ** 2, p.fit_radius * r, self._sums)
            ok = self._sums[:, 0] >= p.min_events
            step = p.step * self._sums[ok, 1:] / self._sums[ok, :1]
            norm = np.linalg.norm(step, axis=1, keepdims=True)
            step *= np.minimum(1.0, p.max_step_px / np.maximum(norm, 1e-12))
            pos[ok] += step
            updated |= ok
            if p.spring:
                _springs(pos, self._neigh, self._rest_d2, p.spring)
        if not self.observed.all():
            follow_neighbours(pos, self.rest_px, self.observed, self._follow)
            updated &= self.observed
        self.positions_px = pos
        self._sync_patches()
        return pos.copy(), updated
