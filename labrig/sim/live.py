"""Run the virtual rig live on the host clock, straight into a recording.

The rig simulates world time in chunks; each chunk's data is published when
the host clock reaches the chunk's end (as real devices deliver data after it
happened), stamped with host receive times. If simulating a chunk takes longer
than the chunk lasts, the rig falls behind: the lag (host time at publication
minus the chunk's end) is measured and reported.

This path skips the device byte protocols: the pty twins (GRBL, Bota, EVK4)
replace these direct puts when they land, with the same timing rules.

The rig file's delivery knobs apply here as through the twins: with USB bursts
(``[sim.camera_delivery] burst_period_ms``) a camera chunk is held until the first
burst release at or after its end and stamped with that release (offline) or with
the host time it was published (real time); F/T samples are dropped with
``[sim.ft] drop_probability`` (deterministic under the run's seed).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from labrig.clock import ClockModel, HostClock, MonotonicClock
from labrig.config import RigConfig
from labrig.indenters import Indenter, indenter_toml
from labrig.physics.grid import network_grid_gel_mm
from labrig.recording import RecordingMetadata, RecordingResult, RecordingWriter
from labrig.recording.finalize import store_clock_model
from labrig.sim.delivery import BurstSchedule
from labrig.sim.motion import PiecewiseLinearPath
from labrig.sim.rig import RigOutput, Solve, VirtualRig
from labrig.sim.truth import truth_streams
from labrig.sim.truth_config import sim_config

FT_RATE_HZ = 800.0
CNC_RATE_HZ = 10.0
#: A status report's time from GRBL sampling its position to the host stamping it, us.
CNC_REPORT_TRANSIT_US = 1000
#: The simulated F/T sensor's clock (its twin will own this).
FT_CLOCK_ORIGIN_US = 2_000_000_000
FT_CLOCK_DRIFT_PPM = -60.0


@dataclass(frozen=True)
class LiveResult:
    recording: RecordingResult
    sim_duration_s: float
    wall_s: float
    max_lag_ms: float
    late_chunks: int
    chunks: int
    events: int


def record_live(
    path: str | Path,
    rig: RigConfig,
    indenter: Indenter,
    tool_path: PiecewiseLinearPath,
    *,
    seed: int = 0,
    chunk_us: int = 10_000,
    realtime: bool = True,
    clock: HostClock | None = None,
    virtual_rig: VirtualRig | None = None,
    progress: Callable[[float], None] | None = None,
    camera_clock_model: ClockModel | None = None,
) -> LiveResult:
    """Simulate ``tool_path`` and record it; paced to the host clock when ``realtime``.

    ``progress`` is called with the simulated seconds done after each chunk.
    ``camera_clock_model``: a rig that does not resync the camera clock; the recording maps
    camera time with this model (e.g. from a sync long before) instead of the one fitted
    on its own events and trigger edges.
    """
    vr = virtual_rig or VirtualRig(rig, indenter, seed=seed)
    clock = clock or MonotonicClock()
    n_markers = len(vr.rest_mm)
    grid_gel = network_grid_gel_mm(rig, vr.camera)
    metadata = RecordingMetadata(
        indenter=indenter.name,
        protocol_toml="# scripted probing path on the virtual rig\n",
        rig_toml=rig.text,
        indenter_toml=indenter_toml(indenter),
        extra={"virtual_rig": True, "seed": seed},
    )
    duration_us = int(tool_path.duration_us)
    phase_starts = {int(start): name for name, start, _ in tool_path.phases}
    ft_period_us = 1e6 / FT_RATE_HZ
    next_ft_us, next_cnc_us, trigger_level = 0.0, 0.0, 0
    bursts = BurstSchedule.from_rig(rig, seed)
    held: list[tuple[int, RigOutput]] = []  # camera chunks waiting for their burst: (release, chunk)
    ft_drop = _FtDrops(sim_config(rig).ft.drop_probability, seed)
    max_lag_us, late, chunks, events = 0.0, 0, 0, 0
    wall0 = time.perf_counter()
    with RecordingWriter(path, metadata, clock=clock, extra_streams=truth_streams(n_markers)) as writer:
        start_ns = writer.t0_host_ns
        last_solve: Solve | None = None
        for t0 in range(0, duration_us, chunk_us):
            t1 = min(t0 + chunk_us, duration_us)
            for t_phase, name in phase_starts.items():
                if t0 <= t_phase < t1:
                    trigger_level ^= 1
                    vr.trigger(t_phase, trigger_level)
                    writer.phase_begin(name, t_phase)
                    writer.put("trigger_out", t_host_us=t_phase, polarity=trigger_level, t_latest_host_us=t_phase)
            out = vr.advance(t1, tool_path)
            if realtime:
                wait_ns = start_ns + t1 * 1000 - clock.now_ns()
                if wait_ns > 0:
                    time.sleep(wait_ns / 1e9)
            now_us = writer.host_us()
            lag = now_us - t1 if realtime else 0
            max_lag_us = max(max_lag_us, lag)
            late += lag > chunk_us
            chunks += 1
            events += len(out.events)
            receive_us = max(now_us, t1) if realtime else t1
            solves = ([last_solve] if last_solve is not None else []) + out.solves
            if bursts is None:
                _publish_chunk(writer, vr, out, receive_us)
            else:
                held.append((bursts.release_after(t1), out))
                held = _publish_released(writer, vr, held, now_us if realtime else t1, realtime)
            next_ft_us = _publish_ft(writer, vr, solves, next_ft_us, t1, ft_period_us, receive_us, ft_drop)
            while next_cnc_us < t1:
                # A status report has no device clock: the host stamps it on arrival, a link's
                # transit after GRBL sampled its position (not when this chunk is published).
                writer.put("cnc", t_host_us=round(next_cnc_us) + CNC_REPORT_TRANSIT_US, position_mm=tool_path(next_cnc_us)[0],
                           feed_mm_min=0.0, state=b"Run")
                next_cnc_us += 1e6 / CNC_RATE_HZ
            publish_truth(writer, out, grid_gel)
            if out.solves:
                last_solve = out.solves[-1]
            if progress is not None:
                progress(t1 / 1e6)
        _publish_released(writer, vr, held, None, realtime)
        writer.phase_end(duration_us)
    if camera_clock_model is not None:
        store_clock_model(writer.path, "camera", camera_clock_model)
    return LiveResult(writer.result, duration_us / 1e6, time.perf_counter() - wall0, max_lag_us / 1000,  # type: ignore[arg-type]
                      late, chunks, events)


def _publish_chunk(writer: RecordingWriter, vr: VirtualRig, out: RigOutput, receive_us: int) -> None:
    ev = out.events
    if len(ev):
        writer.put_events(ev["x"], ev["y"], ev["p"], vr.camera_time_us(ev["t"]), receive_us)
    for t_world, polarity in out.triggers:
        writer.put("triggers", t_device_us=vr.camera_time_us(t_world), polarity=polarity, channel=0)


def _publish_released(
    writer: RecordingWriter, vr: VirtualRig, held: list[tuple[int, RigOutput]], now_us: int | None, realtime: bool
) -> list[tuple[int, RigOutput]]:
    """Publish the held camera chunks whose burst is released by ``now_us`` (None: all, at the end); the rest.

    Stamped with the release (offline) or with the host time now, at or after it (real time)."""
    for release, out in held:
        if now_us is not None and release > now_us:
            break
        _publish_chunk(writer, vr, out, max(writer.host_us(), release) if realtime else release)
    return [item for item in held if now_us is not None and item[0] > now_us]


class _FtDrops:
    """Which F/T samples never reach the host: one draw per sample, in time order."""

    def __init__(self, probability: float, seed: int) -> None:
        self.probability = probability
        self._rng = np.random.default_rng([seed, 8]) if probability > 0 else None

    def kept(self, n: int) -> npt.NDArray[np.bool_] | None:
        """A mask over the next ``n`` samples (None: all kept)."""
        return None if self._rng is None else self._rng.random(n) >= self.probability


def _publish_ft(
    writer: RecordingWriter, vr: VirtualRig, solves: list[Solve], next_us: float, t1: int, period_us: float, receive_us: int,
    drops: _FtDrops,
) -> float:
    times = np.arange(next_us, t1, period_us)
    if times.size == 0 or not solves:
        return next_us
    next_after = float(times[-1] + period_us)
    kept = drops.kept(times.size)
    if kept is not None:
        times = times[kept]
        if times.size == 0:
            return next_after
    t_solve = np.array([s.t_us for s in solves], dtype=np.float64)
    forces, torques = zip(*(vr.ft_wrench(s) for s in solves))
    force = np.stack([np.interp(times, t_solve, np.array(forces)[:, i]) for i in range(3)], axis=1)
    torque = np.stack([np.interp(times, t_solve, np.array(torques)[:, i]) for i in range(3)], axis=1)
    device = (FT_CLOCK_ORIGIN_US + np.floor(times * (1 + FT_CLOCK_DRIFT_PPM * 1e-6))).astype(np.int64) % (1 << 32)
    writer.put(
        "ft",
        t_device_us=device.astype(np.uint32),
        t_host_us=np.full(times.size, receive_us, np.int64),
        force_n=force,
        torque_nm=torque,
        status=np.zeros(times.size, np.uint16),
        temperature_c=np.full(times.size, 30.0, np.float32),
    )
    return next_after


TruthRows = dict[str, dict[str, np.ndarray]]


def truth_rows(out: RigOutput, grid_gel: npt.NDArray[np.float64]) -> TruthRows:
    """A rig chunk's truth as rows for the truth streams (see :func:`truth_streams`), times in world us.

    Compact (the depth on the network grid, not the contact fields), so it can
    cross a process boundary."""
    rows: TruthRows = {}
    if out.truth_t_us.size:
        rows["truth/markers"] = {"t_host_us": out.truth_t_us, "position_mm": out.truth_markers_mm,
                                 "position_px": out.truth_markers_px}
    if out.solves:
        depth, mask = zip(*(_depth_on_grid(s, grid_gel) for s in out.solves))
        t = np.array([s.t_us for s in out.solves], dtype=np.int64)
        rows["truth/contact"] = {
            "t_host_us": t,
            "indentation_mm": np.array([s.depth_mm for s in out.solves]),
            "tip_mm": np.array([s.tip_gel_mm for s in out.solves]),
            "force_n": np.array([s.force_on_gel_n for s in out.solves]),
            "centre_of_pressure_mm": np.array([s.centre_of_pressure_mm for s in out.solves]),
            "sliding": np.array([s.sliding for s in out.solves], dtype=np.uint8),
        }
        rows["truth/marker_forces"] = {"t_host_us": t, "force_n": np.array([s.marker_forces_n for s in out.solves])}
        rows["truth/depth"] = {"t_host_us": t, "depth_mm": np.array(depth), "contact_mask": np.array(mask)}
    return rows


def put_truth_rows(writer: RecordingWriter, rows: TruthRows, offset_us: int = 0) -> None:
    """Put truth rows into ``writer``; recording host time = world time + ``offset_us``."""
    for stream, columns in rows.items():
        writer.put(stream, **{**columns, "t_host_us": columns["t_host_us"] + offset_us})


def publish_truth(
    writer: RecordingWriter, out: RigOutput, grid_gel: npt.NDArray[np.float64], offset_us: int = 0
) -> None:
    """Put a rig chunk's truth into ``writer``'s truth streams; recording host time = world time + ``offset_us``."""
    put_truth_rows(writer, truth_rows(out, grid_gel), offset_us)


#: Per contact anchor and network grid: the grid points on the contact fields (flat index) and their nodes (row, col).
_Nodes = tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.int64]]
_NODE_INDEX: dict[tuple[float | int, ...], tuple[npt.NDArray[np.float64], _Nodes]] = {}


def _depth_on_grid(solve: Solve, grid_gel: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint8]]:
    shape = grid_gel.shape[:2]
    if solve.fields is None or solve.anchor_mm is None:
        return np.zeros(shape, np.float32), np.zeros(shape, np.uint8)
    f = solve.fields
    key = (float(solve.anchor_mm[0]), float(solve.anchor_mm[1]), float(f.x_mm[0]), float(f.x_mm[1]), len(f.x_mm),
           float(f.y_mm[0]), float(f.y_mm[1]), len(f.y_mm), id(grid_gel))
    cached = _NODE_INDEX.get(key)
    if cached is not None and cached[0] is grid_gel:  # the same anchor on the same grid: the same nodes
        at, row, col = cached[1]
    else:
        local = grid_gel.reshape(-1, 2) - solve.anchor_mm
        col = np.rint((local[:, 0] - f.x_mm[0]) / (f.x_mm[1] - f.x_mm[0])).astype(int)
        row = np.rint((local[:, 1] - f.y_mm[0]) / (f.y_mm[1] - f.y_mm[0])).astype(int)
        inside = (col >= 0) & (col < len(f.x_mm)) & (row >= 0) & (row < len(f.y_mm))
        if len(_NODE_INDEX) >= 16:
            _NODE_INDEX.clear()
        at, row, col = np.flatnonzero(inside), row[inside], col[inside]
        _NODE_INDEX[key] = (grid_gel, (at, row, col))
    depth = np.zeros(grid_gel.shape[0] * grid_gel.shape[1], np.float32)
    mask = np.zeros(depth.size, np.uint8)
    depth[at] = f.depth_mm[row, col]
    mask[at] = f.contact_mask[row, col]
    return depth.reshape(shape), mask.reshape(shape)
