"""Safety for probing runs: limits checked before any move, forces watched on every sample, stop requests.

* :class:`SafetyLimits`: the machine workspace the runner may command, the gel
  margin, and per-axis force limits (the indenter's, capped by the rig's).
* :func:`check_targets`: every planned target inside the workspace, refused
  before the first move with one line per problem.
* :class:`SpeedLimits`: the CNC's max rates (``$110-$112``: the virtual rig's ``[sim.grbl]``,
  or the connected controller's ``$$``); a protocol speed above them is refused before any
  move, never silently run slower.
* :class:`ForceMonitor`: sees every F/T sample (from the sensor's reader
  thread). Over a limit it calls ``on_trip`` at once (the runner wires a GRBL
  feed hold: the machine decelerates within one sample period of the
  violation); armed for contact or a force target it calls ``on_reached``
  (a jog cancel) the same way.
* :class:`StopRequest`: Ctrl-C levels. The first asks the runner to finish the
  current phase and stop safely; the second to hold and retract at once.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from labrig.config import RigConfig
from labrig.errors import LabrigError
from labrig.protocol.slip import ContactReading
from labrig.protocol.spec import ProbeSpec
from labrig.sim.truth_config import sim_config


class SafetyError(LabrigError):
    """A plan or a run that would break a safety limit."""


#: A press stops at least this far above an indenter's ``max_depth_mm`` (the gel model's depth), mm:
#: the contact is detected a few micrometres into the gel and the gel's tilt adds depth along a
#: shear, so a depth exactly at the limit ends beyond it.
DEPTH_HEADROOM_MM = 0.05


def deepest_press_mm(max_depth_mm: float) -> float:
    """The deepest depth below contact (mm) a run may ask for with an indenter of this ``max_depth_mm``."""
    return round(max_depth_mm - DEPTH_HEADROOM_MM, 6)


def depth_problem(depth_mm: float, indenter_name: str, max_depth_mm: float) -> str | None:
    """What is wrong with pressing ``depth_mm`` below contact (None: nothing): beyond the indenter's
    ``max_depth_mm`` or within :data:`DEPTH_HEADROOM_MM` of it."""
    deepest = deepest_press_mm(max_depth_mm)
    if depth_mm <= deepest:
        return None
    if depth_mm > max_depth_mm:
        return f"{depth_mm} mm is beyond the {indenter_name}'s max_depth_mm {max_depth_mm}; use at most {deepest:g} mm"
    return (f"{depth_mm} mm leaves no headroom below the {indenter_name}'s max_depth_mm {max_depth_mm} (the gel model's "
            f"depth; contact is detected a little into the gel); use at most {deepest:g} mm")


@dataclass(frozen=True)
class SafetyLimits:
    """Machine-coordinate workspace (mm), gel margin (mm) and force limits (N, tared, sensor axes).

    ``body_margin_mm``: how far beyond the gel (grown by the indenter's footprint) the sensor body
    that carries it is solid below the gel surface, for the hand tools' motion envelope
    (:mod:`labrig.protocol.envelope`).
    """

    workspace_min_mm: tuple[float, float, float] = (-200.0, -200.0, -200.0)
    workspace_max_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gel_margin_mm: float = 1.0
    clearance_mm: float = 5.0
    max_normal_force_n: float = 25.0
    max_shear_force_n: float = 6.0
    body_margin_mm: float = 10.0

    def for_indenter(self, max_normal_force_n: float, max_shear_force_n: float) -> SafetyLimits:
        """These limits capped by an indenter's own."""
        return replace(self, max_normal_force_n=min(self.max_normal_force_n, max_normal_force_n),
                       max_shear_force_n=min(self.max_shear_force_n, max_shear_force_n))


def check_targets(targets: Sequence[tuple[str, npt.ArrayLike]], limits: SafetyLimits) -> None:
    """Raise :class:`SafetyError` listing every named machine target outside the workspace."""
    lo, hi = np.asarray(limits.workspace_min_mm), np.asarray(limits.workspace_max_mm)
    problems = []
    for name, target in targets:
        p = np.asarray(target, dtype=np.float64)
        for axis, value, low, high in zip("XYZ", p, lo, hi, strict=True):
            if not low - 1e-9 <= value <= high + 1e-9:
                problems.append(f"{name}: {axis} = {value:.3f} mm is outside the workspace [{low:.1f}, {high:.1f}] mm")
    if problems:
        raise SafetyError("refused before moving:\n  " + "\n  ".join(problems)
                          + "\n  check the location, depth and the rig's [safety] workspace and gel pose")


#: The speeds of a run and the machine axes each moves along: the normal moves (approach, press,
#: retract) along Z, shears in the gel plane along X and Y (held to the slower of the two).
SPEED_AXES: dict[str, tuple[int, ...]] = {"approach.speed_mm_s": (2,), "normal_speed_mm_s": (2,),
                                          "shear_speed_mm_s": (0, 1), "retract_speed_mm_s": (2,)}

#: Each speed field's key in a protocol file.
SPEED_KEYS = {"approach.speed_mm_s": "approach.speed_mm_s", "normal_speed_mm_s": "normal.speed_mm_s",
              "shear_speed_mm_s": "shear.speed_mm_s", "retract_speed_mm_s": "retract.speed_mm_s"}


@dataclass(frozen=True)
class SpeedLimits:
    """A CNC's per-axis max rates (mm/min, x, y, z: GRBL's ``$110-$112``) and where they are set."""

    max_rate_mm_min: tuple[float, float, float]
    virtual: bool  # the virtual rig's [sim.grbl], else a connected controller's settings

    @classmethod
    def of_rig(cls, rig: RigConfig) -> SpeedLimits:
        """The virtual CNC's: the rig file's ``[sim.grbl]`` (GRBL's defaults without one)."""
        return cls(sim_config(rig).grbl.max_rate_mm_min, virtual=True)

    @classmethod
    def of_grbl(cls, settings: Mapping[int, float]) -> SpeedLimits | None:
        """A connected controller's, from its ``$$`` settings; None if they lack ``$110-$112``."""
        if not all(n in settings for n in (110, 111, 112)):
            return None
        return cls((float(settings[110]), float(settings[111]), float(settings[112])), virtual=False)

    def problems(self, spec: ProbeSpec) -> list[tuple[str, str]]:
        """(field, message) for each speed of ``spec`` above the max rate of an axis it moves along."""
        out = []
        for field, axes in SPEED_AXES.items():
            if field == "shear_speed_mm_s" and not spec.has_shear:
                continue
            speed = spec.approach.speed_mm_s if field == "approach.speed_mm_s" else float(getattr(spec, field))
            axis = min(axes, key=lambda i: self.max_rate_mm_min[i])
            limit_mm_s = self.max_rate_mm_min[axis] / 60.0
            if speed > limit_mm_s + 1e-9:
                out.append((field, f"{speed:g} mm/s is above {self._limit_text(axis)}; {self._remedy(axis, limit_mm_s)}"))
        return out

    def check(self, spec: ProbeSpec) -> None:
        """Raise :class:`SafetyError` (before any move) if a speed of ``spec`` is above the max rates."""
        found = self.problems(spec)
        if found:
            raise SafetyError("refused before moving: " + "; ".join(f"{SPEED_KEYS[field]} {message}" for field, message in found))

    def _limit_text(self, axis: int) -> str:
        rate = self.max_rate_mm_min[axis]
        where = (f"[sim.grbl] max_rate_mm_min = {rate:g} mm/min" if self.virtual else f"${110 + axis} = {rate:g} mm/min")
        machine = "the virtual CNC" if self.virtual else "the connected GRBL"
        return f"{machine}'s {'XYZ'[axis]} max rate {rate / 60:.3g} mm/s ({where})"

    def _remedy(self, axis: int, limit_mm_s: float) -> str:
        where = ("raise max_rate_mm_min in the rig file's [sim.grbl] (or a campaign's [vary])" if self.virtual
                 else f"raise ${110 + axis} on the controller")
        return f"{where}, or give at most {limit_mm_s:.3g} mm/s"


def check_location(location_mm: tuple[float, float], size_mm: tuple[float, float], footprint_radius_mm: float,
                   margin_mm: float) -> None:
    """The contact location (gel frame) keeps the indenter's footprint ``margin_mm`` inside the gel edge.

    Long footprints (a ridge) only need their centre inside: the check uses the smaller of
    the footprint radius and 3 mm, so edge probing with a sphere stays possible.
    """
    reach = min(footprint_radius_mm, 3.0) + margin_mm
    half_x, half_y = size_mm[0] / 2 - reach, size_mm[1] / 2 - reach
    x, y = location_mm
    if abs(x) > half_x or abs(y) > half_y:
        raise SafetyError(f"location ({x:.2f}, {y:.2f}) mm is too close to the gel's edge: keep |x| <= {half_x:.2f} "
                          f"and |y| <= {half_y:.2f} mm for this indenter")


@dataclass(frozen=True)
class Trip:
    """Why the monitor stopped the machine."""

    reason: str
    force_n: tuple[float, float, float]
    t_host_ns: int


class ForceMonitor:
    """Watches tared forces on every sample; trips once on a limit, fires once on an armed target."""

    def __init__(self, limits: SafetyLimits, on_trip: Callable[[], None]) -> None:
        self.limits = limits
        self.on_trip = on_trip
        # Python floats: a sample (800 Hz) makes no small arrays.
        self._baseline = [0.0, 0.0, 0.0]
        self._peak = [0.0, 0.0, 0.0]
        self._last = (0.0, 0.0, 0.0)
        self.last_t_host_ns: int | None = None  # when the last sample arrived
        self.trip: Trip | None = None
        self.samples = 0
        self._lock = threading.Lock()
        self._armed: tuple[str, float, Callable[[], None]] | None = None
        self._reached = threading.Event()
        self.reached_force_n: tuple[float, float, float] | None = None
        self._recent_fz = np.zeros(1)
        self._recent_i = 0

    @property
    def baseline_n(self) -> npt.NDArray[np.float64]:
        """Subtracted from every sample (N)."""
        return np.array(self._baseline)

    @property
    def peak_n(self) -> npt.NDArray[np.float64]:
        """Largest |F| per axis seen (N); assign to restart it."""
        return np.array(self._peak)

    @peak_n.setter
    def peak_n(self, value: npt.ArrayLike) -> None:
        with self._lock:
            self._peak = np.asarray(value, dtype=np.float64).reshape(3).tolist()

    @property
    def last_n(self) -> npt.NDArray[np.float64]:
        """The last sample less the baseline (N)."""
        return np.array(self._last)

    def normal_reading(self) -> tuple[float, int | None]:
        """The last sample's tared |Fz| (N) and when it arrived (host ns; None before any)."""
        with self._lock:
            return abs(self._last[2]), self.last_t_host_ns

    def contact_reading(self) -> ContactReading | None:
        """The last sample, tared, as the force on the gel (the sensor's x, y as the gel's; Fz pressing negative);
        None before any."""
        with self._lock:
            if self.last_t_host_ns is None:
                return None
            x, y, z = self._last
            return ContactReading(self.last_t_host_ns, np.array([x, y, -abs(z)]))

    def set_baseline(self, force_n: npt.ArrayLike) -> None:
        with self._lock:
            self._baseline = np.asarray(force_n, dtype=np.float64).reshape(3).tolist()

    def arm(self, kind: str, threshold_n: float, on_reached: Callable[[], None], *,
            average_samples: int = 1) -> threading.Event:
        """Fire ``on_reached`` once when the mean |Fz| of the last ``average_samples`` samples
        exceeds ``threshold_n`` (kind "contact" or "force"); returns the event set then."""
        with self._lock:
            self._reached.clear()
            self.reached_force_n = None
            self._recent_fz = np.zeros(max(1, int(average_samples)))
            self._recent_i = 0
            self._armed = (kind, float(threshold_n), on_reached)
        return self._reached

    def disarm(self) -> None:
        with self._lock:
            self._armed = None

    def on_sample(self, t_host_ns: int, force_n: npt.ArrayLike) -> None:
        """Call for every F/T sample (sensor axes, raw); cheap."""
        x, y, z = force_n if isinstance(force_n, tuple) else np.asarray(force_n, dtype=np.float64).reshape(3).tolist()
        fire: Callable[[], None] | None = None
        trip: Callable[[], None] | None = None
        with self._lock:
            b = self._baseline
            f = (x - b[0], y - b[1], z - b[2])
            self.samples += 1
            self._last = f
            self.last_t_host_ns = t_host_ns
            peak = self._peak
            for i in range(3):
                size = abs(f[i])
                if not size <= peak[i] and peak[i] == peak[i]:  # as np.maximum: a NaN comes and stays
                    peak[i] = size
            shear = math.hypot(f[0], f[1])
            if self.trip is None:
                if abs(f[2]) > self.limits.max_normal_force_n:
                    self.trip = Trip(f"normal force |Fz| = {abs(f[2]):.2f} N over the limit "
                                     f"{self.limits.max_normal_force_n:.2f} N", f, t_host_ns)
                elif shear > self.limits.max_shear_force_n:
                    self.trip = Trip(f"shear force |Fxy| = {shear:.2f} N over the limit "
                                     f"{self.limits.max_shear_force_n:.2f} N", f, t_host_ns)
                if self.trip is not None:
                    trip = self.on_trip
            if self._armed is not None:
                self._recent_fz[self._recent_i % self._recent_fz.size] = abs(f[2])
                self._recent_i += 1
                if self._recent_i >= self._recent_fz.size and float(self._recent_fz.mean()) > self._armed[1]:
                    fire = self._armed[2]
                    self._armed = None
                    self.reached_force_n = f
        if trip is not None:
            trip()
        if fire is not None:
            fire()
            self._reached.set()


class StopRequest:
    """Ctrl-C levels: 0 run, 1 finish the phase and stop, 2 hold and retract now."""

    def __init__(self) -> None:
        self._level = 0
        self._lock = threading.Lock()
        self.changed = threading.Event()

    @property
    def level(self) -> int:
        return self._level

    def request(self) -> int:
        """One more press; returns the new level."""
        with self._lock:
            self._level = min(self._level + 1, 2)
            self.changed.set()
            return self._level

    def reset(self) -> None:
        with self._lock:
            self._level = 0
            self.changed.clear()
