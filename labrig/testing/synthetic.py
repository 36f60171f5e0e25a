"""Synthetic device streams of one probing run, for tests, benchmarks and the demo.

This is not the virtual rig (labrig.sim): there is no contact mechanics or
optics here, only streams with the right shapes, rates, clocks and latencies.
A piecewise-linear indenter path (Normal Down, Wait, Shear, ...) drives a
Hertz-like normal force, a saturating shear force, and an event rate that
follows the indenter's speed; events fall on rings around a 12 x 13 marker
grid. Each device stamps data on its own drifting clock and delivers it to
the host with USB-like latency, so clock fits have a known truth.

All host times are in the recording's time base (us since the start).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.recording import RecordingMetadata, RecordingWriter

#: (phase, duration weight, dz over the phase in mm, dx over the phase in mm)
PROBING_PATH: tuple[tuple[str, float, float, float], ...] = (
    ("approach", 0.6, -0.5, 0.0),
    ("normal_down", 1.5, -1.2, 0.0),
    ("wait", 0.5, 0.0, 0.0),
    ("shear", 1.0, 0.0, 0.8),
    ("wait", 0.5, 0.0, 0.0),
    ("shear_opposite", 1.0, 0.0, -0.8),
    ("wait", 0.5, 0.0, 0.0),
    ("normal_up", 1.5, 1.2, 0.0),
    ("retract", 0.6, 0.5, 0.0),
)

SENSOR_WIDTH, SENSOR_HEIGHT = 1280, 720
GRID_ROWS, GRID_COLS, PITCH_PX = 12, 13, 56.0
RING_RADIUS_PX = 7.0


@dataclass(frozen=True)
class DeviceClock:
    """A device clock: ``device_us = origin_us + host_send_us * (1 + drift_ppm 1e-6)``."""

    origin_us: int
    drift_ppm: float
    min_latency_us: float = 1000.0
    latency_spread_us: float = 2000.0
    burst_every_s: float = 2.0
    burst_us: float = 20_000.0

    def device_us(self, host_send_us: npt.NDArray[np.float64]) -> npt.NDArray[np.int64]:
        return (self.origin_us + np.floor(host_send_us * (1 + self.drift_ppm * 1e-6))).astype(np.int64)

    def receive_us(self, host_send_us: npt.NDArray[np.float64], rng: np.random.Generator) -> npt.NDArray[np.int64]:
        latency = self.min_latency_us + rng.uniform(0, self.latency_spread_us, host_send_us.shape)
        burst = (np.floor(host_send_us / (self.burst_every_s * 1e6)) % 7 == 3) & (
            (host_send_us % (self.burst_every_s * 1e6)) < 30_000
        )
        latency = latency + burst * rng.uniform(0, self.burst_us, host_send_us.shape)
        return np.floor(host_send_us + latency).astype(np.int64)


@dataclass(frozen=True)
class SyntheticRun:
    """One synthetic probing run. Rates in Hz, durations in s, depths in mm."""

    duration_s: float = 8.0
    peak_event_rate_hz: float = 2e6
    idle_event_rate_hz: float = 20e3
    ft_rate_hz: float = 800.0
    cnc_rate_hz: float = 10.0
    packet_us: int = 1000
    trigger_period_s: float = 0.5
    surface_z_mm: float = -10.0
    stiffness_n_per_mm15: float = 12.0
    friction: float = 0.8
    seed: int = 0
    camera_clock: DeviceClock = field(default_factory=lambda: DeviceClock(origin_us=11_718_656, drift_ppm=35.0))
    ft_clock: DeviceClock = field(default_factory=lambda: DeviceClock(origin_us=4_294_000_000, drift_ppm=-80.0))

    # -- the indenter's path ---------------------------------------------------

    def phase_times_us(self) -> list[tuple[str, int, int]]:
        weights = np.array([w for _, w, _, _ in PROBING_PATH])
        bounds = np.concatenate(([0.0], np.cumsum(weights) / weights.sum())) * self.duration_s * 1e6
        return [(name, int(bounds[i]), int(bounds[i + 1])) for i, (name, *_rest) in enumerate(PROBING_PATH)]

    def pose_mm(self, t_us: npt.ArrayLike) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Indenter (x, z) in machine mm at host times ``t_us``."""
        t = np.asarray(t_us, dtype=np.float64)
        knots_t = [0.0]
        knots_x, knots_z = [0.0], [self.surface_z_mm + 0.5]
        for (_, _, end), (_, _, dz, dx) in zip(self.phase_times_us(), PROBING_PATH):
            knots_t.append(end)
            knots_x.append(knots_x[-1] + dx)
            knots_z.append(knots_z[-1] + dz)
        return np.interp(t, knots_t, knots_x), np.interp(t, knots_t, knots_z)

    def force_n(self, t_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Fx, Fy, Fz on the sensor at host times ``t_us`` (Fz < 0 pressing)."""
        x, z = self.pose_mm(t_us)
        depth = np.clip(self.surface_z_mm - z, 0, None)
        fz = self.stiffness_n_per_mm15 * depth**1.5
        fx = np.clip(x * 6.0, -self.friction * fz, self.friction * fz)
        return np.stack([fx, 0.05 * fx, -fz], axis=1)

    def event_rate_hz(self, t_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        t = np.asarray(t_us, dtype=np.float64)
        dt = 1000.0
        x0, z0 = self.pose_mm(t)
        x1, z1 = self.pose_mm(t + dt)
        speed = np.hypot(x1 - x0, z1 - z0) / dt * 1e6  # mm/s
        in_contact = z0 < self.surface_z_mm
        return self.idle_event_rate_hz + self.peak_event_rate_hz * np.clip(speed / 0.8, 0, 1) * in_contact

    # -- streams (each yields batches in host-receive order) ------------------

    def camera_packets(self) -> Iterator[tuple[Any, ...]]:
        """(x, y, p, t_device_us, t_host_us) per USB packet of ``packet_us``."""
        rng = np.random.default_rng(self.seed)
        centres = _marker_centres()
        starts = np.arange(0, int(self.duration_s * 1e6), self.packet_us, dtype=np.float64)
        rates = self.event_rate_hz(starts)
        counts = rng.poisson(rates * self.packet_us * 1e-6)
        sends = starts + self.packet_us
        receives = self.camera_clock.receive_us(sends, rng)
        for start, n, receive in zip(starts, counts, receives):
            marker = rng.integers(0, len(centres), n)
            angle = rng.uniform(0, 2 * np.pi, n)
            radius = RING_RADIUS_PX + rng.normal(0, 0.8, n)
            x = np.clip(centres[marker, 0] + radius * np.cos(angle), 0, SENSOR_WIDTH - 1).astype(np.uint16)
            y = np.clip(centres[marker, 1] + radius * np.sin(angle), 0, SENSOR_HEIGHT - 1).astype(np.uint16)
            p = (np.cos(angle) > 0).astype(np.uint8)
            t_host = start + np.arange(n) * (self.packet_us / max(n, 1))
            yield x, y, p, self.camera_clock.device_us(t_host), int(receive)

    def ft_batches(self, samples_per_batch: int = 8) -> Iterator[dict[str, npt.NDArray[Any]]]:
        """F/T samples in small batches, raw uint32 device stamps that wrap."""
        rng = np.random.default_rng(self.seed + 1)
        period_us = 1e6 / self.ft_rate_hz
        sends = np.arange(0, self.duration_s * 1e6, period_us)
        receives = self.ft_clock.receive_us(sends, rng)
        force = self.force_n(sends) + rng.normal(0, 0.01, (sends.size, 3))
        torque = np.stack([force[:, 1] * 0.02, -force[:, 0] * 0.02, force[:, 0] * 0.001], axis=1)
        device = self.ft_clock.device_us(sends) % (1 << 32)
        for i in range(0, sends.size, samples_per_batch):
            s = slice(i, i + samples_per_batch)
            n = len(sends[s])
            yield {
                "t_device_us": device[s].astype(np.uint32),
                "t_host_us": receives[s],
                "force_n": force[s].astype(np.float32),
                "torque_nm": torque[s].astype(np.float32),
                "status": np.zeros(n, np.uint16),
                "temperature_c": np.full(n, 31.5, np.float32),
            }

    def cnc_samples(self) -> Iterator[dict[str, Any]]:
        rng = np.random.default_rng(self.seed + 2)
        times = np.arange(0, self.duration_s * 1e6, 1e6 / self.cnc_rate_hz)
        x, z = self.pose_mm(times)
        moving = np.abs(np.gradient(z)) + np.abs(np.gradient(x)) > 1e-6
        for t, xi, zi, mv in zip(times, x, z, moving):
            yield {
                "t_host_us": int(t + rng.uniform(2000, 6000)),
                "position_mm": [xi, 0.0, zi],
                "feed_mm_min": 48.0 if mv else 0.0,
                "state": b"Run" if mv else b"Idle",
            }

    def protocol_events(self) -> Iterator[tuple[str, dict[str, Any]]]:
        """("phase", {...}), ("gcode", {...}) and ("trigger", {...}) in host-time order."""
        items: list[tuple[int, str, dict[str, Any]]] = []
        for name, start, end in self.phase_times_us():
            items.append((start, "phase", {"name": name, "t_host_us": start}))
            _, z = self.pose_mm([end])
            items.append((start, "gcode", {"t_host_us": start, "direction": 0, "line": f"G1 Z{z[0]:.3f} F48".encode()}))
            items.append((start + 4000, "gcode", {"t_host_us": start + 4000, "direction": 1, "line": b"ok"}))
        if self.trigger_period_s > 0:
            for k, t in enumerate(np.arange(self.trigger_period_s / 2, self.duration_s, self.trigger_period_s) * 1e6):
                items.append((int(t), "trigger", {"t_host_us": int(t), "polarity": (k + 1) % 2, "t_latest_host_us": int(t)}))
        items.sort(key=lambda item: item[0])
        for _, kind, payload in items:
            yield kind, payload

    def trigger_edges_device_us(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint8]]:
        """What the camera stamps for each trigger edge (device us, polarity)."""
        host, polarity = [], []
        for kind, payload in self.protocol_events():
            if kind == "trigger":
                host.append(payload["t_host_us"])
                polarity.append(payload["polarity"])
        return self.camera_clock.device_us(np.array(host, np.float64)), np.array(polarity, np.uint8)


def _marker_centres() -> npt.NDArray[np.float64]:
    cols, rows = np.meshgrid(np.arange(GRID_COLS), np.arange(GRID_ROWS))
    x = SENSOR_WIDTH / 2 + (cols.ravel() - (GRID_COLS - 1) / 2) * PITCH_PX
    y = SENSOR_HEIGHT / 2 + (rows.ravel() - (GRID_ROWS - 1) / 2) * PITCH_PX
    return np.stack([x, y], axis=1)


def feed_writer(writer: Any, run: SyntheticRun) -> None:
    """Run the camera, F/T, CNC and protocol producers as threads into ``writer``.

    ``writer`` is an open :class:`labrig.recording.RecordingWriter`. Producers
    push as fast as they can (no real-time pacing); times are the synthetic ones.
    """
    import threading

    edges_dev, edges_pol = run.trigger_edges_device_us()

    def camera() -> None:
        for x, y, p, t_dev, t_host in run.camera_packets():
            writer.put_events(x, y, p, t_dev, t_host)
        if edges_dev.size:
            writer.put("triggers", t_device_us=edges_dev, polarity=edges_pol, channel=np.zeros(edges_dev.size, np.uint8))

    def ft() -> None:
        for batch in run.ft_batches():
            writer.put("ft", **batch)

    def cnc() -> None:
        for sample in run.cnc_samples():
            writer.put("cnc", **sample)

    def protocol() -> None:
        for kind, payload in run.protocol_events():
            if kind == "phase":
                writer.phase_begin(payload["name"], payload["t_host_us"])
            elif kind == "gcode":
                writer.put("gcode", **payload)
            else:
                writer.put("trigger_out", **payload)
        writer.phase_end(int(run.duration_s * 1e6))

    threads = [threading.Thread(target=f, name=f"synthetic-{f.__name__}") for f in (camera, ft, cnc, protocol)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()


def record_synthetic(path: Any, run: SyntheticRun | None = None, **writer_kwargs: Any) -> Any:
    """Write one synthetic run through the real writer; returns its RecordingResult."""
    run = run or SyntheticRun()
    metadata = RecordingMetadata(indenter="sphere", protocol_toml="# synthetic probing run\n", extra={"synthetic": True})
    with RecordingWriter(path, metadata, **writer_kwargs) as writer:
        feed_writer(writer, run)
    return writer.result
