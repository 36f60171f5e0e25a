"""What ``labrig run REC`` and ``labrig run --live`` share: the --view and --out checks and the printed summaries."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.markup import escape
from rich.table import Table

from labrig.cli.console import console
from labrig.errors import LabrigError


def depth_every_option(depth_every_ms: float | None) -> int | None:
    """``--depth-every-ms`` in us (None: the depth source on every window), or one line saying what is wrong."""
    if depth_every_ms is None:
        return None
    if not depth_every_ms > 0:
        raise LabrigError(f"--depth-every-ms must be positive, not {depth_every_ms:g}")
    return round(depth_every_ms * 1000)


def check_view(view: Path | None) -> None:
    """Refuse a --view that is not a GIF before anything runs."""
    if view is not None and view.suffix.lower() != ".gif":
        raise LabrigError("--view writes a GIF: give a path ending in .gif")


def check_out(out: Path | None) -> None:
    """Refuse an --out that does not name an HDF5 file before anything runs."""
    if out is not None and out.suffix.lower() not in (".h5", ".hdf5"):
        raise LabrigError(f"--out {out}: the results are written as HDF5 (per-window markers, displacements, forces); "
                          "give a path ending in .h5")


def stage_table(stage_median_ms: dict[str, float], title: str | None = None) -> Table:
    """The per-stage median latencies (ms) as a rich table."""
    table = Table(title=title)
    table.add_column("stage")
    table.add_column("median ms", justify="right")
    for name, ms in stage_median_ms.items():
        table.add_row(name, f"{ms:.3f}")
    return table


def print_run(s: dict[str, Any]) -> None:
    """``labrig run REC``'s summary."""
    console.print(stage_table(s["stage_median_ms"], f"labrig run {Path(s['recording']).name} ({s['depth_source']} depth)"))
    mode = f"{s['window_events']} events" if s["window_events"] else f"{s['window_us'] / 1000:g} ms"
    console.print(f"{s['windows']} windows of {mode} over {s['duration_s']:.2f} s in {s['wall_s']:.2f} s; "
                  f"processing {s['processing_per_window_ms']:.2f} ms per window (real-time factor "
                  f"{s['real_time_factor']:.2f})")
    f = s["peak_net_force_on_gel_n"]
    console.print(f"peak normal force {s['peak_normal_force_on_gel_n']:.2f} N at {s['peak_at_us'] / 1e6:.3f} s "
                  f"(net force on the gel, gel frame: {f[0]:+.2f}, {f[1]:+.2f}, {f[2]:+.2f} N); "
                  f"E = {s['youngs_modulus_mpa']:.3g} MPa "
                  f"from {escape(s['sources']['modulus'])}; camera: {escape(s['sources']['camera'])}")
    for key in ("out", "view"):
        if s[key]:
            console.print(f"{key}: {s[key]}")


def print_live_run(s: dict[str, Any]) -> None:
    """``labrig run --live``'s summary (with the probing run and the F/T comparison when there was one)."""
    console.print(f"[bold]labrig run --live[/]: {escape(s['source'])}, {escape(s['depth_source'])} depth")
    console.print(stage_table(s["stage_median_ms"]))
    mode = f"{s['window_events']} events" if s["window_events"] else f"{s['window_us'] / 1000:g} ms"
    console.print(f"{s['windows_tracked']} windows of {mode} tracked over {s['stream_s']:.2f} s of camera time "
                  f"(wall {s['stream_wall_s']:.2f} s, {s['end_reason']}): {s['windows_processed']} with forces, "
                  f"{s['windows_skipped']} skipped (tracked only), {s['windows_late']} late")
    style = "green" if not s["windows_skipped"] and not s["dropped_chunks"] else "yellow"
    console.print(f"[{style}]processing {s['processing_per_window_ms']:.2f} ms per window (real-time factor "
                  f"{s['real_time_factor']:.2f}); latency median {s['latency_median_ms']:.1f} ms, p95 "
                  f"{s['latency_p95_ms']:.1f} ms; dropped chunks {s['dropped_chunks']}[/]")
    if s.get("event_to_force_p99_ms") is not None:
        console.print(f"event to force (a window's newest event to its forces): median "
                      f"{s['event_to_force_median_ms']:.1f} ms, p99 {s['event_to_force_p99_ms']:.1f} ms")
    f = s["peak_net_force_on_gel_n"]
    console.print(f"peak normal force {s['peak_normal_force_on_gel_n']:.2f} N (net force on the gel, gel frame: "
                  f"{f[0]:+.2f}, {f[1]:+.2f}, {f[2]:+.2f} N); E = {s['youngs_modulus_mpa']:.3g} MPa "
                  f"from {escape(s['sources']['modulus'])}")
    if s["camera_error"]:
        console.print(f"[yellow]the camera stream ended with an error: {escape(s['camera_error'])}[/]")
    c, p = s["ft_comparison"], s["probe"]
    if p is not None:
        style = "green" if p["exit_status"] == "complete" else "yellow"
        where = "virtual rig" if s["virtual_rig"] else "rig"
        console.print(f"probing run on the {where}: [{style}]{p['exit_status']}[/]" + (f" ({p['reason']})" if p["reason"] else "")
                      + f"; recording {'kept at ' + p['recording'] if p['recording'] else 'compared, then deleted'}")
    if c is not None:
        ratio = f"{c['peak_normal_force_ratio']:.2f}" if c["peak_normal_force_ratio"] is not None else "-"
        corr = f"{c['normal_force_correlation']:.2f}" if c["normal_force_correlation"] is not None else "-"
        console.print(f"against the F/T sensor (force on the gel, gel frame; {c['windows_compared']} windows): peak "
                      f"normal force {c['pipeline_peak_normal_force_n']:.2f} N live vs {c['ft_peak_normal_force_n']:.2f} N "
                      f"F/T (ratio {ratio}); Fz RMS error {c['normal_force_rms_error_n']:.2f} N, correlation {corr}")
    for key in ("out", "view"):
        if s[key]:
            console.print(f"{key}: {s[key]}")
