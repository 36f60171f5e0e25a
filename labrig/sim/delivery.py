"""How the virtual camera's data reaches the host: USB bursts, and hot pixels on the sensor.

Both come from ``[sim.camera_delivery]`` (:mod:`labrig.sim.imperfections`) and are
deterministic: which pixels are hot follows the section's ``seed`` (a property of
the sensor), when they fire and when bursts are released follow the run's seed.
Times are integer microseconds of the rig's world time.

* :class:`BurstSchedule`: the host receives the camera's data in bursts released at
  ``k * period + U(0, jitter)``; data produced at world time t arrives with the first
  release at or after t. Release times rise with k (the jitter never exceeds the period).
* :class:`HotPixels`: Poisson events at ``hot_pixel_rate_hz`` on each hot pixel,
  polarity at random, drawn per 100 ms epoch of world time so that they do not depend
  on how the run is chunked; they add to the pixel's own events (no refractory
  interplay).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig
from labrig.eventtypes import EVENT_DTYPE
from labrig.sim.imperfections import hot_pixel_indices
from labrig.sim.truth_config import sim_config

#: Hot-pixel events are drawn per epoch of this many world microseconds.
HOT_EPOCH_US = 100_000


class BurstSchedule:
    """Release times of the camera's USB bursts (world us)."""

    def __init__(self, period_us: int, jitter_us: int, seed: int = 0) -> None:
        if period_us <= 0 or not 0 <= jitter_us <= period_us:
            raise ValueError("a burst period > 0 and a jitter in [0, period] are needed")
        self.period_us, self.jitter_us, self.seed = int(period_us), int(jitter_us), int(seed)

    @classmethod
    def from_rig(cls, rig: RigConfig, seed: int = 0) -> BurstSchedule | None:
        """The rig's schedule, or None without bursts (``burst_period_ms`` 0)."""
        d = sim_config(rig).camera_delivery
        if d.burst_period_ms <= 0:
            return None
        return cls(round(d.burst_period_ms * 1000), round(d.burst_jitter_ms * 1000), seed)

    def release_us(self, k: int) -> int:
        """World time of the k-th release."""
        jitter = 0 if self.jitter_us == 0 else int(np.random.default_rng([self.seed, 6, k]).integers(0, self.jitter_us))
        return k * self.period_us + jitter

    def release_after(self, t_us: int) -> int:
        """The first release at or after ``t_us``: when data produced at ``t_us`` reaches the host."""
        k = max((int(t_us) - self.jitter_us) // self.period_us, 0)
        while (release := self.release_us(k)) < t_us:
            k += 1
        return release


class HotPixels:
    """The hot pixels of a rig's sensor and their events (see the module docstring)."""

    def __init__(self, rig: RigConfig, seed: int = 0) -> None:
        d, roi = sim_config(rig).camera_delivery, rig.roi
        flat = hot_pixel_indices(d, roi.width_px * roi.height_px)
        #: Sensor pixel coordinates of the hot pixels.
        self.x = (flat % roi.width_px + roi.x0_px).astype(np.uint16)
        self.y = (flat // roi.width_px + roi.y0_px).astype(np.uint16)
        self.rate_hz = d.hot_pixel_rate_hz
        self.seed = int(seed)

    def __len__(self) -> int:
        return int(self.x.size)

    def events(self, t0_us: int, t1_us: int) -> npt.NDArray[np.void]:
        """Their events with t0_us <= t < t1_us (EVENT_DTYPE), sorted by t, then y, x."""
        parts = [self._epoch(k) for k in range(t0_us // HOT_EPOCH_US, -(-t1_us // HOT_EPOCH_US))] if len(self) else []
        if not parts:
            return np.zeros(0, EVENT_DTYPE)
        ev = np.concatenate(parts)
        return ev[(ev["t"] >= t0_us) & (ev["t"] < t1_us)]

    def _epoch(self, k: int) -> npt.NDArray[np.void]:
        rng = np.random.default_rng([self.seed, 7, k])
        counts = rng.poisson(self.rate_hz * HOT_EPOCH_US * 1e-6, len(self))
        n = int(counts.sum())
        out = np.zeros(n, EVENT_DTYPE)
        out["x"], out["y"] = np.repeat(self.x, counts), np.repeat(self.y, counts)
        out["t"] = k * HOT_EPOCH_US + rng.integers(0, HOT_EPOCH_US, n)
        out["p"] = rng.integers(0, 2, n)
        return out[np.lexsort((out["x"], out["y"], out["t"]))]


def merge_events(a: npt.NDArray[np.void], b: npt.NDArray[np.void]) -> npt.NDArray[np.void]:
    """Two event arrays as one, sorted by time (stable: ``a`` first at equal times)."""
    if b.size == 0:
        return a
    ev = np.concatenate([a, b])
    return ev[np.argsort(ev["t"], kind="stable")]
