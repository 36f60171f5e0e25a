"""Recording writer at 10 Mev/s, for every bulk codec side by side.

Measured: ``--duration-s`` (default 10 s) of synthetic data, camera events at a
mean 10 million events/s plus 800 Hz F/T and 10 Hz CNC, put by three producer
threads into a RecordingWriter while its writer thread writes. Camera packets
are pre-generated (1 s pool, replayed with time offsets) so numpy event
generation is not timed. The camera producer is unpaced, but keeps at most
``--in-flight-events`` events put and not yet written, so the writer works on
live-sized batches (with no limit it would get the whole run in a few writes).

Per codec (median over ``--repeat`` interleaved runs):
* real-time factor = wall time open() -> close() returned / data time; target < 0.5;
* bytes per event = file size / events; compression ratio = raw row bytes / file size;
* dropped rows (must be 0).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import MAX_IN_FLIGHT_EVENTS, RAW_EVENT_BYTES, emit, file_size, make_pool, print_json, raw_bytes, record

from labrig.recording.codecs import CODECS, DEFAULT_BULK_CODEC

TARGET_RTF = 0.5


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration-s", type=float, default=10.0, help="data time per run (s)")
    ap.add_argument("--codecs", default=",".join(CODECS), help="comma-separated bulk codecs (default: all)")
    ap.add_argument("--rate-hz", type=float, default=10e6, help="mean camera event rate (default 10e6)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per codec, interleaved; the median is reported")
    ap.add_argument("--queue-batches", type=int, default=4096, help="RecordingWriter queue_batches")
    ap.add_argument("--in-flight-events", type=int, default=MAX_IN_FLIGHT_EVENTS, help="producer waits above this; 0: never")
    ap.add_argument("--tmp-dir", default=None, help="where the files are written (deleted after)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def run(
    duration_s: float = 10.0,
    codecs: str = ",".join(CODECS),
    rate_hz: float = 10e6,
    repeat: int = 3,
    queue_batches: int = 4096,
    in_flight_events: int = MAX_IN_FLIGHT_EVENTS,
    tmp_dir: str | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    names = [c.strip() for c in codecs.split(",") if c.strip()]
    unknown = [c for c in names if c not in CODECS]
    if unknown:
        raise SystemExit(f"unknown codecs {unknown}; choose from {list(CODECS)}")
    pool = make_pool(rate_hz, 1.0)
    expected = pool.replay_events(duration_s)
    runs: dict[str, list[dict[str, float]]] = {c: [] for c in names}
    with tempfile.TemporaryDirectory(prefix="labrig-bench-writer-", dir=tmp_dir) as tmp:
        for i in range(repeat):
            for codec in names:  # interleaved, so drifts of the machine hit every codec alike
                path = Path(tmp) / f"{codec}-{i}.h5"
                result, wall_s = record(
                    path, pool, duration_s, bulk_codec=codec, queue_batches=queue_batches, max_in_flight=in_flight_events
                )
                size = file_size(result.path)
                runs[codec].append(
                    {
                        "wall_s": wall_s,
                        "file_bytes": size,
                        "raw_bytes": raw_bytes(result),
                        "events": result.rows["events"],
                        "dropped_rows": sum(result.dropped.values()),
                    }
                )
                result.path.unlink()
                if progress:
                    print(f"  writer run {i + 1}/{repeat} {codec:15s} {wall_s:6.2f} s", file=sys.stderr, flush=True)
    figures: dict[str, Any] = {
        "data_duration_s": duration_s,
        "mean_event_rate_hz": expected / duration_s,
        "events_expected": expected,
        "raw_bytes_per_event": RAW_EVENT_BYTES,
        "queue_batches": queue_batches,
        "in_flight_events_max": in_flight_events,
        "repeat": repeat,
        "target_real_time_factor_max": TARGET_RTF,
        "default_bulk_codec": DEFAULT_BULK_CODEC,
        "codecs": {},
    }
    for codec, rs in runs.items():
        rtf = [r["wall_s"] / duration_s for r in rs]
        last = rs[-1]
        figures["codecs"][codec] = {
            "real_time_factor": statistics.median(rtf),
            "real_time_factor_min": min(rtf),
            "real_time_factor_max": max(rtf),
            "write_rate_events_per_s": last["events"] / statistics.median(r["wall_s"] for r in rs),
            "bytes_per_event": last["file_bytes"] / last["events"],
            "compression_ratio": last["raw_bytes"] / last["file_bytes"],
            "file_bytes": last["file_bytes"],
            "events_written": last["events"],
            "events_missing": expected - min(r["events"] for r in rs),
            "dropped_rows": max(r["dropped_rows"] for r in rs),
        }
    return figures


def render(f: dict[str, Any]) -> None:
    rows = []
    for codec, c in f["codecs"].items():
        ok = c["real_time_factor"] < f["target_real_time_factor_max"] and c["dropped_rows"] == 0 and not c["events_missing"]
        rows.append(
            [
                codec + (" (default)" if codec == f["default_bulk_codec"] else ""),
                f"{c['real_time_factor']:.3f}",
                f"{c['real_time_factor_min']:.2f}-{c['real_time_factor_max']:.2f}",
                f"{c['write_rate_events_per_s'] / 1e6:.1f}",
                f"{c['bytes_per_event']:.2f}",
                f"{c['compression_ratio']:.2f}",
                f"{c['dropped_rows']}",
                "yes" if ok else "NO",
            ]
        )
    emit(
        f"Writer: {f['data_duration_s']:g} s at {f['mean_event_rate_hz'] / 1e6:.2f} Mev/s + 800 Hz F/T + 10 Hz CNC "
        f"(median of {f['repeat']})",
        ["codec", "real-time factor", "range", "Mev/s written", "bytes/event", "compression", "dropped rows", "RTF<0.5"],
        rows,
        [
            f"real-time factor = wall(open..close) / data time; raw event = {f['raw_bytes_per_event']} B; "
            f"compression = raw row bytes / file bytes; queue_batches={f['queue_batches']}, "
            f"in-flight events <= {f['in_flight_events_max']}."
        ],
    )


def main(argv: list[str] | None = None) -> None:
    args = vars(parse_args(argv))
    as_json = args.pop("json")
    t = time.perf_counter()
    figures = run(**args)
    figures["bench_wall_s"] = time.perf_counter() - t
    if as_json:
        print_json(figures)
    else:
        render(figures)


if __name__ == "__main__":
    main()
