"""Virtual rig: real-time factor of the standard probing sequence on one core.

Simulated: the sphere indenter on the default rig, the paper's sequence from
motion.probing_path (approach, normal down ``--depth-mm`` (1.5 mm) at 1.5 mm/s,
wait 0.3 s, shear ``--shear-mm`` (+1 mm), wait, shear back, wait, normal up,
retract; ~4.9 s), advanced in ``--chunk-ms`` (100 ms) calls of
``VirtualRig.advance`` as a device twin serving it live would, with chunk ends
also at the phase boundaries so each chunk's wall time belongs to one phase.
Single-threaded: the script restarts itself with OPENBLAS_NUM_THREADS=1 (and
OMP/MKL) unless already set (BLAS reads it when numpy loads); no worker
processes. Callers of run() set it themselves.

Measured (median over ``--repeat`` runs, each on a fresh VirtualRig):
* real-time factor = wall time of the advance calls / simulated time;
  required <= 1.0, aimed <= 0.5; overall and per phase; also the CPU-time
  factor (process time / simulated time), which other load on a shared
  machine disturbs less;
* events (count, Mev per simulated second), renders and solves per simulated
  second, and per-call costs of Renderer.render, EventSensor.step,
  VirtualRig.solve and of its ContactTable.fields lookup (wrapped timers);
* memory: peak RSS of the process (ru_maxrss) and its growth over the first
  timed run; with ``--tracemalloc`` also the tracemalloc peak of one extra,
  untimed run (Python and numpy allocations of the simulation alone).

Not in the real-time factor, reported apart: the contact table's load from the
disk cache (warmed first: built if missing), its recorded build time, a cold
build into a temp cache with ``--cold``, and the VirtualRig construction.
"""

from __future__ import annotations

import argparse
import gc
import os
import resource
import statistics
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from typing import Any

from _common import bench_main, emit

from labrig.config import load_rig
from labrig.indenters import load_indenter
from labrig.physics.mechanics import ContactTable
from labrig.sim.motion import probing_path
from labrig.sim.rig import VirtualRig
from labrig.sim.truth_config import true_contact_table

REQUIRED_RTF = 1.0
TARGET_RTF = 0.5


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--indenter", default="sphere", help="indenter name (protocols/indenters.toml)")
    ap.add_argument("--depth-mm", type=float, default=1.5, help="indentation depth (mm)")
    ap.add_argument("--shear-mm", type=float, default=1.0, help="shear travel (mm)")
    ap.add_argument("--seed", type=int, default=1, help="VirtualRig seed")
    ap.add_argument("--chunk-ms", type=float, default=100.0, help="simulated time per advance call (ms)")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs; the median is reported")
    ap.add_argument("--cold", action="store_true", help="also build the contact table from scratch (slow)")
    ap.add_argument("--tracemalloc", action="store_true", help="one extra untimed run under tracemalloc")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


class _Timer:
    """Wall time and calls of a wrapped callable."""

    def __init__(self) -> None:
        self.s = 0.0
        self.calls = 0

    def wrap(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.s += time.perf_counter() - t
                self.calls += 1

        return timed


def _maxrss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _chunk_ends(path: Any, chunk_us: int) -> list[int]:
    total = int(path.duration_us)
    ends = set(range(chunk_us, total, chunk_us)) | {int(t1) for _, _, t1 in path.phases} | {total}
    return sorted(t for t in ends if 0 < t <= total)


def _phase_of(path: Any, t_end_us: int) -> int:
    for i, (_, t0, t1) in enumerate(path.phases):
        if t0 < t_end_us <= int(t1):
            return i
    return len(path.phases) - 1


def simulate(rig: Any, indenter: Any, table: ContactTable, path: Any, seed: int, chunk_us: int) -> dict[str, Any]:
    """One timed run of the whole path on a fresh VirtualRig."""
    t = time.perf_counter()
    vr = VirtualRig(rig, indenter, seed=seed, table=table)
    init_s = time.perf_counter() - t
    timers = {name: _Timer() for name in ("render", "sensor_step", "solve", "table_lookup")}
    vr.renderer.render = timers["render"].wrap(vr.renderer.render)  # type: ignore[method-assign]
    vr.sensor.step = timers["sensor_step"].wrap(vr.sensor.step)  # type: ignore[method-assign]
    vr.solve = timers["solve"].wrap(vr.solve)  # type: ignore[method-assign]
    fields = table.fields
    table.fields = timers["table_lookup"].wrap(fields)  # type: ignore[method-assign]
    n_phases = len(path.phases)
    phase_wall = [0.0] * n_phases
    phase_cpu = [0.0] * n_phases
    phase_events = [0] * n_phases
    events = renders = solves = 0
    rss0 = _maxrss_mib()
    try:
        start = time.perf_counter()
        for t_end in _chunk_ends(path, chunk_us):
            t, c = time.perf_counter(), time.process_time()
            out = vr.advance(t_end, path)
            dt = time.perf_counter() - t
            i = _phase_of(path, t_end)
            phase_wall[i] += dt
            phase_cpu[i] += time.process_time() - c
            phase_events[i] += out.events.size
            events += out.events.size
            renders += out.renders
            solves += len(out.solves)
        wall_s = time.perf_counter() - start
    finally:
        table.fields = fields  # type: ignore[method-assign]
    return {
        "init_s": init_s,
        "wall_s": wall_s,
        "events": events,
        "renders": renders,
        "solves": solves,
        "phase_wall_s": phase_wall,
        "phase_cpu_s": phase_cpu,
        "phase_events": phase_events,
        "timers": {name: (tm.s, tm.calls) for name, tm in timers.items()},
        "rss_growth_mib": _maxrss_mib() - rss0,
    }


def traced_peak_mib(rig: Any, indenter: Any, table: ContactTable, path: Any, seed: int, chunk_us: int) -> float:
    """tracemalloc peak (MiB) of constructing a VirtualRig and running the path (slower: not timed)."""
    tracemalloc.start()
    try:
        vr = VirtualRig(rig, indenter, seed=seed, table=table)
        for t_end in _chunk_ends(path, chunk_us):
            vr.advance(t_end, path)
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def run(
    indenter: str = "sphere",
    depth_mm: float = 1.5,
    shear_mm: float = 1.0,
    seed: int = 1,
    chunk_ms: float = 100.0,
    repeat: int = 3,
    cold: bool = False,
    tracemalloc: bool = False,
    progress: bool = True,
) -> dict[str, Any]:
    rig = load_rig()
    ind = load_indenter(indenter)
    t = time.perf_counter()
    table = true_contact_table(ind, rig)  # warms the cache (builds the table if it is missing)
    warm_s = time.perf_counter() - t
    t = time.perf_counter()
    table = true_contact_table(ind, rig)
    load_s = time.perf_counter() - t
    cold_s = None
    if cold:
        with tempfile.TemporaryDirectory(prefix="labrig-bench-rig-") as tmp:
            t = time.perf_counter()
            true_contact_table(ind, rig, cache_dir=tmp)
            cold_s = time.perf_counter() - t
    path = probing_path(rig, ind, depth_mm=depth_mm, shear_mm=shear_mm)
    chunk_us = round(chunk_ms * 1000)
    sim_s = path.duration_us * 1e-6
    runs = []
    for i in range(repeat):
        runs.append(simulate(rig, ind, table, path, seed, chunk_us))
        gc.collect()  # the previous VirtualRig (its wrapped methods make reference cycles)
        if progress:
            print(f"  rig run {i + 1}/{repeat}: {runs[-1]['wall_s']:.2f} s wall for {sim_s:.2f} s simulated", flush=True)
    peak_traced = traced_peak_mib(rig, ind, table, path, seed, chunk_us) if tracemalloc else None
    median = sorted(runs, key=lambda r: r["wall_s"])[len(runs) // 2]
    rtf = [r["wall_s"] / sim_s for r in runs]
    phases = []
    counts: dict[str, int] = {}
    for k, (name, t0, t1) in enumerate(path.phases):
        counts[name] = counts.get(name, 0) + 1
        duration = (t1 - t0) * 1e-6
        phases.append({
            "name": name if name != "wait" else f"wait_{counts[name]}",
            "start_s": t0 * 1e-6,
            "duration_s": duration,
            "wall_s": median["phase_wall_s"][k],
            "real_time_factor": median["phase_wall_s"][k] / duration if duration > 0 else 0.0,
            "cpu_time_factor": min(r["phase_cpu_s"][k] for r in runs) / duration if duration > 0 else 0.0,
            "events": median["phase_events"][k],
            "event_rate_mev_per_s": median["phase_events"][k] / duration / 1e6 if duration > 0 else 0.0,
        })
    costs = {}
    for name, (total_s, calls) in median["timers"].items():
        costs[name] = {"calls": calls, "total_s": total_s, "per_call_ms": total_s / calls * 1e3 if calls else 0.0,
                       "real_time_factor": total_s / sim_s}
    other_s = median["wall_s"] - sum(median["timers"][k][0] for k in ("render", "sensor_step", "solve"))
    return {
        "indenter": indenter,
        "depth_mm": depth_mm,
        "shear_mm": shear_mm,
        "seed": seed,
        "chunk_ms": chunk_ms,
        "repeat": repeat,
        "simulated_s": sim_s,
        "required_real_time_factor_max": REQUIRED_RTF,
        "target_real_time_factor_max": TARGET_RTF,
        "real_time_factor": statistics.median(rtf),
        "real_time_factor_min": min(rtf),
        "real_time_factor_max": max(rtf),
        "cpu_time_factor": min(sum(r["phase_cpu_s"]) for r in runs) / sim_s,
        "wall_s": median["wall_s"],
        "events": median["events"],
        "event_rate_mev_per_s": median["events"] / sim_s / 1e6,
        "renders": median["renders"],
        "solves": median["solves"],
        "renders_per_s": median["renders"] / sim_s,
        "solves_per_s": median["solves"] / sim_s,
        "costs": costs,
        "other_s": other_s,
        "phases": phases,
        "table_load_s": load_s,
        "table_warm_s": warm_s,
        "table_build_recorded_s": table.meta.get("build_seconds"),
        "table_cold_build_s": cold_s,
        "table_mib": table.nbytes / 2**20,
        "rig_init_s": median["init_s"],
        "peak_rss_mib": _maxrss_mib(),
        "rss_growth_first_run_mib": runs[0]["rss_growth_mib"],
        "tracemalloc_peak_mib": peak_traced,
    }


def render(f: dict[str, Any]) -> None:
    def verdict(rtf: float) -> str:
        if rtf <= f["target_real_time_factor_max"]:
            return "yes"
        return "<= 1 only" if rtf <= f["required_real_time_factor_max"] else "NO"

    rows = [["whole sequence", f"{f['simulated_s']:.3f}", f"{f['wall_s']:.3f}", f"{f['real_time_factor']:.3f}",
             f"{f['cpu_time_factor']:.3f}", f"{f['events']:,}", f"{f['event_rate_mev_per_s']:.3f}",
             verdict(f["real_time_factor"])]]
    for p in f["phases"]:
        rows.append([f"  {p['name']}", f"{p['duration_s']:.3f}", f"{p['wall_s']:.3f}", f"{p['real_time_factor']:.3f}",
                     f"{p['cpu_time_factor']:.3f}", f"{p['events']:,}", f"{p['event_rate_mev_per_s']:.3f}",
                     verdict(p["real_time_factor"])])
    emit(
        f"Virtual rig: {f['indenter']}, {f['depth_mm']:g} mm deep, +/-{f['shear_mm']:g} mm shear, one core "
        f"(median of {f['repeat']}, runs {f['real_time_factor_min']:.3f}-{f['real_time_factor_max']:.3f})",
        ["phase", "simulated s", "wall s", "real-time factor", "CPU-time factor (best run)", "events", "Mev/s",
         "RTF<=0.5"],
        rows,
        [],
    )
    c = f["costs"]
    emit(
        "Where the time goes (wrapped timers; solve includes its table lookup)",
        ["part", "calls", "per call ms", "total s", "real-time factor"],
        [[name, f"{v['calls']}", f"{v['per_call_ms']:.3f}", f"{v['total_s']:.3f}", f"{v['real_time_factor']:.3f}"]
         for name, v in c.items()]
        + [["rest of advance (stepping, truth samples)", "", "", f"{f['other_s']:.3f}",
            f"{f['other_s'] / f['simulated_s']:.3f}"]],
        [
            f"real-time factor = wall time / simulated time: {f['real_time_factor']:.3f} "
            f"(<= {f['required_real_time_factor_max']:g} required, <= {f['target_real_time_factor_max']:g} aimed); "
            f"{f['renders_per_s']:.0f} renders and {f['solves_per_s']:.0f} solves per simulated second; "
            f"{f['events']:,} events = {f['event_rate_mev_per_s']:.3f} Mev per simulated second.",
            f"memory: peak RSS {f['peak_rss_mib']:.0f} MiB (ru_maxrss, whole process), grew by "
            f"{f['rss_growth_first_run_mib']:.0f} MiB over the first run"
            + (f"; tracemalloc peak of one run {f['tracemalloc_peak_mib']:.0f} MiB" if f["tracemalloc_peak_mib"] else "")
            + f"; contact table {f['table_mib']:.0f} MiB.",
            f"not timed above: table load from cache {f['table_load_s'] * 1e3:.0f} ms (first call {f['table_warm_s']:.2f} s), "
            + (f"recorded build {f['table_build_recorded_s']:.1f} s, " if f["table_build_recorded_s"] else "")
            + (f"cold build {f['table_cold_build_s']:.1f} s, " if f["table_cold_build_s"] is not None else "")
            + f"VirtualRig construction {f['rig_init_s'] * 1e3:.0f} ms.",
        ],
    )


SINGLE_THREAD = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def main(argv: list[str] | None = None) -> None:
    if argv is None and any(os.environ.get(var) != "1" for var in SINGLE_THREAD):
        os.environ.update(dict.fromkeys(SINGLE_THREAD, "1"))
        os.execv(sys.executable, [sys.executable, *sys.argv])  # numpy is loaded: start again, single-threaded
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
