"""Normal-force regulation as a state machine: a force reading in, a velocity along the gel normal out.

Sans-I/O, in the manner of :mod:`labrig.devices.grbl_protocol`: :meth:`ForceLoop.update` takes the time
and the newest normal force (N on the gel, pressing positive; from the F/T sensor or from the event
sensor's estimate) and returns a :class:`LoopCommand`: the speed to press in at (mm/s along the gel's
inward normal; negative backs off) for the next segment, or a stop with its reason. An executor turns
the command into motion (a short jog segment through the drivers, the tool's path in virtual time) and
calls again when the next reading arrives.

The law is proportional-integral on the force error, in velocity: ``v = kp e + ki integral(e)``, clipped to
``max_speed_mm_s``. The gel is a spring (about 2-10 N/mm for the shipped indenters), so pressing at ``v``
changes the force at ``k v``: the proportional term alone gives a first-order approach to the target
with time constant ``1 / (k kp)`` and no steady error for a constant target; the integral term takes out
the steady error of a drifting load (a shear that unloads the normal). The error accumulates only within
``integral_band_n`` of the target and while the command is not clipped, so a step's approach winds up no
integral to be worked off slowly after it.

Trips, each a stop with one line saying why (the executor then stops the motion and retracts):

* **stalled**: the newest reading is older than ``stale_after_s`` (a camera lost, a pipeline behind);
* **saturated**: the command stayed clipped for ``saturation_s`` (a target the rig cannot reach);
* **oscillating**: the error changed sign ``oscillation_crossings`` times within ``oscillation_window_s``
  with an amplitude over ``oscillation_band_n`` (gains too high for the gel or the feedback's delay).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.recording.schema import Column, StreamSpec


@dataclass(frozen=True)
class ForceLoopParams:
    """Gains and limits of the normal-force loop (units in the names)."""

    kp_mm_s_per_n: float = 1.5  # press-in speed per newton of error
    segment_s: float = 0.01  # a command's span: the loop reads and commands this often
    ki_mm_s_per_n_s: float = 1.0  # press-in speed per newton-second of accumulated error
    integral_band_n: float = 0.5  # the error accumulates only while within this of the target
    max_speed_mm_s: float = 2.0  # either way along the normal
    stale_after_s: float = 0.02  # a reading older than this stops the loop
    saturation_s: float = 3.0  # clipped this long: the target is out of reach
    oscillation_band_n: float = 0.5  # error swings under this are not counted as oscillation
    oscillation_crossings: int = 4  # sign changes of the error (each over the band) ...
    oscillation_window_s: float = 1.0  # ... within this long trip the loop

    def __post_init__(self) -> None:
        for name in ("kp_mm_s_per_n", "segment_s", "max_speed_mm_s", "stale_after_s", "saturation_s",
                     "oscillation_window_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, not {value}")
        if not (math.isfinite(self.ki_mm_s_per_n_s) and self.ki_mm_s_per_n_s >= 0):
            raise ValueError(f"ki_mm_s_per_n_s must be zero or positive, not {self.ki_mm_s_per_n_s}")
        if not (math.isfinite(self.integral_band_n) and self.integral_band_n >= 0):
            raise ValueError(f"integral_band_n must be zero or positive, not {self.integral_band_n}")
        if self.oscillation_crossings < 2 or self.oscillation_band_n < 0:
            raise ValueError("oscillation_crossings must be at least 2 and oscillation_band_n not negative")


@dataclass(frozen=True)
class LoopCommand:
    """What to do until the next reading: press in at ``speed_mm_s`` (mm/s along the gel's inward normal,
    negative backs off), or stop (``stop`` the reason, ``speed_mm_s`` 0). ``error_n``: target minus reading;
    ``clipped``: the speed is at its limit."""

    speed_mm_s: float
    error_n: float
    clipped: bool = False
    stop: str | None = None


class ForceLoop:
    """The loop for one target (N on the gel, pressing positive); :meth:`update` once per reading."""

    def __init__(self, target_n: float, params: ForceLoopParams | None = None) -> None:
        if not (math.isfinite(target_n) and target_n >= 0):
            raise ValueError(f"the force target must be zero or positive (N), not {target_n}")
        self.params = params or ForceLoopParams()
        self.target_n = float(target_n)
        self.integral_n_s = 0.0
        self.stopped: str | None = None
        self._last_t_s: float | None = None
        self._clipped_since_s: float | None = None
        self._last_sign = 0
        self._crossings: deque[float] = deque()

    def retarget(self, target_n: float) -> None:
        """A new target (a step); the integral is kept (it holds the load's drift)."""
        if not (math.isfinite(target_n) and target_n >= 0):
            raise ValueError(f"the force target must be zero or positive (N), not {target_n}")
        self.target_n = float(target_n)

    def update(self, t_s: float, force_n: float, reading_t_s: float | None = None) -> LoopCommand:
        """The command at time ``t_s`` (s, any fixed origin) from the newest reading ``force_n`` (N, pressing
        positive) taken at ``reading_t_s`` (default ``t_s``). Once stopped, every later call stops too."""
        p = self.params
        error = self.target_n - float(force_n)
        if self.stopped is not None:
            return LoopCommand(0.0, error, stop=self.stopped)
        age_s = t_s - (t_s if reading_t_s is None else reading_t_s)
        if age_s > p.stale_after_s or not math.isfinite(force_n):
            return self._stop(error, f"the force feedback stalled: the newest reading is {age_s * 1e3:.0f} ms old "
                                     f"(more than {p.stale_after_s * 1e3:.0f} ms)")
        dt = 0.0 if self._last_t_s is None else max(t_s - self._last_t_s, 0.0)
        self._last_t_s = t_s
        raw = p.kp_mm_s_per_n * error + p.ki_mm_s_per_n_s * (self.integral_n_s + error * dt)
        clipped = abs(raw) > p.max_speed_mm_s
        if not clipped and abs(error) <= p.integral_band_n:
            self.integral_n_s += error * dt
        else:
            raw = p.kp_mm_s_per_n * error + p.ki_mm_s_per_n_s * self.integral_n_s
            clipped = abs(raw) > p.max_speed_mm_s
        speed = float(np.clip(raw, -p.max_speed_mm_s, p.max_speed_mm_s))
        if clipped:
            self._clipped_since_s = t_s if self._clipped_since_s is None else self._clipped_since_s
            if t_s - self._clipped_since_s >= p.saturation_s:
                return self._stop(error, f"saturated: the speed stayed at its {p.max_speed_mm_s:g} mm/s limit for "
                                         f"{p.saturation_s:g} s with the force {error:+.2f} N off its target")
        else:
            self._clipped_since_s = None
        if self._oscillating(t_s, error):
            return self._stop(error, f"oscillating: the force crossed its target {p.oscillation_crossings} times "
                                     f"within {p.oscillation_window_s:g} s by more than {p.oscillation_band_n:g} N; "
                                     "lower kp_mm_s_per_n")
        return LoopCommand(speed, error, clipped)

    def _oscillating(self, t_s: float, error: float) -> bool:
        p = self.params
        if abs(error) <= p.oscillation_band_n:
            return False
        sign = 1 if error > 0 else -1
        if self._last_sign and sign != self._last_sign:
            self._crossings.append(t_s)
        self._last_sign = sign
        while self._crossings and t_s - self._crossings[0] > p.oscillation_window_s:
            self._crossings.popleft()
        return len(self._crossings) >= p.oscillation_crossings

    def _stop(self, error: float, reason: str) -> LoopCommand:
        self.stopped = reason
        return LoopCommand(0.0, error, stop=reason)


# -- how well a loop did -------------------------------------------------------------------------------


@dataclass(frozen=True)
class StepResponse:
    """A step to ``target_n`` (N) from ``start_n``: 10-90 % rise time (s), overshoot (% of the step),
    settling time into +/- ``band`` of the step for good (s; nan if it never settles); times from the step."""

    target_n: float
    start_n: float
    rise_s: float
    overshoot_pct: float
    settling_s: float


def step_response(t_s: npt.ArrayLike, force_n: npt.ArrayLike, target_n: float, t_step_s: float = 0.0,
                  start_n: float | None = None, band: float = 0.05) -> StepResponse:
    """The :class:`StepResponse` of readings ``force_n`` (N) at times ``t_s`` (s, increasing) to a step to
    ``target_n`` at ``t_step_s``; ``start_n``: the force before the step (default the last reading before it,
    else the first)."""
    t = np.asarray(t_s, np.float64)
    f = np.asarray(force_n, np.float64)
    after = t >= t_step_s
    if not after.any():
        raise ValueError("no reading after the step")
    if start_n is None:
        start_n = float(f[~after][-1]) if (~after).any() else float(f[0])
    t, f = t[after] - t_step_s, f[after]
    size = target_n - start_n
    if size == 0:
        raise ValueError("a step needs a target other than its start")
    progress = (f - start_n) / size  # 0 at the start, 1 at the target
    ten, ninety = np.flatnonzero(progress >= 0.1), np.flatnonzero(progress >= 0.9)
    rise = float(t[ninety[0]] - t[ten[0]]) if ten.size and ninety.size else math.nan
    overshoot = max(float(progress.max()) - 1.0, 0.0) * 100.0
    outside = np.flatnonzero(np.abs(progress - 1.0) > band)
    if outside.size == 0:
        settling = 0.0
    elif outside[-1] + 1 < t.size:
        settling = float(t[outside[-1] + 1])
    else:
        settling = math.nan
    return StepResponse(float(target_n), float(start_n), rise, overshoot, settling)


def hold_rms_n(force_n: npt.ArrayLike, target_n: float) -> float:
    """RMS (N) of the readings' distance from the target while it was held."""
    f = np.asarray(force_n, np.float64)
    if f.size == 0:
        raise ValueError("no readings")
    return float(np.sqrt(np.mean((f - target_n) ** 2)))


# -- a move with the loop on the normal -------------------------------------------------------------------


class HeldMove:
    """The jog segments of a move along the gel plane with the force loop on the normal.

    From ``start_mm`` (machine mm) toward ``target_mm``'s place in the gel plane (its component along ``normal``,
    the gel's inward unit normal in machine axes, is ignored) at ``speed_mm_s``, in segments of the loop's
    ``segment_s``; the loop moves the tool along ``normal`` by its command times the segment, never further in
    than ``deepest_mm`` (a point the tool's component along ``normal`` stays at or short of: the deepest press
    allowed). An executor calls :meth:`next_segment` once per segment with the newest reading and sends the
    segment it returns."""

    def __init__(self, start_mm: npt.ArrayLike, target_mm: npt.ArrayLike, normal: npt.ArrayLike,
                 speed_mm_s: float, loop: ForceLoop, deepest_mm: npt.ArrayLike | None = None) -> None:
        self.start = np.asarray(start_mm, np.float64)
        self.normal = np.asarray(normal, np.float64) / np.linalg.norm(normal)
        delta = np.asarray(target_mm, np.float64) - self.start
        self.lateral = delta - (delta @ self.normal) * self.normal
        self.loop = loop
        segment_mm = speed_mm_s * loop.params.segment_s
        self.segments = max(1, math.ceil(float(np.linalg.norm(self.lateral)) / segment_mm - 1e-9))
        self.done = 0
        self.normal_mm = 0.0  # along the inward normal since the start
        self.last = LoopCommand(0.0, 0.0)
        self._end = self.start.copy()
        self.max_normal_mm = math.inf if deepest_mm is None else float(
            (np.asarray(deepest_mm, np.float64) - self.start) @ self.normal)

    def next_segment(self, t_s: float, force_n: float, reading_t_s: float | None = None
                     ) -> tuple[npt.NDArray[np.float64], float] | str | None:
        """The next segment's end (machine mm) and feed (mm/min); the loop's stop (its reason) instead; None once
        the move's last segment has been handed out."""
        if self.done >= self.segments:
            return None
        command = self.loop.update(t_s, force_n, reading_t_s)
        self.last = command
        if command.stop is not None:
            return command.stop
        self.done += 1
        self.normal_mm = min(self.normal_mm + command.speed_mm_s * self.loop.params.segment_s, self.max_normal_mm)
        end = self.start + self.lateral * (self.done / self.segments) + self.normal * self.normal_mm
        feed_mm_min = max(float(np.linalg.norm(end - self._end)) / self.loop.params.segment_s * 60, 1.0)
        self._end = end
        return end, feed_mm_min


#: What the loop did, segment by segment (a recording of a run that holds a force has it).
CONTROL_STREAM = StreamSpec(
    "control",
    (
        Column("t_host_us", "<i8", "us", "host time the segment was commanded"),
        Column("target_n", "<f4", "N", "the normal force to hold, on the gel, pressing positive"),
        Column("feedback_n", "<f4", "N", "the reading the command came from"),
        Column("reading_age_us", "<i8", "us", "how old the reading was"),
        Column("speed_mm_s", "<f4", "mm/s", "commanded press-in speed along the gel normal"),
        Column("clipped", "u1", "", "1: the speed was at its limit"),
        Column("position_mm", "<f8", "mm", "the segment's end, machine X, Y, Z", (3,)),
    ),
    chunk_rows=1024,
    description="the force loop's commands (feedback, command, segment)",
)
