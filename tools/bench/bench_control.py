"""The force loop: holding a normal force while shearing, on the virtual rig in virtual time, read from the F/T.

Each run (``labrig.protocol.virtual_run.record_virtual``, the probing procedure's held shear, the virtual GRBL
taking the loop's jog segments): press at the centre to the held force (a force target), then shear 1 mm at
2 mm/s and back holding it (``[shear] hold_force_n``, the default loop). Regulation rows: the sphere, the flat
punch (cylinder) and the ridge at 5 N and 10 N; the RMS of the F/T's |Fz| from the target over both shears. The
step row: the sphere pressed to 10 N, then held at 5 N: the shear's start is a step of the loop from 10 N to 5 N
(rise, overshoot, settling into 5 % from the shear's start). The loop's rate is its commands' (the control
stream's) median rate.

The feedback here is the F/T sensor (``feedback = "ft"``), the baseline; the event sensor's estimate as feedback
is not in the loop yet, so there are no ``_events`` rows to set beside these.

Stable keys: ``loop_hz_median``, ``hold_rms_n_ft`` (sphere, 5 N), ``step_overshoot_pct_ft``, ``step_settling_s_ft``
(targets: overshoot <= 10 %, settling <= 0.5 s, hold RMS <= 0.3 N), and the per-row ``rows``.
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from _common import bench_main, emit

from labrig.config import load_rig
from labrig.indenters import load_indenter
from labrig.protocol.force_loop import hold_rms_n, step_response
from labrig.protocol.spec import ApproachSpec, ProbeSpec
from labrig.protocol.virtual_run import record_virtual
from labrig.recording import Recording

INDENTERS = ("sphere", "cylinder", "ridge")
FORCES_N = (5.0, 10.0)
SHEAR_MM = 1.0
SHEAR_SPEED_MM_S = 2.0


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def _spec(indenter: str, press_n: float, hold_n: float) -> ProbeSpec:
    return ProbeSpec(indenter, force_n=press_n, normal_speed_mm_s=1.5, wait_s=0.3, shear_mm=SHEAR_MM,
                     shear_speed_mm_s=SHEAR_SPEED_MM_S, shear_hold_force_n=hold_n,
                     approach=replace(ApproachSpec(), start_height_mm=0.5, max_travel_mm=2.0))


def _run(folder: Path, indenter: str, press_n: float, hold_n: float) -> dict[str, Any]:
    """One held shear; its F/T readings (s, N) in each shear and the control stream's rate."""
    rig = load_rig()
    result = record_virtual(_spec(indenter, press_n, hold_n), folder / f"{indenter}-{press_n:g}-{hold_n:g}.h5", rig,
                            load_indenter(indenter), seed=1)
    if result.exit_status != "complete":
        raise RuntimeError(f"{indenter}, {hold_n:g} N: the run was {result.exit_status}: {result.reason}")
    with Recording(result.path) as rec:
        ft = rec.stream("ft")
        t_us = ft["t_host_us"]
        fz = np.abs(ft["force_n"][:, 2] - ft["force_n"][:100, 2].mean())
        shears = [p for p in rec.phases() if p.name in ("shear", "shear_opposite")]
        control_t = rec.column("control", "t_host_us")
    parts = [((t_us >= p.t_start_us) & (t_us < p.t_end_us)) for p in shears]
    return {"t_s": [(t_us[m] - shears[0].t_start_us) / 1e6 for m in parts], "force_n": [fz[m] for m in parts],
            "loop_hz": 1e6 / float(np.median(np.diff(control_t)))}


def run(progress: bool = True) -> dict[str, Any]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="labrig-bench-control-") as tmp:
        folder = Path(tmp)
        for indenter in INDENTERS:
            for force in FORCES_N:
                if progress:
                    print(f"holding {force:g} N with the {indenter} ...", flush=True)
                r = _run(folder, indenter, force, force)
                rows.append({"indenter": indenter, "target_n": force, "feedback": "ft",
                             "hold_rms_n": hold_rms_n(np.concatenate(r["force_n"]), force), "loop_hz": r["loop_hz"]})
        if progress:
            print("a step from 10 N to 5 N with the sphere ...", flush=True)
        step_run = _run(folder, "sphere", 10.0, 5.0)
    step = step_response(step_run["t_s"][0], step_run["force_n"][0], 5.0, start_n=10.0)
    sphere_5 = next(r for r in rows if r["indenter"] == "sphere" and r["target_n"] == 5.0)
    return {
        "rows": rows,
        "loop_hz_median": float(np.median([r["loop_hz"] for r in rows])),
        "hold_rms_n_ft": sphere_5["hold_rms_n"],
        "step_rise_s_ft": step.rise_s,
        "step_overshoot_pct_ft": step.overshoot_pct,
        "step_settling_s_ft": step.settling_s,
        "shear_mm": SHEAR_MM,
        "shear_speed_mm_s": SHEAR_SPEED_MM_S,
    }


def render(f: dict[str, Any]) -> None:
    rows = [[r["indenter"], f"{r['target_n']:g}", r["feedback"], f"{r['hold_rms_n']:.3f}", f"{r['loop_hz']:.0f}"]
            for r in f["rows"]]
    emit(f"Holding a normal force while shearing {f['shear_mm']:g} mm at {f['shear_speed_mm_s']:g} mm/s "
         "(virtual rig, virtual time)", ["indenter", "target N", "feedback", "hold RMS N", "loop Hz"], rows,
         [f"step 10 -> 5 N (sphere, the shear's start): rise {f['step_rise_s_ft']:.3f} s, overshoot "
          f"{f['step_overshoot_pct_ft']:.1f} %, settling {f['step_settling_s_ft']:.3f} s (targets: overshoot <= 10 %, "
          "settling <= 0.5 s); hold RMS target <= 0.3 N. The event sensor's estimate is not in the loop yet."])


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
