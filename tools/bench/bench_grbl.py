"""GRBL streaming over a pty: character counting against plain send-response, in lines per second.

Setup (not timed): a GrblTwin (1.1h, 115200 baud, 250 us to parse a line; rates 6000 mm/min,
accelerations 5000 mm/s**2 so motion never limits the rate) is served on a pseudo-terminal by
TwinServer; a Grbl driver connects (soft reset, status, $$).

Measured: ``Grbl.stream`` of ``--lines`` (1000) short collinear G1 lines (0.02 mm each, about 9
bytes, the feed on the first line only), from the first write to the last ``ok``, once with
character counting (up to 127 unanswered bytes in GRBL's RX buffer) and once with send-response
(one line in flight), interleaved over ``--repeat`` runs (median reported). Each run is repeated at
every ``--latencies-us`` link latency: 0 is a bare UART on a pty; 1000 us is what a USB-serial
bridge adds each way (an Uno's USB chip; an FTDI at its default latency timer adds 16 ms).
Reported per latency: lines/s of both modes, their ratio (target >= 3), the most bytes in
flight, and RX overflows seen by the twin (must be 0). The baud-rate bound is 11520 bytes/s
divided by the mean line length.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from typing import Any

from _common import bench_main, emit

from labrig.devices.grbl import Grbl
from labrig.sim.grbl_twin import GrblTwin
from labrig.sim.serial_pty import TwinServer

TARGET_RATIO = 3.0
SETTINGS = {110: 6000, 111: 6000, 112: 3000, 120: 5000, 121: 5000, 122: 5000}
STEP_MM = 0.02
FEED_MM_MIN = 6000


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lines", type=int, default=1000, help="G1 lines per stream")
    ap.add_argument("--repeat", type=int, default=3, help="runs per mode and latency, interleaved; the median is reported")
    ap.add_argument("--latencies-us", default="0,1000", help="comma-separated link latencies to model, us each way")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def program(n: int) -> list[str]:
    lines = [f"G1X-{STEP_MM * i:.2f}" for i in range(1, n + 1)]
    lines[0] += f"F{FEED_MM_MIN}"
    return lines


def one_run(lines: list[str], mode: str, latency_us: float) -> dict[str, float]:
    twin = GrblTwin(settings=SETTINGS, link_latency_us=latency_us)
    with TwinServer({"grbl": twin}) as server:
        grbl = Grbl(server.paths["grbl"], poll_hz=0)
        try:
            grbl.connect()
            t = time.perf_counter()
            result = grbl.stream(lines, mode=mode, timeout_s=10.0)
            wall_s = time.perf_counter() - t
            end = grbl.wait_idle(timeout_s=30.0)
        finally:
            grbl.close()
        error = server.error
    if error is not None:
        raise SystemExit(f"twin server failed: {error!r}")
    expected = -STEP_MM * len(lines)
    if abs(end.position_mm[0] - expected) > 1e-6:
        raise SystemExit(f"{mode}: ended at X{end.position_mm[0]}, expected X{expected}")
    return {
        "lines_per_s": len(lines) / wall_s,
        "wall_s": wall_s,
        "max_in_flight_bytes": result.max_in_flight_bytes,
        "rx_overflow_bytes": twin.rx_overflow_bytes,
        "twin_max_rx_fill_bytes": twin.max_rx_fill_bytes,
    }


def run(lines: int = 1000, repeat: int = 3, latencies_us: str = "0,1000", progress: bool = True) -> dict[str, Any]:
    prog = program(lines)
    mean_bytes = sum(len(line) + 1 for line in prog) / len(prog)
    figures: dict[str, Any] = {
        "lines": lines,
        "repeat": repeat,
        "baud_rate": 115200,
        "mean_line_bytes": mean_bytes,
        "baud_limit_lines_per_s": 11520.0 / mean_bytes,
        "target_speedup_ratio_min": TARGET_RATIO,
        "runs": [],
    }
    for latency in [float(v) for v in latencies_us.split(",") if v.strip()]:
        per_mode: dict[str, list[dict[str, float]]] = {"count": [], "send-response": []}
        for i in range(repeat):
            for mode in per_mode:  # interleaved, so drifts of the machine hit both modes alike
                r = one_run(prog, mode, latency)
                per_mode[mode].append(r)
                if progress:
                    print(
                        f"  latency {latency:g} us run {i + 1}/{repeat} {mode:14s} {r['lines_per_s']:7.0f} lines/s",
                        file=sys.stderr,
                        flush=True,
                    )
        count = statistics.median(r["lines_per_s"] for r in per_mode["count"])
        single = statistics.median(r["lines_per_s"] for r in per_mode["send-response"])
        figures["runs"].append(
            {
                "link_latency_us": latency,
                "count_lines_per_s": count,
                "send_response_lines_per_s": single,
                "speedup_ratio": count / single,
                "count_max_in_flight_bytes": max(r["max_in_flight_bytes"] for r in per_mode["count"]),
                "twin_max_rx_fill_bytes": max(r["twin_max_rx_fill_bytes"] for rs in per_mode.values() for r in rs),
                "rx_overflow_bytes": sum(r["rx_overflow_bytes"] for rs in per_mode.values() for r in rs),
            }
        )
    return figures


def render(f: dict[str, Any]) -> None:
    rows = [
        [
            f"{r['link_latency_us']:g}",
            f"{r['count_lines_per_s']:.0f}",
            f"{r['send_response_lines_per_s']:.0f}",
            f"{r['speedup_ratio']:.2f}",
            f"{r['count_max_in_flight_bytes']}",
            f"{r['rx_overflow_bytes']}",
            "yes" if r["speedup_ratio"] >= f["target_speedup_ratio_min"] and r["rx_overflow_bytes"] == 0 else "NO",
        ]
        for r in f["runs"]
    ]
    emit(
        f"GRBL streaming over a pty: {f['lines']} G1 lines, {f['baud_rate']} baud (median of {f['repeat']})",
        ["link latency us", "counting lines/s", "send-response lines/s", "ratio", "max in flight B", "RX overflow B", "ratio>=3"],
        rows,
        [
            f"mean line {f['mean_line_bytes']:.1f} bytes with its newline; the baud rate alone allows "
            f"{f['baud_limit_lines_per_s']:.0f} lines/s. Latency is added by the twin each way (USB-serial bridge)."
        ],
    )


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
