"""What a pipeline run's summary needs (``labrig run``, recording or live): a compact per-window log
and the summary built from it.
"""

from __future__ import annotations

from array import array
from pathlib import Path
from typing import Any

import numpy as np

from labrig.pipeline.run_setup import PipelineSetup
from labrig.pipeline.runtime import WindowResult


class WindowLog:
    """What the summary needs of each window, 8 bytes a value (a live run may last hours): times (us),
    event count, net force (N, on the gel) and each stage's seconds."""

    def __init__(self) -> None:
        self.t0_us, self.t1_us, self.n_events = array("q"), array("q"), array("q")
        self.net_force_n = array("d")
        self.stage_s: dict[str, array[float]] = {}

    def add(self, r: WindowResult) -> None:
        self.t0_us.append(r.t0_us)
        self.t1_us.append(r.t1_us)
        self.n_events.append(r.n_events)
        self.net_force_n.extend(float(v) for v in r.net_force_n)
        for name, seconds in r.seconds.items():
            self.stage_s.setdefault(name, array("d", [0.0] * (len(self.t0_us) - 1))).append(seconds)

    def __len__(self) -> int:
        return len(self.t0_us)

    def net(self) -> np.ndarray:
        """(W, 3) N."""
        return np.asarray(self.net_force_n).reshape(-1, 3)


def window_summary(recording: str | None, log: WindowLog, wall: float, depth: str, setup: PipelineSetup,
                   window_us: int | None, window_events: int | None, out: Path | None, view: Path | None) -> dict[str, Any]:
    """The run's summary (stable keys, units in names): windows, span (s), processing per window and
    real-time factor, median stage latencies (ms), the peak normal force (N, on the gel) and when (us)."""
    t0, t1, net = np.asarray(log.t0_us), np.asarray(log.t1_us), log.net()
    busy = np.sum([np.asarray(v) for v in log.stage_s.values()], axis=0)
    stages = {k: float(np.median(v) * 1000) for k, v in log.stage_s.items()}
    k = int(np.argmin(net[:, 2]))
    return {
        "recording": recording, "depth_source": depth, "windows": len(log),
        "window_us": window_us, "window_events": window_events, "duration_s": float((t1[-1] - t0[0]) / 1e6),
        "wall_s": wall, "processing_per_window_ms": float(np.median(busy) * 1000),
        "real_time_factor": float(np.median(busy / np.maximum(t1 - t0, 1) * 1e6)),
        "stage_median_ms": stages, "youngs_modulus_mpa": setup.youngs_modulus_mpa, "sources": setup.sources,
        "peak_normal_force_on_gel_n": float(-net[k, 2]) + 0.0, "peak_at_us": int(t1[k]),
        "peak_net_force_on_gel_n": [float(v) for v in net[k]], "out": str(out) if out else None,
        "view": str(view) if view else None,
    }
