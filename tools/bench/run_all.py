"""Run every benchmark and print all their figures (`make bench`).

Each benchmark prints its figures as ratios measured side by side in one run:
recording writer (real-time factor per codec) and reader (slice time / window),
RAW codec (decode rate / the evt3 package's), Metavision HDF5 (ECF decode /
EVT3 decode of the same events), GRBL streaming (character counting /
send-response), Bota reader (frames lost, jitter; decode / real
time), virtual rig (wall time / simulated time), camera clock under load (drift
error / 10 ppm, residual / 50 us), the virtual rig's time resolution against its CPU, its truth
codecs, virtual-time campaigns against through-driver ones. Full runs take tens of minutes on
2 cores; --quick shortens them. ``--baseline REV`` (a git revision, or a checkout's
folder) adds the benchmarks that compare two trees side by side (the virtual camera's event
sensor, the virtual-time stages), this tree against REV.
"""

from __future__ import annotations

import argparse
import importlib
import time
from typing import Any

from _common import print_json

BENCHES = (
    "bench_writer", "bench_reader", "bench_raw", "bench_ecf", "bench_grbl", "bench_bota", "bench_rig", "bench_live",
    "bench_campaign", "bench_groundtruth", "bench_training", "bench_tracker", "bench_depth_state", "bench_ifem",
    "bench_pipeline", "bench_live_latency", "bench_clock", "bench_view", "bench_sim_resolution", "bench_truth_codecs",
    "bench_virtual_campaign", "bench_control", "bench_view_server",
)
#: Benchmarks of this tree against a baseline tree (``--baseline``).
AGAINST_BASELINE = ("bench_sensor_replay", "bench_virtual_stages")
QUICK: dict[str, dict[str, Any]] = {
    "bench_writer": {"duration_s": 3.0, "repeat": 1, "codecs": "bitshuffle-lz4,lz4,gzip"},
    "bench_reader": {"duration_s": 20.0, "events": 15e6, "positions": 50, "naive_calls": 3},
    "bench_ecf": {"events": 1e6, "repeat": 1, "socket_events": 1e6},
    "bench_grbl": {"lines": 300, "repeat": 1},
    "bench_bota": {"seconds": 3.0},
    "bench_clock": {"drifts": "-500,500", "seeds": 3},
    "bench_sim_resolution": {"settings": "0.1,0.01 0.2,0.02 0.4,0.04", "recordings": "0"},
    "bench_truth_codecs": {"codecs": "blosc2-lz4-shuffle,zstd,gzip", "repeat": 1},
    "bench_virtual_campaign": {"recordings": 2, "skip_drivers": True},
    "bench_view_server": {"repeats": 1, "windows": "10ms"},
}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=",".join(BENCHES), help="comma-separated benchmarks to run")
    ap.add_argument("--quick", action="store_true", help="shorter runs (noisier figures)")
    ap.add_argument("--json", action="store_true", help="print all figures as JSON")
    ap.add_argument("--baseline", default=None,
                    help="also compare this tree with REV (a git revision or a labrig checkout's folder) side by side")
    args = ap.parse_args(argv)
    t = time.perf_counter()
    figures: dict[str, Any] = {}
    names = [b.strip() for b in args.only.split(",") if b.strip()]
    if args.baseline is not None and args.only == ap.get_default("only"):
        names += list(AGAINST_BASELINE)
    for name in names:
        if name not in BENCHES + AGAINST_BASELINE:
            raise SystemExit(f"unknown benchmark {name!r}; choose from {', '.join(BENCHES + AGAINST_BASELINE)}")
        if name in AGAINST_BASELINE and args.baseline is None:
            raise SystemExit(f"{name} compares two trees: give --baseline REV")
        module = importlib.import_module(name)
        kwargs = dict(QUICK.get(name, {})) if args.quick else {}
        if name in AGAINST_BASELINE:
            kwargs["baseline"] = args.baseline
        figures[name] = module.run(progress=not args.json, **kwargs)
        if not args.json:
            module.render(figures[name])
            print()
    if args.json:
        figures["bench_wall_s"] = time.perf_counter() - t
        print_json(figures)


if __name__ == "__main__":
    main()
