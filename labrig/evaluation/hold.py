"""Presses held: whether the force estimate keeps a still dent, and lets go of it after the release.

A wait of at least :data:`HELD_PRESS_MIN_S` is a held press. Its normal-force error is the mean
``|predicted - measured|`` of Fz (N, force on the gel, gel frame) over the evaluation windows that end in
its first and in its last :data:`EDGE_S` seconds; an estimate that forgets the dent grows the second.
After the release (the end of Normal Up) the gel is at rest and the F/T reads nothing: the mean
``|predicted Fz|`` over the windows ending :data:`AFTER_RELEASE_S` after it is what the estimate
still holds of the dent.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from labrig.evaluation.forces import ForceResult

HELD_PRESS_MIN_S = 10.0  # s: a wait this long or longer is a held press
EDGE_S = 5.0  # s: the spans at the start and at the end of a held press that are compared
AFTER_RELEASE_S = (0.2, 0.9)  # s after the end of Normal Up: the windows that measure the force left


@dataclass(frozen=True)
class HeldPress:
    """One held press (a long wait) of one recording; forces on the gel, N."""

    recording: str
    wait_index: int  # the run's wait this was: 0 after Normal Down, 1 after Shear, 2 after Shear Opposite
    duration_s: float
    measured_fz_n: float  # mean F/T Fz over the press
    fz_error_first_n: float  # mean |predicted - measured| Fz over the windows ending in the first EDGE_S; nan: none
    fz_error_last_n: float  # the same over the last EDGE_S

    @property
    def error_ratio_last_to_first(self) -> float:
        """How much worse the end of the press is than its start (1: held; nan without both spans)."""
        if not (np.isfinite(self.fz_error_first_n) and np.isfinite(self.fz_error_last_n)) or self.fz_error_first_n <= 0:
            return float("nan")
        return self.fz_error_last_n / self.fz_error_first_n


def _mean_abs(values: npt.NDArray[np.float64]) -> float:
    values = values[np.isfinite(values)]
    return float(np.mean(np.abs(values))) if values.size else float("nan")


def _ending_in(result: ForceResult, start_us: float, end_us: float) -> npt.NDArray[np.bool_]:
    return (result.t1_us >= start_us) & (result.t1_us <= end_us)


def held_presses(result: ForceResult, *, min_s: float = HELD_PRESS_MIN_S, edge_s: float = EDGE_S) -> list[HeldPress]:
    """The recording's waits of ``min_s`` seconds or more, each with its Fz error at the start and at the end."""
    presses = []
    waits = [(start, end) for name, start, end in result.phases if name == "wait"]
    error_z = result.predicted_n[:, 2] - result.measured_n[:, 2] if len(result.t1_us) else np.zeros(0)
    for index, (start, end) in enumerate(waits):
        duration_s = (end - start) / 1e6
        if duration_s < min_s:
            continue
        inside = _ending_in(result, start, end)
        first = _ending_in(result, start, start + edge_s * 1e6)
        last = _ending_in(result, end - edge_s * 1e6, end)
        presses.append(HeldPress(
            recording=result.recording, wait_index=index, duration_s=duration_s,
            measured_fz_n=float(np.nanmean(result.measured_n[inside, 2])) if inside.any() else float("nan"),
            fz_error_first_n=_mean_abs(error_z[first]), fz_error_last_n=_mean_abs(error_z[last])))
    return presses


def force_after_release_n(result: ForceResult, span_s: tuple[float, float] = AFTER_RELEASE_S) -> float:
    """Mean |predicted Fz| (N) over the windows ending ``span_s`` after the end of the last Normal Up; nan
    without that phase or without windows there."""
    ends = [end for name, _, end in result.phases if name == "normal_up"]
    if not ends:
        return float("nan")
    after = _ending_in(result, ends[-1] + span_s[0] * 1e6, ends[-1] + span_s[1] * 1e6)
    return _mean_abs(result.predicted_n[after, 2]) if after.any() else float("nan")


@dataclass(frozen=True)
class HoldSummary:
    """The held presses of a set of recordings; forces N."""

    presses: tuple[HeldPress, ...]
    fz_error_first_n: float  # mean over the presses
    fz_error_last_n: float
    error_ratio_last_to_first: float  # of the two means; nan without presses
    after_release_fz_n: float  # mean |predicted Fz| after the release, over the recordings that held a press


def hold_summary(results: Sequence[ForceResult]) -> HoldSummary:
    """The held presses of ``results`` and their pooled errors (nan where there are none)."""
    presses = tuple(p for r in results for p in held_presses(r))
    holders = {p.recording for p in presses}
    first = _mean_abs(np.array([p.fz_error_first_n for p in presses], dtype=np.float64))
    last = _mean_abs(np.array([p.fz_error_last_n for p in presses], dtype=np.float64))
    after = _mean_abs(np.array([force_after_release_n(r) for r in results if r.recording in holders], dtype=np.float64))
    ratio = last / first if np.isfinite(first) and np.isfinite(last) and first > 0 else float("nan")
    return HoldSummary(presses, first, last, ratio, after)
