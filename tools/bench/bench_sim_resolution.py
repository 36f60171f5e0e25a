"""The virtual rig's time resolution against its cost: CPU per simulated second and event fidelity, side by side.

The rig steps as finely as two knobs say: a render (and event-sensor) step moves no marker's
image more than ``max_step_px`` (the rig file's ``[sim.events]``, 0.2 px), and the mechanics
are solved each time the tool moves ``solve_step_mm`` (a :class:`~labrig.sim.rig.VirtualRig`
argument, 0.02 mm). Each setting ``PX,MM`` records the same paper-campaign recordings in virtual
time with the sensor's noise and leak off (so two settings differ only by their steps), and is
compared with the finest setting given (the reference):

* ``cpu_s_per_sim_s``: process CPU (writer thread included) per simulated second;
* ``count_l1``: sum over pixels and polarities of |events - reference events|, over the reference's events;
* ``dt_p50_us``, ``dt_p95_us``: per reference event, the time to the nearest event of the same
  pixel and polarity in this setting's recording;
* ``markers_mean_px``, ``markers_p999_px``: the true markers' image positions (``/truth/markers``,
  1 kHz, interpolated linearly between solves as the rig renders them) against the reference's at
  the same times: what the solve step trades; ``frames_over_0_2_px``: the samples with a marker
  more than 0.2 px off (lift-off, where the contact lets go between two solves);
* ``solves``: the mechanics solves (``/truth/depth`` maps).

Coarser steps shift events within a step (the sensor ramps its input linearly between steps) and
cost less only in the steps' fixed overheads: what a scene needs, charted against what it costs.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from _common import bench_main, emit

ROOT = Path(__file__).resolve().parents[2]
#: Pixel keys and times are packed into one int64: times relative to the recording's first event.
_TIME_BITS = 36
DEFAULT_SETTINGS = "0.05,0.005 0.1,0.01 0.2,0.02 0.4,0.04 0.8,0.08"
DEFAULT_RECORDINGS = "117,0"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--settings", default=DEFAULT_SETTINGS,
                    help="space-separated max_step_px,solve_step_mm pairs; the first is the reference")
    ap.add_argument("--recordings", default=DEFAULT_RECORDINGS, help="comma-separated indices into the paper campaign")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    return ap.parse_args(argv)


def run(settings: str = DEFAULT_SETTINGS, recordings: str = DEFAULT_RECORDINGS, progress: bool = True) -> dict[str, Any]:
    from labrig.config import load_rig
    from labrig.indenters import load_indenters
    from labrig.protocol.files import load_campaign
    from labrig.sim import _render_kernels
    from labrig.sim.rig import VirtualRig
    from labrig.sim.world_process import prepare_contact_tables

    pairs = [tuple(float(v) for v in s.split(",")) for s in settings.split()]
    rig, indenters = load_rig(), load_indenters()
    campaign = load_campaign(ROOT / "protocols" / "paper.toml", rig, indenters)
    rows: list[dict[str, Any]] = []
    for index in (int(i) for i in recordings.split(",")):
        plan = campaign.plans[index]
        indenter = indenters[plan.spec.indenter]
        prepare_contact_tables(rig, indenter, [plan.spec.shear_direction_deg])
        _render_kernels.warm_up()
        VirtualRig(rig, indenter, seed=0)  # per-process caches, as in bench_virtual_stages
        _record(campaign, index, rig, indenter, *pairs[-1])  # untimed: a process's first recording pays more
        reference = None
        for px, mm in pairs:
            cpu_s, sim_s, events, markers = _record(campaign, index, rig, indenter, px, mm)
            row: dict[str, Any] = {"index": index, "indenter": plan.spec.indenter, "max_step_px": px,
                                   "solve_step_mm": mm, "cpu_s_per_sim_s": cpu_s / sim_s, "events": int(events[0].size),
                                   "solves": markers[2]}
            if reference is None:
                reference = events, markers
            else:
                row.update(_fidelity(events, reference[0]))
                row.update(_marker_error(markers, reference[1]))
            rows.append(row)
            if progress:
                print(f"recording {index} at {px} px, {mm} mm: {cpu_s / sim_s:.3f} CPU s per simulated s", flush=True)
    return {"rows": rows}


def _record(campaign: Any, index: int, rig: Any, indenter: Any, px: float, mm: float
            ) -> tuple[float, float, tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]],
                       tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], int]]:
    """Record one recording at this resolution, noise and leak off: (CPU s, simulated s, (pixel keys, times),
    (true marker times, their image positions (T, N, 2) px, solves))."""
    from labrig.config import rig_with
    from labrig.protocol.virtual_campaign import recording_seed
    from labrig.protocol.virtual_run import record_virtual
    from labrig.recording import Recording
    from labrig.sim import rig as rig_module

    quiet = rig_with(rig, {"sim.events.max_step_px": px, "sim.events.leak_rate_hz": 0.0,
                           "sim.events.shot_noise_rate_hz": 0.0})
    plan = campaign.plans[index]
    # The solve step is a VirtualRig argument, not a rig-file setting: the offline rig builds its VirtualRig with the default.
    init = rig_module.VirtualRig.__init__
    defaults = init.__kwdefaults__
    saved = dict(defaults)
    defaults["solve_step_mm"] = mm
    try:
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "r.h5"
            cpu0 = time.process_time()
            record_virtual(plan.spec, out, quiet, indenter, seed=recording_seed(campaign, plan))
            cpu = time.process_time() - cpu0
            with Recording(out) as rec:
                phases = rec.phases()
                sim_s = (phases[-1].t_end_us - phases[0].t_start_us) / 1e6
                ev = rec.stream("events")
                markers = (rec.column("truth/markers", "t_host_us"),
                           rec.column("truth/markers", "position_px").astype(np.float64), rec.rows("truth/depth"))
    finally:
        defaults.clear()
        defaults.update(saved)
    key = (ev["y"].astype(np.int64) * 4096 + ev["x"]) * 2 + ev["p"]
    return cpu, sim_s, (key, ev["t_device_us"].astype(np.int64)), markers


def _fidelity(events: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]],
              reference: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]) -> dict[str, float]:
    """Per-pixel count difference and nearest same-pixel time offsets against the reference."""
    (key, t), (ref_key, ref_t) = events, reference
    pixels = np.union1d(key, ref_key)
    counts = np.bincount(np.searchsorted(pixels, key), minlength=pixels.size)
    ref_counts = np.bincount(np.searchsorted(pixels, ref_key), minlength=pixels.size)
    t0 = min(int(t.min()), int(ref_t.min()))
    packed = np.sort((key << _TIME_BITS) + (t - t0))
    ref_packed = (ref_key << _TIME_BITS) + (ref_t - t0)
    at = np.searchsorted(packed, ref_packed)
    nearest = np.full(ref_packed.size, np.iinfo(np.int64).max)
    for q in (at - 1, at):
        inside = (q >= 0) & (q < packed.size)
        q = np.clip(q, 0, packed.size - 1)
        same_pixel = inside & ((packed[q] >> _TIME_BITS) == ref_key)
        nearest = np.where(same_pixel, np.minimum(nearest, np.abs(packed[q] - ref_packed)), nearest)
    found = nearest[nearest < np.iinfo(np.int64).max]
    return {"count_l1": float(np.abs(counts - ref_counts).sum() / ref_key.size),
            "matched": float(found.size / ref_key.size),
            "dt_p50_us": float(np.median(found)), "dt_p95_us": float(np.percentile(found, 95))}


def _marker_error(markers: tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], int],
                  reference: tuple[npt.NDArray[np.int64], npt.NDArray[np.float64], int]) -> dict[str, float]:
    """The true markers' image positions against the reference's at the times both have (px)."""
    _, at, ref_at = np.intersect1d(markers[0], reference[0], return_indices=True)
    error = np.hypot(*np.moveaxis(markers[1][at] - reference[1][ref_at], -1, 0))  # (T, N); NaN: a marker not printed
    worst = np.nanmax(error, axis=1)
    return {"markers_mean_px": float(np.nanmean(error)), "markers_p999_px": float(np.nanpercentile(error, 99.9)),
            "frames_over_0_2_px": int(np.sum(worst > 0.2))}


def render(figures: dict[str, Any]) -> None:
    rows = []
    for r in figures["rows"]:
        fidelity = ("reference", "", "", "", "", "") if "count_l1" not in r else (
            f"{100 * r['count_l1']:.1f} %", f"{r['dt_p50_us']:.0f}", f"{r['dt_p95_us']:.0f}",
            f"{r['markers_mean_px']:.4f}", f"{r['markers_p999_px']:.3f}", f"{r['frames_over_0_2_px']}")
        rows.append([f"{r['index']} {r['indenter']}", f"{r['max_step_px']:g}", f"{r['solve_step_mm']:g}",
                     f"{r['solves']}", f"{r['cpu_s_per_sim_s']:.3f}", f"{r['events']:,}", *fidelity])
    emit("Virtual-rig resolution: cost and fidelity (noise and leak off)",
         ["recording", "max step px", "solve step mm", "solves", "CPU s / sim s", "events", "count |diff|", "dt p50 us",
          "dt p95 us", "markers mean px", "markers p99.9 px", "frames > 0.2 px"],
         rows, ["Fidelity against each recording's first setting."
                + (f" Bench wall {figures['bench_wall_s']:.0f} s." if "bench_wall_s" in figures else "")])


def main(argv: list[str] | None = None) -> None:
    bench_main(parse_args, run, render, argv)


if __name__ == "__main__":
    main()
