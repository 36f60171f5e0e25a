"""A camera's clock pairs on a loaded host, with their truth, for clock-fit tests and benchmarks.

What the virtual rig's camera delivers with two CPU-bound processes beside the
recorder on a 2-core host (measured with tools/bench/bench_clock.py), drawn in
microseconds without rendering anything:

* **Packets** (device time of a packet's last event, host receive time) arrive
  at least ``floor_us`` after their last event (the renderer's lag) plus an
  exponential jitter; the floor itself moves by up to ``floor_shift_us`` from
  phase to phase (rendering takes longer in contact). For whole stretches the
  renderer falls behind by up to ``behind_max_us`` and catches up again, and
  some packets are late by a heavy-tailed (Pareto) amount.
* **Trigger edges** at each phase start: the camera stamps the edge on its own
  clock; the host stamp is the earliest the edge can have happened (command
  sent plus wire time). ``prompt_edges`` of them were handled at once (the
  edge follows its stamp by an exponential ``edge_jitter_us``, or precedes it
  by up to ``stamp_excess_us`` when the assumed execute time is a little long);
  the others late by a log-normal 0.1-25 ms.
* Optionally an **early burst**: the first packets, a few microseconds of
  device time apart, stamped by a host that was busy elsewhere.

The camera clock runs ``drift_ppm`` fast: ``device_us = origin_us + host_us *
(1 + drift_ppm 1e-6)`` (host us since the recording's start), as the virtual
rig's camera does; the :class:`~labrig.clock.ClockModel` of the truth has the
drift :attr:`LoadedCameraScene.model_drift_ppm`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

#: Phase starts of a 21 s probing run with 4 s waits (approach ... retract), s.
PHASE_STARTS_S: tuple[float, ...] = (0.2, 4.6, 5.8, 9.8, 10.8, 14.8, 15.7, 19.7, 20.9)
#: Stretches (start, end) in s during which the renderer was behind, as in one such run.
BEHIND_STRETCHES_S: tuple[tuple[float, float], ...] = ((4.3, 13.9), (15.0, 17.9), (20.0, 21.6))


@dataclass(frozen=True)
class LoadedCameraScene:
    """One recording's camera clock pairs on a loaded host. Times in us, rates in Hz."""

    drift_ppm: float = 300.0
    duration_s: float = 21.5
    origin_us: int = 11_718_656
    packet_rate_hz: float = 60.0
    floor_us: float = 31_000.0
    floor_jitter_us: float = 150.0
    floor_shift_us: float = 800.0
    behind_s: tuple[tuple[float, float], ...] = BEHIND_STRETCHES_S
    behind_max_us: float = 1_600_000.0
    late_packet_fraction: float = 0.2
    phase_starts_s: tuple[float, ...] = PHASE_STARTS_S
    prompt_edges: int = 4
    edge_jitter_us: float = 25.0
    stamp_excess_us: float = 10.0
    burst_packets: int = 0
    seed: int = 0

    @property
    def model_drift_ppm(self) -> float:
        """The drift of the true device-to-host model (the camera's rate inverted), ppm."""
        return (1.0 / (1.0 + self.drift_ppm * 1e-6) - 1.0) * 1e6

    def device_us(self, host_us: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """The camera's stamp of host times (us since the start), 1 us resolution."""
        return (self.origin_us + np.floor(np.asarray(host_us, np.float64) * (1 + self.drift_ppm * 1e-6))).astype(np.int64)

    def true_host_us(self, device_us: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """When (host us) the camera stamped ``device_us``: the truth a clock model should give."""
        return (np.asarray(device_us, np.float64) - self.origin_us) / (1 + self.drift_ppm * 1e-6)

    def packets(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """(device_us, receive_us) of every packet, in device order."""
        rng = np.random.default_rng(self.seed)
        sent = np.arange(0.0, self.duration_s * 1e6, 1e6 / self.packet_rate_hz)
        sent = sent + rng.uniform(0, 1e6 / self.packet_rate_hz, sent.size)
        phase = np.searchsorted(np.asarray(self.phase_starts_s) * 1e6, sent)
        floor = self.floor_us + rng.uniform(0, self.floor_shift_us, len(self.phase_starts_s) + 1)[phase]
        latency = floor + rng.exponential(self.floor_jitter_us, sent.size)
        late = rng.random(sent.size) < self.late_packet_fraction
        latency[late] += 200.0 * (1 + rng.pareto(1.2, int(late.sum())))
        for start_s, end_s in self.behind_s:
            a, b = start_s * 1e6, end_s * 1e6
            rise = np.clip((sent - a) / (0.3 * (b - a)), 0, None)
            fall = np.clip((b - sent) / (0.7 * (b - a)), 0, None)
            latency += self.behind_max_us * np.clip(np.minimum(rise, fall), 0, 1)
        receive = sent + latency
        if self.burst_packets:
            # The first packets leave a microsecond apart and reach a busy host together.
            sent[: self.burst_packets] = sent[0] + np.arange(self.burst_packets) * 3.0
            receive[: self.burst_packets] = receive[0] + np.arange(self.burst_packets) * 40.0
        return self.device_us(sent), np.floor(receive).astype(np.int64)

    def trigger_pairs(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """(device_us, host stamp us) of the trigger edges at each phase start."""
        rng = np.random.default_rng(self.seed + 1)
        edges = np.asarray(self.phase_starts_s) * 1e6 + rng.uniform(0, 1000, len(self.phase_starts_s))
        lateness = np.exp(rng.uniform(np.log(100.0), np.log(25_000.0), edges.size))
        prompt = rng.choice(edges.size, size=min(self.prompt_edges, edges.size), replace=False)
        lateness[prompt] = rng.exponential(self.edge_jitter_us, prompt.size) - rng.uniform(0, self.stamp_excess_us, prompt.size)
        return self.device_us(edges), np.round(edges - lateness).astype(np.int64)
