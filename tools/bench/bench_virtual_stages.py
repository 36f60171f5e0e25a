"""Virtual-time recordings per stage: CPU seconds per simulated second, this tree against a baseline, side by side.

Each run records one recording of the paper campaign (``protocols/paper.toml``: by default the
first recording of each indenter at each of its depths, 12 recordings; deeper presses cost more
per simulated second, so a sample of the shallowest alone flatters the campaign) in virtual time
(:func:`labrig.protocol.virtual_run.record_virtual`) in a fresh process, and times it by
stage, in thread CPU time of the recording's main thread (each stage exclusive of the stages it
calls):

* ``contact``: contact mechanics, the contact track's kinematics (every F/T sample and solve)
  and the rig's solves (contact fields, displaced markers, marker forces);
* ``render``: the camera, ``OfflineRig.render_to`` less its solves: renderer, event sensor,
  true markers, the chunk into the writer;
* ``ft``: the Bota twin (UART, noise, frames), the driver's receiver, the tare, the force
  monitor and the F/T rows into the writer, less the contact track it samples;
* ``other``: the rest of the main thread (the GRBL model, the run's sequence, rig set-up);
* ``writer``: the writer thread (process CPU less the main thread's: compression, HDF5).

Across the stages, the main thread's time is also split into ``compiled`` (the rig's numba
kernels and scipy's FFTs, timed where Python calls them) and ``glue`` (the rest: Python and
numpy's small operations): what a faster kernel can gain, and what only fewer Python steps can.

Process start, imports, the contact table's load, the compiled kernels' load and the camera's
per-pixel rays (one rig built and dropped) are left out (warmed before timing): they are paid
once per worker process, not per recording (the campaign
benchmark, bench_virtual_campaign.py, measures whole CLI runs with them). With ``--baseline REV``
(a git revision of this repository, exported for the run, or a labrig checkout's folder) every recording is made by both
trees, alternately, and the ratios baseline / this tree are reported. Reported: simulated
seconds per CPU second (the real-time factor per core; the target is >= 3) from each recording's
median run and from its fastest (load only ever slows a run down, so the fastest runs are the
steadier comparison on a busy machine), and CPU seconds per simulated second per stage (medians).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from _common import bench_main, emit, json_from_tree, trees_to_compare

ROOT = Path(__file__).resolve().parents[2]
STAGES = ("contact", "render", "ft", "other", "writer")
#: The main thread again, split into compiled kernels (numba, FFT) and the rest.
SPLIT = ("compiled", "glue")
#: Modules whose numba kernels count as compiled time (scipy.fft's transforms count too).
COMPILED_MODULES = ("labrig.sim._render_kernels", "labrig.physics.camera", "labrig.physics.mechanics.rotation")
#: Wrapped callables per stage: (module, class, method); those a tree lacks are skipped.
TIMED = {
    "contact": [("labrig.sim.contact_track", "ContactTrack", "sample"),
                ("labrig.sim.contact_track", "ContactTrack", "first_after"),
                ("labrig.sim.contact_track", "ContactTrack", "wrench_state"), ("labrig.sim.rig", "VirtualRig", "solve")],
    "render": [("labrig.sim.offline", "OfflineRig", "render_to")],
    "ft": [("labrig.sim.bota_twin", "BotaTwin", "transmit"), ("labrig.sim.bota_twin", "BotaTwin", "read_frames"),
           ("labrig.devices.bota_protocol", "BotaReceiver", "feed"), ("labrig.sim.offline", "OfflineRig", "_on_frame")],
}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default=None,
                    help="what to compare with: a git revision of this repository (e.g. HEAD~1) or a labrig checkout's folder")
    ap.add_argument("--recordings", default="", help="comma-separated indices into the paper campaign "
                                                     "(default: the first of each indenter and depth)")
    ap.add_argument("--repeat", type=int, default=1, help="runs per recording and tree (the median is kept, and the fastest)")
    ap.add_argument("--probe", default=None, help=argparse.SUPPRESS)  # internal: one timed recording, JSON out
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


class _StageClock:
    """Exclusive thread-CPU time per stage of wrapped callables on one thread (nested stages pause their callers)."""

    def __init__(self) -> None:
        self.seconds = dict.fromkeys(STAGES, 0.0)
        self._stack: list[str] = []
        self._since = 0.0
        self.thread = threading.get_ident()

    def wrap(self, stage: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            if threading.get_ident() != self.thread:
                return fn(*args, **kwargs)
            now = time.thread_time()
            if self._stack:
                self.seconds[self._stack[-1]] += now - self._since
            self._stack.append(stage)
            self._since = now
            try:
                return fn(*args, **kwargs)
            finally:
                now = time.thread_time()
                self.seconds[self._stack.pop()] += now - self._since
                self._since = now

        return timed


class _CompiledClock:
    """Thread-CPU time of the main thread inside compiled callables (outermost calls only)."""

    def __init__(self, thread: int) -> None:
        self.seconds = 0.0
        self.thread = thread
        self._depth = 0

    def wrap(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            if self._depth or threading.get_ident() != self.thread:
                return fn(*args, **kwargs)
            self._depth += 1
            start = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self._depth -= 1
                self.seconds += time.thread_time() - start

        return timed

    def install(self) -> None:
        """Wrap the compiled modules' numba kernels and scipy.fft's transforms (module attributes, looked up at
        each call by their callers)."""
        import importlib

        import scipy.fft
        from numba.core.registry import CPUDispatcher

        for name in COMPILED_MODULES:
            module = importlib.import_module(name)
            for attr, value in list(vars(module).items()):
                if isinstance(value, CPUDispatcher):
                    setattr(module, attr, self.wrap(value))
        for attr in ("rfft", "irfft", "fft", "ifft", "rfft2", "irfft2"):
            setattr(scipy.fft, attr, self.wrap(getattr(scipy.fft, attr)))


def probe(index: int) -> dict[str, Any]:
    """Record the paper campaign's recording ``index`` in virtual time in this process; its figures."""
    import importlib

    from labrig.config import load_rig
    from labrig.indenters import load_indenters
    from labrig.protocol.files import load_campaign
    from labrig.protocol.virtual_campaign import recording_seed
    from labrig.protocol.virtual_run import record_virtual
    from labrig.recording import Recording
    from labrig.sim import _render_kernels
    from labrig.sim.rig import VirtualRig
    from labrig.sim.world_process import prepare_contact_tables

    rig, indenters = load_rig(), load_indenters()
    campaign = load_campaign(ROOT / "protocols" / "paper.toml", rig, indenters)
    plan = campaign.plans[index]
    indenter = indenters[plan.spec.indenter]
    prepare_contact_tables(rig, indenter, [plan.spec.shear_direction_deg])
    _render_kernels.warm_up()
    VirtualRig(rig, indenter, seed=0)  # the per-process caches a campaign worker's first recording fills
    clock = _StageClock()
    compiled = _CompiledClock(clock.thread)
    compiled.install()
    for stage, targets in TIMED.items():
        for module, cls_name, method in targets:
            cls = getattr(importlib.import_module(module), cls_name)
            if hasattr(cls, method):  # an older tree (a baseline) may lack some
                setattr(cls, method, clock.wrap(stage, getattr(cls, method)))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "probe.h5"
        cpu0, main0 = time.process_time(), time.thread_time()
        clock.wrap("other", lambda: record_virtual(plan.spec, out, rig, indenter, seed=recording_seed(campaign, plan)))()
        cpu, main = time.process_time() - cpu0, time.thread_time() - main0
        with Recording(out) as rec:
            phases = rec.phases()
            sim_s = (phases[-1].t_end_us - phases[0].t_start_us) / 1e6
    stages = dict(clock.seconds, writer=cpu - main, compiled=compiled.seconds, glue=main - compiled.seconds)
    return {"index": index, "indenter": plan.spec.indenter, "sim_s": sim_s, "cpu_s": cpu, "stages_cpu_s": stages}


def _run_probe(tree: Path, index: int) -> dict[str, Any]:
    return json_from_tree(tree, Path(__file__).resolve(), "--probe", str(index))  # type: ignore[no-any-return]


def _default_indices() -> list[int]:
    """The first recording of each (indenter, depth) of the paper campaign: its range of presses."""
    from labrig.config import load_rig
    from labrig.indenters import load_indenters
    from labrig.protocol.files import load_campaign

    plans = load_campaign(ROOT / "protocols" / "paper.toml", load_rig(), load_indenters()).plans
    first: dict[tuple[str, float | None], int] = {}
    for i, plan in enumerate(plans):
        first.setdefault((plan.spec.indenter, plan.spec.depth_mm), i)
    return sorted(first.values())


def _median(values: list[float]) -> float:
    v = sorted(values)
    return v[len(v) // 2] if len(v) % 2 else (v[len(v) // 2 - 1] + v[len(v) // 2]) / 2


def _summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Totals over the recordings (per recording: the median run; and the fastest, which this machine's
    load can only slow down)."""
    by_index: dict[int, list[dict[str, Any]]] = {}
    for r in runs:
        by_index.setdefault(r["index"], []).append(r)
    sim = sum(rs[0]["sim_s"] for rs in by_index.values())
    cpu = sum(_median([r["cpu_s"] for r in rs]) for rs in by_index.values())
    fastest = sum(min(r["cpu_s"] for r in rs) for rs in by_index.values())
    stages = {s: sum(_median([r["stages_cpu_s"].get(s, 0.0) for r in rs]) for rs in by_index.values())
              for s in (*STAGES, *SPLIT)}
    return {"recordings": len(by_index), "sim_s": sim, "cpu_s": cpu, "sim_s_per_cpu_s": sim / cpu,
            "cpu_s_fastest": fastest, "sim_s_per_cpu_s_fastest": sim / fastest,
            "cpu_s_per_sim_s": {s: v / sim for s, v in stages.items()}}


def run(baseline: str | Path | None = None, recordings: str = "", repeat: int = 1, probe: str | None = None,
        progress: bool = True) -> dict[str, Any]:
    indices = [int(i) for i in recordings.split(",") if i.strip()] or _default_indices()
    trees = trees_to_compare(ROOT, baseline)
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in trees}
    for _ in range(max(1, repeat)):
        for index in indices:
            for name, tree in trees.items():  # alternately, so load on the machine falls on both alike
                runs[name].append(_run_probe(tree, index))
                if progress:
                    last = runs[name][-1]
                    print(f"  {name}: recording {index} ({last['indenter']}) {last['sim_s']:.1f} s simulated, "
                          f"{last['cpu_s']:.1f} s CPU", file=sys.stderr)
    figures: dict[str, Any] = {name: _summary(rs) for name, rs in runs.items()}
    figures["indices"] = indices
    if "baseline" in figures:
        base, this = figures["baseline"], figures["this_tree"]
        figures["speedup"] = {"total": this["sim_s_per_cpu_s"] / base["sim_s_per_cpu_s"],
                              "total_fastest": this["sim_s_per_cpu_s_fastest"] / base["sim_s_per_cpu_s_fastest"],
                              **{s: base["cpu_s_per_sim_s"][s] / max(this["cpu_s_per_sim_s"][s], 1e-9)
                                 for s in (*STAGES, *SPLIT)}}
    return figures


def render(f: dict[str, Any]) -> None:
    names = [n for n in ("baseline", "this_tree") if n in f]
    columns = ["figure", *[n.replace("_", " ") for n in names]] + (["speed-up"] if "speedup" in f else [])
    rows = [["sim s / CPU s (per core)", *[f"{f[n]['sim_s_per_cpu_s']:.2f}" for n in names]]
            + ([f"{f['speedup']['total']:.2f}x"] if "speedup" in f else []),
            ["  the same, each recording's fastest run", *[f"{f[n]['sim_s_per_cpu_s_fastest']:.2f}" for n in names]]
            + ([f"{f['speedup']['total_fastest']:.2f}x"] if "speedup" in f else [])]
    for s in (*STAGES, *SPLIT):
        label = f"{s}: CPU s / sim s" if s in STAGES else f"main thread, {s}: CPU s / sim s"
        rows.append([label, *[f"{f[n]['cpu_s_per_sim_s'][s]:.3f}" for n in names]]
                    + ([f"{f['speedup'][s]:.2f}x"] if "speedup" in f else []))
    first = f[names[0]]
    notes = [f"{first['recordings']} recordings of protocols/paper.toml (indices {f['indices']}), "
             f"{first['sim_s']:.1f} s simulated; thread CPU of the recording, imports and warm-up left out",
             "target: >= 3 simulated seconds per CPU second"]
    emit("virtual time by stage", columns, rows, notes)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    if args.probe is not None:
        print(json.dumps(probe(int(args.probe))))
        return
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
