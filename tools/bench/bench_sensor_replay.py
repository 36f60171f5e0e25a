"""The virtual camera's event sensor alone, on one recording's inputs: this tree against a baseline, side by side.

A whole virtual-time recording varies by 20-30 % between runs on a shared machine, which hides a
change of a few per cent in one stage. This benchmark takes the event sensor out: it records one
paper-campaign recording once (this tree), keeps every input the rig handed
:meth:`labrig.sim.events.EventSensor.step` (the renderer's changed pixels and dense blocks, the
step times) and the sensor's construction, then replays them into a fresh sensor of each tree,
alternately, ``--repeat`` times each, in subprocesses (``PYTHONPATH`` = the tree). Reported per
tree: the thread CPU of the replay (every run, the fastest, the median) and the events it gave;
the speed-up is baseline / this tree from the fastest runs. The two trees must give the same
events (a sensor change that moves events is not a speed-up; the benchmark says so).

Usage: ``bench_sensor_replay.py --baseline REV [--recording 117] [--repeat 5]``, REV a git revision of this
repository (exported for the run) or a labrig checkout's folder.
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import bench_main, emit, json_from_tree, trees_to_compare

ROOT = Path(__file__).resolve().parents[2]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default=None,
                    help="what to compare with: a git revision of this repository (e.g. HEAD~1) or a labrig checkout's folder")
    ap.add_argument("--recording", type=int, default=117, help="index into the paper campaign (default 117, square)")
    ap.add_argument("--repeat", type=int, default=5, help="replays per tree, alternately")
    ap.add_argument("--replay", nargs=2, default=None, help=argparse.SUPPRESS)  # internal: INPUTS N, JSON out
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def capture(index: int, out: Path) -> int:
    """Record paper-campaign recording ``index`` and pickle its event sensor's construction and step inputs."""
    import numpy as np

    from labrig.config import load_rig
    from labrig.indenters import load_indenters
    from labrig.protocol.files import load_campaign
    from labrig.protocol.virtual_campaign import recording_seed
    from labrig.protocol.virtual_run import record_virtual
    from labrig.sim import events
    from labrig.sim.world_process import prepare_contact_tables

    rig, indenters = load_rig(), load_indenters()
    campaign = load_campaign(ROOT / "protocols" / "paper.toml", rig, indenters)
    plan = campaign.plans[index]
    indenter = indenters[plan.spec.indenter]
    prepare_contact_tables(rig, indenter, [plan.spec.shear_direction_deg])
    made: dict[str, Any] = {}
    steps: list[tuple[Any, ...]] = []
    init, step = events.EventSensor.__init__, events.EventSensor.step

    def captured_init(self: Any, params: Any, width: int, height: int, initial_intensity: Any, **kw: Any) -> None:
        made.update(params=params, width=width, height=height, intensity=np.array(initial_intensity, copy=True), kw=kw)
        init(self, params, width, height, initial_intensity, **kw)

    def captured_step(self: Any, t0: int, t1: int, pixels: Any, values: Any, *, block: Any = None) -> Any:
        b = None if block is None else (block.y0, block.x0, block.changed.copy(), block.values.copy())
        steps.append((t0, t1, np.array(pixels, copy=True), np.array(values, copy=True), b))
        return step(self, t0, t1, pixels, values, block=block)

    events.EventSensor.__init__, events.EventSensor.step = captured_init, captured_step  # type: ignore[method-assign]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            record_virtual(plan.spec, Path(tmp) / "r.h5", rig, indenter, seed=recording_seed(campaign, plan))
    finally:
        events.EventSensor.__init__, events.EventSensor.step = init, step  # type: ignore[method-assign]
    with out.open("wb") as f:
        pickle.dump((made, steps), f, protocol=5)
    return len(steps)


def replay(inputs: Path, runs: int) -> dict[str, Any]:
    """Replay the captured steps into fresh sensors of the tree on ``PYTHONPATH``: CPU s per run, events, a digest."""
    import hashlib

    from labrig.sim import _render_kernels, events
    from labrig.sim.pixels import PixelBlock

    _render_kernels.warm_up()
    with inputs.open("rb") as f:
        made, steps = pickle.load(f)
    cpu: list[float] = []
    digest = ""
    n_events = 0
    for _ in range(runs):
        sensor = events.EventSensor(made["params"], made["width"], made["height"], made["intensity"], **made["kw"])
        h = hashlib.sha256()
        n_events = 0
        start = time.thread_time()
        out = [sensor.step(t0, t1, pixels, values, block=None if b is None else PixelBlock(*b))
               for t0, t1, pixels, values, b in steps]
        cpu.append(time.thread_time() - start)
        for ev in out:
            h.update(ev.tobytes())
            n_events += len(ev)
        digest = h.hexdigest()
    return {"cpu_s": cpu, "events": n_events, "digest": digest}


def _replay_in(tree: Path, inputs: Path, runs: int) -> dict[str, Any]:
    return json_from_tree(tree, Path(__file__).resolve(), "--replay", str(inputs), str(runs))  # type: ignore[no-any-return]


def run(baseline: str | Path | None = None, recording: int = 117, repeat: int = 5, replay: list[str] | None = None,
        progress: bool = True) -> dict[str, Any]:
    trees = trees_to_compare(ROOT, baseline)
    with tempfile.TemporaryDirectory() as tmp:
        inputs = Path(tmp) / "sensor_inputs.pkl"
        n_steps = capture(recording, inputs)
        if progress:
            print(f"recording {recording}: {n_steps} sensor steps captured", file=sys.stderr)
        results: dict[str, dict[str, Any]] = {name: {"cpu_s": []} for name in trees}
        for _ in range(max(1, repeat)):
            for name, tree in trees.items():  # alternately, so load on the machine falls on both alike
                got = _replay_in(tree, inputs, 1)
                results[name]["cpu_s"] += got["cpu_s"]
                results[name].update(events=got["events"], digest=got["digest"])
                if progress:
                    print(f"  {name}: {got['cpu_s'][0]:.3f} s CPU, {got['events']:,} events", file=sys.stderr)
    figures: dict[str, Any] = {"recording": recording, "steps": n_steps}
    for name, r in results.items():
        cpu = sorted(r["cpu_s"])
        figures[name] = {"cpu_s": r["cpu_s"], "cpu_s_fastest": cpu[0], "cpu_s_median": cpu[len(cpu) // 2],
                         "events": r["events"], "digest": r["digest"]}
    if "baseline" in figures:
        base, this = figures["baseline"], figures["this_tree"]
        figures["same_events"] = base["digest"] == this["digest"]
        figures["speedup_fastest"] = base["cpu_s_fastest"] / this["cpu_s_fastest"]
        figures["speedup_median"] = base["cpu_s_median"] / this["cpu_s_median"]
    return figures


def render(f: dict[str, Any]) -> None:
    names = [n for n in ("baseline", "this_tree") if n in f]
    columns = ["figure", *[n.replace("_", " ") for n in names]] + (["speed-up"] if "baseline" in f else [])
    rows = [["CPU s, fastest replay", *[f"{f[n]['cpu_s_fastest']:.3f}" for n in names]]
            + ([f"{f['speedup_fastest']:.2f}x"] if "baseline" in f else []),
            ["CPU s, median replay", *[f"{f[n]['cpu_s_median']:.3f}" for n in names]]
            + ([f"{f['speedup_median']:.2f}x"] if "baseline" in f else []),
            ["CPU s, every replay", *[" ".join(f"{v:.3f}" for v in f[n]["cpu_s"]) for n in names]]
            + ([""] if "baseline" in f else []),
            ["events", *[f"{f[n]['events']:,}" for n in names]] + ([""] if "baseline" in f else [])]
    notes = [f"recording {f['recording']} of protocols/paper.toml: {f['steps']} event-sensor steps, "
             "replayed alternately; thread CPU of the steps"]
    if "baseline" in f and not f["same_events"]:
        notes.append("the two trees give DIFFERENT events: not a like-for-like comparison")
    emit("event sensor on one recording's inputs", columns, rows, notes)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    if args.replay is not None:
        print(json.dumps(replay(Path(args.replay[0]), int(args.replay[1]))))
        return
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
