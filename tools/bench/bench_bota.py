"""Bota F/T driver reading its twin over a pty at 800 Hz, and the codec's decode rate.

Streaming (``--seconds``, default 10): a BotaTwin (sinc length 64 = 800 Hz,
460800 baud, device clock 2e9 us at power-on and -60 ppm) is served on a
pseudo-terminal by TwinServer; a BotaSensor connects, configures, starts and
records every sample's host stamp. Reported:
* frames lost (from the device timestamps against the 1250 us period; must be 0),
  CRC errors, resyncs;
* host timestamp jitter: host receive interval minus the nominal period [us],
  std and p99 of its magnitude (frames read in one chunk share a stamp);
* latency: host stamp minus the host time the twin took the sample [us]
  (includes 803 us on the line for 37 bytes at 460800 baud, and the twin
  server's 0.5 ms tick);
* CPU time of the whole process (driver reader + twin server) per wall second.

Codec alone: BotaReceiver.feed over ``--decode-frames`` pre-encoded frames in
``--chunk-bytes`` pieces; frames/s and that rate as a multiple of real time at 800 Hz.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np
from _common import bench_main, emit

from labrig.clock import CounterUnwrapper
from labrig.devices.bota import BotaSensor, BotaSettings
from labrig.devices.bota_protocol import BotaReceiver, FilterSetup, Frame, encode_frame
from labrig.devices.bota_stream import FtSample
from labrig.sim.bota_twin import BotaTwin, BotaTwinParams
from labrig.sim.serial_pty import TwinServer

SINC_LENGTH = 64
RATE_HZ = FilterSetup(SINC_LENGTH).sample_rate_hz
PERIOD_US = FilterSetup(SINC_LENGTH).period_us


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="streaming time (s)")
    ap.add_argument("--decode-frames", type=int, default=100_000, help="frames decoded by the codec alone")
    ap.add_argument("--chunk-bytes", type=int, default=4096, help="bytes per feed() in the codec run")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def stream(seconds: float) -> dict[str, Any]:
    params = BotaTwinParams(boot_delay_us=200_000, clock_offset_us=2_000_000_000, clock_drift_ppm=-60.0)
    twin = BotaTwin(params)
    samples: list[FtSample] = []
    with TwinServer({"ft": twin}) as server:
        while twin.mode != "run":
            time.sleep(0.01)
        sensor = BotaSensor(server.paths["ft"], clock=server.clock, on_sample=samples.append)
        try:
            t = time.perf_counter()
            sensor.connect(boot_timeout_s=5.0)
            sensor.configure(BotaSettings(sinc_length=SINC_LENGTH))
            connect_s = time.perf_counter() - t
            sensor.start()
            cpu0, wall0 = time.process_time(), time.perf_counter()
            time.sleep(seconds)
            cpu_s, wall_s = time.process_time() - cpu0, time.perf_counter() - wall0
            sensor.stop()
            stats = sensor.stats()
        finally:
            sensor.close()
        twin_error = server.error
    if twin_error is not None:
        raise SystemExit(f"twin server failed: {twin_error!r}")
    device = CounterUnwrapper(32)(np.array([s.t_device_us for s in samples], dtype=np.int64))
    host_us = np.array([s.t_host_ns for s in samples], dtype=np.int64) / 1000.0
    deviation = np.diff(host_us) - PERIOD_US
    latency = host_us - np.array([twin.host_us_of(float(d)) for d in device])
    return {
        "stream_seconds": seconds,
        "sample_rate_hz": RATE_HZ,
        "baud_rate": twin.line_baud_rate,
        "connect_configure_s": connect_s,
        "frames_received": stats.frames,
        "frames_expected": round((device[-1] - device[0]) / PERIOD_US) + 1 if len(device) else 0,
        "frames_lost": stats.frames_lost,
        "crc_errors": stats.crc_errors,
        "resyncs": stats.resyncs,
        "skipped_bytes": stats.skipped_bytes,
        "twin_samples_skipped": twin.samples_skipped,
        "host_interval_jitter_std_us": float(deviation.std()),
        "host_interval_jitter_p99_us": float(np.percentile(np.abs(deviation), 99)),
        "host_interval_jitter_max_us": float(np.abs(deviation).max()),
        "latency_p50_us": float(np.percentile(latency, 50)),
        "latency_p99_us": float(np.percentile(latency, 99)),
        "latency_max_us": float(latency.max()),
        "cpu_percent_process": 100.0 * cpu_s / wall_s,
    }


def decode_rate(n_frames: int, chunk_bytes: int) -> dict[str, Any]:
    rng = np.random.default_rng(0)
    values = rng.normal(0.0, 5.0, (n_frames, 6)).tolist()
    data = b"".join(
        encode_frame(Frame(0, tuple(v[:3]), tuple(v[3:]), (i * 1250) % 2**32, 25.0))  # type: ignore[arg-type]
        for i, v in enumerate(values)
    )
    receiver = BotaReceiver()
    t = time.perf_counter()
    for i in range(0, len(data), chunk_bytes):
        receiver.feed(data[i : i + chunk_bytes])
    elapsed = time.perf_counter() - t
    decoded = receiver.counters().frames
    if decoded != n_frames:
        raise SystemExit(f"codec decoded {decoded} of {n_frames} frames")
    rate = decoded / elapsed
    return {
        "decode_frames": decoded,
        "decode_chunk_bytes": chunk_bytes,
        "decode_rate_frames_per_s": rate,
        "decode_us_per_frame": 1e6 / rate,
        "decode_real_time_ratio_at_800hz": rate / RATE_HZ,
    }


def run(seconds: float = 10.0, decode_frames: int = 100_000, chunk_bytes: int = 4096, progress: bool = True) -> dict[str, Any]:
    if progress:
        print(f"  streaming {seconds:g} s at {RATE_HZ:g} Hz over a pty ...", file=sys.stderr, flush=True)
    figures = stream(seconds)
    if progress:
        print(f"  decoding {decode_frames} frames ...", file=sys.stderr, flush=True)
    figures.update(decode_rate(decode_frames, chunk_bytes))
    return figures


def render(f: dict[str, Any]) -> None:
    jitter_max = f"max {f['host_interval_jitter_max_us']:.0f} us"
    per_frame = f"{f['decode_us_per_frame']:.2f} us/frame"
    rows = [
        ["frames received / expected", f"{f['frames_received']} / {f['frames_expected']}", ""],
        ["frames lost", f"{f['frames_lost']}", "must be 0: " + ("yes" if f["frames_lost"] == 0 else "NO")],
        ["CRC errors / resyncs / skipped bytes", f"{f['crc_errors']} / {f['resyncs']} / {f['skipped_bytes']}", ""],
        ["host interval jitter std", f"{f['host_interval_jitter_std_us']:.0f} us", "receive interval - 1250 us"],
        ["host interval jitter p99 |.|", f"{f['host_interval_jitter_p99_us']:.0f} us", jitter_max],
        ["latency p50 / p99", f"{f['latency_p50_us']:.0f} / {f['latency_p99_us']:.0f} us", f"max {f['latency_max_us']:.0f} us"],
        ["CPU (driver + twin)", f"{f['cpu_percent_process']:.1f} %", "of one core"],
        ["connect + configure", f"{f['connect_configure_s']:.2f} s", "includes a 0.2 s twin boot"],
        ["codec decode rate", f"{f['decode_rate_frames_per_s'] / 1e3:.0f} k frames/s", per_frame],
        ["codec vs real time at 800 Hz", f"{f['decode_real_time_ratio_at_800hz']:.0f} x", ""],
    ]
    emit(
        f"Bota driver over a pty: {f['stream_seconds']:g} s at {f['sample_rate_hz']:g} Hz, {f['baud_rate']} baud",
        ["quantity", "value", "note"],
        rows,
        [f"codec: {f['decode_frames']} frames fed in {f['decode_chunk_bytes']}-byte chunks."],
    )


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
