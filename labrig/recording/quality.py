"""A recording's data quality: a verdict (``clean`` or ``degraded``) with one reason per defect.

Assessed when a recording is finalized and stored in its root attributes (``quality``,
``quality_reasons``: a JSON list), read back by :func:`stored_quality`; campaigns file a
degraded recording as ``degraded`` in the manifest and record it again. What degrades a recording
is damage to the data, each with its threshold:

* rows the recorder dropped (any stream: camera packets, F/T, CNC, truth);
* the camera's events stopping before the protocol's last phase ends (more than
  :data:`CAMERA_SHORT_S`), or a silence of more than :data:`CAMERA_GAP_S` while the gel is
  probed (a sensor at rest still sends its background noise);
* a gap in the F/T samples of more than :data:`FT_GAP_PERIODS` nominal periods;
* a gap in the simulator's truth of more than :data:`TRUTH_GAP_S` (virtual-rig recordings);
* a camera clock fitted on the lower envelope of receive times (no trigger edges) whose
  residuals say the fit is loose (99th percentile above :data:`ENVELOPE_RESIDUAL_P99_US`).

Late arrival alone is not damage: data that a USB link delivers in bursts arrives tens of ms after
it was made, and a clock fitted on the trigger edges places it exactly; so a trigger-fitted
clock's residuals never degrade a recording.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labrig.clock import unwrap_counter
from labrig.recording.reader import Recording

#: Camera events ending this long (s) before the protocol's last phase ends degrade a recording.
CAMERA_SHORT_S = 0.1
#: A silence of the camera this long (s) inside the probing phases degrades a recording.
CAMERA_GAP_S = 0.2
#: A gap in F/T samples longer than this many nominal periods degrades a recording.
FT_GAP_PERIODS = 5
#: A gap this long (s) in the simulator's truth streams degrades a virtual-rig recording.
TRUTH_GAP_S = 0.1
#: An envelope-fitted camera clock with 99 % of its residuals above this (us) is too loose to place events.
ENVELOPE_RESIDUAL_P99_US = 10_000.0
#: The phases inside which the camera must not fall silent.
PROBING_PHASES = ("normal_down", "wait", "shear", "shear_opposite", "normal_up")
CLEAN, DEGRADED = "clean", "degraded"


@dataclass(frozen=True)
class Quality:
    """A recording's verdict and the defects behind it (empty when clean)."""

    reasons: tuple[str, ...] = ()

    @property
    def verdict(self) -> str:
        return DEGRADED if self.reasons else CLEAN

    @property
    def degraded(self) -> bool:
        return bool(self.reasons)

    def describe(self) -> str:
        """One line: ``clean``, or ``degraded: reason; reason``."""
        return self.verdict + (f": {'; '.join(self.reasons)}" if self.reasons else "")

    def to_attrs(self) -> dict[str, str]:
        """The root attributes that store it."""
        return {"quality": self.verdict, "quality_reasons": json.dumps(list(self.reasons))}


def assess(rec: Recording) -> Quality:
    """The quality of a recording (see the module docstring for what degrades one)."""
    reasons = [f"{rows} {stream} rows dropped by the recorder" for stream, rows in dropped_rows(rec).items()]
    reasons += _camera(rec)
    reasons += _ft_gaps(rec)
    reasons += _truth_gaps(rec)
    reasons += _camera_clock(rec)
    return Quality(tuple(reasons))


def store_quality(path: str | Path) -> Quality:
    """Assess a finalized (or recovered) recording file and store its verdict in its root attributes."""
    import h5py

    with Recording(path) as rec:
        quality = assess(rec)
    with h5py.File(path, "r+") as f:
        for key, value in quality.to_attrs().items():
            f.attrs[key] = value
    return quality


def stored_quality(rec: Recording) -> Quality | None:
    """The verdict stored at finalize time, or None (recordings finalized before it was stored)."""
    if "quality" not in rec.attrs:
        return None
    try:
        reasons = json.loads(str(rec.attrs.get("quality_reasons", "[]")))
    except json.JSONDecodeError:
        reasons = ["its stored quality reasons are unreadable"]
    return Quality(tuple(str(r) for r in reasons))


def dropped_rows(rec: Recording) -> dict[str, int]:
    """Rows the recorder dropped, per stream."""
    drops = rec.stream("drops")
    totals: dict[str, int] = {}
    for stream, rows in zip(drops["stream"], drops["rows"]):
        totals[stream.decode()] = totals.get(stream.decode(), 0) + int(rows)
    return totals


def camera_shortfall_s(rec: Recording) -> float:
    """How long before the protocol's last phase ends the camera's events stop (s; 0 when they do not)."""
    phases = rec.phases()
    if not phases:
        return 0.0
    end_us = rec.events_end_us()
    stops_us = phases[0].t_start_us if end_us is None else end_us
    return max(0.0, (phases[-1].t_end_us - stops_us) / 1e6)


def _camera(rec: Recording) -> list[str]:
    out = []
    short_s = camera_shortfall_s(rec)
    if short_s > CAMERA_SHORT_S:
        out.append(f"the camera's events stop {short_s:.1f} s before the protocol ends")
    probing = [p for p in rec.phases() if p.name in PROBING_PHASES]
    if probing and rec.n_events:
        start_us, end_us = min(p.t_start_us for p in probing), max(p.t_end_us for p in probing)
        end_us = min(end_us, rec.events_end_us() or end_us)  # a stream that stopped is reported above
        bin_us = CAMERA_GAP_S * 1e6 / 4
        starts_us, counts = rec.event_counts(bin_ms=bin_us / 1000)
        inside = (starts_us >= start_us) & (starts_us + bin_us <= end_us)
        silent = _longest_run(counts[inside] == 0) * bin_us / 1e6
        if silent > CAMERA_GAP_S:
            out.append(f"the camera sent no events for {silent:.2f} s while the gel was probed")
    return out


def _ft_gaps(rec: Recording) -> list[str]:
    if rec.rows("ft") < 2:
        return []
    steps = np.diff(unwrap_counter(rec.column("ft", "t_device_us"), 32))
    period_us = float(np.median(steps))
    gaps = steps > FT_GAP_PERIODS * period_us if period_us > 0 else np.zeros(0, bool)
    if not gaps.any():
        return []
    return [f"{int(gaps.sum())} gaps in the F/T samples, the longest {steps.max() / 1000:.1f} ms"]


def _truth_gaps(rec: Recording) -> list[str]:
    out = []
    for stream in sorted(s for s in rec.streams if s.startswith("truth/")):
        if rec.rows(stream) < 2:
            continue
        try:
            steps = np.diff(rec.column(stream, "t_host_us"))
        except KeyError:
            continue
        if steps.size and steps.max() > TRUTH_GAP_S * 1e6:
            out.append(f"the sim's {stream} has a gap of {steps.max() / 1e6:.2f} s")
    return out


def _camera_clock(rec: Recording) -> list[str]:
    model = rec.clock_models.get("camera")
    if model is None or model.method == "triggers" or model.residual_p99_us <= ENVELOPE_RESIDUAL_P99_US:
        return []
    return [f"the camera's clock, fitted without trigger edges, leaves 1 % of its samples more than "
            f"{model.residual_p99_us / 1000:.1f} ms off its line"]


def _longest_run(flags: np.ndarray) -> int:
    """The longest run of True in a 1-D boolean array."""
    best = run = 0
    for flag in flags:
        run = run + 1 if flag else 0
        best = max(best, run)
    return best
