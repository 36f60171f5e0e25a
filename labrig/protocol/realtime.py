"""Did a through-driver run keep real time? What fell behind, by how much.

A run through the drivers lives in real time: a camera (the virtual rig's renderer) that
cannot keep up stops short of the run's end, a device twin starved of CPU loses F/T frames,
and a GRBL twin starved for seconds misses the driver's deadlines, which ends the run (on
hardware such a timeout is a fault of the port or cable; on the virtual rig it is the host's
load). Each leaves a recording short of data or none. :class:`Shortfall` measures them for one
run; the recording stores it (root attributes ``camera_behind_s``, ``ft_max_gap_s``,
``late_twin``, ``fell_behind``), the campaign's manifest too (``fell_behind``), and a campaign
retries such a run a bounded number of times instead of keeping it silently short or lost.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol, TypeVar

from labrig.dataset import COMPLETE
from labrig.protocol.safety import StopRequest

#: A camera stream ending this much before the run's end is short, s.
CAMERA_BEHIND_LIMIT_S = 0.05
#: F/T samples missing for this long (the sensor's 800 Hz: 80 frames) make the run short, s.
FT_GAP_LIMIT_S = 0.1
#: A run that fell behind is recorded again at most this many times.
REALTIME_RETRIES = 2
#: The manifest status of a run that fell behind in every try: kept, marked, redone by a rerun.
SHORT = "short"
#: The manifest status of a run whose data was damaged in every try (labrig.recording.quality): kept, marked,
#: redone by a rerun.
DEGRADED = "degraded"


@dataclass(frozen=True)
class Shortfall:
    """How far a run's streams fell behind real time, s (0: kept up)."""

    camera_behind_s: float = 0.0
    ft_max_gap_s: float = 0.0
    #: A virtual rig's twin that missed a driver's deadline and so ended the run: what the driver said.
    late_twin: str = ""

    @property
    def fell_behind(self) -> bool:
        return (self.camera_behind_s > CAMERA_BEHIND_LIMIT_S or self.ft_max_gap_s > FT_GAP_LIMIT_S
                or bool(self.late_twin))

    def describe(self) -> str:
        """One line for the manifest and the recording ("" when the run kept up)."""
        parts = []
        if self.camera_behind_s > CAMERA_BEHIND_LIMIT_S:
            parts.append(f"camera stream ends {self.camera_behind_s:.2f} s early")
        if self.ft_max_gap_s > FT_GAP_LIMIT_S:
            parts.append(f"F/T frames missing for {self.ft_max_gap_s:.2f} s")
        if self.late_twin:
            parts.append(f"the virtual rig answered late ({self.late_twin})")
        return "; ".join(parts)

    def attrs(self) -> dict[str, str | float]:
        """The recording's root attributes."""
        return {"camera_behind_s": round(self.camera_behind_s, 6), "ft_max_gap_s": round(self.ft_max_gap_s, 6),
                "late_twin": self.late_twin, "fell_behind": self.describe()}


class Attempt(Protocol):
    """What :func:`record_in_real_time` needs of a run's outcome (a frozen dataclass)."""

    @property
    def status(self) -> str: ...
    @property
    def reason(self) -> str: ...
    @property
    def fell_behind(self) -> str: ...
    @property
    def late_twin(self) -> str: ...
    @property
    def degraded(self) -> str: ...


OutcomeT = TypeVar("OutcomeT", bound=Attempt)


def record_in_real_time(record: Callable[[], OutcomeT], before_each: Callable[[], object],
                        stop: StopRequest | None = None, retries: int = REALTIME_RETRIES) -> OutcomeT:
    """Record (``before_each`` readies the rig first) until a run kept real time with undamaged data,
    at most ``1 + retries`` times. A complete run that fell behind every time comes back with status
    :data:`SHORT`, one whose data was damaged (``degraded``) every time with :data:`DEGRADED`; a run
    that a late twin of the virtual rig ended every time (``late_twin``) keeps its status (aborted,
    failed); each says so in its reason. Runs aborted or failed for any other reason, and a stop, end
    the tries."""
    tries = 0

    def again(outcome: OutcomeT) -> bool:
        damaged = bool(outcome.fell_behind or outcome.degraded)
        return bool(outcome.late_twin) or (outcome.status == COMPLETE and damaged)

    while True:
        before_each()
        outcome = record()
        tries += 1
        if not again(outcome) or tries > retries or (stop is not None and stop.level):
            break
    if not again(outcome):
        return outcome
    if outcome.status == COMPLETE and not outcome.fell_behind:
        reason = (f"its data was damaged in {tries} of {tries} tries ({outcome.degraded}): the recording is kept but "
                  "degraded; rerun the campaign on a quieter machine to record it again")
        return replace(outcome, status=DEGRADED, reason=reason)  # type: ignore[type-var]
    if outcome.status == COMPLETE:
        reason = (f"fell behind real time in {tries} of {tries} tries ({outcome.fell_behind}): the recording is kept but "
                  "short; rerun the campaign on a quieter machine to record it again")
        return replace(outcome, status=SHORT, reason=reason)  # type: ignore[type-var]
    reason = (f"{outcome.reason}; the virtual rig fell behind real time in {tries} of {tries} tries: rerun the "
              "campaign on a quieter machine")
    return replace(outcome, reason=reason)  # type: ignore[type-var]
