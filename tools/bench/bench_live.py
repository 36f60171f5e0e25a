"""The virtual rig served live, with its twins and a recorder attached: does it keep up?

A :class:`~labrig.sim.world.LiveWorld` serves the GRBL and Bota twins on ptys;
in the same process (the worst case: one GIL for everything) the real drivers
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
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import bench_main, emit

from labrig.clock import CounterUnwrapper
from labrig.config import load_rig
from labrig.devices.bota import BotaSensor, BotaSettings, FtSample, recording_sink
from labrig.devices.grbl import Grbl
from labrig.indenters import load_indenter
from labrig.recording import RecordingMetadata, RecordingWriter
from labrig.sim.live import publish_truth
from labrig.sim.motion import probing_path
from labrig.sim.rig import RigOutput
from labrig.sim.truth import network_grid_gel_mm, truth_streams
from labrig.sim.world import LiveWorld

FT_PERIOD_US = 1250.0


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--depth-mm", type=float, default=1.5)
    ap.add_argument("--shear-mm", type=float, default=1.0)
    ap.add_argument("--speed-mm-s", type=float, default=1.5)
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


def run(depth_mm: float = 1.5, shear_mm: float = 1.0, speed_mm_s: float = 1.5, truth: bool = True,
        progress: bool = True) -> dict[str, Any]:
    rig, indenter = load_rig(), load_indenter("sphere")
    path = probing_path(rig, indenter, depth_mm=depth_mm, shear_mm=shear_mm, normal_speed_mm_s=speed_mm_s,
                        shear_speed_mm_s=speed_mm_s, nominal=True)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "live.h5"
        metadata = RecordingMetadata(indenter="sphere", protocol_toml="# bench_live\n", rig_toml=rig.text,
                                     extra={"virtual_rig": True})
        writer = RecordingWriter(out, metadata, extra_streams=truth_streams(len(rig.markers.rest_positions_mm())))
        writer.open()
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

        world = LiveWorld(rig, indenter, camera_sink=camera, on_chunk=on_chunk, clock=writer.clock)
        state["grid"] = network_grid_gel_mm(rig, world.rig.camera)
        ft: list[FtSample] = []
        sink = recording_sink(writer)

        def on_ft(sample: FtSample) -> None:
            ft.append(sample)
            sink(sample)

        t_wall = time.perf_counter()
        with world:
            state["offset_us"] = (world._origin_us or 0) - writer.t0_host_ns // 1000
            grbl = Grbl(world.paths["grbl"], clock=writer.clock, time_base_ns=writer.t0_host_ns,
                        on_sample=lambda s: writer.put("cnc", **s.columns()),
                        on_gcode=lambda t, d, line: writer.put("gcode", t_host_us=t, direction=d, line=line[:128]))
            bota = BotaSensor(world.paths["bota"], clock=writer.clock, on_sample=on_ft, char_gap_s=0.0)
            grbl.connect()
            bota.connect(boot_timeout_s=5)
            bota.configure(BotaSettings())
            bota.start()
            t_probe = time.perf_counter()
            _probe(grbl, writer, path.position_mm - np.asarray(world.grbl.physical_offset_mm), path.phases)
            probe_s = time.perf_counter() - t_probe
            time.sleep(0.1)
            world_stats = world.stats
            bota.close()
            grbl.close()
        result = writer.close()
        wall_s = time.perf_counter() - t_wall
    sim_s = world_stats.sim_s
    lost = _frames_lost(ft)
    return {
        "sensor_s": probe_s,
        "wall_s": wall_s,
        "renderer_max_lag_ms": world_stats.max_lag_ms,
        "renderer_late_chunks": world_stats.late_chunks,
        "renderer_chunks": world_stats.chunks,
        "renderer_busy_fraction": renderer_clock.cpu_s / max(sim_s, 1e-9),
        "events": world_stats.events,
        "event_rate_hz": world_stats.events / max(sim_s, 1e-9),
        "ft_frames": len(ft),
        "ft_frames_lost": lost,
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
        writer.put("trigger_out", t_host_us=edge.t_ack_us, polarity=level)
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


def render(f: dict[str, Any]) -> None:
    rows = [
        ["renderer max lag (ms)", f"{f['renderer_max_lag_ms']:.1f}"],
        ["renderer late chunks", f"{f['renderer_late_chunks']} / {f['renderer_chunks']}"],
        ["renderer busy (CPU s / sensor s)", f"{f['renderer_busy_fraction']:.2f}"],
        ["events, rate", f"{f['events']:,}, {f['event_rate_hz'] / 1e6:.2f} Mev/s"],
        ["F/T frames, lost", f"{f['ft_frames']:,}, {f['ft_frames_lost']}"],
        ["recorder drops", f"{f['recorder_drops']}"],
        ["probing run (s), exit", f"{f['sensor_s']:.2f}, {f['exit_status']}"],
    ]
    emit("Live virtual rig with twins and recorder (one process)", ["figure", "value"], rows, [
        "Lag is beyond the renderer's fixed 30 ms render lag; F/T and CNC are computed at host time on demand.",
    ])


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    threading.current_thread().name = "bench-live"
    main()
