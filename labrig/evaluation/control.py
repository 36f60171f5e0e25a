"""Runs whose normal force a force loop held: how well it held, with the F/T sensor as the reference.

A recording made with a held press (``[normal] hold_s``) or a held shear (``[shear] hold_force_n``) has a
``control`` stream (:data:`~labrig.protocol.force_loop.CONTROL_STREAM`): every jog segment the loop commanded. A
phase is *held* when the loop commanded through at least half of it; its target is the one the loop held. Per recording:

* the **step**: a held Normal Down is a step of the loop from the contact force to the target: rise (10-90 %),
  overshoot and settling into 5 % of the F/T's |Fz| (:func:`step_response`);
* the **hold**: the RMS of the F/T's |Fz| from the target over the held waits and shears (N);
* the **estimate's hold**: the same for the pipeline's predicted |Fz| over the evaluation windows ending in those
  phases: what the event sensor would have fed the loop;
* the **readings' scatter**: the loop's readings less the F/T's |Fz| over the span each reading covers, their
  spread about its mean within each held wait and shear, pooled (N, 1 sigma): what ``[control] reading_noise_n``
  stands for, measured on the lab's own sensor;
* the loop's rate: its commands' median rate (Hz);
* the **slip reflex** (a held Shear with ``[slip] action``): when it told slip, and, on the virtual rig, when the
  whole contact truly began to slide (``truth/contact`` ``sliding``, gross slip), and the difference (ms; negative:
  told before it slid).

Forces are |Fz| on the gel, N (the F/T's tared by its first samples, before contact).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.evaluation.forces import ForceResult
from labrig.recording import Recording
from labrig.recording.reader import Phase

#: F/T samples averaged for the tare (the approach starts clear of the gel).
TARE_SAMPLES = 100
HELD_AFTER_PRESS = ("wait", "shear", "shear_opposite")
#: A reading stands for the force over this long before its time stamp (us): an estimate's window.
READING_SPAN_US = 10_000


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


@dataclass(frozen=True)
class ControlRun:
    """How the loop held one recording's force (N, s, Hz; nan where the run had no such part)."""

    recording: str
    target_n: float  # the held Normal Down's target, else the first held phase's
    feedback: str
    step_rise_s: float
    step_overshoot_pct: float
    step_settling_s: float
    hold_rms_n_ft: float  # F/T |Fz| against the target over the held waits and shears
    hold_rms_n_estimate: float  # the pipeline's |Fz| against the same; nan without its forces
    loop_hz: float
    origin_us: int  # host us of the first held phase's start: the zero of ``t_s``
    phases_s: tuple[tuple[str, float, float], ...]  # (name, start, end) s from the origin
    t_s: npt.NDArray[np.float64]  # F/T sample times, s from the first held phase's start
    ft_fz_n: npt.NDArray[np.float64]  # F/T |Fz| at those times
    target_series_n: npt.NDArray[np.float64]  # the target in force at those times (nan outside held phases)
    slip_told_s: float = math.nan  # Shear's slip reflex first told slip, s from the origin (nan: never, no reflex)
    slip_onset_s: float = math.nan  # the sim's true onset of gross slip in Shear, s from the origin (nan: none)
    slip_cue: str = ""  # the cue that first told it (labrig.protocol.slip.SLIP_CUES; "": never, or not recorded)
    reading_scatter_n: float = math.nan  # the loop's readings less the F/T, about their mean per held phase (1 sigma)

    @property
    def slip_onset_error_ms(self) -> float:
        """When the reflex told slip less when the contact truly began to slide, ms (nan unless both happened)."""
        return (self.slip_told_s - self.slip_onset_s) * 1e3


def control_run(path: str | Path, forces: ForceResult | None = None) -> ControlRun | None:
    """The :class:`ControlRun` of the recording at ``path`` (None: no force loop ran in it); ``forces``: the
    pipeline's forces on it, for the estimate's hold."""
    with Recording(path) as rec:
        if "control" not in rec.streams:
            return None
        control = rec.stream("control")
        ft = rec.stream("ft")
        phases = rec.phases()
        feedback = str(rec.attrs.get("extra_control_feedback", "ft"))
        truth = rec.stream("truth/contact") if "truth/contact" in rec.streams else None
    slip_told_us, slip_onset_us, slip_cue = _slip_times(control, truth, phases)
    c_t, c_target = control["t_host_us"].astype(np.int64), control["target_n"].astype(np.float64)
    t_us = ft["t_host_us"].astype(np.int64)
    fz = np.abs(ft["force_n"][:, 2] - ft["force_n"][:TARE_SAMPLES, 2].mean()).astype(np.float64)
    gaps = np.diff(c_t)
    period_us = float(np.median(gaps)) if gaps.size else float("nan")
    held = []
    for p in phases:  # held: the loop commanded through at least half of it (not a row at a phase's edge)
        inside = (c_t >= p.t_start_us) & (c_t < p.t_end_us)
        if inside.sum() >= max(2.0, 0.5 * (p.t_end_us - p.t_start_us) / period_us):
            held.append((p, float(np.median(c_target[inside]))))
    if not held:
        return None
    origin_us = held[0][0].t_start_us
    target_series = np.full(fz.shape, np.nan)
    for p, target in held:
        target_series[(t_us >= p.t_start_us) & (t_us < p.t_end_us)] = target
    press = next(((p, target) for p, target in held if p.name == "normal_down"), None)
    rise = overshoot = settling = float("nan")
    if press is not None:
        inside = (t_us >= press[0].t_start_us) & (t_us < press[0].t_end_us)
        step = step_response((t_us[inside] - press[0].t_start_us) / 1e6, fz[inside], press[1], start_n=0.0)
        rise, overshoot, settling = step.rise_s, step.overshoot_pct, step.settling_s
    later = [(p, target) for p, target in held if p.name in HELD_AFTER_PRESS]
    ft_errors = [fz[(t_us >= p.t_start_us) & (t_us < p.t_end_us)] - target for p, target in later]
    hold_ft = _rms(ft_errors)
    scatter = _reading_scatter_n(control, t_us, fz, [p for p, _ in later])
    hold_estimate = float("nan")
    if forces is not None and len(forces.t1_us):
        predicted = np.abs(forces.predicted_n[:, 2])
        hold_estimate = _rms([predicted[(forces.t1_us >= p.t_start_us) & (forces.t1_us < p.t_end_us)] - target
                              for p, target in later])
    return ControlRun(
        recording=Path(path).name, target_n=(press or held[0])[1], feedback=feedback, step_rise_s=rise,
        step_overshoot_pct=overshoot, step_settling_s=settling, hold_rms_n_ft=hold_ft,
        hold_rms_n_estimate=hold_estimate, loop_hz=1e6 / period_us,
        origin_us=origin_us,
        phases_s=tuple((p.name, (p.t_start_us - origin_us) / 1e6, (p.t_end_us - origin_us) / 1e6) for p in phases),
        t_s=(t_us - origin_us) / 1e6, ft_fz_n=fz, target_series_n=target_series,
        slip_told_s=(slip_told_us - origin_us) / 1e6, slip_onset_s=(slip_onset_us - origin_us) / 1e6,
        slip_cue=slip_cue, reading_scatter_n=scatter)


def _reading_scatter_n(control: Mapping[str, npt.NDArray[Any]], t_us: npt.NDArray[np.int64],
                       fz: npt.NDArray[np.float64], phases: Sequence[Phase]) -> float:
    """The loop's readings less the F/T's mean |Fz| over the READING_SPAN_US before each reading's time, about
    their mean within each of ``phases``, pooled: RMS, N (nan: fewer than three readings in every phase)."""
    c_t = control["t_host_us"].astype(np.int64)
    read_us = c_t - control["reading_age_us"].astype(np.int64)
    summed = np.concatenate(([0.0], np.cumsum(fz)))
    hi = np.searchsorted(t_us, read_us, side="right")
    lo = np.searchsorted(t_us, read_us - READING_SPAN_US, side="right")
    reference = np.where(hi > lo, (summed[hi] - summed[lo]) / np.maximum(hi - lo, 1), np.nan)
    residual = control["feedback_n"].astype(np.float64) - reference
    parts = []
    for p in phases:
        inside = residual[(c_t >= p.t_start_us) & (c_t < p.t_end_us) & np.isfinite(residual)]
        if inside.size >= 3:
            parts.append(inside - inside.mean())
    return _rms(parts)


def _slip_times(control: Mapping[str, npt.NDArray[Any]], truth: Mapping[str, npt.NDArray[Any]] | None,
                phases: Sequence[Phase]) -> tuple[float, float, str]:
    """In the first Shear: when the reflex first told slip, when the contact truly began to slide (host us; nan
    where not), and the cue that told it ("" where not recorded)."""
    shear = next((p for p in phases if p.name == "shear"), None)
    if shear is None:
        return math.nan, math.nan, ""
    told = onset = math.nan
    cue = ""
    if "slipping" in control:
        t = control["t_host_us"].astype(np.int64)
        hits = np.flatnonzero((t >= shear.t_start_us) & (t <= shear.t_end_us) & (control["slipping"] > 0))
        if hits.size:
            told = float(t[hits[0]])
            if "slip_cue" in control:
                raw = control["slip_cue"][hits[0]]
                cue = raw.decode() if isinstance(raw, bytes) else str(raw)
    if truth is not None and "sliding" in truth:
        t = truth["t_host_us"].astype(np.int64)
        hits = t[(t >= shear.t_start_us) & (t <= shear.t_end_us) & (truth["sliding"] > 0)]
        onset = float(hits[0]) if hits.size else math.nan
    return told, onset, cue


def _rms(errors: Sequence[npt.NDArray[np.float64]]) -> float:
    values = np.concatenate([e[np.isfinite(e)] for e in errors]) if errors else np.zeros(0)
    return hold_rms_n(values, 0.0) if values.size else float("nan")


def control_runs(paths: Sequence[str | Path], forces: Sequence[ForceResult] = ()) -> list[ControlRun]:
    """The :class:`ControlRun` of every recording in ``paths`` that a force loop ran in; ``forces``: the pipeline's
    results, matched by file name."""
    by_name = {r.recording: r for r in forces}
    runs = (control_run(p, by_name.get(Path(p).name)) for p in paths)
    return [r for r in runs if r is not None]
