"""The paper's tables from per-recording results: plain rows of numbers (mean, std), no formatting.

Each function takes the results of :mod:`labrig.evaluation.depth` or
:mod:`labrig.evaluation.forces` (:class:`DepthResult`, :class:`ForceResult`, one per
recording) and pools the windows, as the paper pools test samples. Rows are dicts whose keys
name the report's columns, units in the keys.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.evaluation.depth import DepthResult
from labrig.evaluation.forces import ForceResult

F64 = npt.NDArray[np.float64]

#: Table II of the paper: (loss, window ms) rows.
TABLE2_ROWS: tuple[tuple[str, float], ...] = (
    ("contact", 5.0), ("contact", 10.0), ("contact", 30.0), ("contact", 50.0), ("contact", 70.0), ("uniform", 10.0))

DEPTH_RANGES_MM: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0)
FORCE_RANGES_N: dict[str, tuple[float, ...]] = {"x": (0.0, 1.0, 2.0, 3.0, 4.0, 6.0), "y": (0.0, 1.0, 2.0, 3.0, 4.0, 6.0),
                                               "z": (0.0, 2.0, 5.0, 10.0, 15.0, 20.0, 30.0)}


def mean_std(values: npt.ArrayLike) -> tuple[float | None, float | None]:
    """Mean and std of the finite values; (None, None) when there are none."""
    v = np.asarray(values, np.float64).ravel()
    v = v[np.isfinite(v)]
    return (float(v.mean()), float(v.std())) if v.size else (None, None)


def pooled(per_recording: Iterable[npt.ArrayLike], masks: Iterable[npt.ArrayLike] | None = None) -> F64:
    """Per-recording arrays of windows concatenated (only the windows where ``masks`` are true, when given)."""
    arrays = [np.asarray(a) for a in per_recording]
    if masks is not None:
        arrays = [a[np.asarray(m, bool)] for a, m in zip(arrays, masks)]
    return np.concatenate(arrays) if arrays else np.zeros(0)


# -- depth -------------------------------------------------------------------------------------


def _depth_parts(results: Sequence[DepthResult]) -> dict[str, F64]:
    """Pooled per-window depth errors (mm) by part of the map: total, contact, noncontact."""
    return {"total": pooled(r.total_mm for r in results), "contact": pooled(r.contact_mm for r in results),
            "noncontact": pooled(r.noncontact_mm for r in results)}


def depth_row(results: Sequence[DepthResult]) -> dict[str, Any]:
    """Depth error (mm) total / contact / non-contact, mean and std over windows, for one model."""
    row: dict[str, Any] = {"windows": int(sum(len(r.total_mm) for r in results))}
    for part, errors in _depth_parts(results).items():
        row[f"{part}_mm"], row[f"{part}_std_mm"] = mean_std(errors)
    row["infer_ms"] = float(np.median([r.infer_ms for r in results])) if results else None
    return row


def depth_by_range(results: Sequence[DepthResult], edges_mm: tuple[float, ...] = DEPTH_RANGES_MM) -> list[dict[str, Any]]:
    """Depth error per ground-truth depth range (the map's deepest cell), the paper's per-range analysis."""
    true = pooled(r.true_max_mm for r in results)
    parts = _depth_parts(results)
    rows = []
    for lo, hi in itertools.pairwise(edges_mm):
        inside = (true >= lo) & (true < hi)
        row: dict[str, Any] = {"range_mm": f"{lo:g}-{hi:g}", "windows": int(inside.sum())}
        for part, errors in parts.items():
            row[f"{part}_mm"], row[f"{part}_std_mm"] = mean_std(errors[inside])
        rows.append(row)
    return rows


# -- forces ------------------------------------------------------------------------------------


def _windows(results: Sequence[ForceResult], probing_only: bool) -> list[npt.NDArray[np.bool_]] | None:
    """The windows to pool per recording: those in the probing phases, or all (None)."""
    return [r.probing for r in results] if probing_only else None


def force_errors(results: Sequence[ForceResult], probing_only: bool = True) -> tuple[F64, F64, F64]:
    """(predicted - measured (W, 3) N, measured (W, 3) N, contact position error (W, 2) px) pooled."""
    mask = _windows(results, probing_only)
    predicted = pooled((r.predicted_n for r in results), mask).reshape(-1, 3)
    measured = pooled((r.measured_n for r in results), mask).reshape(-1, 3)
    position = pooled((r.contact_error_px for r in results), mask).reshape(-1, 2)
    return predicted - measured, measured, position


def table3(results: Sequence[ForceResult], probing_only: bool = True) -> list[dict[str, Any]]:
    """Force MAE (N) per axis and total (norm of the error vector), contact position error (px)."""
    error, _, position = force_errors(results, probing_only)
    position = position[np.isfinite(position).all(1)] if len(position) else position.reshape(0, 2)
    rows = []
    for i, axis in enumerate("xyz"):
        f_mean, f_std = mean_std(np.abs(error[:, i]))
        p_mean, p_std = mean_std(np.abs(position[:, i])) if i < 2 else (None, None)
        rows.append({"axis": axis, "force_mae_n": f_mean, "force_std_n": f_std,
                     "position_mae_px": p_mean, "position_std_px": p_std})
    f_mean, f_std = mean_std(np.linalg.norm(error, axis=1))
    p_mean, p_std = mean_std(np.linalg.norm(position, axis=1))
    rows.append({"axis": "total", "force_mae_n": f_mean, "force_std_n": f_std,
                 "position_mae_px": p_mean, "position_std_px": p_std})
    return rows


def force_by_indenter(results: Sequence[ForceResult], probing_only: bool = True) -> list[dict[str, Any]]:
    """Force MAE (N) per axis and contact position error (px) per indenter, in the order they first appear."""
    rows = []
    for name in dict.fromkeys(r.indenter for r in results):
        mine = [r for r in results if r.indenter == name]
        by_axis = {row["axis"]: row for row in table3(mine, probing_only)}
        rows.append({"indenter": name or "unknown", "recordings": len(mine),
                     **{f"force_{a}_mae_n": by_axis[a]["force_mae_n"] for a in ("x", "y", "z", "total")},
                     "position_total_mae_px": by_axis["total"]["position_mae_px"]})
    return rows


def force_by_range(results: Sequence[ForceResult], ranges_n: dict[str, tuple[float, ...]] = FORCE_RANGES_N,
                   probing_only: bool = True) -> list[dict[str, Any]]:
    """Absolute force error per axis and per measured-force range (|F| on that axis), the paper's Fig. 3."""
    error, measured, _ = force_errors(results, probing_only)
    rows = []
    for i, axis in enumerate("xyz"):
        edges = ranges_n[axis]
        magnitude = np.abs(measured[:, i])
        for lo, hi in itertools.pairwise(edges):
            inside = (magnitude >= lo) & (magnitude < hi)
            m, s = mean_std(np.abs(error[inside, i]))
            bias, _ = mean_std(error[inside, i] * -np.sign(measured[inside, i]))
            rows.append({"axis": axis, "range_n": f"{lo:g}-{hi:g}", "windows": int(inside.sum()),
                         "mae_n": m, "std_n": s, "under_prediction_n": bias})
    return rows


def dense_errors(results: Sequence[ForceResult], probing_only: bool = True) -> dict[str, Any]:
    """Beyond the paper (virtual rig): per-marker force MAE against the sim's field, and the sim's net force
    against the F/T sensor (how much of the error is the measurement's)."""
    mask = _windows(results, probing_only)
    marker = pooled((r.marker_mae_n for r in results), mask).reshape(-1, 3)
    truth = pooled((r.truth_n for r in results), mask).reshape(-1, 3)
    predicted = pooled((r.predicted_n for r in results), mask).reshape(-1, 3)
    measured = pooled((r.measured_n for r in results), mask).reshape(-1, 3)
    out: dict[str, Any] = {}
    for i, axis in enumerate("xyz"):
        out[f"marker_{axis}_mae_n"], out[f"marker_{axis}_std_n"] = mean_std(marker[:, i])
        out[f"net_vs_sim_{axis}_mae_n"], _ = mean_std(np.abs(predicted[:, i] - truth[:, i]))
        out[f"sim_vs_ft_{axis}_mae_n"], _ = mean_std(np.abs(truth[:, i] - measured[:, i]))
    return out


def runtime_row(results: Sequence[ForceResult], stages: tuple[str, ...]) -> dict[str, Any]:
    """Median per-stage time (ms) over recordings, the per-window total and the achieved rate (Hz); the median
    and 95th percentile of every window's processing time (ms) pooled; the machine's cores and its 1-minute load
    average (median over recordings) while they were timed."""
    row: dict[str, Any] = {f"{s}_ms": float(np.median([r.stage_ms[s] for r in results])) for s in stages}
    total = float(np.median([r.total_ms for r in results]))
    row["total_ms"] = total
    row["rate_hz"] = 1000.0 / total if total > 0 else None
    windows = np.concatenate([r.window_ms for r in results]) if results else np.zeros(0)
    row["window_ms_median"] = float(np.median(windows)) if windows.size else None
    row["window_ms_p95"] = float(np.percentile(windows, 95)) if windows.size else None
    loads = [r.load_1min for r in results if np.isfinite(r.load_1min)]
    row["cores"] = max((r.cores for r in results), default=0)
    row["load_1min_median"] = float(np.median(loads)) if loads else None
    return row
