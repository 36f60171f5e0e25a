"""The shared host clock and per-device clock models.

Time bases
----------
* The **host clock** counts integer **nanoseconds** on a monotonic clock
  (``time.monotonic_ns`` by default). It is injectable: tests and the virtual
  rig pass a :class:`ManualClock` and move time themselves.
* A **recording's time base** is host microseconds since the recording's start,
  ``t_us = (host_ns - t0_host_ns) // 1000`` (int64). Every stream stores the
  host receive time of its samples in that base (``t_host_us``).
* **Device time** is whatever the device stamps its data with, in microseconds
  (camera sensor time, the Bota frame counter, ...), stored raw as received.

Clock models
------------
A :class:`ClockModel` maps device time to host time with an offset and a drift::

    host_us = host_ref_us + (device_us - device_ref_us) * (1 + drift_ppm * 1e-6)

Each sample is *sent* at ``send = model(device_us)`` and received at
``receive = send + latency`` with ``latency >= 0``. So the model is a line below
every (device, receive) pair, and the best such line is the one that hugs the
lower envelope: it minimises ``sum(receive - model(device))`` subject to staying
below all points. That linear programme is solved exactly by the edge of the
pairs' lower convex hull that spans the mean device time. Latency bursts only
lift points above the envelope, so they do not move it. The constant minimum
latency cannot be seen from timestamps alone; the model absorbs it.

When the camera records trigger edges whose host time another device knows,
those pairs pin the line directly (least squares with outlier rejection), which
removes the minimum-latency ambiguity as well.
"""

from __future__ import annotations

import bisect
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

NS_PER_US = 1000


class HostClock(Protocol):
    """Anything that tells the host time in integer nanoseconds."""

    def now_ns(self) -> int: ...


class MonotonicClock:
    """The real host clock: ``time.monotonic_ns``."""

    def now_ns(self) -> int:
        return time.monotonic_ns()


class ManualClock:
    """A host clock that only moves when told to (tests, the virtual rig)."""

    def __init__(self, start_ns: int = 0) -> None:
        self._t_ns = int(start_ns)
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        with self._lock:
            return self._t_ns

    def advance_ns(self, dt_ns: int) -> int:
        if dt_ns < 0:
            raise ValueError("a monotonic clock cannot go backwards")
        with self._lock:
            self._t_ns += int(dt_ns)
            return self._t_ns

    def set_ns(self, t_ns: int) -> None:
        with self._lock:
            if t_ns < self._t_ns:
                raise ValueError("a monotonic clock cannot go backwards")
            self._t_ns = int(t_ns)


def unwrap_counter(raw: npt.ArrayLike, bits: int) -> npt.NDArray[np.int64]:
    """Unwrap a free-running unsigned counter of ``bits`` bits to int64.

    Every step backwards by more than half the period counts as one wrap
    (the Bota timestamp is a uint32 of microseconds and wraps every 71.6 min).
    """
    values = np.asarray(raw, dtype=np.int64)
    if values.size == 0:
        return values
    period = np.int64(1) << bits
    steps = np.diff(values)
    wraps = np.concatenate(([0], np.cumsum(steps < -(period // 2)))).astype(np.int64)
    return values + wraps * period


class CounterUnwrapper:
    """Streaming form of :func:`unwrap_counter`, one chunk at a time."""

    def __init__(self, bits: int) -> None:
        self.period = 1 << bits
        self._last: int | None = None
        self._wraps = 0

    def __call__(self, raw: npt.ArrayLike) -> npt.NDArray[np.int64]:
        values = np.asarray(raw, dtype=np.int64)
        if values.size == 0:
            return values
        previous = values[:1] if self._last is None else np.array([self._last])
        steps = np.diff(np.concatenate((previous, values)))
        wraps = self._wraps + np.cumsum(steps < -(self.period // 2))
        self._last = int(values[-1])
        self._wraps = int(wraps[-1])
        return values + wraps * self.period


@dataclass(frozen=True)
class ClockModel:
    """Device time to host time: offset and drift, with how it was found.

    ``method`` is one of ``identity``, ``envelope`` (lower envelope of receive
    times), ``triggers`` (hardware trigger pairs) or ``envelope+trigger`` (drift
    from the envelope, offset from a single trigger).
    Residuals are ``receive - model(device)`` in microseconds over the pairs the
    model was fitted on: their floor is 0 for an envelope fit, and their spread
    is the transport latency.
    """

    device_ref_us: float = 0.0
    host_ref_us: float = 0.0
    drift_ppm: float = 0.0
    method: str = "identity"
    n_pairs: int = 0
    n_triggers: int = 0
    residual_p50_us: float = 0.0
    residual_p99_us: float = 0.0
    residual_max_us: float = 0.0

    @property
    def rate(self) -> float:
        return 1.0 + self.drift_ppm * 1e-6

    def to_host_us(self, device_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        d = np.asarray(device_us, dtype=np.float64)
        return self.host_ref_us + (d - self.device_ref_us) * self.rate

    def to_host_us_int(self, device_us: npt.ArrayLike) -> npt.NDArray[np.int64]:
        return np.rint(self.to_host_us(device_us)).astype(np.int64)

    def to_device_us(self, host_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        h = np.asarray(host_us, dtype=np.float64)
        return self.device_ref_us + (h - self.host_ref_us) / self.rate

    def with_residuals(
        self, device_us: npt.ArrayLike, host_us: npt.ArrayLike
    ) -> ClockModel:
        """The same model with residual statistics over the given pairs."""
        r = np.asarray(host_us, dtype=np.float64) - self.to_host_us(device_us)
        if r.size == 0:
            return self
        p50, p99 = np.percentile(r, [50, 99])
        return _replace(
            self,
            residual_p50_us=float(p50),
            residual_p99_us=float(p99),
            residual_max_us=float(r.max()),
        )

    def to_attrs(self) -> dict[str, float | int | str]:
        return asdict(self)

    @classmethod
    def from_attrs(cls, attrs: dict[str, object]) -> ClockModel:
        known = set(cls.__dataclass_fields__)
        plain = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in attrs.items() if k in known}
        return cls(**plain)  # type: ignore[arg-type]


def _replace(model: ClockModel, **changes: object) -> ClockModel:
    values = asdict(model)
    values.update(changes)
    return ClockModel(**values)  # type: ignore[arg-type]


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
    sum_x: int = 0

    def add(self, x: int, y: int) -> None:
        xs, ys = self.xs, self.ys
        if xs and x < xs[-1]:
            self.n_out_of_order += 1
            return
        self.n_points += 1
        self.sum_x += x
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

    def supporting_line(self) -> tuple[float, float, float] | None:
        """(x_ref, y_ref, slope) of the hull edge under the mean device time."""
        xs, ys = self.xs, self.ys
        if len(xs) < 2:
            return None
        x_mean = self.sum_x / self.n_points
        i = bisect.bisect_right(xs, x_mean) - 1
        i = min(max(i, 0), len(xs) - 2)
        slope = (ys[i + 1] - ys[i]) / (xs[i + 1] - xs[i])
        return float(xs[i]), float(ys[i]), slope


def _model_from_hull(hull: LowerHull) -> ClockModel | None:
    line = hull.supporting_line()
    if line is None:
        return None
    x_ref, y_ref, slope = line
    return ClockModel(
        device_ref_us=x_ref,
        host_ref_us=y_ref,
        drift_ppm=(slope - 1.0) * 1e6,
        method="envelope",
        n_pairs=hull.n_points,
    )


def fit_lower_envelope(device_us: npt.ArrayLike, host_us: npt.ArrayLike) -> ClockModel:
    """Fit the offset-and-drift model on the lower envelope of receive times.

    ``device_us``: device send stamps (unwrapped, non-decreasing).
    ``host_us``: host receive times of the same samples.
    With fewer than two distinct device times the model is a pure offset.
    """
    d = np.asarray(device_us, dtype=np.int64)
    h = np.asarray(host_us, dtype=np.int64)
    if d.shape != h.shape:
        raise ValueError("device and host times must have the same length")
    if d.size == 0:
        return ClockModel()
    hull = LowerHull()
    order = np.argsort(d, kind="stable")
    hull.add_many(d[order], h[order])
    model = _model_from_hull(hull)
    if model is None:
        offset = float((h - d).min())
        model = ClockModel(device_ref_us=0.0, host_ref_us=offset, method="envelope", n_pairs=int(d.size))
    return model.with_residuals(d, h)


#: Crystal oscillators stay within about +-100 ppm; a fitted drift beyond this is noise.
MAX_PLAUSIBLE_DRIFT_PPM = 200.0


def fit_triggers(
    device_us: npt.ArrayLike,
    host_us: npt.ArrayLike,
    fallback: ClockModel | None = None,
    reject_us: float = 50.0,
) -> ClockModel:
    """Fit on hardware trigger pairs: the device stamp of an edge and its host time.

    Two or more pairs: least squares of host on device time, then pairs off the
    line by more than ``reject_us`` (mismatched or missed edges) are dropped
    and the line refitted. One pair: drift from ``fallback`` (an envelope fit),
    offset from the trigger.
    """
    d = np.asarray(device_us, dtype=np.float64)
    h = np.asarray(host_us, dtype=np.float64)
    if d.size == 0:
        if fallback is None:
            raise ValueError("no trigger pairs and no fallback model")
        return fallback
    if d.size == 1 or np.ptp(d) == 0:
        drift = fallback.drift_ppm if fallback is not None else 0.0
        return ClockModel(
            device_ref_us=float(d[0]),
            host_ref_us=float(np.median(h)),
            drift_ppm=drift,
            method="envelope+trigger",
            n_pairs=fallback.n_pairs if fallback else 0,
            n_triggers=int(d.size),
        )
    keep = np.ones(d.size, dtype=bool)
    for _ in range(3):
        d_ref = float(d[keep].mean())
        slope, intercept = np.polyfit(d[keep] - d_ref, h[keep], 1)
        residual = h - (intercept + slope * (d - d_ref))
        new_keep = np.abs(residual) <= max(reject_us, 5 * _mad(residual[keep]))
        if new_keep.sum() < 2 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    drift = (float(slope) - 1.0) * 1e6
    if abs(drift) > MAX_PLAUSIBLE_DRIFT_PPM:
        # Host edge times jittered by milliseconds over a short span: the slope is noise. Keep a
        # plausible drift (the fallback's, else none) and take the offset as the median.
        prior = fallback.drift_ppm if fallback is not None and abs(fallback.drift_ppm) <= MAX_PLAUSIBLE_DRIFT_PPM else 0.0
        d_ref = float(np.median(d[keep]))
        offset = float(np.median(h[keep] - (d[keep] - d_ref) * (1 + prior * 1e-6)))
        return ClockModel(device_ref_us=d_ref, host_ref_us=offset, drift_ppm=prior, method="triggers-offset",
                          n_pairs=fallback.n_pairs if fallback else 0, n_triggers=int(keep.sum()))
    return ClockModel(
        device_ref_us=d_ref,
        host_ref_us=float(intercept),
        drift_ppm=drift,
        method="triggers",
        n_pairs=fallback.n_pairs if fallback else 0,
        n_triggers=int(keep.sum()),
    )


def _mad(x: npt.NDArray[np.float64]) -> float:
    return float(np.median(np.abs(x - np.median(x)))) if x.size else 0.0


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
    current best envelope fit (``None`` until two distinct device times).
    Thread-safe: one writer thread adds, any thread reads.
    """

    def __init__(self) -> None:
        self._hull = LowerHull()
        self._model: ClockModel | None = None
        self._lock = threading.Lock()

    def add(self, device_us: npt.ArrayLike, host_us: npt.ArrayLike) -> None:
        with self._lock:
            self._hull.add_many(device_us, host_us)
            self._model = _model_from_hull(self._hull)

    @property
    def model(self) -> ClockModel | None:
        return self._model

    @property
    def n_out_of_order(self) -> int:
        return self._hull.n_out_of_order
