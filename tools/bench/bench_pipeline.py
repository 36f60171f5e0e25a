"""Whole pipeline: real-time factor per 10 ms window, per-stage latency and peak memory.

Setup (not timed): a simulated recording (6 mm sphere, 1 mm deep, 0.5 mm shear at 3 mm/s,
the paper's probing sequence; about 1.6 s and 0.4 M events), the surface operator (from the
disk cache, else built once: its build time is reported) and, for the network rows, depth
networks: the default (the newest trained one in ``models/`` if any, else the bundled SAE +
brightness network) and the bundled SAE-only baseline side by side, each built by the one
builder (``depth_sources.depth_source``) afresh for every pass; untrained U-Nets of
``--widths`` only where no network can be loaded (the cost does not depend on the weights).

Measured, per depth source and execution mode (serial: stages in turn; threads: tracking
of window k+1 while window k's depth and forces run): processing time per window, as a
share of the 10 ms window (the real-time factor; <= 1 keeps up, the issue aims at 0.5),
median and p95 over every window, the wall time of the whole stream over its duration, the
median latency of each stage, and the process's peak resident memory (ru_maxrss).
Also the event-count mode (20,000 events per window, the paper's evaluation), and the 1 kHz stretch:
1 ms windows, tracking and forces every window, the default network every 10 ms (its map kept in
between), serial on one core; its real-time factor is the mean processing per window over 1 ms
(the network's windows cost more than the others, and all of them must fit on average).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import resource
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from _common import bench_main, emit

from labrig.config import load_rig, rig_with
from labrig.indenters import load_indenter
from labrig.pipeline import depth_sources, ifem, run_setup, runtime
from labrig.recording import Recording
from labrig.sim.live import record_live
from labrig.sim.motion import probing_path

WINDOW_US = 10_000
#: The 1 kHz stretch's network parts when it runs in steps (the headline).
DEPTH_PARTS = 3


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--widths", default="16,32", help="untrained U-Net widths to time when models/ has no network")
    ap.add_argument("--repeat", type=int, default=2, help="passes over the recording per configuration (best kept)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _networks(folder: Path, widths: list[int]) -> list[tuple[str, Path]]:
    try:
        from labrig.models import bundled_model_path

        default = depth_sources.default_model_path()
        return [("model:" + default.stem, default), ("model:sae-only", bundled_model_path("sae-only"))]
    except Exception:
        pass
    try:
        from labrig.pipeline.depthnet import UNetConfig, build_unet, export_onnx
    except Exception:
        return []
    out = []
    for width in widths:
        path = folder / f"untrained-w{width}.onnx"
        export_onnx(build_unet(UNetConfig(width=width)), path, card={"scale_mm": 2.5, "window_ms": 10.0,
                                                                      "note": "untrained, for timing only"})
        out.append((f"untrained U-Net w{width}", path))
    return out


@contextlib.contextmanager
def _one_core(pin: bool) -> Iterator[None]:
    """With ``pin``: this thread (and the threads it starts) on one CPU, the one it runs on, until the end."""
    if not pin or not hasattr(os, "sched_setaffinity"):
        yield
        return
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {min(before)})
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def _measure(setup: run_setup.PipelineSetup, rec: Recording, depth: str | Path, concurrent: bool,
             repeat: int, window_events: int | None = None, window_us: int = WINDOW_US,
             depth_every_us: int | None = None, reference: bool = False, depth_lane: bool = False,
             one_core: bool = False, depth_parts: int | None = None) -> dict[str, Any]:
    """``depth``: "truth" or a network's path; a fresh source each pass (a network may carry state);
    ``reference``: the per-window reference path (``Pipeline(reference=True)``); ``depth_lane``: the network in
    its own thread; ``one_core``: the run held to one core (the lane's thread shares it); ``depth_parts``: the network
    in steps in the windows' thread, cut in this many parts."""
    best: dict[str, Any] | None = None
    for _ in range(repeat):
        source = depth_sources.depth_source("truth" if depth == "truth" else "model", setup, rec,
                                            None if depth == "truth" else depth, threads=1)
        with _one_core(one_core):
            pipe = runtime.Pipeline(setup, source, depth_every_us=depth_every_us, reference=reference,
                                    depth_lane=depth_lane, depth_parts=depth_parts)
            pipe.warm_up()
            start = time.perf_counter()
            results = list(pipe.run(rec, window_us=None if window_events else window_us, window_events=window_events,
                                    concurrent=concurrent))
            wall = time.perf_counter() - start
            pipe.close()
        span_us = np.array([max(r.t1_us - r.t0_us, 1) for r in results], float)
        busy = np.array([sum(r.seconds.values()) for r in results])
        duration_s = (results[-1].t1_us - results[0].t0_us) / 1e6
        figures = {
            "windows": len(results),
            "processing_ms_median": float(np.median(busy) * 1e3),
            "processing_ms_p95": float(np.percentile(busy, 95) * 1e3),
            "processing_ms_mean": float(np.mean(busy) * 1e3),
            "rtf_mean": float(np.mean(busy) / (np.median(span_us) / 1e6)),
            "rtf_median": float(np.median(busy / span_us * 1e6)),
            "rtf_p95": float(np.percentile(busy / span_us * 1e6, 95)),
            "rtf_p99": float(np.percentile(busy / span_us * 1e6, 99)),
            "stream_wall_over_duration": wall / duration_s,
            "stage_ms_median": {k: float(np.median([r.seconds[k] for r in results]) * 1e3) for k in runtime.STAGES},
            "window_ms_median": float(np.median(span_us) / 1e3),
        }
        if best is None or figures["stream_wall_over_duration"] < best["stream_wall_over_duration"]:
            best = figures
    assert best is not None
    return best


def run(widths: str = "16,32", repeat: int = 2, progress: bool = True) -> dict[str, Any]:
    rig = load_rig()
    linear = rig_with(rig, {"sim.mechanics.stiffening": 0.0})
    sphere = load_indenter("sphere")
    figures: dict[str, Any] = {"window_ms": WINDOW_US / 1000, "configs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        path = folder / "sphere.h5"
        if progress:
            print("simulating the recording ...", flush=True)
        tool = probing_path(linear, sphere, depth_mm=1.0, shear_mm=0.5, normal_speed_mm_s=3.0, shear_speed_mm_s=3.0,
                            wait_s=0.1)
        record_live(path, linear, sphere, tool, seed=5, realtime=False)
        start = time.perf_counter()
        op = ifem.build_surface_operator(rig)
        figures["operator_load_s"] = time.perf_counter() - start
        figures["operator_build_s"] = op.build_seconds
        figures["operator_nodes"] = len(op.node_xy_mm)
        figures["rss_before_mb"] = _peak_rss_mb()
        networks = _networks(folder, [int(w) for w in widths.split(",") if w.strip()])
        with Recording(path) as rec:
            setup = run_setup.setup_for_recording(rec, calibration_dir=None)
            figures["events"] = rec.n_events
            sources: list[tuple[str, str | Path]] = [("truth", "truth"), *networks]
            for name, source in sources:
                for concurrent in (False, True):
                    key = f"{name} / {'threads' if concurrent else 'serial'}"
                    if progress:
                        print(f"timing {key} ...", flush=True)
                    figures["configs"][key] = _measure(setup, rec, source, concurrent, repeat)
            if progress:
                print("timing 20,000-event windows ...", flush=True)
            figures["configs"]["truth / threads / 20k events"] = _measure(setup, rec, sources[0][1], True, repeat,
                                                                          window_events=20_000)
            name, network = sources[1]
            for reference, lane, pin, parts in ((True, False, False, None), (False, False, False, None),
                                                (False, False, True, DEPTH_PARTS), (False, True, True, None),
                                                (False, True, False, None)):
                key = (f"{name} / serial / 1 ms, depth 10 ms{' / reference path' if reference else ''}"
                       f"{(' / depth lane, ' + ('one core' if pin else 'two cores')) if lane else ''}"
                       f"{f' / depth in {parts} steps, one core' if parts else ''}")
                if progress:
                    print(f"timing {key} ...", flush=True)
                figures["configs"][key] = _measure(setup, rec, network, False, repeat, window_us=1_000,
                                                   depth_every_us=10_000, reference=reference, depth_lane=lane,
                                                   one_core=pin, depth_parts=parts)
            key = f"{name} / serial / reference path"
            if progress:
                print(f"timing {key} ...", flush=True)
            figures["configs"][key] = _measure(setup, rec, network, False, repeat, reference=True)
    figures["peak_rss_mb"] = _peak_rss_mb()
    figures.update(headline(figures["configs"], name))
    return figures


def headline(configs: dict[str, Any], network: str) -> dict[str, float]:
    """The headline figures (stable keys): the 1 kHz stretch's mean and p99 processing per 1 ms window (one core, the
    network in :data:`DEPTH_PARTS` steps, one per window), the whole pipeline's median per 10 ms window (the default
    network, serial); ``_serial``: the 1 kHz stretch with the whole network in the window it is due; ``_lane_one_core``
    and ``_two_cores``: with the network in a thread of its own; ``_reference``: the reference path (every window's
    depth-map work redone), all in the same run."""
    stretch = f"{network} / serial / 1 ms, depth 10 ms"
    fast, ref = f"{stretch} / depth in {DEPTH_PARTS} steps, one core", f"{stretch} / reference path"
    two, lane = f"{stretch} / depth lane, two cores", f"{stretch} / depth lane, one core"
    out = {"rtf_1ms_mean_serial": configs[stretch]["rtf_mean"], "rtf_1ms_p99_serial": configs[stretch]["rtf_p99"],
           "rtf_1ms_mean_lane_one_core": configs[lane]["rtf_mean"], "rtf_1ms_p99_lane_one_core": configs[lane]["rtf_p99"],
           "rtf_1ms_mean_two_cores": configs[two]["rtf_mean"], "rtf_1ms_p99_two_cores": configs[two]["rtf_p99"]}
    pairs = (("", fast, f"{network} / serial"), ("_reference", ref, f"{network} / serial / reference path"))
    for suffix, one_ms, ten_ms in pairs:
        out[f"rtf_1ms_mean{suffix}"] = configs[one_ms]["rtf_mean"]
        out[f"rtf_1ms_p99{suffix}"] = configs[one_ms]["rtf_p99"]
        out[f"rtf_10ms_median{suffix}"] = configs[ten_ms]["rtf_median"]
    return out


def render(f: dict[str, Any]) -> None:
    rows = []
    for key, c in f["configs"].items():
        s = c["stage_ms_median"]
        rows.append([key, str(c["windows"]), f"{c['window_ms_median']:.1f}", f"{c['processing_ms_median']:.2f}",
                     f"{c['rtf_median']:.3f}", f"{c['rtf_p95']:.3f}", f"{c['stream_wall_over_duration']:.3f}",
                     *(f"{s[k]:.3f}" for k in runtime.STAGES)])
    emit("Pipeline per window (processing / window length = real-time factor; stage medians in ms)",
         ["depth / mode", "windows", "window ms", "proc ms", "RTF med", "RTF p95", "wall / dur", *runtime.STAGES], rows,
         [*(f"{key}: mean {c['processing_ms_mean']:.3f} ms per {c['window_ms_median']:.0f} ms window, "
            f"mean RTF {c['rtf_mean']:.2f} (the 1 kHz stretch: real time on one core needs <= 1)"
            for key, c in f["configs"].items() if "1 ms" in key),
          f"{f['events']:,} events; surface operator: {f['operator_nodes']} nodes, built in "
          f"{f['operator_build_s']:.1f} s once, loaded in {f['operator_load_s'] * 1e3:.0f} ms; peak RSS "
          f"{f['peak_rss_mb']:.0f} MB ({f['rss_before_mb']:.0f} MB before the networks). Target RTF <= 1 (aim 0.5).",
          "Headline (default path / reference path, same run): " + ", ".join(
              f"{k} {f[k]:.3f} / {f[k + '_reference']:.3f}" for k in ("rtf_1ms_mean", "rtf_1ms_p99", "rtf_10ms_median"))
          + f" (targets 1.0, 2.0, 0.20; aims 0.5, 1.0, 0.10; the 1 kHz stretch with the network in {DEPTH_PARTS} steps); "
          f"with the whole network in its due window: mean {f['rtf_1ms_mean_serial']:.3f}, p99 "
          f"{f['rtf_1ms_p99_serial']:.3f}; in a thread on the same core: mean {f['rtf_1ms_mean_lane_one_core']:.3f}, p99 "
          f"{f['rtf_1ms_p99_lane_one_core']:.3f}; the lane on a second "
          f"core: mean {f['rtf_1ms_mean_two_cores']:.3f}, p99 {f['rtf_1ms_p99_two_cores']:.3f}"])


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
