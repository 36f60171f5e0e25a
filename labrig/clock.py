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

Fits (:mod:`labrig.clock_fit`) keep the drift within ``DRIFT_BOUND_PPM`` (a constraint of the line fits,
not a rejection of them) and store how well the data pinned it: the half-width
of its 95 % confidence interval, ``drift_uncertainty_ppm``.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import asdict, dataclass, replace
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
    """Device time to host time: offset and drift, with how it was found and how well.

    ``method`` is one of ``identity``, ``envelope`` (lower envelope of receive
    times), ``triggers`` (drift and offset from hardware trigger pairs) or
    ``envelope+trigger`` (drift from the envelope, offset from the triggers).
    Residuals are ``receive - model(device)`` in microseconds over the pairs the
    model was fitted on: their floor is 0 for an envelope fit, and their spread
    is the transport latency.

    Quality: ``drift_uncertainty_ppm`` is the half-width of the fitted drift's
    95 % confidence interval (Student's t on the scatter of the points it rests
    on; infinite where the data do not tell, e.g. an identity model or a span
    too short). ``trigger_spread_us`` is how far below the model the stamps of
    the edges it rests on scatter (max - min of stamp - model, us): the
    lateness of a prompt edge, a scale for the offset's error (infinite without
    two such edges). ``n_trigger_pairs``: camera edges paired with a known host
    edge; ``n_triggers``: those the model was fitted on. ``offset_bound_us``: where the edges'
    latest times are known too (their device's answer), how far above the model the truth can
    lie at most (the model rests on the earliest times; infinite: no latest times).
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
    drift_uncertainty_ppm: float = math.inf
    trigger_spread_us: float = math.inf
    n_trigger_pairs: int = 0
    offset_bound_us: float = math.inf

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
        return replace(
            self,
            residual_p50_us=float(p50),
            residual_p99_us=float(p99),
            residual_max_us=float(r.max()),
        )

    def to_attrs(self) -> dict[str, float | int | str]:
        return asdict(self)

    @classmethod
    def from_attrs(cls, attrs: dict[str, object]) -> ClockModel:
        """The model from stored attributes; unknown keys are ignored and missing ones (files
        older than a field) take their defaults."""
        known = set(cls.__dataclass_fields__)
        plain = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in attrs.items() if k in known}
        return cls(**plain)  # type: ignore[arg-type]
