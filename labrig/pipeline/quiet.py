"""Quiet windows: when a window's events are only the sensor's background noise, nothing moved.

An event camera reports change. While the indenter rests (before contact, and in the
protocol's waits) a window holds only noise events, spread evenly over the array, and the
depth network answers that nearly empty SAE with a thin false dimple: summed over the gel
by the inverse FEM, tens of newtons of normal force at rest. The gel has not moved, so the
depth map of the last window that saw motion still holds; :class:`QuietHold` keeps it
(zeros before any motion).

The noise floor is a low percentile of recent event rates (events/s in the network's
window): the sensor's noise differs with the sensor, the light and the bias settings, so it
is measured, not configured. A window is quiet when its rate is below ``quiet_ratio`` times
the floor. A stream starts at rest: its first window defines the floor and is quiet. The
floor forgets after ``history_windows``; a motion that never pauses for ``floor_percentile``
percent of that history would raise the floor to its own rate (the protocol pauses between
every phase).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True)
class QuietParams:
    """How quiet windows are found. ``history_windows`` at 10 ms windows is about 20 s."""

    history_windows: int = 2048
    floor_percentile: float = 5.0
    quiet_ratio: float = 1.6

    def __post_init__(self) -> None:
        if self.history_windows < 1:
            raise ValueError("history_windows must be at least 1")
        if not 0.0 <= self.floor_percentile <= 100.0:
            raise ValueError("floor_percentile must be in [0, 100]")
        if self.quiet_ratio <= 0.0:
            raise ValueError("quiet_ratio must be positive")


class NoiseFloor:
    """Running noise-floor estimate over the last windows' event rates (events/s)."""

    def __init__(self, params: QuietParams = QuietParams()) -> None:
        self.params = params
        self._rates_hz: deque[float] = deque(maxlen=params.history_windows)
        self.floor_hz = float("nan")

    def is_quiet(self, n_events: int, duration_us: float) -> bool:
        """Add one window (``n_events`` over ``duration_us``) and say whether it is quiet."""
        rate_hz = n_events / max(float(duration_us), 1.0) * 1e6
        self._rates_hz.append(rate_hz)
        self.floor_hz = float(np.percentile(self._rates_hz, self.params.floor_percentile))
        return rate_hz < self.params.quiet_ratio * self.floor_hz or n_events == 0


class QuietHold:
    """Keeps the last active window's depth map through quiet windows (zeros before any motion)."""

    def __init__(self, shape: tuple[int, ...], params: QuietParams = QuietParams()) -> None:
        self.floor = NoiseFloor(params)
        self.held_mm = np.zeros(shape, np.float32)
        self.quiet = False

    def __call__(self, n_events: int, duration_us: float) -> bool:
        """True when the window is quiet (use :attr:`held_mm`); else call :meth:`update` with its map."""
        self.quiet = self.floor.is_quiet(n_events, duration_us)
        return self.quiet

    def update(self, depth_mm: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        self.held_mm = depth_mm
        return depth_mm
