"""Run the recording benchmarks (writer, then reader) and print all their figures.

Targets: writer real-time factor < 0.5 at 10 Mev/s with 0 dropped rows
(bench_writer.py); a 10 ms event slice in well under 10 ms (bench_reader.py).
Defaults are the full runs (a few minutes on 2 cores); flags shorten them.
"""

from __future__ import annotations

import argparse
import time

import bench_reader
import bench_writer
from _common import print_json


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--writer-duration-s", type=float, default=10.0, help="writer: data time per run (s)")
    ap.add_argument("--codecs", default=None, help="writer: comma-separated codecs (default: all)")
    ap.add_argument("--repeat", type=int, default=3, help="writer: runs per codec")
    ap.add_argument("--reader-duration-s", type=float, default=60.0, help="reader: data time of the file (s)")
    ap.add_argument("--reader-events", type=float, default=50e6, help="reader: events in the file (about)")
    ap.add_argument("--positions", type=int, default=200, help="reader: random 10 ms windows")
    ap.add_argument("--naive-calls", type=int, default=10, help="reader: windows read the naive way")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args(argv)

    t = time.perf_counter()
    writer_kwargs = {"codecs": args.codecs} if args.codecs else {}
    writer = bench_writer.run(duration_s=args.writer_duration_s, repeat=args.repeat, progress=not args.json, **writer_kwargs)
    reader = bench_reader.run(
        duration_s=args.reader_duration_s,
        events=args.reader_events,
        positions=args.positions,
        naive_calls=args.naive_calls,
        progress=not args.json,
    )
    if args.json:
        print_json({"writer": writer, "reader": reader, "bench_wall_s": time.perf_counter() - t})
    else:
        bench_writer.render(writer)
        print()
        bench_reader.render(reader)


if __name__ == "__main__":
    main()
