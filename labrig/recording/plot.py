"""Overview plot of a recording: event rate, forces and CNC Z over time, phases shaded."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from labrig.recording.reader import Recording

PHASE_COLORS = ("#dbe9f6", "#fde6cf", "#e3f1dc", "#f3dcef", "#fff6c9", "#e0e0e0")


def plot_overview(rec: Recording, out: str | os.PathLike[str]) -> Path:
    """Write a three-panel PNG overview of ``rec`` to ``out``; returns the path."""
    fig, (ax_rate, ax_force, ax_z) = plt.subplots(3, 1, figsize=(11, 7.5), sharex=True, constrained_layout=True)
    t_us, counts = rec.event_counts(bin_ms=10.0)
    ax_rate.plot(t_us / 1e6, counts / 0.010 / 1e6, color="#333333", lw=0.8)
    ax_rate.set_ylabel("event rate (Mev/s)")

    if rec.rows("ft"):
        ft = rec.ft()
        for i, (axis, color) in enumerate(zip("xyz", ("#1f77b4", "#2ca02c", "#d62728"))):
            ax_force.plot(ft["t_us"] / 1e6, ft["force_n"][:, i], color=color, lw=0.8, label=f"F{axis}")
        ax_force.legend(loc="upper right", ncol=3, fontsize=8)
    ax_force.set_ylabel("force (N)")

    if rec.rows("cnc"):
        t_s = rec.column("cnc", "t_host_us") / 1e6
        ax_z.step(t_s, rec.column("cnc", "position_mm")[:, 2], where="post", color="#9467bd", lw=1.0)
    ax_z.set_ylabel("CNC Z (mm)")
    ax_z.set_xlabel("time (s, host clock since start)")

    names = list(dict.fromkeys(p.name for p in rec.phases()))
    for phase in rec.phases():
        color = PHASE_COLORS[names.index(phase.name) % len(PHASE_COLORS)]
        for ax in (ax_rate, ax_force, ax_z):
            ax.axvspan(phase.t_start_us / 1e6, phase.t_end_us / 1e6, color=color, alpha=0.7, lw=0, zorder=0)
        mid = (phase.t_start_us + phase.t_end_us) / 2e6
        ax_rate.annotate(
            phase.name, (mid, 1.0), xycoords=("data", "axes fraction"), ha="center", va="bottom", fontsize=7, rotation=20
        )
    status = rec.exit_status + ("" if rec.finalized else ", not finalized")
    fig.suptitle(f"{rec.path.name}  ({rec.attrs.get('indenter') or 'no indenter'}; {status})", fontsize=10)
    out_path = Path(out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path, dpi=110)
    plt.close(fig)
    return out_path
