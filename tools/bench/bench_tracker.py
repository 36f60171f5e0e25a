"""Marker tracker cost: the share of a 10 ms window spent tracking 20,000 events on 156 markers.

Setup (not timed): ``--windows`` (300) windows of ``--events`` (20,000) synthetic
events each over the rig's 12 x 13 markers, which drift together on a slow
circle (up to 2 px per window): three quarters are rim events (ON on each dot's
leading half-rim, OFF on its trailing one, 1 px jitter), the rest uniform noise
over the ROI. All trackers see the same windows, after a warm-up (the numba
kernels load from their disk cache or compile); the events are spread evenly over
each window's 10 ms, so Evetac's tracker runs its ten 1 ms slices.

Measured: ``update(events)`` wall time per window, median and p95, as a share
of the 10 ms window (the paper's C++ tracker took 4.6 ms: 0.46). Target for the
paper's tracker: <= 0.05. Side by side: the paper's tracker without its polarity guard, the
circle-fit baseline and Evetac's published tracker, each as a ratio measured in the same run.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
from _common import bench_main, emit

from labrig.config import load_rig
from labrig.eventtypes import EVENT_DTYPE
from labrig.pipeline.evetac import EvetacParams, EvetacTracker
from labrig.pipeline.tracking import CircleFitParams, CircleFitTracker, Tracker, TrackerParams, rest_positions_px

WINDOW_US = 10_000


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--windows", type=int, default=300, help="windows per tracker")
    ap.add_argument("--events", type=int, default=20_000, help="events per window")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def make_windows(rest_px: np.ndarray, roi: Any, windows: int, events: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    offset = np.zeros(2)
    for w in range(windows):
        step = 2.0 * np.array([np.cos(w / 20), np.sin(w / 20)])
        offset = offset + step
        n_rim = 3 * events // 4
        marker = rng.integers(0, len(rest_px), n_rim)
        angle = rng.uniform(-np.pi / 2, np.pi / 2, n_rim)
        lead = rng.random(n_rim) < 0.5
        heading = np.arctan2(step[1], step[0]) + np.where(lead, 0.0, np.pi)
        xy = rest_px[marker] + offset - 0.5 * step + 7.0 * np.stack([np.cos(heading + angle), np.sin(heading + angle)], 1)
        xy += rng.normal(0, 1.0, xy.shape)
        ev = np.zeros(events, EVENT_DTYPE)
        ev["x"][:n_rim] = np.clip(np.rint(xy[:, 0]), 0, 1279)
        ev["y"][:n_rim] = np.clip(np.rint(xy[:, 1]), 0, 719)
        ev["p"][:n_rim] = lead
        ev["x"][n_rim:] = rng.integers(roi.x0_px, roi.x1_px, events - n_rim)
        ev["y"][n_rim:] = rng.integers(roi.y0_px, roi.y1_px, events - n_rim)
        ev["p"][n_rim:] = rng.integers(0, 2, events - n_rim)
        ev["t"] = np.sort(rng.integers(w * WINDOW_US, (w + 1) * WINDOW_US, events))
        out.append(ev)
    return out


def _time(tracker: Any, windows: list[np.ndarray]) -> np.ndarray:
    for ev in windows[:5]:
        tracker.update(ev)  # warm-up
    tracker.reset()
    times = []
    for ev in windows:
        t = time.perf_counter()
        tracker.update(ev)
        times.append(time.perf_counter() - t)
    return np.array(times)


def run(windows: int = 300, events: int = 20_000, progress: bool = True) -> dict[str, Any]:
    rig = load_rig()
    rest = rest_positions_px(rig)
    data = make_windows(rest, rig.roi, windows, events)
    figures: dict[str, Any] = {"windows": windows, "events_per_window": events, "markers": len(rest),
                               "window_ms": WINDOW_US / 1000}
    trackers = (("paper", Tracker(rest, TrackerParams())),
                ("paper-unguarded", Tracker(rest, TrackerParams(polarity_guard=None))),
                ("paper-no-follow-no-lag", Tracker(rest, TrackerParams(lopsided_ratio=None, lag_noise_px=None))),
                ("circle-fit", CircleFitTracker(rest, CircleFitParams())),
                ("evetac", EvetacTracker(rest, EvetacParams())))
    for name, tracker in trackers:
        if progress:
            print(f"timing the {name} tracker ...", flush=True)
        t = _time(tracker, data)
        final = np.linalg.norm(tracker.positions_px - rest, axis=1)
        figures[name] = {
            "median_ms": float(np.median(t) * 1e3), "p95_ms": float(np.percentile(t, 95) * 1e3),
            "median_window_fraction": float(np.median(t) / (WINDOW_US / 1e6)),
            "p95_window_fraction": float(np.percentile(t, 95) / (WINDOW_US / 1e6)),
            "final_displacement_px_median": float(np.median(final)),
        }
    figures["paper_over_unguarded_median"] = figures["paper"]["median_ms"] / figures["paper-unguarded"]["median_ms"]
    figures["paper_over_no_follow_no_lag_median"] = (figures["paper"]["median_ms"]
                                                     / figures["paper-no-follow-no-lag"]["median_ms"])
    figures["circle_fit_over_paper_median"] = figures["circle-fit"]["median_ms"] / figures["paper"]["median_ms"]
    figures["evetac_over_paper_median"] = figures["evetac"]["median_ms"] / figures["paper"]["median_ms"]
    figures["evetac_over_circle_fit_median"] = figures["evetac"]["median_ms"] / figures["circle-fit"]["median_ms"]
    return figures


def render(f: dict[str, Any]) -> None:
    rows = [[name, f"{f[name]['median_ms']:.3f}", f"{f[name]['p95_ms']:.3f}", f"{f[name]['median_window_fraction']:.4f}",
             f"{f[name]['p95_window_fraction']:.4f}"]
            for name in ("paper", "paper-unguarded", "paper-no-follow-no-lag", "circle-fit", "evetac")]
    emit(f"Marker tracking: {f['events_per_window']} events, {f['markers']} markers per {f['window_ms']:.0f} ms window",
         ["tracker", "median ms", "p95 ms", "median / window", "p95 / window"], rows,
         [f"target for the paper's tracker: <= 0.05 of the window; the paper's C++ tracker: 0.46. "
          f"the paper's tracker with its polarity guard / without: {f['paper_over_unguarded_median']:.2f} x; "
          f"with its neighbour-following and lag correction / without: {f['paper_over_no_follow_no_lag_median']:.2f} x; "
          f"circle-fit / paper: {f['circle_fit_over_paper_median']:.2f} x; Evetac (published) / paper: "
          f"{f['evetac_over_paper_median']:.2f} x; Evetac / circle-fit: {f['evetac_over_circle_fit_median']:.2f} x"])


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
