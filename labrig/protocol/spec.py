"""Probing runs and campaigns as plain data: what to press, where, how deep, how fast.

Every quantity carries its unit in its name (mm, mm/s, N, s, deg). Locations are
in the gel frame (see :mod:`labrig.config`): mm from the gel centre, x along the
marker columns, y along the rows. Shear directions are angles in the gel's x-y
plane, 0 deg = +x, 90 deg = +y.

One run follows the paper's sequence: approach (search for contact), Normal
Down, Wait, Shear, Wait, Shear Opposite, Wait, Normal Up, retract. A run with
``shear_mm == 0`` skips Shear, Shear Opposite and their waits.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from labrig.dataset import SPLITS
from labrig.errors import LabrigError
from labrig.protocol.force_loop import ForceLoopParams
from labrig.protocol.slip import SlipParams
from labrig.protocol.variation import SensorVariation

#: Depth assumed when timing a force-target run that has no depth cap (see ``nominal_duration_s``).
FORCE_TARGET_DEPTH_GUESS_MM = 1.5


class ProtocolError(LabrigError):
    """A bad probing protocol or campaign; ``problems`` holds each one (file, line, field, message)."""

    def __init__(self, message: str, problems: tuple[Problem, ...] = ()) -> None:
        super().__init__(message)
        self.problems = problems


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a protocol or campaign file, located in it."""

    file: str
    line: int
    field: str
    message: str

    def __str__(self) -> str:
        return f"{self.file}:{self.line}: {self.field}: {self.message}"


@dataclass(frozen=True)
class ApproachSpec:
    """Contact search: descend from ``start_height_mm`` above the nominal gel surface at
    ``speed_mm_s`` until |Fz| exceeds ``contact_force_n``; give up after ``max_travel_mm``
    below the start height (so ``max_travel_mm > start_height_mm`` reaches past the surface)."""

    start_height_mm: float = 2.0
    speed_mm_s: float = 0.5
    contact_force_n: float = 0.1
    max_travel_mm: float = 4.0


@dataclass(frozen=True)
class ProbeSpec:
    """One probing run.

    The normal target is exactly one of ``depth_mm`` (below the contact point) or
    ``force_n`` (|Fz| to reach); a force target stops at ``max_depth_mm`` even if
    the force is not reached (``None``: the indenter's own ``max_depth_mm``).
    ``retract_height_mm`` is the height above the contact point to return to.
    ``shear_hold_force_n``: during Shear and Shear Opposite the normal force is held at this (N on the gel) by the
    force loop (:mod:`labrig.protocol.force_loop`, gains and limits ``control``), read from ``feedback``; the tool
    then moves along the gel normal as the loop commands (None: the shears keep the pressed depth).
    ``press_hold_s``: with a force target, the loop presses to it from the contact point (a step of the loop) and
    holds it for this long (Normal Down), then holds it through the waits, and through the shears unless
    ``shear_hold_force_n`` says another force (None: a force target is searched for at the normal speed and the
    depth it is found at is kept).
    With the normal force held during the shears, ``shear_force_n`` ends Shear once the tangential force (read from
    ``feedback``) reaches it (N, at most ``shear_mm`` along), and ``slip_action`` (one of
    :data:`~labrig.protocol.slip.SLIP_ACTIONS`) is Shear's reflex when the contact slips, told with ``slip``.
    ``release_force_n``: Normal Up first releases to this normal force under the loop and holds it
    ``release_hold_s``, then rises to the contact point.
    """

    indenter: str
    location_mm: tuple[float, float] = (0.0, 0.0)
    depth_mm: float | None = None
    force_n: float | None = None
    normal_speed_mm_s: float = 1.5
    wait_s: float = 0.4
    shear_direction_deg: float = 0.0
    shear_mm: float = 1.0
    shear_speed_mm_s: float = 1.5
    approach: ApproachSpec = field(default_factory=ApproachSpec)
    retract_height_mm: float = 2.0
    retract_speed_mm_s: float = 5.0
    max_depth_mm: float | None = None
    shear_hold_force_n: float | None = None
    press_hold_s: float | None = None
    feedback: str = "ft"
    control: ForceLoopParams = field(default_factory=ForceLoopParams)
    shear_force_n: float | None = None
    slip_action: str | None = None
    slip: SlipParams = field(default_factory=SlipParams)
    release_force_n: float | None = None
    release_hold_s: float = 0.5

    def __post_init__(self) -> None:
        if (self.depth_mm is None) == (self.force_n is None):
            raise ProtocolError(
                f"probe with indenter {self.indenter!r}: give exactly one normal target, depth_mm or force_n"
                f" (got depth_mm={self.depth_mm}, force_n={self.force_n})"
            )

    @property
    def holds_force(self) -> bool:
        """The force loop runs in this probe (a held press or a held shear)."""
        return (self.press_hold_s is not None or (self.shear_hold_force_n is not None and self.has_shear)
                or self.release_force_n is not None)

    @property
    def shear_held_n(self) -> float | None:
        """The normal force the shears hold (N on the gel), None if they keep the pressed depth."""
        if not self.has_shear:
            return None
        if self.shear_hold_force_n is not None:
            return self.shear_hold_force_n
        return self.force_n if self.press_hold_s is not None else None

    @property
    def reads_events(self) -> bool:
        """The force loop reads the event sensor's estimate (the pipeline must run beside the run)."""
        return self.holds_force and self.feedback == "events"

    @property
    def has_shear(self) -> bool:
        return self.shear_mm > 0

    def control_record(self) -> dict[str, str | float | int]:
        """What a recording of this probe keeps of its force loop, as the metadata's extra keys: the feedback
        (``control_feedback``) and every setting of the loop (``control_<field>``, units in the names), defaults
        included; empty when no force is held."""
        if not self.holds_force:
            return {}
        return {"control_feedback": self.feedback,
                **{f"control_{name}": value for name, value in asdict(self.control).items()}}

    def phases(self) -> tuple[str, ...]:
        """Phase names in order; ``"wait"`` appears once per wait."""
        if not self.has_shear:
            return ("approach", "normal_down", "wait", "normal_up", "retract")
        return ("approach", "normal_down", "wait", "shear", "wait", "shear_opposite", "wait", "normal_up", "retract")

    def nominal_depth_mm(self) -> float:
        """The depth the run is expected to reach: the target depth, or for a force
        target its depth cap (an upper bound), else ``FORCE_TARGET_DEPTH_GUESS_MM``."""
        if self.depth_mm is not None:
            return self.depth_mm
        return self.max_depth_mm if self.max_depth_mm is not None else FORCE_TARGET_DEPTH_GUESS_MM

    def phase_durations_s(self) -> tuple[tuple[str, float], ...]:
        """(phase, nominal seconds) in order; the approach counts 0 (its length depends on
        where contact is found)."""
        depth = self.nominal_depth_mm()
        move = {
            "approach": 0.0,
            "normal_down": depth / self.normal_speed_mm_s if self.press_hold_s is None else self.press_hold_s,
            "wait": self.wait_s,
            "shear": self.shear_mm / self.shear_speed_mm_s if self.has_shear else 0.0,
            "normal_up": depth / self.normal_speed_mm_s + (self.release_hold_s if self.release_force_n is not None
                                                            else 0.0),
            "retract": self.retract_height_mm / self.retract_speed_mm_s,
        }
        move["shear_opposite"] = move["shear"]
        return tuple((name, move[name]) for name in self.phases())

    def nominal_duration_s(self) -> float:
        """Approximate length of the run from contact to the end of the retract (approach excluded)."""
        return sum(seconds for _, seconds in self.phase_durations_s())


@dataclass(frozen=True)
class RecordingPlan:
    """One recording of a campaign: ``index`` is its place in the run order (0-based)."""

    id: str
    index: int
    spec: ProbeSpec
    repetition: int
    split: str
    group: int = 0


@dataclass(frozen=True)
class Campaign:
    """A list of recordings to make, each with its probing run and its dataset split."""

    name: str
    seed: int
    plans: tuple[RecordingPlan, ...]
    source: Path | None = None
    protocol: Path | None = None
    #: Per-recording sensor changes (the file's ``[vary]``; virtual rig only).
    variation: SensorVariation | None = None

    def __len__(self) -> int:
        return len(self.plans)

    def by_split(self) -> dict[str, tuple[RecordingPlan, ...]]:
        """Plans per split, in run order; every split name is present (possibly empty)."""
        out: dict[str, list[RecordingPlan]] = {name: [] for name in SPLITS}
        for plan in self.plans:
            out.setdefault(plan.split, []).append(plan)
        return {name: tuple(plans) for name, plans in out.items()}

    def split_counts(self) -> dict[str, int]:
        return {name: len(plans) for name, plans in self.by_split().items()}

    def indenters(self) -> tuple[str, ...]:
        """Indenters in order of first use."""
        return tuple(dict.fromkeys(plan.spec.indenter for plan in self.plans))

    def total_nominal_s(self) -> float:
        return sum(plan.spec.nominal_duration_s() for plan in self.plans)
