"""Clock models fitted to (device time, host receive time) pairs: the latency envelope, trigger edges, the live fit.

A :class:`~labrig.clock.ClockModel` maps device time to host time with an offset and a drift.
**Envelope** (:func:`fit_lower_envelope`, :class:`OnlineClockFit`). Each sample is
*sent* at ``model(device_us)`` and received ``latency >= 0`` later, so the model
is a line below every (device, receive) pair, resting on the latency floor. On a
loaded host, stretches of a recording arrive late by milliseconds to seconds and
the floor's prompt pairs may cover a few seconds only; the hull edge under the
mean device time (the exact solution of *minimise sum(receive - model)*) then
takes its slope from two nearby points, thousands of ppm off. So the floor is
found robustly: the hull-supporting line whose 20 % quantile of residuals is
least (late stretches covering the rest do not pull it), then a least-squares
line through the lowest pair of each of 16 stretches of the recording within the
floor band, lowered onto the exact hull. The constant minimum latency cannot be
seen from timestamps alone; the model absorbs it. A floor that moves with the
load (a camera's, with the event rate) looks like drift here.

**Trigger edges** (:func:`fit_triggers`). When the camera stamps edges whose host
time another device knows (the CNC output toggled at each phase), each pair pins
the line up to the host stamp's error. A host stamp is the earliest the edge can
have happened (the command's send plus its time on the wire): an edge handled at
once lies on the line within tens of us, one the device handled late lies below
it by up to milliseconds. The fit finds the tightest cluster of edges (least
quantile over the lines through two edges, few edges allowed far above) and
rests the line on the cluster's highest stamps (the linear programme of
one-sided errors). This pins the offset too, minimum latency included. The drift
of the triggers is kept unless the envelope's is far more certain.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from labrig.clock import ClockModel

#: Edges whose earliest time lies within this of the trigger line (us) bound its offset from above too.
PROMPT_EDGE_US = 2000.0
#: ``trigger_out.t_latest_host_us`` of an edge whose latest time is not known (and in files
#: written before the column existed).
UNKNOWN_LATEST_US = int(np.iinfo(np.int64).max)

#: Fitted drifts stay within +-this, ppm: a constraint of the line fits, far beyond the tens to
#: few hundred ppm of crystal oscillators (a fit held at it shows a large uncertainty).
DRIFT_BOUND_PPM = 2000.0
#: The envelope fit keeps, per bin of this much device time (us), the pair received earliest
#: relative to its device time: the samples of the latency floor.
ENVELOPE_BIN_US = 10_000
#: The latency floor is the supporting line under which this fraction of the envelope's bins lies
#: closest; stretches of late delivery may cover the rest of a recording.
FLOOR_QUANTILE = 0.2
#: Points this close to a line (us) count as on it whatever their own scatter: the 1 us stamp
#: resolution and scheduling noise.
MIN_BAND_US = 20.0
#: A floor band or trigger band is this many times the scatter of the tightest points found.
BAND_FACTOR = 4.0
#: The envelope's drift is fitted through the lowest pair of each of this many stretches of a
#: recording (at least four bins a stretch).
FLOOR_STRETCHES = 16
#: Scatter below this (us) is not believed when judging a fit's uncertainty: the stamps' resolution.
MIN_SCATTER_US = 0.5
#: Drift uncertainties are the half-widths of confidence intervals of this level.
CONFIDENCE = 0.95
#: The envelope's drift replaces the triggers' only when its uncertainty is below the triggers'
#: divided by this: a latency floor that moves with the host's load (the camera's, with the
#: event rate) looks like drift to the envelope, and its uncertainty cannot show that.
TRIGGER_PREFERENCE = 4.0
#: Lines tried through pairs of trigger edges at most (pairs spread over the recording beyond).
MAX_TRIGGER_CANDIDATES = 2000
#: A line through two trigger pairs is refused with more than this fraction of the pairs above its
#: band: stamps are the earliest the edges can have happened. One more may lie far above (beyond
#: BAND_FACTOR bands): a host thread descheduled between sending a line and stamping it.
MAX_ABOVE_FRACTION = 0.1


@dataclass
class LowerHull:
    """The lower convex hull of (device_us, host_us) points, built online.

    Points must arrive in non-decreasing device time (out-of-order points are
    ignored and counted). Integer coordinates keep the orientation test exact.
    Appending is amortised O(1); the hull of n noisy pairs has O(log n) vertices.
    """

    xs: list[int] = field(default_factory=list)
    ys: list[int] = field(default_factory=list)
    n_points: int = 0
    n_out_of_order: int = 0

    def add(self, x: int, y: int) -> None:
        xs, ys = self.xs, self.ys
        if xs and x < xs[-1]:
            self.n_out_of_order += 1
            return
        self.n_points += 1
        if xs and x == xs[-1]:
            if y >= ys[-1]:
                return
            xs.pop()
            ys.pop()
        while len(xs) >= 2:
            # Pop the last vertex while it does not make a strict left turn.
            cross = (xs[-1] - xs[-2]) * (y - ys[-2]) - (ys[-1] - ys[-2]) * (x - xs[-2])
            if cross > 0:
                break
            xs.pop()
            ys.pop()
        xs.append(x)
        ys.append(y)

    def add_many(self, device_us: npt.ArrayLike, host_us: npt.ArrayLike) -> None:
        for x, y in zip(np.asarray(device_us, np.int64).tolist(), np.asarray(host_us, np.int64).tolist()):
            self.add(x, y)

    def edge_slopes(self) -> npt.NDArray[np.float64]:
        """Slopes (host us per device us) of the hull's edges, left to right (increasing)."""
        x, y = np.asarray(self.xs, np.int64), np.asarray(self.ys, np.int64)
        return np.diff(y).astype(np.float64) / np.diff(x).astype(np.float64)

    def support(self, slope: float) -> tuple[int, int]:
        """The vertex (x, y) where a line of ``slope`` touches the hull from below: the point
        with the lowest ``y - slope * x``, so the line through it stays below every point."""
        if not self.xs:
            raise ValueError("an empty hull supports no line")
        x, y = np.asarray(self.xs, np.int64), np.asarray(self.ys, np.int64)
        # y - x is exact in integers; the drift part is small, so the comparison keeps its precision.
        k = int(np.argmin((y - x).astype(np.float64) - (slope - 1.0) * (x - x[0]).astype(np.float64)))
        return self.xs[k], self.ys[k]


class EnvelopePairs:
    """(device, receive) pairs reduced to what the envelope fit needs, one chunk at a time.

    Keeps the exact :class:`LowerHull` (the fitted line is lowered onto it) and,
    per bin of ``bin_us`` of device time, the pair received earliest relative to
    its device time (the latency floor's samples): O(duration / bin) memory for
    any sample rate. Pairs must arrive in non-decreasing device time; earlier
    ones are ignored and counted, as the hull does.
    """

    def __init__(self, bin_us: int = ENVELOPE_BIN_US) -> None:
        self.hull = LowerHull()
        self.bin_us = int(bin_us)
        self._done_x: list[npt.NDArray[np.int64]] = []
        self._done_y: list[npt.NDArray[np.int64]] = []
        self._open: tuple[int, int] | None = None  # the last bin's pair, which later pairs may still replace
        self._max_x: int | None = None

    @property
    def n_pairs(self) -> int:
        return self.hull.n_points

    def add(self, device_us: npt.ArrayLike, host_us: npt.ArrayLike) -> None:
        d = np.asarray(device_us, dtype=np.int64).ravel()
        h = np.asarray(host_us, dtype=np.int64).ravel()
        if d.shape != h.shape:
            raise ValueError("device and host times must have the same length")
        if d.size == 0:
            return
        self.hull.add_many(d, h)
        first = d[0] if self._max_x is None else self._max_x
        in_order = d >= np.maximum.accumulate(np.concatenate(([first], d[:-1])))
        d, h = d[in_order], h[in_order]
        if d.size == 0:
            return
        self._max_x = int(d[-1])
        bins = np.floor_divide(d, self.bin_us)
        order = np.lexsort((h - d, bins))  # by bin, then earliest relative arrival (stable on ties)
        firsts = order[np.concatenate(([True], np.diff(bins[order]) != 0))]
        xs, ys = d[firsts], h[firsts]
        if self._open is not None:
            ox, oy = self._open
            if ox // self.bin_us == xs[0] // self.bin_us:
                if oy - ox <= ys[0] - xs[0]:
                    xs[0], ys[0] = ox, oy
            else:
                self._close_bins(np.array([ox]), np.array([oy]))
        self._close_bins(xs[:-1], ys[:-1])
        self._open = (int(xs[-1]), int(ys[-1]))

    def _close_bins(self, xs: npt.NDArray[np.int64], ys: npt.NDArray[np.int64]) -> None:
        if xs.size:
            self._done_x.append(xs.astype(np.int64))
            self._done_y.append(ys.astype(np.int64))

    def snapshot(self) -> EnvelopePairs:
        """A copy that later :meth:`add` calls leave alone, to fit outside a lock (cheap: the
        closed bins' arrays are shared, and never written again)."""
        copy = EnvelopePairs(self.bin_us)
        copy.hull = LowerHull(list(self.hull.xs), list(self.hull.ys), self.hull.n_points, self.hull.n_out_of_order)
        copy._done_x, copy._done_y = list(self._done_x), list(self._done_y)
        copy._open, copy._max_x = self._open, self._max_x
        return copy

    def bins(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """(device_us, host_us) of each bin's earliest-received pair, in device order."""
        xs, ys = list(self._done_x), list(self._done_y)
        if self._open is not None:
            xs.append(np.array([self._open[0]], np.int64))
            ys.append(np.array([self._open[1]], np.int64))
        if not xs:
            empty = np.zeros(0, np.int64)
            return empty, empty
        return np.concatenate(xs), np.concatenate(ys)


@dataclass(frozen=True)
class _LineFit:
    """A fitted line ``host = host_ref_us + (device - device_ref_us) * (1 + drift_ppm 1e-6)``
    with its quality: the drift's uncertainty (ppm), how many points it rests on and their
    spread about it (us)."""

    device_ref_us: float
    host_ref_us: float
    drift_ppm: float
    drift_uncertainty_ppm: float
    n_on_line: int
    spread_us: float


def _least_squares_slope(u: npt.NDArray[np.float64], v: npt.NDArray[np.float64]) -> float:
    du = u - u.mean()
    return float(np.sum(du * (v - v.mean())) / np.sum(du**2))


def _slope_uncertainty_ppm(u: npt.NDArray[np.float64], r: npt.NDArray[np.float64], min_scatter_us: float) -> float:
    """Half-width (ppm) of the CONFIDENCE interval of a slope fitted on device offsets ``u``
    (us) with residuals ``r`` (us): Student's t on the residuals' degrees of freedom, so a
    line through three points is trusted far less than one through sixteen. The scatter is
    taken as at least half the residuals' range and ``min_scatter_us`` (a few points can
    line up by chance). Infinite below three points: no scatter to judge by."""
    if u.size < 3:
        return math.inf
    from scipy.special import stdtrit

    dof = u.size - 2
    sigma = max(math.sqrt(float(np.sum(r**2)) / dof), float(np.ptp(r)) / 2, min_scatter_us)
    standard_error = sigma / math.sqrt(float(np.sum((u - u.mean()) ** 2)))
    return float(stdtrit(dof, 0.5 + CONFIDENCE / 2)) * standard_error * 1e6


def _latency_floor(pairs: EnvelopePairs) -> _LineFit | None:
    """The line under every pair of ``pairs`` that rests on their latency floor (``None``
    until two distinct device times).

    Candidate drifts are the hull's edge slopes (and midpoints) within DRIFT_BOUND_PPM; the
    one whose supporting line has the least FLOOR_QUANTILE quantile of the bins' residuals
    wins (stretches of late delivery cannot pull it) and sets the floor band. The drift is
    then refined by least squares through the lowest bin of each of FLOOR_STRETCHES
    stretches that lies within the band (a floor that scatters from stretch to stretch widens
    the uncertainty); within that uncertainty, the linear programme over the bins within the
    band (*minimise sum(receive - model)*, their lower hull's edge over their mean) sets the
    drift, which a sharp floor pins far better. The line is lowered onto the exact hull.
    Where the drift's uncertainty exceeds DRIFT_BOUND_PPM (a floor of a second or less) the
    line keeps drift 0 and the uncertainty says why.
    """
    hull = pairs.hull
    if len(hull.xs) < 2:
        return None
    x, y = pairs.bins()
    n = x.size
    bound = DRIFT_BOUND_PPM * 1e-6
    u = (x - x[0]).astype(np.float64)
    v = (y - x).astype(np.float64)  # latency plus a constant, us
    beta, uncertainty, on = 0.0, math.inf, np.array([0])
    if n >= 2:
        edges = np.clip(hull.edge_slopes() - 1.0, -bound, bound)
        candidates = np.unique(np.concatenate((edges, (edges[1:] + edges[:-1]) / 2, [0.0])))
        k = min(n - 1, max(1, math.ceil(FLOOR_QUANTILE * n) - 1))
        scores = np.array([np.partition((v - b * u) - (v - b * u).min(), k)[k] for b in candidates])
        best = int(np.argmin(scores))
        beta, band = float(candidates[best]), max(MIN_BAND_US, BAND_FACTOR * float(scores[best]))
        n_stretches = min(FLOOR_STRETCHES, max(2, n // 4))
        starts = np.unique(np.searchsorted(u, np.linspace(0.0, u[-1], n_stretches + 1)[:-1]))
        for _ in range(8):
            r = v - beta * u
            lowest = starts + np.array([np.argmin(part) for part in np.split(r, starts[1:])])
            lowest = lowest[r[lowest] - r.min() <= band]
            if lowest.size < 2:
                break
            on = lowest
            refined = min(max(_least_squares_slope(u[on], v[on]), -bound), bound)
            if refined == beta:
                break
            beta = refined
        r = v[on] - beta * u[on]
        # A floor as thick as the band may wander by a quarter of it between stretches unseen.
        uncertainty = _slope_uncertainty_ppm(u[on], r - r.mean(), band / BAND_FACTOR)
        r = v - beta * u
        floor = r - r.min() <= band
        if floor.sum() >= 2:
            # On a sharp floor the linear programme over the floor's bins (their lower hull's edge
            # over their mean) is far more precise than any line through stretch minima.
            steepest, _ = _upper_hull_line(u[floor], -v[floor], bound)
            if abs(-steepest - beta) * 1e6 <= uncertainty:
                beta = -steepest
        if uncertainty > DRIFT_BOUND_PPM:
            beta = 0.0  # the pairs cannot tell the drift within the bound: no drift rather than a guess
    rate = 1.0 + beta
    device_ref = float(x[0]) + float(u[on].mean())
    vx, vy = hull.support(rate)
    return _LineFit(
        device_ref_us=device_ref,
        host_ref_us=vy + (device_ref - vx) * rate,
        drift_ppm=beta * 1e6,
        drift_uncertainty_ppm=uncertainty,
        n_on_line=int(on.size),
        spread_us=float(np.ptp(v[on] - beta * u[on])),
    )


def _envelope_model(pairs: EnvelopePairs) -> ClockModel | None:
    """The envelope model of ``pairs`` (``None`` until two distinct device times)."""
    floor = _latency_floor(pairs)
    if floor is None:
        return None
    return ClockModel(
        device_ref_us=floor.device_ref_us,
        host_ref_us=floor.host_ref_us,
        drift_ppm=floor.drift_ppm,
        method="envelope",
        n_pairs=pairs.n_pairs,
        drift_uncertainty_ppm=floor.drift_uncertainty_ppm,
    )


def fit_lower_envelope(device_us: npt.ArrayLike, host_us: npt.ArrayLike) -> ClockModel:
    """Fit the offset-and-drift model on the lower envelope of receive times.

    ``device_us``: device send stamps (unwrapped). ``host_us``: host receive times of the same
    samples. The line stays below every pair and rests on the latency floor (see the module
    docstring). With fewer than two distinct device times the model is a pure offset.
    """
    d = np.asarray(device_us, dtype=np.int64)
    h = np.asarray(host_us, dtype=np.int64)
    if d.shape != h.shape:
        raise ValueError("device and host times must have the same length")
    if d.size == 0:
        return ClockModel()
    order = np.argsort(d, kind="stable")
    pairs = EnvelopePairs()
    pairs.add(d[order], h[order])
    model = _envelope_model(pairs)
    if model is None:
        offset = float((h - d).min())
        model = ClockModel(device_ref_us=0.0, host_ref_us=offset, method="envelope", n_pairs=int(d.size))
    return model.with_residuals(d, h)


def _upper_hull_line(u: npt.NDArray[np.float64], v: npt.NDArray[np.float64], bound: float) -> tuple[float, float]:
    """(slope, intercept) of the line above every point (u, v) that lies lowest on average:
    the edge of their upper convex hull over the mean of ``u``, its slope within +-``bound``."""
    order = np.lexsort((-v, u))  # by u, the highest first among equal u
    hull_u: list[float] = []
    hull_v: list[float] = []
    for x, y in zip(u[order].tolist(), v[order].tolist()):
        if hull_u and x == hull_u[-1]:
            continue
        while len(hull_u) >= 2 and (
            (hull_u[-1] - hull_u[-2]) * (y - hull_v[-2]) - (hull_v[-1] - hull_v[-2]) * (x - hull_u[-2]) >= 0
        ):
            hull_u.pop()
            hull_v.pop()
        hull_u.append(x)
        hull_v.append(y)
    slope = 0.0
    if len(hull_u) >= 2:
        k = min(max(int(np.searchsorted(hull_u, float(u.mean()), side="right")) - 1, 0), len(hull_u) - 2)
        slope = min(max((hull_v[k + 1] - hull_v[k]) / (hull_u[k + 1] - hull_u[k]), -bound), bound)
    return slope, float(np.max(v - slope * u))


def _trigger_line(
    device_us: npt.NDArray[np.float64], host_us: npt.NDArray[np.float64], latest_us: npt.NDArray[np.float64] | None = None
) -> _LineFit | None:
    """The line through the tightest cluster of trigger pairs, resting on its highest stamps.

    A host stamp is the earliest the edge can have happened: prompt edges lie on the line,
    late ones below it, none far above. Every line through two pairs (drift within
    DRIFT_BOUND_PPM) is scored by the distance of its quarter-nearest pair (at least the
    third), and its band is BAND_FACTOR times that; lines with more than a tenth of the
    pairs above their band (one more far above: a late host stamp) are refused. The pairs within the band of the best line are
    refitted as the linear programme their one-sided errors call for: the line above all of
    them that lies lowest on average (the upper hull's edge over their mean device time),
    which rests on the most prompt edges where least squares would follow the slightly
    late ones. ``None`` when fewer than three pairs agree, or they tell the drift no better
    than DRIFT_BOUND_PPM.

    ``latest_us`` (host us per pair, ``inf`` where unknown): the latest each edge can have
    happened. No edge happened after its latest time, so a line passing more than MIN_BAND_US
    above one is refused: late edges that happen to line up (a loaded host) cannot outscore
    the prompt ones then.
    """
    n = device_us.size
    if n < 3 or np.ptp(device_us) == 0:
        return None
    bound = DRIFT_BOUND_PPM * 1e-6
    x0 = float(device_us.min())
    u = device_us - x0
    v = host_us - device_us  # offset + drift * u - lateness, us
    i, j = np.triu_indices(n, 1)
    i, j = i[u[j] != u[i]], j[u[j] != u[i]]
    slopes = (v[j] - v[i]) / (u[j] - u[i])
    plausible = np.abs(slopes) <= bound
    i, slopes = i[plausible], slopes[plausible]
    if slopes.size > MAX_TRIGGER_CANDIDATES:
        pick = np.linspace(0, slopes.size - 1, MAX_TRIGGER_CANDIDATES).round().astype(np.int64)
        i, slopes = i[pick], slopes[pick]
    if slopes.size == 0:
        return None
    intercepts = v[i] - slopes * u[i]
    lateness = intercepts[:, None] + slopes[:, None] * u[None, :] - v[None, :]
    k = max(3, math.ceil(n / 4)) - 1
    scores = np.partition(np.abs(lateness), k, axis=1)[:, k]
    bands = np.maximum(MIN_BAND_US, BAND_FACTOR * scores)
    above = (lateness < -bands[:, None]).sum(axis=1)
    far_above = (lateness < -BAND_FACTOR * bands[:, None]).sum(axis=1)
    scores[above - np.minimum(far_above, 1) > n * MAX_ABOVE_FRACTION] = np.inf
    if latest_us is not None and np.isfinite(latest_us).any():
        known = np.isfinite(latest_us)
        ceiling = latest_us[known] - device_us[known]  # in v's terms: offset + drift * u can reach no higher
        over = intercepts[:, None] + slopes[:, None] * u[None, known] - ceiling[None, :]
        scores[over.max(axis=1) > MIN_BAND_US] = np.inf
    best = int(np.argmin(scores))
    if not np.isfinite(scores[best]):
        return None
    band = float(bands[best])
    slope, intercept = float(slopes[best]), float(intercepts[best])
    on = np.abs(intercept + slope * u - v) <= band
    for _ in range(4):
        if on.sum() < 3 or np.ptp(u[on]) == 0:
            return None
        slope, intercept = _upper_hull_line(u[on], v[on], bound)
        refined = np.abs(intercept + slope * u - v) <= band
        if np.array_equal(refined, on):
            break
        on = refined
    if on.sum() < 3 or np.ptp(u[on]) == 0:
        return None
    r = v[on] - (intercept + slope * u[on])
    uncertainty = _slope_uncertainty_ppm(u[on], r, band / BAND_FACTOR)
    if uncertainty > DRIFT_BOUND_PPM:
        return None
    centre = float(u[on].mean())
    return _LineFit(
        device_ref_us=x0 + centre,
        host_ref_us=x0 + centre + intercept + slope * centre,
        drift_ppm=slope * 1e6,
        drift_uncertainty_ppm=uncertainty,
        n_on_line=int(on.sum()),
        spread_us=float(np.ptp(r)),
    )


def fit_triggers(
    device_us: npt.ArrayLike,
    host_us: npt.ArrayLike,
    fallback: ClockModel | None = None,
    latest_host_us: npt.ArrayLike | None = None,
) -> ClockModel:
    """Fit on hardware trigger pairs: the device stamp of an edge and its host time.

    A host stamp is the earliest the edge can have happened (the command's send plus its
    time on the wire): prompt edges lie on the model, edges the device handled late lie
    below it. With three or more pairs that agree, the line through them gives drift and
    offset (method ``triggers``, see :func:`_trigger_line`), unless ``fallback`` (an
    envelope fit) knows the drift TRIGGER_PREFERENCE times better: then its drift is kept
    and the model rests on the highest stamps (``envelope+trigger``, also with one or two
    pairs). Without a fallback, pairs that agree on no cluster are fitted by least squares
    and the drift's uncertainty is unknown.

    ``latest_host_us``: per pair, the latest the edge can have happened (its device's answer
    received; ``UNKNOWN_LATEST_US`` or ``None``: not known). The line rests on the earliest
    times of the most prompt edges, which lag their stamps by the host's wake-up and the
    device's read (30-100 us on a loaded host); the latest times bound from above how far the
    truth can lie over it (``offset_bound_us``, :func:`_headroom_us`) and refuse lines that pass
    above one (late edges lined up by chance on a loaded host). The line is not raised
    towards them: an answer's way back is slower and far more variable than the line's way out
    (0.3-3 ms against 30-100 us, measured on the virtual rig under load), so the middle of the
    band was 2-5 times further from the truth than its floor.
    """
    d = np.asarray(device_us, dtype=np.float64)
    h = np.asarray(host_us, dtype=np.float64)
    if d.size == 0:
        if fallback is None:
            raise ValueError("no trigger pairs and no fallback model")
        return fallback
    n_pairs = fallback.n_pairs if fallback is not None else 0
    line = _trigger_line(d, h, _known_latest(latest_host_us, d.size))
    envelope_uncertainty = fallback.drift_uncertainty_ppm if fallback is not None else math.inf
    if line is None or line.drift_uncertainty_ppm > TRIGGER_PREFERENCE * envelope_uncertainty:
        if fallback is not None:
            drift, uncertainty, method = fallback.drift_ppm, fallback.drift_uncertainty_ppm, "envelope+trigger"
        elif d.size >= 2 and np.ptp(d) > 0:
            bound = DRIFT_BOUND_PPM * 1e-6
            drift = min(max(_least_squares_slope(d - d.min(), h - d), -bound), bound) * 1e6
            uncertainty, method = math.inf, "triggers"
        else:
            drift, uncertainty, method = 0.0, math.inf, "envelope+trigger"
        line = _rest_on_highest_stamps(d, h, drift, uncertainty)
    else:
        method = "triggers"
    return ClockModel(
        device_ref_us=line.device_ref_us,
        host_ref_us=line.host_ref_us,
        drift_ppm=line.drift_ppm,
        method=method,
        n_pairs=n_pairs,
        n_triggers=line.n_on_line,
        drift_uncertainty_ppm=line.drift_uncertainty_ppm,
        trigger_spread_us=line.spread_us if line.n_on_line >= 2 else math.inf,
        n_trigger_pairs=int(d.size),
        offset_bound_us=_headroom_us(d, h, latest_host_us, line),
    )


def _known_latest(latest_host_us: npt.ArrayLike | None, n: int) -> npt.NDArray[np.float64] | None:
    """Latest host times per pair as floats, ``inf`` where not known; None when none is."""
    if latest_host_us is None:
        return None
    latest = np.asarray(latest_host_us, dtype=np.float64)
    if latest.shape != (n,):
        raise ValueError(f"latest_host_us has shape {latest.shape}, not one time per pair ({n},)")
    return np.where(latest < UNKNOWN_LATEST_US, latest, np.inf)


def _headroom_us(
    d: npt.NDArray[np.float64], h: npt.NDArray[np.float64], latest_host_us: npt.ArrayLike | None, line: _LineFit
) -> float:
    """How far above ``line`` (us) the truth can lie: the lowest latest time of the prompt edges
    (earliest time within PROMPT_EDGE_US of the line: a late edge's answer is late too, and a
    far-off one may be paired wrongly) above the line. Infinite where no latest time is known or
    one lies below the line (the bound says nothing then)."""
    if latest_host_us is None:
        return math.inf
    latest = np.asarray(latest_host_us, dtype=np.float64)
    model = line.host_ref_us + (d - line.device_ref_us) * (1.0 + line.drift_ppm * 1e-6)
    prompt = (latest < UNKNOWN_LATEST_US) & (h - model >= -PROMPT_EDGE_US)
    if not prompt.any():
        return math.inf
    headroom = float(np.min(latest[prompt] - model[prompt]))
    return headroom if headroom >= 0 else math.inf


def _rest_on_highest_stamps(
    d: npt.NDArray[np.float64], h: npt.NDArray[np.float64], drift_ppm: float, drift_uncertainty_ppm: float
) -> _LineFit:
    """The line of a given drift through the highest trigger stamp (no edge happened before
    its stamp), resting on the stamps within the band that the drift's uncertainty allows
    over their span (at least MIN_BAND_US) below it."""
    rate = 1.0 + drift_ppm * 1e-6
    x0 = float(d.min())
    lift = h - (d - x0) * rate
    band = MIN_BAND_US
    if math.isfinite(drift_uncertainty_ppm):
        band = max(band, drift_uncertainty_ppm * 1e-6 * float(np.ptp(d)))
    on = lift >= lift.max() - band
    centre = float(d[on].mean())
    return _LineFit(
        device_ref_us=centre,
        host_ref_us=float(lift.max()) + (centre - x0) * rate,
        drift_ppm=drift_ppm,
        drift_uncertainty_ppm=drift_uncertainty_ppm,
        n_on_line=int(on.sum()),
        spread_us=float(np.ptp(lift[on])),
    )


def match_trigger_edges(
    device_edges_us: npt.ArrayLike,
    host_edges_us: npt.ArrayLike,
    coarse: ClockModel,
    tolerance_us: float,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Pair each camera trigger edge with the known host edge nearest to it.

    ``coarse`` (an envelope fit) predicts the host time of each device edge;
    a pair is kept when the nearest host edge is within ``tolerance_us`` and no
    other device edge claims it. Returns the indices of matched pairs.
    """
    dev = np.asarray(device_edges_us, dtype=np.float64)
    host = np.asarray(host_edges_us, dtype=np.float64)
    if dev.size == 0 or host.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    order = np.argsort(host)
    host_sorted = host[order]
    predicted = coarse.to_host_us(dev)
    j = np.zeros(dev.size, dtype=np.int64)
    if host_sorted.size > 1:
        j = np.clip(np.searchsorted(host_sorted, predicted), 1, host_sorted.size - 1)
        left_closer = np.abs(predicted - host_sorted[j - 1]) <= np.abs(host_sorted[j] - predicted)
        j = np.where(left_closer, j - 1, j)
    distance = np.abs(host_sorted[j] - predicted)
    ok = distance <= tolerance_us
    dev_idx = np.flatnonzero(ok)
    host_idx = order[j[ok]]
    _, first = np.unique(host_idx, return_index=True)
    unique = np.bincount(host_idx, minlength=host.size)[host_idx[first]] == 1
    keep = first[unique]
    return dev_idx[keep].astype(np.int64), host_idx[keep].astype(np.int64)


def align_trigger_edges(
    device_edges_us: npt.ArrayLike,
    host_edges_us: npt.ArrayLike,
    tolerance_us: float,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Pair edges by the pattern of their intervals, whatever the latency (no coarse model).

    Every (device, host) pair proposes an offset; the offset under which most
    device edges land within ``tolerance_us`` of a distinct host edge wins (ties:
    the smaller summed residual). Drift over a recording must stay within the
    tolerance (60 ppm over 5 min is 18 ms). Returns the indices of matched pairs.
    """
    dev = np.asarray(device_edges_us, dtype=np.float64)
    host = np.asarray(host_edges_us, dtype=np.float64)
    empty = np.zeros(0, dtype=np.int64)
    if dev.size == 0 or host.size == 0:
        return empty, empty
    order = np.argsort(host)
    host_sorted = host[order]
    best: tuple[int, float, npt.NDArray[np.int64], npt.NDArray[np.int64]] = (0, np.inf, empty, empty)
    for offset in np.unique((host[None, :] - dev[:, None]).ravel()):
        predicted = dev + offset
        j = np.clip(np.searchsorted(host_sorted, predicted), 1, max(host_sorted.size - 1, 1)) if host_sorted.size > 1 \
            else np.zeros(dev.size, dtype=np.int64)
        if host_sorted.size > 1:
            j = np.where(np.abs(predicted - host_sorted[j - 1]) <= np.abs(host_sorted[j] - predicted), j - 1, j)
        distance = np.abs(host_sorted[j] - predicted)
        ok = np.flatnonzero(distance <= tolerance_us)
        _, first = np.unique(j[ok], return_index=True)
        ok = ok[first]
        score = (ok.size, float(distance[ok].sum()))
        if score[0] > best[0] or (score[0] == best[0] and score[1] < best[1]):
            best = (score[0], score[1], ok.astype(np.int64), order[j[ok]].astype(np.int64))
    return best[2], best[3]


class OnlineClockFit:
    """Live clock model for one device, updated as samples arrive.

    Feed (device_us, host_us) pairs with :meth:`add`; :attr:`model` is the
    envelope fit of the pairs so far (``None`` until two distinct device times),
    as :func:`fit_lower_envelope` fits them: its drift bounded by DRIFT_BOUND_PPM
    and qualified by its uncertainty from the first pairs on (infinite while
    they span less than two bins; drift 0 while they cannot tell it within the
    bound). Reading :attr:`model` refits after new pairs at most once per ten
    times the last fit's duration, so a thread polling it costs at most about a
    tenth of a core; :meth:`refit` fits at once. Fits run outside the lock, so
    :meth:`add` (the recorder's writer thread) never waits for one.
    Thread-safe: one writer thread adds, any thread reads.
    """

    def __init__(self) -> None:
        self._pairs = EnvelopePairs()
        self._model: ClockModel | None = None
        self._stale = False
        self._next_fit_s = 0.0
        self._lock = threading.Lock()

    def add(self, device_us: npt.ArrayLike, host_us: npt.ArrayLike) -> None:
        with self._lock:
            self._pairs.add(device_us, host_us)
            self._stale = True

    @property
    def model(self) -> ClockModel | None:
        with self._lock:
            if not self._stale or (self._model is not None and time.perf_counter() < self._next_fit_s):
                return self._model
            pairs, self._stale = self._pairs.snapshot(), False
        return self._fit(pairs)

    def refit(self) -> ClockModel | None:
        """The model of every pair added so far, fitted now."""
        with self._lock:
            if not self._stale:
                return self._model
            pairs, self._stale = self._pairs.snapshot(), False
        return self._fit(pairs)

    def _fit(self, pairs: EnvelopePairs) -> ClockModel | None:
        started = time.perf_counter()
        model = _envelope_model(pairs)
        now = time.perf_counter()
        with self._lock:
            if model is not None and (self._model is None or model.n_pairs >= self._model.n_pairs):
                self._model = model  # a slower fit of fewer pairs, finishing later, does not overwrite
            self._next_fit_s = now + 10 * (now - started)
            return self._model

    @property
    def n_out_of_order(self) -> int:
        return self._pairs.hull.n_out_of_order
