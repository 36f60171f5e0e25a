"""Event slicing of the recording reader: a 10 ms window out of a 60 s, ~50 Mev file.

Setup (not timed as a figure): ``--duration-s`` (60 s) of camera events at
``--events`` / duration (~0.83 Mev/s) plus F/T and CNC, written through
RecordingWriter with the default bulk codec from a pre-generated 1 s packet
pool replayed with time offsets, into a temp dir deleted at the end.

Measured, at ``--positions`` (200) random window starts t0 (host us):
* indexed: ``Recording.events_between(t0, t0 + 10_000)``; median and p95 time
  as a fraction of the 10 ms window. Target: well below 1.
* naive, side by side at the first ``--naive-calls`` positions: load the whole
  ``t_device_us`` column, map it to host time, take a boolean mask of the window,
  then read x/y/p over the masked rows. The ratio naive / indexed is what the
  time index buys. Both must return the same number of events.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import emit, file_size, make_pool, print_json, record

from labrig.recording import Recording
from labrig.recording.codecs import DEFAULT_BULK_CODEC

WINDOW_US = 10_000


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration-s", type=float, default=60.0, help="data time of the file (s)")
    ap.add_argument("--events", type=float, default=50e6, help="events in the file (about)")
    ap.add_argument("--positions", type=int, default=200, help="random windows for events_between")
    ap.add_argument("--naive-calls", type=int, default=10, help="windows read the naive way (slow)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the window positions")
    ap.add_argument("--tmp-dir", default=None, help="where the file is written (deleted after)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def naive_window(rec: Recording, t0: float, t1: float) -> int:
    """Events in [t0, t1) found by a mask over the whole (freshly loaded) time column."""
    t = rec.clock_model("camera").to_host_us_int(rec.column("events", "t_device_us"))
    mask = (t >= t0) & (t < t1)
    rows = np.flatnonzero(mask)
    if rows.size == 0:
        return 0
    i0, i1 = int(rows[0]), int(rows[-1]) + 1
    keep = mask[i0:i1]
    cols = [rec.column("events", c, i0, i1)[keep] for c in ("x", "y", "p")]
    return len(cols[0])


def run(
    duration_s: float = 60.0,
    events: float = 50e6,
    positions: int = 200,
    naive_calls: int = 10,
    seed: int = 1,
    tmp_dir: str | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    pool = make_pool(events / duration_s, 1.0)
    with tempfile.TemporaryDirectory(prefix="labrig-bench-reader-", dir=tmp_dir) as tmp:
        t = time.perf_counter()
        result, _ = record(Path(tmp) / "reader.h5", pool, duration_s)
        write_s = time.perf_counter() - t
        if result.dropped:
            raise SystemExit(f"the writer dropped rows {result.dropped}; the file is incomplete")
        if progress:
            print(f"  reader: wrote {result.rows['events']:,} events in {write_s:.1f} s", file=sys.stderr, flush=True)
        starts = np.random.default_rng(seed).uniform(0, duration_s * 1e6 - WINDOW_US, positions)
        with Recording(result.path) as rec:
            t = time.perf_counter()
            rec.event_index()
            index_s = time.perf_counter() - t
            rec.events_between(starts[0], starts[0] + WINDOW_US)  # warm-up: file metadata, caches
            indexed, counts = [], []
            for t0 in starts:
                t = time.perf_counter()
                counts.append(rec.events_between(t0, t0 + WINDOW_US).size)
                indexed.append(time.perf_counter() - t)
            naive, mismatches = [], 0
            for k, t0 in enumerate(starts[:naive_calls]):
                t = time.perf_counter()
                n = naive_window(rec, t0, t0 + WINDOW_US)
                naive.append(time.perf_counter() - t)
                mismatches += n != counts[k]
            n_events, n_bytes = rec.n_events, file_size(result.path)
    window_s = WINDOW_US / 1e6
    idx, nv = np.array(indexed), np.array(naive)
    same = idx[: len(nv)]
    return {
        "file_events": n_events,
        "file_duration_s": duration_s,
        "file_bytes": n_bytes,
        "bulk_codec": DEFAULT_BULK_CODEC,
        "file_write_s": write_s,
        "index_load_s": index_s,
        "window_us": WINDOW_US,
        "positions": positions,
        "events_per_window_median": float(np.median(counts)),
        "indexed_median_s": float(np.median(idx)),
        "indexed_p95_s": float(np.percentile(idx, 95)),
        "indexed_median_window_fraction": float(np.median(idx)) / window_s,
        "indexed_p95_window_fraction": float(np.percentile(idx, 95)) / window_s,
        "naive_calls": len(nv),
        "naive_median_s": float(np.median(nv)) if nv.size else None,
        "naive_median_window_fraction": float(np.median(nv)) / window_s if nv.size else None,
        "naive_over_indexed_median": float(np.median(nv) / np.median(same)) if nv.size else None,
        "naive_count_mismatches": mismatches,
    }


def render(f: dict[str, Any]) -> None:
    frac = f["indexed_median_window_fraction"], f["indexed_p95_window_fraction"]
    rows = [
        ["events_between (index)", f"{f['positions']}", f"{frac[0]:.4f}", f"{frac[1]:.4f}", "1"],
    ]
    if f["naive_calls"]:
        rows.append(
            [
                "naive (load column + mask)",
                f"{f['naive_calls']}",
                f"{f['naive_median_window_fraction']:.2f}",
                "",
                f"{f['naive_over_indexed_median']:.0f}",
            ]
        )
    emit(
        f"Reader: 10 ms windows out of {f['file_events'] / 1e6:.1f} Mev / {f['file_duration_s']:g} s "
        f"({f['bulk_codec']}, {f['file_bytes'] / 1e6:.0f} MB)",
        ["method", "windows", "median time / 10 ms", "p95 time / 10 ms", "median vs index"],
        rows,
        [
            f"median {f['events_per_window_median']:.0f} events per window; index load {f['index_load_s'] * 1e3:.1f} ms "
            f"(once); naive count mismatches: {f['naive_count_mismatches']}; file written in {f['file_write_s']:.1f} s."
        ],
    )


def main(argv: list[str] | None = None) -> None:
    args = vars(parse_args(argv))
    as_json = args.pop("json")
    figures = run(**args, progress=not as_json)
    if as_json:
        print_json(figures)
    else:
        render(figures)


if __name__ == "__main__":
    main()
