"""The virtual rig's truth streams under each codec, side by side: writer CPU, reader CPU, bytes.

A virtual recording's truth (1 kHz marker positions, a depth map per solve) is most of its
bytes, and compressing it is most of its writer thread's CPU. This records one recording of
the paper campaign (``protocols/paper.toml``, by default index 3: the sphere 1.5 mm deep, one
of the heaviest) in virtual time, then writes its truth streams again with each codec, with
the streams' own chunking (:func:`labrig.sim.truth.truth_streams`), ``--repeat`` times
interleaved, and reads them back. Reported per codec (fastest run): process CPU seconds to
write (compression included) and to read, the file's megabytes, and the ratios to the codec
in use (:data:`labrig.recording.codecs.TRUTH_CODEC`).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import bench_main, emit

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_CODECS = "blosc2-lz4-shuffle,zstd,blosc2-lz4,bitshuffle-lz4,lz4,blosc2-zstd,gzip"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", type=int, default=3, help="index into the paper campaign (default 3)")
    ap.add_argument("--codecs", default=DEFAULT_CODECS, help="comma-separated codecs")
    ap.add_argument("--repeat", type=int, default=3, help="runs per codec, interleaved; the fastest is kept")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def run(recording: int = 3, codecs: str = DEFAULT_CODECS, repeat: int = 3, progress: bool = True) -> dict[str, Any]:
    import h5py
    import numpy as np

    from labrig.config import load_rig
    from labrig.indenters import load_indenters
    from labrig.protocol.files import load_campaign
    from labrig.protocol.virtual_campaign import recording_seed
    from labrig.protocol.virtual_run import record_virtual
    from labrig.recording.codecs import CODECS, TRUTH_CODEC, codec_kwargs
    from labrig.sim.truth import truth_streams
    from labrig.sim.world_process import prepare_contact_tables

    names = [c.strip() for c in codecs.split(",") if c.strip()]
    unknown = [c for c in names if c not in CODECS]
    if unknown:
        raise SystemExit(f"unknown codecs {unknown}; choose from {list(CODECS)}")
    rig, indenters = load_rig(), load_indenters()
    campaign = load_campaign(ROOT / "protocols" / "paper.toml", rig, indenters)
    plan = campaign.plans[recording]
    indenter = indenters[plan.spec.indenter]
    prepare_contact_tables(rig, indenter, [plan.spec.shear_direction_deg])
    with tempfile.TemporaryDirectory() as tmp:
        source = Path(tmp) / "source.h5"
        if progress:
            print(f"recording {plan.id} in virtual time ...", flush=True)
        record_virtual(plan.spec, source, rig, indenter, seed=recording_seed(campaign, plan))
        specs = truth_streams(len(rig.markers.rest_positions_mm()))
        arrays: dict[str, tuple[int, np.ndarray]] = {}
        with h5py.File(source) as f:
            for spec in specs:
                for column in spec.columns:
                    key = f"{spec.name}/{column.name}"  # truth streams live under /truth
                    arrays[key] = (spec.chunk_rows, f[key][...])
        raw_mb = sum(a.nbytes for _, a in arrays.values()) / 1e6
        best: dict[str, dict[str, float]] = {c: {"write_cpu_s": np.inf, "read_cpu_s": np.inf} for c in names}
        for _ in range(repeat):
            for codec in names:
                path = Path(tmp) / f"{codec}.h5"
                t = time.process_time()
                with h5py.File(path, "w") as f:
                    for key, (rows, a) in arrays.items():
                        f.create_dataset(key, data=a, chunks=(min(rows, max(len(a), 1)), *a.shape[1:]),
                                         **codec_kwargs(codec))
                write = time.process_time() - t
                t = time.process_time()
                with h5py.File(path) as f:
                    for key in arrays:
                        f[key][...]
                read = time.process_time() - t
                b = best[codec]
                b["write_cpu_s"], b["read_cpu_s"] = min(b["write_cpu_s"], write), min(b["read_cpu_s"], read)
                b["size_mb"] = path.stat().st_size / 1e6
    ref = best.get(TRUTH_CODEC)
    for b in best.values():
        if ref is not None:
            b["write_ratio_to_current"] = ref["write_cpu_s"] / b["write_cpu_s"]
            b["size_ratio_to_current"] = b["size_mb"] / ref["size_mb"]
    return {"recording": plan.id, "raw_mb": raw_mb, "truth_codec": TRUTH_CODEC, "codecs": best}


def render(figures: dict[str, Any]) -> None:
    rows = []
    for name, b in figures["codecs"].items():
        speed, size = b.get("write_ratio_to_current", float("nan")), b.get("size_ratio_to_current", float("nan"))
        rows.append([name + (" (in use)" if name == figures["truth_codec"] else ""), f"{b['write_cpu_s']:.3f}",
                     f"{b['read_cpu_s']:.3f}", f"{b['size_mb']:.1f}", f"{speed:.2f}x", f"{size:.2f}"])
    emit(f"Truth streams of {figures['recording']} ({figures['raw_mb']:.1f} MB raw), per codec",
         ["codec", "write CPU s", "read CPU s", "MB", "write speed vs in use", "bytes vs in use"], rows,
         ["Process CPU (compression threads included), fastest of the runs; one recording's truth streams."])


if __name__ == "__main__":
    bench_main(parse_args, run, render)
