"""The live view server's cost to the pipeline: `labrig run --live` with and without `--view-server`, side by side.

Setup (not timed): a simulated press (6 mm sphere, 1 mm deep, 0.5 mm shear at 3 mm/s; about 1.6 s) exported
to an EVT3 RAW file, replayed at 1x as the rig's camera (``[devices] camera = "raw"``), with the bundled depth
network. Measured, each in a fresh ``labrig run --live --json`` process, runs with and without the server
interleaved (off, on, off, on, ...): with the server a headless WebSocket client
(:mod:`labrig.testing.foxglove_client`) subscribes to every channel, so the server serializes and sends every
window (force field, net force, depth map, tracks). Windows of 10 ms (depth every window) and of 1 ms with
depth every 10 ms (1000 windows a second: the view thins them to its default 100 Hz, or with ``--view-hz 0``
serves every one).

Per setting (medians over the repeats): the pipeline's processing per window, its event-to-force latency p99,
its real-time factor and windows skipped, with and without the server, and their ratios (on / off); the
share of the pipeline's windows the client received and its message rate against the pipeline's window rate.

Stable keys: per setting ``processing_ratio``, ``latency_p99_ratio``, ``real_time_factor_ratio``,
``delivered_share``, ``rate_ratio``; headline ``view_server_processing_ratio`` (10 ms windows).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import bench_main, emit, raw_replay_rig

from labrig.config import load_rig
from labrig.testing.foxglove_client import FoxgloveClient

ROOT = Path(__file__).resolve().parents[2]
#: (name, labrig run options) of the window settings.
WINDOWS = (("10 ms", ["--window-ms", "10"]), ("1 ms, depth 10 ms", ["--window-ms", "1", "--depth-every-ms", "10"]),
           ("1 ms, depth 10 ms, every window", ["--window-ms", "1", "--depth-every-ms", "10", "--view-hz", "0"]))
TOPIC = "/labrig/force_field"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2, help="runs with and without the server per setting")
    ap.add_argument("--windows", choices=("10ms", "1ms", "both"), default="both",
                    help="10 ms windows, 1 ms windows with depth every 10 ms, or both")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def _live(args: list[str], serve: bool) -> dict[str, Any]:
    """One ``labrig run --live`` process; with ``serve``, a client subscribed for the whole run."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    extra = ["--view-server", "--view-port", "0"] if serve else []
    proc = subprocess.Popen([sys.executable, "-m", "labrig.cli", "run", "--live", *args, *extra, "--json"], cwd=ROOT,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    client = None
    if serve:
        assert proc.stderr is not None
        deadline = time.monotonic() + 300
        while client is None and time.monotonic() < deadline:
            line = proc.stderr.readline()
            if not line:
                break
            if found := re.search(r"ws://[\d.]+:\d+", line):
                client = FoxgloveClient(found.group(0)).start()
    stdout, stderr = proc.communicate(timeout=600)
    if client is not None:
        time.sleep(0.2)
        client.close()
    if proc.returncode != 0:
        raise RuntimeError(f"labrig run --live {' '.join(args)}: {stderr.strip().splitlines()[-1:]}")
    s: dict[str, Any] = json.loads(stdout)
    if client is not None:
        received = client.topics.get(TOPIC)
        s["client_messages"] = len(received.arrivals_s) if received else 0
        s["client_rate_hz"] = received.rate_hz() if received else 0.0
    return s


def _figures(runs: list[dict[str, Any]]) -> dict[str, float]:
    def median(key: str) -> float:
        return float(statistics.median(float(r[key]) for r in runs))

    out = {"processing_per_window_ms": median("processing_per_window_ms"), "latency_p99_ms": median("event_to_force_p99_ms"),
           "real_time_factor": median("real_time_factor"),
           "skipped_share": float(statistics.median(r["windows_skipped"] / max(r["windows_tracked"], 1) for r in runs))}
    if "client_messages" in runs[0]:
        def offered(r: dict[str, Any]) -> int:  # the windows the view's rate lets through to the server
            return int(r["windows_processed"]) - int(r["view_server"].get("windows_thinned", 0))

        out["delivered_share"] = float(statistics.median(r["client_messages"] / max(offered(r), 1) for r in runs))
        out["rate_ratio"] = float(statistics.median(
            r["client_rate_hz"] / max(offered(r) / r["stream_wall_s"], 1e-9) for r in runs))
        out["view_windows_skipped"] = float(statistics.median(r["view_server"]["windows_skipped"] for r in runs))
    return out


def run(repeats: int = 2, windows: str = "both", progress: bool = True) -> dict[str, Any]:
    wanted = [WINDOWS[i] for i, key in enumerate(("10ms", "1ms", "1ms")) if windows in (key, "both")]
    figures: dict[str, Any] = {"configs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        rig = load_rig()
        if progress:
            print("simulating the press and exporting it to EVT3 ...", flush=True)
        rig_file = raw_replay_rig(folder, rig)
        base = ["--rig", str(rig_file), "--calibration", str(rig.path.parent), "--seconds", "30"]
        for name, options in wanted:
            runs: dict[bool, list[dict[str, Any]]] = {False: [], True: []}
            for i in range(repeats):
                for serve in (False, True):
                    if progress:
                        print(f"live: {name}, server {'on' if serve else 'off'} ({i + 1}/{repeats}) ...", flush=True)
                    runs[serve].append(_live([*base, *options], serve))
            off, on = _figures(runs[False]), _figures(runs[True])
            figures["configs"][name] = {
                "off": off, "on": on,
                "processing_ratio": on["processing_per_window_ms"] / off["processing_per_window_ms"],
                "latency_p99_ratio": on["latency_p99_ms"] / off["latency_p99_ms"],
                "real_time_factor_ratio": on["real_time_factor"] / off["real_time_factor"],
                "delivered_share": on["delivered_share"], "rate_ratio": on["rate_ratio"]}
    headline = figures["configs"].get("10 ms")
    figures["view_server_processing_ratio"] = headline["processing_ratio"] if headline else None
    return figures


def render(f: dict[str, Any]) -> None:
    rows = []
    for name, c in f["configs"].items():
        for mode in ("off", "on"):
            m = c[mode]
            rows.append([f"{name} / server {mode}", f"{m['processing_per_window_ms']:.2f}", f"{m['latency_p99_ms']:.1f}",
                         f"{m['real_time_factor']:.2f}", f"{100 * m['skipped_share']:.1f}",
                         f"{100 * m['delivered_share']:.1f}" if "delivered_share" in m else "-",
                         f"{m['rate_ratio']:.2f}" if "rate_ratio" in m else "-"])
        rows.append([f"{name} / on : off", f"{c['processing_ratio']:.2f}", f"{c['latency_p99_ratio']:.2f}",
                     f"{c['real_time_factor_ratio']:.2f}", "", "", ""])
    emit("Live view server: labrig run --live with and without --view-server (a client subscribed), RAW replay 1x",
         ["windows / server", "processing ms/window", "event-to-force p99 ms", "RTF", "skipped %", "delivered %",
          "client rate / window rate"], rows,
         [f"view_server_processing_ratio {f['view_server_processing_ratio']} (10 ms windows, on / off; 1.0: no cost)"])


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
