"""Metavision HDF5 (ECF) decode side by side with EVT3 RAW decode of the same events; EVK4 twin socket throughput.

Setup (not timed): ``--events`` synthetic events over ``--duration-s`` (half isolated random
pixels, half runs of 2..40 neighbouring pixels on one row at one time, as the EVT3 benchmark
uses), written by labrig as a Metavision HDF5 file (ECF chunks of 16384 events, encoder mode
chosen per chunk) and as an EVT3 RAW file, in a temp dir deleted at the end.

Measured, median over ``--repeat`` interleaved runs (page cache warm):
* ``read_metavision_hdf5`` (h5py raw-chunk reads + labrig's ECF decoder) and ``read_raw`` on the
  EVT3 file, in Mev/s, and their ratio (ECF / EVT3); both outputs are checked equal to the input;
* ECF chunk decode alone (bytes already in memory), Mev/s; bytes per event of each format;
* twin socket: ``Evk4Twin.feed`` in ``--chunk-events`` chunks as fast as the FIFO takes them,
  ``SimCamera`` reading over the Unix socket; events delivered per second end to end (encode,
  socket, decode), with nothing dropped.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import bench_main, emit


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=float, default=4e6)
    ap.add_argument("--duration-s", type=float, default=20.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--socket-events", type=float, default=4e6)
    ap.add_argument("--chunk-events", type=int, default=20_000)
    ap.add_argument("--json", action="store_true")
    return ap.parse_args(argv)


def make_events(n: int, duration_s: float, seed: int = 1) -> np.ndarray:
    from labrig.eventtypes import EVENT_DTYPE

    rng = np.random.default_rng(seed)
    half = n // 2
    runs: list[np.ndarray] = []
    total = 0
    while total < n - half:
        k = int(rng.integers(2, 41))
        r = np.zeros(k, EVENT_DTYPE)
        r["x"] = int(rng.integers(0, 1280 - 41)) + np.arange(k)
        r["y"], r["p"], r["t"] = int(rng.integers(0, 720)), int(rng.integers(0, 2)), int(rng.integers(0, duration_s * 1e6))
        runs.append(r)
        total += k
    iso = np.zeros(half, EVENT_DTYPE)
    iso["x"], iso["y"], iso["p"] = rng.integers(0, 1280, half), rng.integers(0, 720, half), rng.integers(0, 2, half)
    iso["t"] = rng.integers(0, duration_s * 1e6, half)
    ev = np.concatenate([iso, *runs])[:n]
    return ev[np.argsort(ev["t"], kind="stable")]


def file_decode(events: np.ndarray, repeat: int, progress: bool) -> dict[str, Any]:
    from labrig.devices.ecf import decode_ecf_chunk, encode_ecf_chunk, read_metavision_hdf5, write_metavision_hdf5
    from labrig.devices.raw import read_raw, write_raw

    with tempfile.TemporaryDirectory(prefix="bench-ecf-") as tmp:
        h5, raw = Path(tmp) / "ev.hdf5", Path(tmp) / "ev.raw"
        if progress:
            print("  writing the HDF5 (ECF) and EVT3 files ...", file=sys.stderr, flush=True)
        write_metavision_hdf5(h5, events, attrs={"geometry": "1280x720"})
        write_raw(raw, events)
        assert np.array_equal(read_metavision_hdf5(h5).events, events), "ECF decode differs from the input"
        assert np.array_equal(read_raw(raw).events, events), "EVT3 decode differs from the input"
        chunks = [encode_ecf_chunk(events[a : a + 16384]) for a in range(0, events.size, 16384)]
        t_ecf, t_raw, t_chunk = [], [], []
        for _ in range(repeat):
            t = time.perf_counter()
            read_metavision_hdf5(h5)
            t_ecf.append(time.perf_counter() - t)
            t = time.perf_counter()
            read_raw(raw)
            t_raw.append(time.perf_counter() - t)
            t = time.perf_counter()
            for c in chunks:
                decode_ecf_chunk(c)
            t_chunk.append(time.perf_counter() - t)
        n = events.size
        ecf, evt3 = n / statistics.median(t_ecf) / 1e6, n / statistics.median(t_raw) / 1e6
        return {
            "events": n,
            "ecf_file_decode_mev_s": ecf,
            "evt3_file_decode_mev_s": evt3,
            "ecf_over_evt3_decode_ratio": ecf / evt3,
            "ecf_over_evt3_best_ratio": min(t_raw) / min(t_ecf),
            "ecf_chunk_decode_mev_s": n / statistics.median(t_chunk) / 1e6,
            "ecf_bytes_per_event": sum(len(c) for c in chunks) / n,
            "evt3_bytes_per_event": (raw.stat().st_size) / n,
        }


def socket_throughput(n_events: int, chunk_events: int, progress: bool) -> dict[str, Any]:
    from labrig.devices.camera import SimCamera
    from labrig.sim.evk4_twin import Evk4Twin

    if progress:
        print(f"  streaming {n_events:,} events through the twin socket ...", file=sys.stderr, flush=True)
    events = make_events(chunk_events * 50, 5.0, seed=3)
    span = int(events["t"].max()) + 1
    with tempfile.TemporaryDirectory(prefix="bench-twin-") as tmp:
        twin = Evk4Twin(Path(tmp) / "evk4.sock", max_buffered_events=1 << 21).start()
        cam = SimCamera(twin.path, queue_chunks=1 << 16).open()
        cam.start()
        twin.wait_connected(5.0)
        got = 0
        done = threading.Event()

        def consume() -> None:
            nonlocal got
            while not done.is_set() or got < n_events:
                chunk = cam.read(timeout_s=0.5)
                if chunk is None:
                    if done.is_set():
                        return
                    continue
                got += chunk.events.size

        reader = threading.Thread(target=consume)
        t = time.perf_counter()
        reader.start()
        fed = lap = 0
        while fed < n_events:
            for a in range(0, events.size, chunk_events):
                part = events[a : a + chunk_events].copy()
                part["t"] += lap * span
                while twin.buffered_events + part.size > twin.max_buffered_events:
                    time.sleep(0.0005)  # pace on the FIFO (a live world would drop instead)
                twin.feed(part)
                fed += part.size
                if fed >= n_events:
                    break
            lap += 1
        done.set()
        reader.join(60)
        elapsed = time.perf_counter() - t
        figures = {
            "socket_events": fed,
            "socket_events_received": got,
            "socket_mev_s": got / elapsed / 1e6,
            "socket_mb_s": twin.bytes_sent / elapsed / 1e6,
            "socket_dropped_events": twin.dropped_events + cam.stats.dropped_events,
            "socket_chunk_events": chunk_events,
        }
        cam.close()
        twin.close()
    return figures


def run(
    events: float = 4e6,
    duration_s: float = 20.0,
    repeat: int = 3,
    socket_events: float = 4e6,
    chunk_events: int = 20_000,
    progress: bool = True,
) -> dict[str, Any]:
    ev = make_events(int(events), duration_s)
    figures = file_decode(ev, repeat, progress)
    figures.update(socket_throughput(int(socket_events), chunk_events, progress))
    return figures


def render(f: dict[str, Any]) -> None:
    rows = [
        ["decode Metavision HDF5 (ECF)", f"{f['ecf_file_decode_mev_s']:.1f} Mev/s", f"{f['ecf_bytes_per_event']:.2f} B/event"],
        ["decode EVT3 RAW (same events)", f"{f['evt3_file_decode_mev_s']:.1f} Mev/s", f"{f['evt3_bytes_per_event']:.2f} B/event"],
        ["ratio ECF / EVT3", f"{f['ecf_over_evt3_decode_ratio']:.2f}", f"best-of {f['ecf_over_evt3_best_ratio']:.2f}"],
        ["ECF chunk decode only", f"{f['ecf_chunk_decode_mev_s']:.1f} Mev/s", "bytes in memory"],
        ["twin socket end to end", f"{f['socket_mev_s']:.1f} Mev/s", f"{f['socket_mb_s']:.0f} MB/s EVT3"],
        ["socket events dropped", f"{f['socket_dropped_events']}", "must be 0"],
    ]
    emit(
        f"ECF vs EVT3 decode, {f['events'] / 1e6:.1f} M events; EVK4 twin socket, {f['socket_events'] / 1e6:.1f} M events",
        ["quantity", "value", "note"],
        rows,
        [f"socket: chunks of {f['socket_chunk_events']} events, paced on the twin's FIFO; encode + Unix socket + decode."],
    )


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
