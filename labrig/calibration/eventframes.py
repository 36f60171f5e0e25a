"""Events to frames without a neural network: blink periods, per-pixel counts, sub-pixel blobs.

Blink periods
-------------
A blink (target dots or LED ring switching) makes a burst of events of one
polarity: ON when the light comes on, OFF when it goes off. The recording is
scanned once in slices (bounded memory) into per-bin ON and OFF counts
(``bin_us``, 1 ms by default). Bins count as *active* above a tenth of the
95th percentile of the bin counts (the background, shot noise and leak, is
orders of magnitude lower), and as ON or OFF when one polarity holds at least
75 % of their events. Runs of active bins with one polarity are switches
(mixed bins join the run they touch); consecutive opposite switches pair into
one blink; bursts under 500 events are noise. Nothing depends on the scene's timing.

Frames
------
A blink's frame is, per pixel, the ON events of its ON switch plus the OFF
events of its OFF switch (both polarities see the same log-intensity step,
through independent thresholds, so the sum halves the threshold mismatch).
Noise filtering is by counts: a lit pixel fires many times per switch, while
shot noise and leak add isolated single events, and the per-pixel threshold
spread makes counts of equally lit pixels differ; the blob mask is a
two-level (Otsu) threshold of the counts smoothed by a Gaussian (sigma
1.5 px) less their local background (a white top-hat with a 61 px square,
wider than any blob: a lit membrane or the ROI's edge is not a blob), opened
with a 3x3 kernel, so isolated noisy pixels never make blobs.

Blobs
-----
Counts are turned into a coverage estimate ``clip((n - background) / (lit -
background), 0, 1)`` (background: the median count in a ring around the
blob, so a lit membrane around a marker is removed; lit: the median count of
all blob interiors). Each blob's centre is the
coverage-weighted centroid inside a disc of the blob's half-extent plus
1.25 px, re-centred three times. Clipping at 0 and 1 removes most of the
per-pixel threshold mismatch inside and around the blob; the disc keeps far
pixels (pure noise) out. A symmetric blob (a dot's image is a symmetric
ellipse) keeps its centroid under any such monotonic weighting.

LED-blink frames and discs
--------------------------
The LED scene (extrinsics) lights the whole membrane, so counts are not
noise against darkness but marker against membrane, both lit, and at high
threshold spread a membrane pixel with a low threshold fires as often as a
marker. :func:`harmonic_frame` combines the two polarities (the harmonic mean
of D / C_on and D / C_off is D over the mean threshold); :func:`find_discs`
is a disc-minus-ring matched filter over the lit pixels, at the scale that
responds most; :func:`fit_discs` fits a disc with an erfc edge per marker
(robust least squares). Threshold mismatch is fixed per pixel, so more blinks
of the same scene add no information about it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
import numpy.typing as npt

from labrig.recording import Recording

#: Events read per slice while scanning a recording.
SCAN_SLICE_US = 200_000


@dataclass(frozen=True)
class Switch:
    """One switch of the light: polarity (1 ON, 0 OFF) and its host-time window [t0, t1) us."""

    polarity: int
    t0_us: int
    t1_us: int
    events: int


@dataclass(frozen=True)
class Blink:
    """An ON switch and the OFF switch next to it (either order)."""

    on: Switch
    off: Switch

    @property
    def t0_us(self) -> int:
        return min(self.on.t0_us, self.off.t0_us)

    @property
    def t1_us(self) -> int:
        return max(self.on.t1_us, self.off.t1_us)


@dataclass(frozen=True)
class Blobs:
    """Sub-pixel blob centres (N, 2) px, their areas (px) and half-extents (px); optionally a strength each
    (the matched-filter response over its noise, :func:`find_discs`)."""

    xy: npt.NDArray[np.float64]
    area_px: npt.NDArray[np.float64]
    radius_px: npt.NDArray[np.float64]
    strength: npt.NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.xy)


Counts = npt.NDArray[np.int64]


def polarity_counts(rec: Recording, bin_us: int = 1000) -> tuple[Counts, Counts, Counts]:
    """(bin start host us, ON counts, OFF counts) over the whole recording, read slice by slice."""
    t_bins, _ = rec.event_counts(bin_ms=bin_us / 1000)
    if t_bins.size == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty, empty
    start = int(np.floor(t_bins[0] / bin_us)) * bin_us
    stop = int(rec.end_us()) + bin_us
    n_bins = (stop - start) // bin_us + 1
    on = np.zeros(n_bins, np.int64)
    off = np.zeros(n_bins, np.int64)
    for t0 in range(start, stop, SCAN_SLICE_US):
        ev = rec.events_between(t0, t0 + SCAN_SLICE_US)
        if len(ev) == 0:
            continue
        k = (ev["t"] - start) // bin_us
        k = np.clip(k, 0, n_bins - 1)
        on += np.bincount(k[ev["p"] == 1], minlength=n_bins)
        off += np.bincount(k[ev["p"] == 0], minlength=n_bins)
    return start + np.arange(n_bins, dtype=np.int64) * bin_us, on, off


def find_switches(rec: Recording, bin_us: int = 1000, min_events: int = 500) -> list[Switch]:
    """The light switches in a recording, from its event-rate bursts and their polarity.

    A switch lights many pixels at once; bursts of fewer than ``min_events`` events are noise."""
    t, on, off = polarity_counts(rec, bin_us)
    total = on + off
    if total.size == 0 or total.max() == 0:
        return []
    active = total > 0.1 * np.percentile(total, 95)
    frac_on = on / np.maximum(total, 1)
    label = np.where(frac_on >= 0.75, 1, np.where(frac_on <= 0.25, 0, -1))
    switches: list[Switch] = []
    current: list[int] = []  # [polarity, first bin, last bin]
    active_bins: list[int] = np.flatnonzero(active).tolist()
    for k in active_bins:
        pol = int(label[k])
        if current and k == current[2] + 1 and pol in (-1, current[0]):
            current[2] = k
            continue
        if current and k == current[2] + 1 and current[0] == -1 and pol >= 0:
            current[0], current[2] = pol, k
            continue
        if current and current[0] >= 0:
            switches.append(_switch(current, t, total, bin_us))
        current = [pol, k, k]
    if current and current[0] >= 0:
        switches.append(_switch(current, t, total, bin_us))
    return [s for s in switches if s.events >= min_events]


def _switch(run: list[int], t: npt.NDArray[np.int64], total: npt.NDArray[np.int64], bin_us: int) -> Switch:
    pol, k0, k1 = run
    return Switch(pol, int(t[k0]), int(t[k1]) + bin_us, int(total[k0 : k1 + 1].sum()))


def pair_blinks(switches: list[Switch]) -> list[Blink]:
    """Consecutive opposite switches as blinks (greedy, in time order)."""
    blinks: list[Blink] = []
    k = 0
    while k + 1 < len(switches):
        a, b = switches[k], switches[k + 1]
        if a.polarity != b.polarity:
            blinks.append(Blink(on=a if a.polarity == 1 else b, off=b if a.polarity == 1 else a))
            k += 2
        else:
            k += 1
    return blinks


def find_blinks(rec: Recording, bin_us: int = 1000) -> list[Blink]:
    """Blinks in a recording (see the module docstring)."""
    return pair_blinks(find_switches(rec, bin_us))


def accumulate(rec: Recording, blink: Blink, width: int, height: int) -> npt.NDArray[np.float64]:
    """Per-pixel count of a blink's ON events (ON switch) plus OFF events (OFF switch), (height, width)."""
    counts = np.zeros(width * height, np.float64)
    for switch in (blink.on, blink.off):
        ev = rec.events_between(switch.t0_us, switch.t1_us)
        ev = ev[ev["p"] == switch.polarity]
        inside = (ev["x"] < width) & (ev["y"] < height)
        flat = ev["y"][inside].astype(np.int64) * width + ev["x"][inside]
        counts += np.bincount(flat, minlength=width * height)
    return counts.reshape(height, width)


def otsu_threshold(values: npt.NDArray[np.floating]) -> float:
    """Otsu's two-class threshold of non-negative values (on a 256-level histogram)."""
    values = values[np.isfinite(values)]
    if values.size == 0:
        return 0.0
    top = float(values.max())
    if top <= 0:
        return 0.0
    hist, edges = np.histogram(values, bins=256, range=(0.0, top))
    centres = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    mean0 = m0 / np.maximum(w0, 1)
    mean1 = (m0[-1] - m0) / np.maximum(w1, 1)
    between = w0 * w1 * (mean0 - mean1) ** 2
    return float(edges[int(np.argmax(between)) + 1])


def detect_blobs(
    frame: npt.NDArray[np.float64],
    *,
    min_area_px: int = 12,
    max_area_px: int = 20_000,
    border_px: int = 2,
    background_px: int = 61,
) -> Blobs:
    """Bright blobs of a count frame, with sub-pixel centres (module docstring)."""
    frame = np.asarray(frame, dtype=np.float64)
    counts = frame[frame > 0]
    if counts.size == 0:
        return Blobs(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    smooth = cv2.GaussianBlur(frame.astype(np.float32), (0, 0), 1.5)
    kernel_bg = cv2.getStructuringElement(cv2.MORPH_RECT, (background_px, background_px))
    smooth = smooth - cv2.morphologyEx(smooth, cv2.MORPH_OPEN, kernel_bg)  # white top-hat: blobs above their surround
    threshold = otsu_threshold(smooth[smooth > 0])
    mask = (smooth > threshold).astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    mask = cast(npt.NDArray[np.uint8], cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel))
    n, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    interior = cv2.erode(mask, kernel) > 0
    lit = float(np.median(frame[interior])) if interior.any() else float(frame.max())
    height, width = frame.shape
    xy, areas, radii = [], [], []
    for k in range(1, n):
        x, y, w, h, area = (int(v) for v in stats[k])
        if area < min_area_px or area > max_area_px:
            continue
        if x < border_px or y < border_px or x + w > width - border_px or y + h > height - border_px:
            continue
        radius = 0.5 * max(w, h)
        centre = _refine_centroid(frame, lit, x, y, w, h, radius)
        if centre is None:
            continue
        xy.append(centre)
        areas.append(float(area))
        radii.append(radius)
    return Blobs(np.array(xy, dtype=np.float64).reshape(-1, 2), np.array(areas), np.array(radii))


def _refine_centroid(
    frame: npt.NDArray[np.float64], lit: float, x: int, y: int, w: int, h: int, radius: float, iterations: int = 3
) -> npt.NDArray[np.float64] | None:
    """Coverage-weighted centroid in a disc around the blob; background from a ring around the disc."""
    height, width = frame.shape
    r_mask = radius + 1.25
    pad = int(np.ceil(r_mask)) + 5
    x0, x1 = max(x - pad, 0), min(x + w + pad, width)
    y0, y1 = max(y - pad, 0), min(y + h + pad, height)
    patch = frame[y0:y1, x0:x1]
    yy, xx = np.mgrid[y0:y1, x0:x1]
    centre = np.array([x + (w - 1) / 2, y + (h - 1) / 2], dtype=np.float64)
    dist = np.hypot(xx - centre[0], yy - centre[1])
    ring = (dist > r_mask + 1.5) & (dist <= r_mask + 4.5)
    background = float(np.median(patch[ring])) if ring.any() else 0.0
    coverage = np.clip((patch - background) / max(lit - background, 1e-9), 0.0, 1.0)
    for _ in range(iterations):
        dist = np.hypot(xx - centre[0], yy - centre[1])
        weight = coverage * np.clip(r_mask + 0.5 - dist, 0.0, 1.0)
        total = weight.sum()
        if total <= 0:
            return None
        centre = np.array([(weight * xx).sum() / total, (weight * yy).sum() / total])
    return centre


# -- switch frames of both polarities, disc detection and fitting (the LED-blink scene) ---------------------------


def accumulate_polarities(rec: Recording, blinks: list[Blink], width: int, height: int) -> tuple[Counts, Counts]:
    """Per-pixel ON events of the blinks' ON switches and OFF events of their OFF switches, (height, width) each."""
    on = np.zeros(width * height, np.int64)
    off = np.zeros(width * height, np.int64)
    for blink in blinks:
        for switch, out in ((blink.on, on), (blink.off, off)):
            ev = rec.events_between(switch.t0_us, switch.t1_us)
            ev = ev[(ev["p"] == switch.polarity) & (ev["x"] < width) & (ev["y"] < height)]
            out += np.bincount(ev["y"].astype(np.int64) * width + ev["x"], minlength=width * height)
    return on.reshape(height, width), off.reshape(height, width)


def harmonic_frame(on: npt.ArrayLike, off: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """``2 on off / (on + off)`` per pixel (0 where both are 0).

    A switch of log step D gives about D / C_on ON and D / C_off OFF events;
    their harmonic mean is D / mean(C_on, C_off). The per-pixel threshold is
    roughly Gaussian, its inverse heavy-tailed: a pixel with one low threshold
    (a membrane speck as bright as a marker in the plain sum) is tamed by the
    other polarity."""
    on = np.asarray(on, np.float64)
    off = np.asarray(off, np.float64)
    total = on + off
    return np.divide(2 * on * off, total, out=np.zeros_like(total), where=total > 0)


def _disc_kernel(radius: float, size: int) -> npt.NDArray[np.float32]:
    """A disc of ``radius`` px with a one-pixel linear edge, in a size x size kernel."""
    half = size // 2
    yy, xx = np.mgrid[-half : half + 1, -half : half + 1]
    return np.clip(radius + 0.5 - np.hypot(xx, yy), 0.0, 1.0).astype(np.float32)


def disc_response(frame: npt.ArrayLike, radius: float) -> npt.NDArray[np.float32]:
    """Matched filter for bright discs of ``radius``: the mean inside the disc less the mean of a ring
    (radius + 1.5 to 2 radius + 2) around it, over lit pixels only (count > 0: the ROI's edge is no disc);
    0 where the disc is not all lit or the ring not half lit."""
    f = np.asarray(frame, np.float32)
    lit = (f > 0).astype(np.float32)
    size = 2 * int(np.ceil(2 * radius + 2.5)) + 1
    inner = _disc_kernel(radius, size)
    ring = _disc_kernel(2 * radius + 2, size) - _disc_kernel(radius + 1.5, size)

    def filt(a: npt.NDArray[np.float32], k: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        return cast(npt.NDArray[np.float32], cv2.filter2D(a, -1, k, borderType=cv2.BORDER_CONSTANT))

    n_in, n_ring = filt(lit, inner), filt(lit, ring)
    out = cast(npt.NDArray[np.float32], filt(f, inner) / np.maximum(n_in, 1e-6) - filt(f, ring) / np.maximum(n_ring, 1e-6))
    out[(n_in < 0.9 * inner.sum()) | (n_ring < 0.5 * ring.sum())] = 0.0
    return out


def robust_sigma(values: npt.ArrayLike) -> float:
    """1.4826 x the median absolute deviation."""
    v = np.asarray(values, np.float64)
    if v.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(v - np.median(v))))


def find_discs(
    frame: npt.ArrayLike,
    n_expected: int,
    *,
    radii_px: npt.ArrayLike | None = None,
    min_strength: float = 3.0,
    max_candidates: float = 2.0,
) -> Blobs:
    """Bright discs of a count frame, strongest first, at whole pixels (centres: :func:`fit_discs`).

    For each trial radius the matched filter (:func:`disc_response`) is divided
    by its robust spread over the lit pixels (a strength in noise sigmas); its
    local maxima at least a disc diameter apart are candidates. The radius whose
    ``n_expected`` strongest candidates are strongest on average is the disc
    size; candidates above ``min_strength``, at most ``max_candidates`` x
    ``n_expected`` of them, are returned (``radius_px``: the disc size)."""
    f = np.asarray(frame, np.float64)
    lit = f > 0
    empty = Blobs(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0))
    if lit.sum() < 100 or n_expected < 1:
        return empty
    radii = np.geomspace(2.5, 20.0, 10) if radii_px is None else np.asarray(radii_px, np.float64)
    best: tuple[float, float, npt.NDArray[np.float64], npt.NDArray[np.float64]] | None = None
    for radius in radii:
        response = disc_response(f, float(radius))
        sigma = robust_sigma(response[lit])
        if sigma <= 0:
            continue
        size = 2 * int(np.ceil(2 * radius)) + 1
        peak = (response >= cv2.dilate(response, np.ones((size, size), np.uint8))) & (response > 0)
        ys, xs = np.nonzero(peak)
        response_strength = response[ys, xs] / sigma
        order = np.argsort(-response_strength)
        xy = np.stack([xs[order], ys[order]], axis=1).astype(np.float64)
        strength = response_strength[order].astype(np.float64)
        score = float(strength[:n_expected].mean()) if strength.size else 0.0
        if best is None or score > best[0]:
            best = (score, float(radius), xy, strength)
    if best is None:
        return empty
    _, radius, xy, strength = best
    keep = np.flatnonzero(strength >= min_strength)[: int(max_candidates * n_expected)]
    n = len(keep)
    return Blobs(xy[keep], np.full(n, np.pi * radius**2), np.full(n, radius), strength[keep])


@dataclass(frozen=True)
class DiscFit:
    """Least-squares disc fits: centres (N, 2) px, radii px, edge widths px (Gaussian sigma), contrast, and ok."""

    xy: npt.NDArray[np.float64]
    radius_px: npt.NDArray[np.float64]
    edge_px: npt.NDArray[np.float64]
    contrast: npt.NDArray[np.float64]
    ok: npt.NDArray[np.bool_]


def fit_discs(
    frame: npt.ArrayLike,
    xy: npt.ArrayLike,
    radius_px: float,
    *,
    edge_px: float | None = None,
    fixed_radius: float | None = None,
    max_shift: float | None = None,
    iterations: int = 20,
) -> DiscFit:
    """Sub-pixel disc centres: each patch (half-size 2 radius + 3) is fitted with ``background + contrast *
    0.5 erfc((|p - c| - R) / (sqrt(2) s))`` by robust least squares (soft-L1 weights, scale: the frame's noise;
    damped Gauss-Newton, all discs at once).

    ``fixed_radius`` and ``edge_px`` fix R and s (one size for all discs: fewer free parameters, less noise);
    otherwise each is fitted (R within 0.5 to 2 radius_px, s within 0.2 to 4 px). A fit whose centre moves
    more than ``max_shift`` (default: the radius) from its start, whose contrast is not positive, or whose
    patch leaves the frame, is not ok."""
    f = np.asarray(frame, np.float64)
    start = np.asarray(xy, np.float64).reshape(-1, 2)
    height, width = f.shape
    lit = f[f > 0]
    scale = max(robust_sigma(lit), 1e-3) if lit.size else 1.0
    shift = radius_px if max_shift is None else max_shift
    half = int(np.ceil(2 * radius_px + 3))
    n = len(start)
    corner = np.rint(start).astype(np.int64) - half
    inside = (corner[:, 0] >= 0) & (corner[:, 1] >= 0) & (corner[:, 0] + 2 * half < width) & (
        corner[:, 1] + 2 * half < height)
    out = DiscFit(np.full((n, 2), np.nan), np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan),
                  np.zeros(n, bool))
    if not inside.any():
        return out
    k = np.flatnonzero(inside)
    oy, ox = np.mgrid[0 : 2 * half + 1, 0 : 2 * half + 1]
    xx = (corner[k, 0, None] + ox.ravel()[None, :]).astype(np.float64)  # (m, P)
    yy = (corner[k, 1, None] + oy.ravel()[None, :]).astype(np.float64)
    values = f[yy.astype(np.int64), xx.astype(np.int64)]
    background = np.median(values, axis=1)
    contrast = np.maximum(np.percentile(values, 90, axis=1) - background, 1e-3)
    m = len(k)
    free_r, free_s = fixed_radius is None, edge_px is None
    p = np.column_stack([start[k], contrast, background,
                         np.full(m, radius_px if free_r else float(fixed_radius)),  # type: ignore[arg-type]
                         np.full(m, 0.8 if free_s else float(edge_px))])  # type: ignore[arg-type]
    cols = [0, 1, 2, 3] + ([4] if free_r else []) + ([5] if free_s else [])
    damping = np.full(m, 1e-3)
    cost = _disc_cost(p, xx, yy, values, scale)
    for _ in range(iterations):
        r, jac = _disc_model(p, xx, yy, values)
        w = 1.0 / np.sqrt(1.0 + (r / scale) ** 2)  # soft-L1 as reweighted least squares
        jac = jac[:, :, cols]
        jtj = np.einsum("mpi,mp,mpj->mij", jac, w, jac)
        jtr = np.einsum("mpi,mp,mp->mi", jac, w, r)
        diag = np.einsum("mii->mi", jtj)
        # A flat patch (no disc, no noise) has a zero Jacobian: a floor on the diagonal keeps its step 0, not singular.
        step = np.linalg.solve(jtj + (damping[:, None] * np.maximum(diag, 1e-12))[:, :, None] * np.eye(len(cols)),
                               -jtr[:, :, None])[..., 0]
        trial = p.copy()
        trial[:, cols] += step
        trial[:, 4] = np.clip(trial[:, 4], 0.5 * radius_px, 2.0 * radius_px) if free_r else trial[:, 4]
        trial[:, 5] = np.clip(trial[:, 5], 0.2, 4.0) if free_s else trial[:, 5]
        new_cost = _disc_cost(trial, xx, yy, values, scale)
        better = new_cost < cost
        p[better], cost[better] = trial[better], new_cost[better]
        damping = np.where(better, damping / 3, damping * 4)
    moved = np.hypot(p[:, 0] - start[k, 0], p[:, 1] - start[k, 1])
    out.xy[k] = p[:, :2]
    out.contrast[k] = p[:, 2]
    out.radius_px[k] = p[:, 4]
    out.edge_px[k] = p[:, 5]
    out.ok[k] = (moved <= shift) & (p[:, 2] > 0)
    return out


def _disc_model(p: npt.NDArray[np.float64], xx: npt.NDArray[np.float64], yy: npt.NDArray[np.float64],
                values: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Residuals (m, P) and their Jacobian (m, P, 6) in p = (cx, cy, contrast, background, radius, edge)."""
    from scipy.special import erfc

    dx, dy = xx - p[:, 0, None], yy - p[:, 1, None]
    d = np.maximum(np.hypot(dx, dy), 1e-9)
    s = p[:, 5, None]
    u = (d - p[:, 4, None]) / (np.sqrt(2.0) * s)
    g = 0.5 * erfc(u)
    dg_du = -np.exp(-u * u) / np.sqrt(np.pi)
    a = p[:, 2, None]
    common = a * dg_du / (np.sqrt(2.0) * s)
    jac = np.stack([common * (-dx / d), common * (-dy / d), g, np.ones_like(g), -common, a * dg_du * (-u / s)], axis=2)
    return p[:, 3, None] + a * g - values, jac


def _disc_cost(p: npt.NDArray[np.float64], xx: npt.NDArray[np.float64], yy: npt.NDArray[np.float64],
               values: npt.NDArray[np.float64], scale: float) -> npt.NDArray[np.float64]:
    """Soft-L1 cost per disc."""
    r, _ = _disc_model(p, xx, yy, values)
    return (2 * (np.sqrt(1 + (r / scale) ** 2) - 1)).sum(axis=1)
