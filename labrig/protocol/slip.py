"""Slip of the indenter on the gel, told from a force reading: the reflex a held shear may have.

Sans-I/O: :meth:`SlipDetector.update` takes a :class:`ContactReading` (the net force on the gel and, from the event
sensor's estimate, the force on each marker's cell) and says whether the contact slips. Under Coulomb friction
``mu`` a patch of the contact slides where its tangential traction reaches ``mu`` times its normal traction; the
slip spreads in from the contact's edge as a shear goes on, and the whole contact slides (gross slip) once every
patch is at the limit, when the net tangential force reaches ``mu`` times the normal force.

* **From the dense field** (the event sensor's estimate): the share of the contact's markers (those carrying at
  least ``contact_fraction`` of the most loaded marker's normal force) whose tangential force reaches
  ``at_friction * mu`` times their normal force. The contact slips when the share reaches ``share``.
* **From the net force** (the F/T sensor, which has no field): the contact slips when ``|Ft| / (mu |Fn|)`` reaches
  ``net_ratio``.

* **From the tangential force's stall** (either source, given the tool's travel along the shear at each reading's
  time): sticking, the tangential force rises in proportion to the travel (the contact's tangential stiffness);
  sliding as a whole, it stops rising while the tool shears on. The contact slips when the slope of |Ft| against the
  travel over the last ``stall_span_mm`` has fallen to ``stall_ratio`` of the steepest it has been in this move,
  with the net force at least ``stall_friction_ratio`` of friction (a stick that has hardly loaded is not a slide).
  It needs no estimate of friction's share per marker, so it tells a flat punch or a ridge whose estimated field
  never reaches friction at every marker.
* **From the field's stall** (the event sensor's estimate, with the tool's travel): sticking, the contact's markers
  are dragged along with the tool; sliding as a whole, they stay where friction holds them while the tool shears on.
  The contact slips when the slope of the contact's tangential displacement (its markers' displacements weighted by
  their normal force) against the travel over the last ``follow_span_mm`` has fallen to ``follow_ratio`` of its
  steepest, with the same friction gate. The markers are tracked in every window, so where they stop with the
  slide this slope turns at once; a sliding edge can drag the tracked markers near it along, and then it turns
  late.

Each cue must hold on its own in ``persist`` fresh readings in a row. What a held shear does then is the protocol's
``[slip] action`` (:data:`SLIP_ACTIONS`): record it, stop the shear where it is, or press harder until the
tangential force is ``press_ratio`` of friction again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

#: What a held shear does when its contact slips: record it only, stop the shear there, or raise the held force.
SLIP_ACTIONS = ("report", "stop", "press")
#: The cues that tell slip: the dense field's share at friction, the net force's friction ratio, the stall of |Ft|
#: against the travel, the stall of the contact's tracked displacement.
SLIP_CUES = ("share", "net ratio", "force stall", "field stall")


@dataclass(frozen=True)
class SlipParams:
    """How slip is told and what pressing against it does (units in the names; ratios are dimensionless)."""

    share: float = 0.9  # the share of the contact's markers at friction that means the contact slips
    at_friction: float = 0.9  # a marker is at friction when |Ft| >= at_friction * mu * Fn
    net_ratio: float = 0.98  # with the net force only: |Ft| >= net_ratio * mu * |Fn|
    persist: int = 2  # fresh readings in a row that must say so
    press_ratio: float = 0.7  # "press": the held normal force rises to |Ft| / (press_ratio * mu)
    contact_fraction: float = 0.1  # a marker is in contact with at least this share of the largest normal force
    min_marker_n: float = 0.02  # ... and at least this much (N)
    friction: float | None = None  # Coulomb coefficient indenter-gel; None: the rig file's [gel] friction
    stall_ratio: float | None = 0.1  # the stall: d|Ft|/d(travel) down to this share of its steepest; None: off
    stall_span_mm: float = 0.1  # ... fitted over this much of the latest travel (mm)
    stall_friction_ratio: float = 0.5  # ... with |Ft| / (mu |Fn|) at least this (both stalls)
    follow_ratio: float | None = 0.1  # the field's stall: d|u_t|/d(travel) of the contact down to this; None: off
    follow_span_mm: float = 0.05  # ... fitted over this much of the latest travel (mm)

    def __post_init__(self) -> None:
        for name in ("stall_ratio", "follow_ratio"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and 0 < value <= 1):
                raise ValueError(f"{name} must be in (0, 1], not {value}")
        for name in ("stall_span_mm", "follow_span_mm"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number (mm), not {value}")
        for name in ("share", "at_friction", "net_ratio", "press_ratio", "contact_fraction", "stall_friction_ratio"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 < value <= 1):
                raise ValueError(f"{name} must be in (0, 1], not {value}")
        if self.persist < 1:
            raise ValueError(f"persist must be at least 1, not {self.persist}")
        if self.friction is not None and not (math.isfinite(self.friction) and self.friction > 0):
            raise ValueError(f"friction must be a positive number, not {self.friction}")


@dataclass(frozen=True)
class ContactReading:
    """A force reading with its tangential part: the net force on the gel (gel frame, N; a press: Fz < 0) and, where
    the source has the dense field, each marker's force (M, 3) and displacement from rest (M, 3; gel frame, mm);
    measured at ``t_host_ns``."""

    t_host_ns: int
    net_force_n: F64
    marker_forces_n: F64 | None = None
    marker_displacements_mm: F64 | None = None

    @property
    def tangential_n(self) -> float:
        """|Ft| on the gel, N."""
        return float(math.hypot(self.net_force_n[0], self.net_force_n[1]))

    @property
    def normal_n(self) -> float:
        """The normal force on the gel, pressing positive, N."""
        return float(-self.net_force_n[2])


@dataclass(frozen=True)
class SlipCheck:
    """One reading's verdict: ``share`` of the contact's markers at friction (nan without the field),
    ``friction_ratio`` = |Ft| / (mu |Fn|) of the net force, ``stiffness_ratio`` = d|Ft|/d(travel) now over its
    steepest in the move, ``following_ratio`` = the same of the contact's tangential displacement (nan: not measured),
    whether the contact ``slipping`` (persisting), and the ``cue`` that tells it (one of :data:`SLIP_CUES`; "" while
    it does not)."""

    share: float
    friction_ratio: float
    slipping: bool
    stiffness_ratio: float = math.nan
    following_ratio: float = math.nan
    cue: str = ""


class TravelSlope:
    """The least-squares slope of a reading against the tool's travel over the latest ``span_mm`` of it (or over the
    last three readings, where readings come further apart: a live pipeline that skipped windows), over the steepest
    such slope so far in the move: 1 while the reading rises with the travel as steeply as it has, 0 once it stops
    rising. A reading counts once the tool has moved on since the last; nan until the span is covered."""

    def __init__(self, span_mm: float) -> None:
        self.span_mm = float(span_mm)
        self.ratio = math.nan
        self._travel_mm: list[float] = []
        self._values: list[float] = []
        self._steepest = 0.0

    def update(self, travel_mm: float, value: float) -> float:
        span = self.span_mm
        if self._travel_mm and travel_mm <= self._travel_mm[-1] + 1e-3 * span:
            return self.ratio  # the tool has not moved on: nothing new about the slope
        self._travel_mm.append(float(travel_mm))
        self._values.append(float(value))
        while len(self._travel_mm) > 3 and self._travel_mm[0] < travel_mm - span:  # the latest span, 3 readings at least
            del self._travel_mm[0], self._values[0]
        if len(self._travel_mm) < 3 or travel_mm - self._travel_mm[0] < 0.6 * span:
            self.ratio = math.nan
            return self.ratio
        slope = float(np.polyfit(self._travel_mm, self._values, 1)[0])
        self._steepest = max(self._steepest, slope)
        self.ratio = slope / self._steepest if self._steepest > 0 else math.nan
        return self.ratio


class SlipDetector:
    """Slip from each new reading of one held move; :meth:`update` per reading (a reading seen before counts once)."""

    def __init__(self, friction: float, params: SlipParams | None = None) -> None:
        if not (math.isfinite(friction) and friction > 0):
            raise ValueError(f"friction must be a positive number, not {friction}")
        self.friction = float(friction)
        self.params = params or SlipParams()
        self.last = SlipCheck(math.nan, math.nan, False)
        self._runs: tuple[int, ...] = (0, 0, 0)  # readings in a row telling slip: at friction, the two stalls
        self._seen_ns: int | None = None
        self._force_stall = TravelSlope(self.params.stall_span_mm)  # |Ft| against the travel
        self._field_stall = TravelSlope(self.params.follow_span_mm)  # the contact's |u_t| against the travel

    def update(self, reading: ContactReading, travel_mm: float | None = None) -> SlipCheck:
        """One reading's verdict; ``travel_mm``: how far the tool had sheared when it was measured (mm; None: no
        stall cue)."""
        if reading.t_host_ns == self._seen_ns:
            return self.last
        self._seen_ns = reading.t_host_ns
        p = self.params
        normal = reading.normal_n
        ratio = reading.tangential_n / (self.friction * normal) if normal > 0 else math.nan
        share = self.share_at_friction(reading.marker_forces_n) if reading.marker_forces_n is not None else math.nan
        at_friction = share >= p.share if not math.isnan(share) else ratio >= p.net_ratio
        stiffness = following = math.nan
        if travel_mm is not None:
            stiffness = self._force_stall.update(travel_mm, reading.tangential_n)
            if reading.marker_forces_n is not None and reading.marker_displacements_mm is not None:
                moved = self.contact_displacement_mm(reading.marker_forces_n, reading.marker_displacements_mm)
                if math.isfinite(moved):
                    following = self._field_stall.update(travel_mm, moved)
        loaded = ratio >= p.stall_friction_ratio  # a stick that has hardly loaded is not a slide
        says = (at_friction,
                loaded and p.stall_ratio is not None and stiffness <= p.stall_ratio,
                loaded and p.follow_ratio is not None and following <= p.follow_ratio)
        self._runs = tuple(run + 1 if cue else 0 for run, cue in zip(self._runs, says, strict=True))
        share_cue, net_cue, force_cue, field_cue = SLIP_CUES
        names = (share_cue if not math.isnan(share) else net_cue, force_cue, field_cue)
        cue = next((name for name, run in zip(names, self._runs, strict=True) if run >= p.persist), "")
        self.last = SlipCheck(share, ratio, bool(cue), stiffness, following, cue)
        return self.last

    def _contact(self, marker_forces_n: npt.ArrayLike) -> tuple[F64, npt.NDArray[np.bool_]] | None:
        """Each marker's normal force (N, pressing positive) and which markers are in the contact; None: no
        contact."""
        p = self.params
        forces = np.asarray(marker_forces_n, np.float64).reshape(-1, 3)
        normal = -forces[:, 2]
        finite = np.isfinite(forces).all(axis=1)
        if not finite.any():
            return None
        largest = float(normal[finite].max())
        contact = finite & (normal >= max(p.contact_fraction * largest, p.min_marker_n))
        return (normal, contact) if contact.any() else None

    def contact_displacement_mm(self, marker_forces_n: npt.ArrayLike, marker_displacements_mm: npt.ArrayLike
                                ) -> float:
        """|u_t| of the contact: the tangential displacement of its markers weighted by their normal force (mm; nan:
        no contact). Sticking, it grows with the tool's travel; sliding as a whole, it stops."""
        found = self._contact(marker_forces_n)
        if found is None:
            return math.nan
        normal, contact = found
        moved = np.asarray(marker_displacements_mm, np.float64).reshape(-1, 3)[contact, :2]
        weight = normal[contact]
        keep = np.isfinite(moved).all(axis=1)
        if not keep.any():
            return math.nan
        mean = (weight[keep, None] * moved[keep]).sum(axis=0) / weight[keep].sum()
        return float(math.hypot(mean[0], mean[1]))

    def share_at_friction(self, marker_forces_n: npt.ArrayLike) -> float:
        """The share of the contact's markers whose |Ft| reaches ``at_friction * mu * Fn`` (nan: no contact)."""
        found = self._contact(marker_forces_n)
        if found is None:
            return math.nan
        normal, contact = found
        forces = np.asarray(marker_forces_n, np.float64).reshape(-1, 3)
        tangential = np.hypot(forces[contact, 0], forces[contact, 1])
        return float(np.mean(tangential >= self.params.at_friction * self.friction * normal[contact]))

    def press_target_n(self, reading: ContactReading) -> float:
        """The normal force that takes the tangential force back to ``press_ratio`` of friction, N."""
        return reading.tangential_n / (self.params.press_ratio * self.friction)


@dataclass(frozen=True)
class SlipReflex:
    """A held shear's reflex: ``action`` (one of :data:`SLIP_ACTIONS`) when slip is told with ``params`` at the
    Coulomb coefficient ``friction``; "press" never holds more than ``press_limit_n`` (N)."""

    action: str
    params: SlipParams
    friction: float
    press_limit_n: float

    def __post_init__(self) -> None:
        if self.action not in SLIP_ACTIONS:
            raise ValueError(f"the slip action must be one of {', '.join(SLIP_ACTIONS)}, not {self.action!r}")
