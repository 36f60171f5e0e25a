"""Shared helpers of the recording benchmarks: a replayed camera-packet pool, producers, output.

Event generation in numpy is not what the benchmarks measure, so a pool of
camera packets (``pool_s`` of a SyntheticRun whose idle/peak rates give the
requested mean rate) is made before timing, then replayed with time offsets.
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.recording import RecordingMetadata, RecordingResult, RecordingWriter
from labrig.testing.synthetic import SyntheticRun

#: Idle event rate as a fraction of the peak rate (SyntheticRun's default is 1 %).
IDLE_FRACTION = 0.01
#: Bytes of one event as produced: x, y (uint16), p (uint8), t_device_us (int64).
RAW_EVENT_BYTES = 13
#: Default cap on camera events put but not yet written (~100 ms at 10 Mev/s, the buffering a camera driver has).
MAX_IN_FLIGHT_EVENTS = 1 << 20

#: Side producers (F/T, CNC) may run this far ahead of the camera replay, in data time (us).
SIDE_LEAD_US = 10_000

Packet = tuple[npt.NDArray[np.uint16], npt.NDArray[np.uint16], npt.NDArray[np.uint8], npt.NDArray[np.int64], int]


class DataClock:
    """Host data time (us) the camera replay has reached; the other producers follow it."""

    def __init__(self) -> None:
        self.us = float("-inf")

    def wait_until(self, t_us: float) -> None:
        while t_us > self.us + SIDE_LEAD_US:
            time.sleep(0.001)


@dataclass(frozen=True)
class PacketPool:
    """Camera packets of ``duration_s`` of one synthetic run, replayable end to end."""

    run: SyntheticRun
    packets: list[Packet]
    duration_s: float

    @property
    def n_events(self) -> int:
        return sum(len(p[0]) for p in self.packets)

    def replay_events(self, duration_s: float) -> int:
        """Events in ``duration_s`` of replay (the packets :meth:`replay` yields)."""
        n = self.n_packets(duration_s)
        per_pool, rest = divmod(n, len(self.packets))
        return per_pool * self.n_events + sum(len(p[0]) for p in self.packets[:rest])

    def n_packets(self, duration_s: float) -> int:
        return round(duration_s * 1e6) // int(self.run.packet_us)

    def replay(self, writer: RecordingWriter, duration_s: float, max_in_flight: int = 0, clock: DataClock | None = None) -> None:
        """Put ``duration_s`` of packets into ``writer``, shifting device and host times per lap.

        ``max_in_flight`` > 0: wait while more events than that are put but not yet written,
        so the writer sees live-sized batches instead of the whole run at once.
        ``clock`` is advanced to each packet's host time, for the other producers.
        """
        clock = clock or DataClock()
        pool_us = round(self.duration_s * 1e6)
        rate = 1 + self.run.camera_clock.drift_ppm * 1e-6
        n = len(self.packets)
        put = 0
        for i in range(self.n_packets(duration_s)):
            lap, j = divmod(i, n)
            x, y, p, t_dev, t_host = self.packets[j]
            while max_in_flight and put - writer.stats["events"].rows_written > max_in_flight:
                time.sleep(0.0005)
            writer.put_events(x, y, p, t_dev + round(lap * pool_us * rate), t_host + lap * pool_us)
            put += len(x)
            clock.us = t_host + lap * pool_us
        clock.us = float("inf")


def make_pool(mean_rate_hz: float, pool_s: float = 1.0, seed: int = 0) -> PacketPool:
    """Pre-generate ``pool_s`` of camera packets whose mean event rate is ``mean_rate_hz``."""
    probe = SyntheticRun(duration_s=pool_s, peak_event_rate_hz=1.0, idle_event_rate_hz=0.0)
    starts = np.arange(0, int(pool_s * 1e6), probe.packet_us, dtype=np.float64)
    shape = float(probe.event_rate_hz(starts).mean())  # mean rate per 1 Hz of peak rate
    peak = mean_rate_hz / (shape + IDLE_FRACTION)
    run = SyntheticRun(duration_s=pool_s, peak_event_rate_hz=peak, idle_event_rate_hz=IDLE_FRACTION * peak, seed=seed)
    return PacketPool(run, list(run.camera_packets()), pool_s)


def record(
    path: Path,
    pool: PacketPool,
    duration_s: float,
    *,
    bulk_codec: str | None = None,
    queue_batches: int = 4096,
    max_in_flight: int = MAX_IN_FLIGHT_EVENTS,
) -> tuple[RecordingResult, float]:
    """Record ``duration_s`` (camera replay + F/T + CNC producer threads); (result, wall s open->close).

    F/T and CNC producers keep pace with the camera replay's data time (at most
    SIDE_LEAD_US ahead), so all streams arrive interleaved as in a live run.
    """
    side = SyntheticRun(duration_s=duration_s, seed=pool.run.seed)
    ft = list(side.ft_batches())
    cnc = list(side.cnc_samples())
    kwargs: dict[str, Any] = {"queue_batches": queue_batches}
    if bulk_codec is not None:
        kwargs["bulk_codec"] = bulk_codec
    metadata = RecordingMetadata(indenter="sphere", extra={"benchmark": True})

    clock = DataClock()
    t_start = time.perf_counter()
    writer = RecordingWriter(path, metadata, **kwargs).open()
    threads = [
        threading.Thread(target=pool.replay, args=(writer, duration_s, max_in_flight, clock), name="bench-camera"),
        threading.Thread(target=_put_all, args=(writer, clock, "ft", ft), name="bench-ft"),
        threading.Thread(target=_put_all, args=(writer, clock, "cnc", cnc), name="bench-cnc"),
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    result = writer.close()
    return result, time.perf_counter() - t_start


def _put_all(writer: RecordingWriter, clock: DataClock, stream: str, items: list[dict[str, Any]]) -> None:
    """Put items in data time alongside the camera replay (not all at once)."""
    for item in items:
        clock.wait_until(float(np.max(item["t_host_us"])))
        writer.put(stream, **item)


def raw_bytes(result: RecordingResult) -> int:
    """Uncompressed bytes of every row written (events dominate)."""
    from labrig.recording.schema import CORE_STREAMS

    itemsize = {s.name: sum(c.np_dtype.itemsize * int(np.prod(c.shape)) for c in s.columns) for s in CORE_STREAMS}
    return sum(itemsize[name] * rows for name, rows in result.rows.items())


def file_size(path: Path) -> int:
    return os.stat(path).st_size


def baseline_tree(root: Path, baseline: str | Path) -> Path:
    """The labrig tree ``--baseline`` names: a folder holding a checkout, else a git revision of ``root``'s
    repository (a commit, a tag, ``HEAD~3``), exported once per process into a temporary folder
    (``git archive``) that is removed at exit."""
    import atexit
    import shutil
    import subprocess
    import tempfile

    folder = Path(baseline)
    if folder.is_dir():
        if not (folder / "labrig" / "__init__.py").exists():
            raise SystemExit(f"--baseline {folder} is not a labrig checkout (no labrig/__init__.py there)")
        return folder.resolve()
    revision = str(baseline)
    if revision in _EXPORTED:
        return _EXPORTED[revision]
    commit = subprocess.run(["git", "-C", str(root), "rev-parse", "--verify", "--quiet", f"{revision}^{{commit}}"],
                            capture_output=True, text=True, check=False).stdout.strip()
    if not commit:
        raise SystemExit(f"--baseline {revision}: neither a folder nor a git revision of {root}; give a commit "
                         "(e.g. HEAD~1) or a labrig checkout's folder")
    out = Path(tempfile.mkdtemp(prefix=f"labrig-baseline-{commit[:10]}-"))
    atexit.register(shutil.rmtree, out, ignore_errors=True)
    archive = subprocess.Popen(["git", "-C", str(root), "archive", commit], stdout=subprocess.PIPE)
    subprocess.run(["tar", "-x", "-C", str(out)], stdin=archive.stdout, check=True)
    if archive.wait() != 0 or not (out / "labrig" / "__init__.py").exists():
        raise SystemExit(f"--baseline {revision}: could not export {commit[:10]} (git archive failed)")
    _EXPORTED[revision] = out
    return out


_EXPORTED: dict[str, Path] = {}


def trees_to_compare(root: Path, baseline: str | Path | None) -> dict[str, Path]:
    """This tree, and the baseline to compare it with (:func:`baseline_tree`: a checkout's folder or a git
    revision), by name."""
    trees = {"this_tree": root}
    if baseline is not None:
        trees["baseline"] = baseline_tree(root, baseline)
    return trees


def json_from_tree(tree: Path, script: Path, *args: str) -> Any:
    """Run a benchmark script's internal mode with ``tree``'s labrig (one thread of BLAS); its last line, as JSON."""
    import subprocess
    import sys

    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    done = subprocess.run([sys.executable, str(script), *args], env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{script.name} {' '.join(args)} with {tree} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def emit(title: str, columns: list[str], rows: list[list[str]], notes: list[str]) -> None:
    """Print an aligned table (rich) and its notes."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, title_justify="left")
    for i, name in enumerate(columns):
        table.add_column(name, justify="left" if i == 0 else "right")
    for row in rows:
        table.add_row(*row)
    console = Console(width=max(140, Console().width), highlight=False)
    console.print(table)
    for note in notes:
        console.print(note, soft_wrap=True)


def print_json(figures: dict[str, Any]) -> None:
    print(json.dumps(figures, indent=2, sort_keys=True))


def bench_main(
    parse_args: Callable[[list[str] | None], argparse.Namespace],
    run: Callable[..., dict[str, Any]],
    render: Callable[[dict[str, Any]], None],
    argv: list[str] | None = None,
) -> None:
    """The shared ``main`` of a benchmark: parse, run (timed), print a table or JSON."""
    args = vars(parse_args(argv))
    as_json = args.pop("json")
    t = time.perf_counter()
    figures = run(**args, progress=not as_json)
    figures["bench_wall_s"] = time.perf_counter() - t
    if as_json:
        print_json(figures)
    else:
        render(figures)


def raw_replay_rig(folder: Path, rig: Any) -> Path:
    """A rig file in ``folder`` whose camera replays, as an EVT3 RAW file at 1x, a simulated press of ``rig`` (6 mm
    sphere, 1 mm deep, 0.5 mm shear at 3 mm/s, seed 5): the live benchmarks' camera. Not timed."""
    import re

    from labrig.indenters import load_indenter
    from labrig.recording.convert import export_raw
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    h5, raw = folder / "press.h5", folder / "press.raw"
    sphere = load_indenter("sphere")
    tool = probing_path(rig, sphere, depth_mm=1.0, shear_mm=0.5, normal_speed_mm_s=3.0, shear_speed_mm_s=3.0,
                        wait_s=0.1)
    record_live(h5, rig, sphere, tool, seed=5, realtime=False)
    export_raw(h5, raw)
    text = re.sub(r'(?m)^camera\s*=\s*"sim"', 'camera = "raw"', rig.path.read_text(), count=1)
    rig_file = folder / "rig.toml"
    rig_file.write_text(re.sub(r'(?m)^camera_path\s*=\s*""', f'camera_path = "{raw}"', text, count=1))
    return rig_file
