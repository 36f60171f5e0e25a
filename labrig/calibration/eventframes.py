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
"""

from __future__ import annotations

from dataclasses import dataclass

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
    """Sub-pixel blob centres (N, 2) px, their areas (px) and half-extents (px)."""

    xy: npt.NDArray[np.float64]
    area_px: npt.NDArray[np.float64]
    radius_px: npt.NDArray[np.float64]

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
    for k in np.flatnonzero(active):
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


def otsu_threshold(values: npt.NDArray[np.float64]) -> float:
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
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel)
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
