"""Where the force loop reads its force: the F/T sensor, or the event sensor's estimate, behind one seam.

The loop (:mod:`labrig.protocol.force_loop`) asks a :class:`ForceReading` for the newest normal force (N on the
gel, pressing positive) and the host time it was *measured*: for the F/T sensor
(:class:`~labrig.protocol.safety.ForceMonitor`) the sample's arrival; for the event sensor
(:class:`EstimateFeedback`) the end of the pipeline window the estimate came from, on the host clock. The pipeline
that fills an :class:`EstimateFeedback` runs beside the probing run: in virtual time on the rendered chunks
(:class:`~labrig.protocol.event_estimate.EventEstimator`), through the drivers in the live pipeline
(:class:`~labrig.live.rig.ProbeStream`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from labrig.protocol.slip import ContactReading

F64 = npt.NDArray[np.float64]

#: The feedbacks a protocol may name: the F/T sensor (800 Hz, the baseline) or the event sensor's estimate.
FEEDBACKS = ("ft", "events")
#: An event estimate older than this stops the loop unless the protocol says otherwise, s. A window's estimate is
#: one window span old when the window closes, and the virtual rig's live camera hands its events over 30-40 ms
#: after they happen, in bursts on a loaded host (measured: reading ages of 18-78 ms through the drivers on two
#: cores); a camera lost or a pipeline far behind stalls beyond that. A real EVK4 delivers within milliseconds:
#: a lab may set ``[control] stale_after_s`` lower.
EVENTS_STALE_AFTER_S = 0.15
#: The same on the embedded virtual rig, s. It renders its camera on the host that runs the pipeline, and on a small
#: machine falls behind real time where the scene is dear (measured on two cores beside the live pipeline: a 5 N
#: press and a sliding shear handed their events over up to 0.12-0.43 s late); a real EVK4 does not. The loop's law
#: uses the tool's place at each reading's time, so a late reading slows it without making it overshoot, and the F/T
#: limits still trip within one sample.
VIRTUAL_RIG_EVENTS_STALE_AFTER_S = 0.5
#: The scatter the force loop allows an event estimate unless the protocol says otherwise (N, 1 sigma; ``[control]
#: reading_noise_n``): an error this small earns half the move a clean reading's would, and a back-off's unloading
#: is believed once the readings have fallen by twice it. The estimate's errors persist for windows, so this is
#: several times the scatter ``labrig evaluate`` reports for a held run (``control_reading_scatter_n``), not that
#: scatter itself.
EVENTS_READING_NOISE_N = 0.3
#: The force loop's settings (``ForceLoopParams`` fields) for ``feedback = "events"`` unless the protocol says
#: otherwise.
EVENTS_LOOP_DEFAULTS: dict[str, Any] = {"stale_after_s": EVENTS_STALE_AFTER_S,
                                        "reading_noise_n": EVENTS_READING_NOISE_N}


class ForceReading(Protocol):
    """A source of the loop's feedback."""

    def normal_reading(self) -> tuple[float, int | None]:
        """The newest normal force on the gel (N, pressing positive) and the host time it was measured (ns; None
        before any)."""
        ...

    def contact_reading(self) -> ContactReading | None:
        """The newest reading with its tangential part (and the dense field where the source has it); None before
        any."""
        ...


@dataclass(frozen=True)
class Estimate:
    """One pipeline window's forces on the gel (gel frame, N; a press: Fz < 0) and its markers' displacements from
    rest (gel frame, mm), measured at ``t_host_ns`` (the window's end, host ns)."""

    t_host_ns: int
    net_force_n: F64  # (3,)
    marker_forces_n: F64  # (M, 3)
    marker_displacements_mm: F64 | None = None  # (M, 3)


class EstimateFeedback:
    """The event sensor's newest estimate, published by the pipeline's thread and read by the loop's."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._newest: Estimate | None = None
        self.windows = 0

    def publish(self, estimate: Estimate) -> None:
        with self._lock:
            self._newest = estimate
            self.windows += 1

    @property
    def newest(self) -> Estimate | None:
        with self._lock:
            return self._newest

    def normal_reading(self) -> tuple[float, int | None]:
        newest = self.newest
        if newest is None:
            return 0.0, None
        return float(-newest.net_force_n[2]), newest.t_host_ns

    def contact_reading(self) -> ContactReading | None:
        newest = self.newest
        if newest is None:
            return None
        return ContactReading(newest.t_host_ns, newest.net_force_n, newest.marker_forces_n,
                              newest.marker_displacements_mm)
