"""The force loop: pressing to a force, holding it and holding it while shearing, on the virtual rig in virtual time.

Each run (``labrig.protocol.virtual_run.record_virtual``, the probing procedure with a held press, the virtual GRBL
taking the loop's jog segments): from the contact point the loop presses to the target and holds it 1 s (Normal
Down: a step of the loop from the contact force to the target), holds it through the waits, and holds it while
shearing 1 mm at 2 mm/s and back. Rows: the sphere, the flat punch (cylinder) and the ridge at 5 N and 10 N, on
the shipped rig (GRBL's default acceleration, 10 mm/s**2) and the sphere at 5 N on a rig whose CNC accelerates at
50 mm/s**2 (both feedbacks). Per row: the step's rise (10-90 %), overshoot and settling into 5 % (from Normal
Down's start), the RMS of the F/T's |Fz| from the target over both shears, and the loop's rate (its commands' median rate).

Each case runs twice, side by side: with the F/T sensor as the loop's feedback (``feedback = "ft"``, 800 Hz, the
baseline) and with the event sensor's estimate (``feedback = "events"``: the pipeline with the shipped calibration
and the bundled network runs beside the run on the rendered camera chunks, its estimate stamped at its window's
end); the step and the hold are always measured on the F/T sensor, the reference. Per row the events / ft ratio of
the hold RMS is printed.

The slip reflex (``[slip] action = "report"``): the sphere, the flat punch and the ridge held at 1.5 N while
shearing 2 mm at 2 mm/s (their contacts slide as a whole: the sim's ``truth/contact`` ``sliding``), and at 5 N while
shearing 1 mm (they stick), on both feedbacks: when the reflex told slip less the true onset of gross slip (ms), and
whether it told slip in a shear that stuck (a false trip).

Stable keys: ``loop_hz_median``; ``slip_onset_error_ms`` and ``slip_onset_error_ms_ft`` (the sphere sliding; target
within 50 ms), ``slip_onset_error_ms_worst_events`` and ``slip_onset_error_ms_worst_ft`` (the largest |error| over
the three sliding indenters), ``slip_false_trips_events`` and ``slip_false_trips_ft`` (stick-only shears that told
slip; target 0), ``slip_rows``; for the sphere at 5 N on the shipped rig ``hold_rms_n_ft``, ``hold_rms_n_events``,
``hold_rms_ratio_events_ft``, ``step_rise_s_ft``, ``step_overshoot_pct_ft``, ``step_settling_s_ft`` and the same
``_events`` (targets: overshoot <= 10 %, settling <= 0.5 s, hold RMS <= 0.3 N with events, aim within 1.2x of ft);
``step_settling_s_ft_accel_50``, ``step_overshoot_pct_ft_accel_50`` and the same ``_events_accel_50``,
``hold_rms_n_events_accel_50`` (the same on the faster CNC: at 10 mm/s**2 no loop can settle within 0.5 s);
the per-row ``rows``.
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from _common import bench_main, emit

from labrig.config import DEFAULT_RIG, RigConfig, load_rig, parse_rig
from labrig.evaluation.control import control_run, hold_rms_n, step_response
from labrig.indenters import load_indenter
from labrig.protocol.feedback import EVENTS_LOOP_DEFAULTS, FEEDBACKS
from labrig.protocol.force_loop import ForceLoopParams
from labrig.protocol.spec import ApproachSpec, ProbeSpec
from labrig.protocol.virtual_run import record_virtual
from labrig.recording import Recording
from labrig.sim.imperfections import GRBL_DEFAULT_ACCELERATION_MM_S2

INDENTERS = ("sphere", "cylinder", "ridge")
FORCES_N = (5.0, 10.0)
SHEAR_MM = 1.0
SHEAR_SPEED_MM_S = 2.0
PRESS_HOLD_S = 1.0
FAST_ACCEL_MM_S2 = 50.0
#: (indenter, held force N, shear mm): sliding at 1.5 N over 2 mm, sticking at 5 N over 1 mm.
SLIP_CASES = tuple((i, 1.5, 2.0) for i in INDENTERS) + tuple((i, 5.0, 1.0) for i in INDENTERS)
SLIP_PRESS_HOLD_S = 0.5


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def _spec(indenter: str, force_n: float, feedback: str) -> ProbeSpec:
    control = ForceLoopParams(**EVENTS_LOOP_DEFAULTS) if feedback == "events" else ForceLoopParams()
    return ProbeSpec(indenter, force_n=force_n, press_hold_s=PRESS_HOLD_S, wait_s=0.3, shear_mm=SHEAR_MM,
                     shear_speed_mm_s=SHEAR_SPEED_MM_S, feedback=feedback, control=control,
                     approach=replace(ApproachSpec(), start_height_mm=0.5, max_travel_mm=2.0))


def _rig(accel_mm_s2: float | None) -> RigConfig:
    """The shipped rig, or the same with the virtual CNC accelerating at ``accel_mm_s2`` on every axis."""
    if accel_mm_s2 is None:
        return load_rig()
    text = DEFAULT_RIG.read_text() + f"\n[sim.grbl]\nacceleration_mm_s2 = {accel_mm_s2:g}\n"
    return parse_rig(text, DEFAULT_RIG)


def _run(folder: Path, indenter: str, force_n: float, feedback: str, accel_mm_s2: float | None = None
         ) -> dict[str, Any]:
    """One run with a held press and held shears: its step, hold RMS and loop rate."""
    name = f"{indenter}-{force_n:g}-{accel_mm_s2 or 'default'}-{feedback}"
    result = record_virtual(_spec(indenter, force_n, feedback), folder / f"{name}.h5", _rig(accel_mm_s2),
                            load_indenter(indenter), seed=1)
    if result.exit_status != "complete":
        raise RuntimeError(f"{name}: the run was {result.exit_status}: {result.reason}")
    with Recording(result.path) as rec:
        ft = rec.stream("ft")
        t_us = ft["t_host_us"]
        fz = np.abs(ft["force_n"][:, 2] - ft["force_n"][:100, 2].mean())
        phases = rec.phases()
        control_t = rec.column("control", "t_host_us")
    press = next(p for p in phases if p.name == "normal_down")
    in_press = (t_us >= press.t_start_us) & (t_us < press.t_end_us)
    step = step_response((t_us[in_press] - press.t_start_us) / 1e6, fz[in_press], force_n, start_n=0.0)
    sheared = np.zeros(t_us.shape, bool)
    for p in phases:
        if p.name in ("shear", "shear_opposite"):
            sheared |= (t_us >= p.t_start_us) & (t_us < p.t_end_us)
    return {"indenter": indenter, "target_n": force_n, "feedback": feedback,
            "accel_mm_s2": accel_mm_s2 or GRBL_DEFAULT_ACCELERATION_MM_S2,
            "step_rise_s": step.rise_s, "step_overshoot_pct": step.overshoot_pct,
            "step_settling_s": step.settling_s if np.isfinite(step.settling_s) else None,
            "hold_rms_n": hold_rms_n(fz[sheared], force_n),
            "loop_hz": 1e6 / float(np.median(np.diff(control_t)))}


def _slip_run(folder: Path, indenter: str, force_n: float, shear_mm: float, feedback: str) -> dict[str, Any]:
    """One held shear with the reflex reporting: when it told slip against the true onset of gross slip."""
    spec = replace(_spec(indenter, force_n, feedback), press_hold_s=SLIP_PRESS_HOLD_S, wait_s=0.2, shear_mm=shear_mm,
                   slip_action="report")
    name = f"slip-{indenter}-{force_n:g}-{shear_mm:g}-{feedback}"
    result = record_virtual(spec, folder / f"{name}.h5", load_rig(), load_indenter(indenter), seed=1)
    if result.exit_status != "complete":
        raise RuntimeError(f"{name}: the run was {result.exit_status}: {result.reason}")
    run = control_run(result.path)
    assert run is not None
    slid, told = bool(np.isfinite(run.slip_onset_s)), bool(np.isfinite(run.slip_told_s))
    shear = next(p for p in run.phases_s if p[0] == "shear")
    return {"indenter": indenter, "held_n": force_n, "shear_mm": shear_mm, "feedback": feedback,
            "slid": slid, "told": told,
            "onset_s": run.slip_onset_s - shear[1] if slid else None,
            "told_s": run.slip_told_s - shear[1] if told else None,
            "onset_error_ms": run.slip_onset_error_ms if slid and told else None, "cue": run.slip_cue or None,
            "false_trip": told and not slid}


def run(progress: bool = True) -> dict[str, Any]:
    rows = []
    cases = [(i, f, None) for i in INDENTERS for f in FORCES_N] + [("sphere", 5.0, FAST_ACCEL_MM_S2)]
    with tempfile.TemporaryDirectory(prefix="labrig-bench-control-") as tmp:
        for indenter, force, accel in cases:
            for feedback in FEEDBACKS:
                if progress:
                    print(f"pressing to {force:g} N with the {indenter} on {feedback}"
                          + (f" (CNC at {accel:g} mm/s**2)" if accel else "") + " ...", flush=True)
                rows.append(_run(Path(tmp), indenter, force, feedback, accel))
        slip_rows = []
        for indenter, force, shear_mm in SLIP_CASES:
            for feedback in FEEDBACKS:
                if progress:
                    print(f"shearing {shear_mm:g} mm with the {indenter} held at {force:g} N on {feedback}, the slip "
                          "reflex reporting ...", flush=True)
                slip_rows.append(_slip_run(Path(tmp), indenter, force, shear_mm, feedback))
    for row in rows:
        if row["feedback"] == "events":
            ft = next(r for r in rows if r["feedback"] == "ft" and r["indenter"] == row["indenter"]
                      and r["target_n"] == row["target_n"] and r["accel_mm_s2"] == row["accel_mm_s2"])
            row["hold_rms_ratio_events_ft"] = row["hold_rms_n"] / ft["hold_rms_n"]
    head = {r["feedback"]: r for r in rows if r["indenter"] == "sphere" and r["target_n"] == 5.0
            and r["accel_mm_s2"] == GRBL_DEFAULT_ACCELERATION_MM_S2}
    fast = {r["feedback"]: r for r in rows if r["accel_mm_s2"] == FAST_ACCEL_MM_S2}
    out: dict[str, Any] = {"rows": rows, "loop_hz_median": float(np.median([r["loop_hz"] for r in rows]))}
    for feedback, row in head.items():
        out.update({f"hold_rms_n_{feedback}": row["hold_rms_n"], f"step_rise_s_{feedback}": row["step_rise_s"],
                    f"step_overshoot_pct_{feedback}": row["step_overshoot_pct"],
                    f"step_settling_s_{feedback}": row["step_settling_s"]})
    out.update({
        "hold_rms_ratio_events_ft": head["events"]["hold_rms_n"] / head["ft"]["hold_rms_n"],
        **{f"step_{key}_{feedback}_accel_50": fast[feedback][f"step_{key}"]
           for feedback in FEEDBACKS for key in ("settling_s", "overshoot_pct")},
        "hold_rms_n_events_accel_50": fast["events"]["hold_rms_n"],
        "shear_mm": SHEAR_MM,
        "shear_speed_mm_s": SHEAR_SPEED_MM_S,
        "slip_rows": slip_rows,
    })
    for feedback, suffix in (("events", ""), ("ft", "_ft")):
        sphere = next(r for r in slip_rows if r["indenter"] == "sphere" and r["held_n"] == 1.5 and r["feedback"] == feedback)
        out[f"slip_onset_error_ms{suffix}"] = sphere["onset_error_ms"]
        out[f"slip_false_trips_{feedback}"] = sum(r["false_trip"] for r in slip_rows if r["feedback"] == feedback)
        errors = [abs(r["onset_error_ms"]) if r["told"] else float("inf")
                  for r in slip_rows if r["feedback"] == feedback and r["slid"]]
        out[f"slip_onset_error_ms_worst_{feedback}"] = max(errors) if errors else None
    return out


def render(f: dict[str, Any]) -> None:
    def settling(r: dict[str, Any]) -> str:
        return "never" if r["step_settling_s"] is None else f"{r['step_settling_s']:.3f}"

    rows = [[r["indenter"], f"{r['target_n']:g}", f"{r['accel_mm_s2']:g}", r["feedback"], f"{r['step_rise_s']:.3f}",
             f"{r['step_overshoot_pct']:.1f}", settling(r), f"{r['hold_rms_n']:.3f}",
             f"{r['hold_rms_ratio_events_ft']:.2f}" if "hold_rms_ratio_events_ft" in r else "", f"{r['loop_hz']:.0f}"]
            for r in f["rows"]]
    emit(f"Pressing to a force from contact, then holding it while shearing {f['shear_mm']:g} mm at "
         f"{f['shear_speed_mm_s']:g} mm/s (virtual rig, virtual time)",
         ["indenter", "target N", "CNC accel mm/s2", "feedback", "rise s", "overshoot %", "settling s", "hold RMS N",
          "events / ft", "loop Hz"], rows,
         ["targets (sphere, 5 N): overshoot <= 10 %, settling <= 0.5 s, hold RMS <= 0.3 N with events (aim: "
          "within 1.2x of ft). Step and hold measured on the F/T sensor whatever the feedback."])

    def ms(value: float | None) -> str:
        return "" if value is None else f"{value * 1e3:.0f}"

    emit(f"The slip reflex: held shears at {SHEAR_SPEED_MM_S:g} mm/s, when it told slip against the true onset of gross "
         "slip (virtual rig, virtual time)",
         ["indenter", "held N", "shear mm", "feedback", "slid at ms", "told at ms", "told - onset ms", "cue",
          "false trip"],
         [[r["indenter"], f"{r['held_n']:g}", f"{r['shear_mm']:g}", r["feedback"], ms(r["onset_s"]), ms(r["told_s"]),
           "" if r["onset_error_ms"] is None else f"{r['onset_error_ms']:+.0f}", r["cue"] or "",
           "yes" if r["false_trip"] else ""]
          for r in f["slip_rows"]],
         ["times from Shear's start; targets: within 50 ms of the onset, no false trip in a shear that sticks. events: "
          "the share of the estimate's contact markers at friction, or its tracked contact ceasing to follow the "
          "tool; ft: the net force's friction ratio; either: the stall of |Ft| against the travel."])


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
