"""A recording's summary as plain data (what ``labrig inspect`` prints).

Keys are stable and carry their units and frames: ``ft_sensor_*`` is the F/T sensor's own reading
(the force on the indenter, in the sensor's axes); ``labrig inspect`` adds the same force as the
force on the gel in the gel frame (``force_on_gel_*``, :mod:`labrig.calibration.ft_frame`), labrig's
one convention. ``--json`` prints this dict as is.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from labrig.clock import unwrap_counter
from labrig.recording.quality import assess, dropped_rows, stored_quality
from labrig.recording.reader import Recording

AXES = ("x", "y", "z")


def summarize(rec: Recording) -> dict[str, Any]:
    attrs = rec.attrs
    phases = rec.phases()
    start_us = min([0] + [p.t_start_us for p in phases])
    end_us = rec.end_us()
    duration_s = max(0.0, (end_us - start_us) / 1e6)
    n_events = rec.n_events
    _, counts = rec.event_counts(bin_ms=10.0)

    summary: dict[str, Any] = {
        "file": str(rec.path),
        "schema_version": attrs.get("schema_version"),
        "labrig_version": attrs.get("labrig_version"),
        "created": attrs.get("created"),
        "indenter": attrs.get("indenter", ""),
        "exit_status": rec.exit_status,
        "exit_reason": attrs.get("exit_reason", ""),
        "finalized": rec.finalized,
        "duration_s": duration_s,
        "events": n_events,
        "event_rate_hz": n_events / duration_s if duration_s > 0 else 0.0,
        "event_rate_peak_hz": float(counts.max() / 0.010) if counts.size else 0.0,
        "triggers": rec.rows("triggers"),
        "ft_samples": rec.rows("ft"),
        "cnc_samples": rec.rows("cnc"),
        "gcode_lines": rec.rows("gcode"),
    }
    warnings: list[str] = []
    summary.update(_ft_summary(rec, warnings))
    summary.update(_cnc_summary(rec))
    summary["phases"] = [
        {"name": p.name, "start_s": p.t_start_us / 1e6, "end_s": p.t_end_us / 1e6, "duration_s": p.duration_s}
        for p in phases
    ]
    summary["clock"] = {
        device: {
            "method": m.method,
            "drift_ppm": m.drift_ppm,
            "pairs": m.n_pairs,
            "triggers": m.n_triggers,
            "residual_p50_us": m.residual_p50_us,
            "residual_p99_us": m.residual_p99_us,
            "residual_max_us": m.residual_max_us,
        }
        for device, m in sorted(rec.clock_models.items())
    }
    summary["dropped"] = dropped_rows(rec)

    if not rec.finalized:
        warnings.append(f"not finalized: the recorder stopped unexpectedly; run `labrig recover {rec.path}`")
    if rec.exit_status == "aborted":
        warnings.append(f"aborted: {summary['exit_reason'] or 'no reason given'}")
    for stream, rows in summary["dropped"].items():
        warnings.append(f"{rows} {stream} rows dropped by the recorder")
    quality = stored_quality(rec) or assess(rec)
    summary["quality"] = quality.verdict
    summary["quality_reasons"] = list(quality.reasons)
    warnings += [reason for reason in quality.reasons if not reason.endswith("rows dropped by the recorder")]
    summary["warnings"] = warnings
    return summary


def _ft_summary(rec: Recording, warnings: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if rec.rows("ft") == 0:
        for axis in AXES:
            out[f"ft_sensor_f{axis}_min_n"] = out[f"ft_sensor_f{axis}_max_n"] = None
            out[f"ft_sensor_t{axis}_min_nm"] = out[f"ft_sensor_t{axis}_max_nm"] = None
        out["ft_rate_hz"] = 0.0
        return out
    force = rec.column("ft", "force_n")
    torque = rec.column("ft", "torque_nm")
    for i, axis in enumerate(AXES):  # the sensor's own reading: the force on the indenter, sensor axes
        out[f"ft_sensor_f{axis}_min_n"] = float(force[:, i].min())
        out[f"ft_sensor_f{axis}_max_n"] = float(force[:, i].max())
        out[f"ft_sensor_t{axis}_min_nm"] = float(torque[:, i].min())
        out[f"ft_sensor_t{axis}_max_nm"] = float(torque[:, i].max())
    device_us = unwrap_counter(rec.column("ft", "t_device_us"), 32)
    steps = np.diff(device_us)
    period_us = float(np.median(steps)) if steps.size else 0.0
    out["ft_rate_hz"] = 1e6 / period_us if period_us > 0 else 0.0
    flagged = int((rec.column("ft", "status") != 0).sum())
    if flagged:
        warnings.append(f"{flagged} F/T samples flagged by the sensor (overrange, invalid or throttled)")
    return out


def _cnc_summary(rec: Recording) -> dict[str, Any]:
    out: dict[str, Any] = {}
    position = rec.column("cnc", "position_mm") if rec.rows("cnc") else np.zeros((0, 3))
    for i, axis in enumerate(AXES):
        out[f"cnc_{axis}_min_mm"] = float(position[:, i].min()) if len(position) else None
        out[f"cnc_{axis}_max_mm"] = float(position[:, i].max()) if len(position) else None
    return out
