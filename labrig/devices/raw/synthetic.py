"""Synthetic event streams for RAW benchmarks and tests (not sensor-realistic, codec-realistic).

Half isolated events at random pixels, half horizontal runs of 2..40 pixels sharing one time,
row and polarity (what vectors encode), sorted by (t, y, p, x) like a sensor's readout.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.devices.raw.stream import EVENT_DTYPE, TRIGGER_DTYPE


def synthetic_events(
    n_events: int,
    duration_us: int = 40_000_000,
    width: int = 1280,
    height: int = 720,
    run_fraction: float = 0.5,
    t0_us: int = 1,
    seed: int = 0,
) -> npt.NDArray[Any]:
    """``n_events`` events (EVENT_DTYPE) with t in [t0_us, t0_us + duration_us), sorted by (t, y, p, x)."""
    rng = np.random.default_rng(seed)
    n_run_target = int(n_events * run_fraction)
    lens = rng.integers(2, 41, size=max(1, n_run_target // 21 + 1))
    lens = lens[: np.searchsorted(np.cumsum(lens), n_run_target) + 1]
    n_runs = lens.size
    starts = np.cumsum(lens) - lens
    total = int(lens.sum())
    within = np.arange(total) - np.repeat(starts, lens)
    x0 = rng.integers(0, width - lens + 1)
    run_x = np.repeat(x0, lens) + within
    run_y = np.repeat(rng.integers(0, height, n_runs), lens)
    run_p = np.repeat(rng.integers(0, 2, n_runs), lens)
    run_t = np.repeat(rng.integers(0, duration_us, n_runs), lens)
    n_iso = max(0, n_events - total)
    x = np.concatenate([run_x, rng.integers(0, width, n_iso)])[:n_events]
    y = np.concatenate([run_y, rng.integers(0, height, n_iso)])[:n_events]
    p = np.concatenate([run_p, rng.integers(0, 2, n_iso)])[:n_events]
    t = np.concatenate([run_t, rng.integers(0, duration_us, n_iso)])[:n_events] + t0_us
    key = np.sort(((t.astype(np.int64) * height + y) * 2 + p) * width + x)  # (t, y, p, x) in one int64
    out = np.empty(n_events, EVENT_DTYPE)
    key, out["x"] = np.divmod(key, width)
    key, out["p"] = np.divmod(key, 2)
    out["t"], out["y"] = np.divmod(key, height)
    return out


def synthetic_triggers(
    n: int, duration_us: int = 40_000_000, t0_us: int = 1, max_id: int = 15, seed: int = 0
) -> npt.NDArray[Any]:
    """``n`` trigger edges (TRIGGER_DTYPE) sorted by t, alternating rising / falling per channel."""
    rng = np.random.default_rng(seed + 1)
    out = np.empty(n, TRIGGER_DTYPE)
    out["t"] = np.sort(rng.integers(0, duration_us, n)) + t0_us
    out["id"] = rng.integers(0, max_id + 1, n)
    out["p"] = np.arange(n) % 2 == 0
    return out
