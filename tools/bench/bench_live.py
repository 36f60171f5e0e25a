"""The virtual rig served live, with its twins and a recorder attached: does it keep up?

A :class:`~labrig.sim.world.LiveWorld` serves the GRBL, Bota and EVK4 twins,
either as ``labrig sim serve`` in its own process (``--mode process``, as a
lab would run it) or in the recorder's process (``--mode thread``, the worst
case: one GIL for everything, truth recorded too). The real drivers
run the standard probing sequence (sphere, 1.5 mm deep, +/-1 mm shear, waits
0.3 s; one G-code move per phase, M8/M9 toggled at each phase start for the
camera trigger) while a RecordingWriter records F/T samples, CNC status, the
G-code log, camera events and trigger edges (and the truth).

Reported, all against real time:
* renderer: its max lag behind the host clock (beyond its fixed render lag),
  chunks late by more than one chunk, and its busy fraction (CPU time of the
  renderer thread / sensor time);
* F/T: frames lost (device timestamps against the 1250 us period; must be 0);
* recorder: rows dropped (must be 0), events per second of sensor time.
The F/T twin's wrench and the GRBL position are computed at host time on
demand, so a lagging renderer delays camera events only (they carry their
own timestamps).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import bench_main, emit

from labrig.clock import CounterUnwrapper
from labrig.config import RigConfig, load_rig
from labrig.devices.bota import BotaSensor, BotaSettings
from labrig.devices.bota_stream import FtSample
from labrig.devices.camera import open_camera
from labrig.devices.grbl import Grbl
from labrig.indenters import Indenter, load_indenter
from labrig.physics.grid import network_grid_gel_mm
from labrig.protocol.routing import ft_sink, put_cnc, put_gcode, record_camera
from labrig.recording import RecordingMetadata, RecordingResult, RecordingWriter
from labrig.sim.live import publish_truth
from labrig.sim.motion import PiecewiseLinearPath, probing_path
from labrig.sim.rig import RigOutput
from labrig.sim.truth import truth_streams
from labrig.sim.world import LiveWorld

FT_PERIOD_US = 1250.0


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--depth-mm", type=float, default=1.5)
    ap.add_argument("--shear-mm", type=float, default=1.0)
    ap.add_argument("--speed-mm-s", type=float, default=1.5)
    ap.add_argument("--mode", choices=("process", "thread", "both"), default="both",
                    help="world in its own process, in the recorder's, or both runs")
    ap.add_argument("--no-truth", dest="truth", action="store_false", help="do not record the truth streams")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


class _RendererClock:
    """CPU time of the renderer thread, sampled from inside it."""

    def __init__(self) -> None:
        self.cpu_s = 0.0
        self._last: float | None = None

    def tick(self) -> None:
        now = time.thread_time()
        if self._last is not None:
            self.cpu_s += now - self._last
        self._last = now


def run(mode: str = "both", depth_mm: float = 1.5, shear_mm: float = 1.0, speed_mm_s: float = 1.5,
        truth: bool = True, progress: bool = True) -> dict[str, Any]:
    modes = ("process", "thread") if mode == "both" else (mode,)
    return {m: (_run_process if m == "process" else _run_thread)(depth_mm, shear_mm, speed_mm_s, truth) for m in modes}


def _path(rig: RigConfig, indenter: Indenter, depth_mm: float, shear_mm: float, speed_mm_s: float) -> PiecewiseLinearPath:
    return probing_path(rig, indenter, depth_mm=depth_mm, shear_mm=shear_mm, normal_speed_mm_s=speed_mm_s,
                        shear_speed_mm_s=speed_mm_s, nominal=True)


def _writer(out: Path, rig: RigConfig, truth: bool) -> RecordingWriter:
    metadata = RecordingMetadata(indenter="sphere", protocol_toml="# bench_live\n", rig_toml=rig.text,
                                 extra={"virtual_rig": True})
    extra = truth_streams(len(rig.markers.rest_positions_mm())) if truth else ()
    return RecordingWriter(out, metadata, extra_streams=extra).open()


def _drivers(paths: dict[str, str], writer: RecordingWriter, ft: list[FtSample]) -> tuple[Grbl, BotaSensor]:
    sink = ft_sink(writer)

    def on_ft(sample: FtSample) -> None:
        ft.append(sample)
        sink(sample)

    grbl = Grbl(paths["grbl"], clock=writer.clock, time_base_ns=writer.t0_host_ns,
                on_sample=lambda s: put_cnc(writer, s, time_base_ns=writer.t0_host_ns),
                on_gcode=lambda t, d, line: put_gcode(writer, t, d, line, time_base_ns=writer.t0_host_ns))
    bota = BotaSensor(paths["bota"], clock=writer.clock, on_sample=on_ft, char_gap_s=0.0)
    grbl.connect()
    bota.connect(boot_timeout_s=5)
    bota.configure(BotaSettings())
    bota.start()
    return grbl, bota


def _run_process(depth_mm: float, shear_mm: float, speed_mm_s: float, truth: bool) -> dict[str, Any]:
    """The world as `labrig sim serve`; the recorder reads the camera through its socket."""
    rig, indenter = load_rig(), load_indenter("sphere")
    with tempfile.TemporaryDirectory() as tmp:
        serve = subprocess.Popen(
            [sys.executable, "-m", "labrig.cli", "sim", "serve", "--json", "--camera-socket", f"{tmp}/evk4.sock"],
            stdout=subprocess.PIPE, text=True)
        assert serve.stdout is not None
        paths = {d["device"]: d["path"] for d in (json.loads(serve.stdout.readline()) for _ in range(3))}
        writer = _writer(Path(tmp) / "live.h5", rig, truth=False)
        ft: list[FtSample] = []
        t_wall = time.perf_counter()
        camera = open_camera("sim", path=paths["evk4"], clock=writer.clock).open()
        stop = threading.Event()
        recorded: list[Any] = []
        reader = threading.Thread(target=lambda: recorded.append(record_camera(camera, writer, stop)))
        reader.start()
        grbl, bota = _drivers(paths, writer, ft)
        path = _path(rig, indenter, depth_mm, shear_mm, speed_mm_s)
        t_probe = time.perf_counter()
        _probe(grbl, writer, path.position_mm, path.phases)  # the served CNC is homed: machine coordinates
        probe_s = time.perf_counter() - t_probe
        time.sleep(0.2)
        bota.close()
        grbl.close()
        stop.set()
        reader.join()
        camera.close()
        serve.terminate()
        out, _ = serve.communicate(timeout=30)
        stats = json.loads(out.strip().splitlines()[-1])["stats"]
        result = writer.close()
        wall_s = time.perf_counter() - t_wall
    return _figures(stats, probe_s, wall_s, None, ft, result)


def _run_thread(depth_mm: float, shear_mm: float, speed_mm_s: float, truth: bool) -> dict[str, Any]:
    """Everything in this process; the truth goes into the recording too."""
    rig, indenter = load_rig(), load_indenter("sphere")
    path = _path(rig, indenter, depth_mm, shear_mm, speed_mm_s)
    with tempfile.TemporaryDirectory() as tmp:
        writer = _writer(Path(tmp) / "live.h5", rig, truth)
        renderer_clock = _RendererClock()
        state: dict[str, Any] = {}

        def camera(events: np.ndarray, triggers: list[tuple[int, int]]) -> None:
            receive = writer.host_us()
            if len(events):
                writer.put_events(events["x"], events["y"], events["p"], events["t"], receive)
            for t, polarity in triggers:
                writer.put("triggers", t_device_us=t, polarity=polarity, channel=0)

        def on_chunk(chunk: RigOutput) -> None:
            renderer_clock.tick()
            if truth:
                publish_truth(writer, chunk, state["grid"], state["offset_us"])

        world = LiveWorld(rig, indenter, camera_sink=camera, on_chunk=on_chunk, clock=writer.clock, homed=True)
        state["grid"] = network_grid_gel_mm(rig, world.rig.camera)
        ft: list[FtSample] = []
        t_wall = time.perf_counter()
        with world:
            state["offset_us"] = (world._origin_us or 0) - writer.t0_host_ns // 1000
            grbl, bota = _drivers(world.paths, writer, ft)
            t_probe = time.perf_counter()
            _probe(grbl, writer, path.position_mm, path.phases)
            probe_s = time.perf_counter() - t_probe
            time.sleep(0.1)
            bota.close()
            grbl.close()
        result = writer.close()
        wall_s = time.perf_counter() - t_wall
    stats = world.stats.as_dict()
    return _figures(stats, probe_s, wall_s, renderer_clock.cpu_s, ft, result)


def _figures(stats: dict[str, Any], probe_s: float, wall_s: float, renderer_cpu_s: float | None,
             ft: list[FtSample], result: RecordingResult) -> dict[str, Any]:
    sim_s = max(float(stats["sim_s"]), 1e-9)
    return {
        "sensor_s": probe_s,
        "wall_s": wall_s,
        "renderer_max_lag_ms": stats["max_lag_ms"],
        "renderer_late_chunks": stats["late_chunks"],
        "renderer_chunks": stats["chunks"],
        "renderer_busy_fraction": None if renderer_cpu_s is None else renderer_cpu_s / sim_s,
        "events": stats["events"],
        "event_rate_hz": stats["events"] / sim_s,
        "events_recorded": result.rows.get("events", 0),
        "ft_frames": len(ft),
        "ft_frames_lost": _frames_lost(ft),
        "recorder_drops": int(sum(result.dropped.values())),
        "exit_status": result.exit_status,
    }


def _probe(grbl: Grbl, writer: RecordingWriter, work_mm: np.ndarray, phases: tuple[tuple[str, float, float], ...]) -> None:
    """One G-code move (or dwell) per phase, the camera trigger toggled at each phase start."""
    grbl.move_to(*work_mm[0].tolist(), feed_mm_min=1200, wait=True)
    level = 0
    for i, (name, t0, t1) in enumerate(phases):
        level ^= 1
        edge = grbl.set_output(bool(level), timeout_s=30)
        writer.put("trigger_out", t_host_us=edge.t_ack_us, polarity=level, t_latest_host_us=edge.t_ack_us)
        writer.phase_begin(name, edge.t_ack_us)
        duration_s = (t1 - t0) / 1e6
        distance = float(np.linalg.norm(work_mm[i + 1] - work_mm[i]))
        if distance < 1e-6:
            grbl.send(f"G4 P{duration_s:.3f}", timeout_s=30)
        else:
            grbl.move_to(*work_mm[i + 1].tolist(), feed_mm_min=distance / duration_s * 60, timeout_s=30)
    grbl.set_output(not level, timeout_s=30)  # waits for the last move
    writer.phase_end(grbl.now_us())


def _frames_lost(samples: list[FtSample]) -> int:
    if len(samples) < 2:
        return 0
    t = CounterUnwrapper(32)(np.array([s.t_device_us for s in samples], dtype=np.int64)).astype(np.float64)
    gaps = np.round(np.diff(t) / FT_PERIOD_US) - 1
    return int(gaps[gaps > 0].sum())


def render(figures: dict[str, Any]) -> None:
    modes = [m for m, v in figures.items() if isinstance(v, dict)]
    rows = []
    for label, key, fmt in [
        ("renderer max lag (ms)", "renderer_max_lag_ms", "{:.1f}"),
        ("renderer late chunks", "renderer_late_chunks", "{}"),
        ("renderer chunks", "renderer_chunks", "{}"),
        ("renderer busy (CPU s / sensor s)", "renderer_busy_fraction", "{:.2f}"),
        ("events made", "events", "{:,}"),
        ("events recorded", "events_recorded", "{:,}"),
        ("event rate (Mev/s)", "event_rate_hz", "{:.3f}"),
        ("F/T frames", "ft_frames", "{:,}"),
        ("F/T frames lost", "ft_frames_lost", "{}"),
        ("recorder drops", "recorder_drops", "{}"),
        ("probing run (s)", "sensor_s", "{:.2f}"),
        ("exit", "exit_status", "{}"),
    ]:
        scale = 1e-6 if key == "event_rate_hz" else 1
        rows.append([label, *("-" if figures[m][key] is None else fmt.format(figures[m][key] * scale) for m in modes)])
    emit("Live virtual rig with its twins and a recorder", ["figure", *modes], rows, [
        "Lag: host time at hand-over minus the chunk's end, beyond the renderer's fixed 30 ms render lag.",
        "F/T and CNC positions are computed at host time on demand; a lagging renderer only delays camera events.",
    ])


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    threading.current_thread().name = "bench-live"
    main()
