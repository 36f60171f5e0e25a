"""Charts of an evaluation, one function per chart, each returning a matplotlib Figure.

Figures are built on the Agg canvas directly (no pyplot state, safe to make many), every
axis is labelled with its unit, and ``out=PATH`` also writes a PNG. The decisions drawn on
the charts are pure functions beside them: :func:`pareto_front`, :func:`knee_index`,
:func:`recommend`, :func:`breakdown_point`, :func:`group_by_range`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.transforms import blended_transform_factory
from numpy.typing import ArrayLike

AXIS_COLORS = {"x": "#1f77b4", "y": "#2ca02c", "z": "#d62728"}
CYCLE = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf")
VIOLIN_MAX_SAMPLES = 20_000

Series = ArrayLike | Mapping[str, ArrayLike]
PathLike = str | os.PathLike[str]


# -- shared -------------------------------------------------------------------------------------


def axis_label(name: str, unit: str) -> str:
    """``"name (unit)"``, or ``name`` alone for a dimensionless quantity (``unit=""``)."""
    return f"{name} ({unit})" if unit else name


def new_figure(width_in: float, height_in: float) -> Figure:
    """A figure on its own Agg canvas, laid out with constrained layout."""
    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: Figure, path: PathLike, dpi: int = 110) -> Path:
    """Write ``fig`` as PNG through a temporary file and a rename; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fig.savefig(tmp, format="png", dpi=dpi)
    tmp.replace(path)
    return path


def _finish(fig: Figure, title: str, out: PathLike | None) -> Figure:
    if title:
        fig.suptitle(title)
    if out is not None:
        save_png(fig, out)
    return fig


def _named(series: Series, default: str = "") -> dict[str, np.ndarray]:
    if isinstance(series, Mapping):
        return {str(k): np.asarray(v, dtype=float) for k, v in series.items()}
    return {default: np.asarray(series, dtype=float)}


def _color(name: str, i: int) -> str:
    return AXIS_COLORS.get(name.lower(), CYCLE[i % len(CYCLE)])


# -- error per ground-truth range ---------------------------------------------------------------


def group_by_range(values_true: ArrayLike, errors: ArrayLike, edges: ArrayLike) -> list[np.ndarray]:
    """The finite ``errors`` whose ``values_true`` fall in each range ``[edges[i], edges[i+1])``.

    The last range includes its upper edge; values outside ``[edges[0], edges[-1]]`` are left out.
    """
    v = np.asarray(values_true, dtype=float).ravel()
    e = np.asarray(errors, dtype=float).ravel()
    edges_a = np.asarray(edges, dtype=float)
    if v.shape != e.shape:
        raise ValueError(f"{v.size} true values for {e.size} errors")
    if edges_a.size < 2 or np.any(np.diff(edges_a) <= 0):
        raise ValueError("range edges must be at least two increasing numbers")
    keep = np.isfinite(v) & np.isfinite(e) & (v >= edges_a[0]) & (v <= edges_a[-1])
    index = np.clip(np.searchsorted(edges_a, v[keep], side="right") - 1, 0, edges_a.size - 2)
    return [e[keep][index == i] for i in range(edges_a.size - 1)]


def error_by_range(
    values_true: Series,
    errors: Series,
    bins: Sequence[float] | Mapping[str, Sequence[float]],
    *,
    value_name: str,
    value_unit: str,
    error_name: str,
    error_unit: str,
    kind: Literal["box", "violin"] = "box",
    title: str = "",
    out: PathLike | None = None,
) -> Figure:
    """Distributions of an error per range of the ground-truth value, with the count per range.

    ``values_true`` and ``errors`` are arrays, or mappings from a panel name to arrays (one
    panel each, e.g. ``{"x": ..., "y": ..., "z": ...}`` for the paper's force error per force
    range); ``bins`` are range edges in the value's unit, shared or per panel. Boxes span the
    quartiles with the median line, the triangle is the mean, whiskers reach the 5th and 95th
    percentiles (no outliers drawn); a violin is a kernel density of at most
    ``VIOLIN_MAX_SAMPLES`` samples per range.
    """
    truth, err = _named(values_true), _named(errors)
    if truth.keys() != err.keys():
        raise ValueError(f"panels of the true values {list(truth)} differ from those of the errors {list(err)}")
    fig = new_figure(max(4.0, 3.6 * len(truth)), 3.6)
    axes = fig.subplots(1, len(truth), squeeze=False)[0]
    for i, (ax, name) in enumerate(zip(axes, truth)):
        edges = np.asarray(bins[name] if isinstance(bins, Mapping) else bins, dtype=float)
        groups = group_by_range(truth[name], err[name], edges)
        filled = [j for j, g in enumerate(groups) if g.size]
        color = _color(name, i)
        if filled and kind == "violin":
            rng = np.random.default_rng(0)
            data = [
                groups[j] if groups[j].size <= VIOLIN_MAX_SAMPLES else rng.choice(groups[j], VIOLIN_MAX_SAMPLES, replace=False)
                for j in filled
            ]
            parts = ax.violinplot(data, positions=filled, widths=0.7, showmedians=True, showextrema=False)
            for body in parts["bodies"]:
                body.set_facecolor(color)
                body.set_alpha(0.45)
            parts["cmedians"].set_color("#1d2430")
        elif filled:
            ax.boxplot(
                [groups[j] for j in filled],
                positions=filled,
                widths=0.6,
                whis=(5, 95),
                showfliers=False,
                showmeans=True,
                patch_artist=True,
                boxprops={"facecolor": color, "alpha": 0.45},
                medianprops={"color": "#1d2430"},
                meanprops={"marker": "^", "markerfacecolor": "white", "markeredgecolor": "#1d2430", "markersize": 5},
            )
        ax.set_xticks(range(len(groups)))
        ax.set_xticklabels([f"{lo:g}\u2013{hi:g}\nn={g.size}" for lo, hi, g in zip(edges[:-1], edges[1:], groups)], fontsize=8)
        ax.set_xlim(-0.6, len(groups) - 0.4)
        ax.set_xlabel(axis_label(f"{value_name} {name}".strip(), value_unit))
        ax.set_ylabel(axis_label(f"{error_name} {name}".strip(), error_unit))
        if name:
            ax.set_title(name)
        if any(np.any(g < 0) for g in groups):
            ax.axhline(0.0, color="#888888", lw=0.8, zorder=0)
        ax.grid(axis="y", alpha=0.3)
    if kind == "box":
        axes[0].legend(
            handles=[
                Patch(facecolor="#bbbbbb", label="25-75 %"),
                Line2D([], [], color="#1d2430", label="median"),
                Line2D([], [], ls="", marker="^", markerfacecolor="white", markeredgecolor="#1d2430", label="mean"),
                Line2D([], [], color="black", lw=0.8, label="5-95 %"),
            ],
            fontsize=7,
            loc="upper left",
        )
    return _finish(fig, title, out)


# -- accuracy against latency -------------------------------------------------------------------


class Candidate(NamedTuple):
    """A model or setting: its ``label``, ``latency_ms`` per window and ``error`` (any unit, lower is better)."""

    label: str
    latency_ms: float
    error: float


def pareto_front(latency: ArrayLike, error: ArrayLike) -> np.ndarray:
    """Indices of the points no other point beats on both latency and error, by increasing latency.

    Along the front latency rises and error falls strictly; non-finite points are never on it.
    """
    lat = np.asarray(latency, dtype=float)
    err = np.asarray(error, dtype=float)
    front: list[int] = []
    best = np.inf
    for i in np.lexsort((err, lat)):
        if np.isfinite(lat[i]) and np.isfinite(err[i]) and err[i] < best:
            front.append(int(i))
            best = err[i]
    return np.asarray(front, dtype=int)


def knee_index(latency: ArrayLike, error: ArrayLike, log_latency: bool = False) -> int | None:
    """Index of the knee of the Pareto front: the front point farthest below the chord from its
    fastest to its most accurate end, both axes scaled to [0, 1] (latency on a log scale if asked).

    None when the front has fewer than three points or none lies below the chord.
    """
    front = pareto_front(latency, error)
    if front.size < 3:
        return None
    x = np.asarray(latency, dtype=float)[front]
    if log_latency:
        x = np.log10(x)
    y = np.asarray(error, dtype=float)[front]
    xn = (x - x[0]) / (x[-1] - x[0])
    yn = (y - y[-1]) / (y[0] - y[-1])
    below = 1.0 - xn - yn
    k = int(np.argmax(below))
    return int(front[k]) if below[k] > 1e-9 else None


def recommend(points: Sequence[Candidate | tuple[str, float, float]], tolerance: float = 0.05) -> Candidate:
    """The fastest point whose error is within ``tolerance`` (relative) of the best error.

    Ties on latency go to the lower error; points with a non-finite latency or error are ignored.
    """
    candidates = [Candidate(*p) for p in points]
    valid = [c for c in candidates if np.isfinite(c.latency_ms) and np.isfinite(c.error)]
    if not valid:
        raise ValueError("no point with a finite latency and error")
    best = min(c.error for c in valid)
    limit = best + tolerance * abs(best)
    return min((c for c in valid if c.error <= limit), key=lambda c: (c.latency_ms, c.error))


def pareto(
    points: Sequence[Candidate | tuple[str, float, float]],
    *,
    error_name: str,
    error_unit: str,
    tolerance: float = 0.05,
    budget_ms: float | None = 10.0,
    log_latency: bool = False,
    title: str = "",
    out: PathLike | None = None,
) -> Figure:
    """Error against latency per window: every point labelled, the Pareto front as a staircase,
    its knee ringed, the band within ``tolerance`` of the best error shaded and the
    :func:`recommend` choice starred; a dashed line at the real-time ``budget_ms``."""
    candidates = [Candidate(*p) for p in points]
    lat = np.array([c.latency_ms for c in candidates], dtype=float)
    err = np.array([c.error for c in candidates], dtype=float)
    front = pareto_front(lat, err)
    fig = new_figure(6.4, 4.4)
    ax = fig.subplots()
    on_front = np.zeros(len(candidates), dtype=bool)
    on_front[front] = True
    ax.scatter(lat[~on_front], err[~on_front], color="#9aa3ad", s=28, label="dominated", zorder=2)
    ax.scatter(lat[on_front], err[on_front], color=CYCLE[0], s=36, label="Pareto front", zorder=3)
    if front.size:
        ax.step(lat[front], err[front], where="post", color=CYCLE[0], lw=1.2, zorder=2)
    labels_at: dict[tuple[float, float], list[str]] = {}
    for c in candidates:
        if np.isfinite(c.latency_ms) and np.isfinite(c.error):
            labels_at.setdefault((c.latency_ms, c.error), []).append(c.label)
    for (latency_ms, error), labels in labels_at.items():  # one setting reached by two knobs: one label
        ax.annotate(" = ".join(labels), (latency_ms, error), xytext=(4, 4), textcoords="offset points", fontsize=7)
    if front.size:
        best = err[front[-1]]
        ax.axhspan(best, best + tolerance * abs(best), color="#2ca02c", alpha=0.12, lw=0, label=f"within {tolerance:.0%} of best")
        choice = recommend(candidates, tolerance)
        ax.scatter(
            [choice.latency_ms], [choice.error], marker="*", s=220, color="#2ca02c", edgecolor="black",
            zorder=4, label=f"recommended: {choice.label}",
        )  # fmt: skip
    knee = knee_index(lat, err, log_latency=log_latency)
    if knee is not None:
        ax.scatter(
            [lat[knee]], [err[knee]], s=260, facecolor="none", edgecolor="#ff7f0e", lw=2,
            zorder=4, label=f"knee: {candidates[knee].label}",
        )  # fmt: skip
    if budget_ms is not None:
        ax.axvline(budget_ms, color="#d62728", ls="--", lw=1, label=f"real-time budget {budget_ms:g} ms")
    if log_latency:
        ax.set_xscale("log")
    ax.set_xlabel("latency per window (ms)")
    ax.set_ylabel(axis_label(error_name, error_unit))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    return _finish(fig, title, out)


# -- breakdown under stress ---------------------------------------------------------------------


def breakdown_point(
    x: ArrayLike, error: ArrayLike, factor: float = 2.0, baseline: float | None = None, log_x: bool = False
) -> float | None:
    """The stress ``x`` at which ``error`` first reaches ``factor`` times its baseline, or None.

    Samples are taken in order of increasing ``x``; the baseline is the error at the lowest
    stress unless given. Between the last sample below the threshold and the first at or
    above it, ``x`` is interpolated linearly (in ``log10(x)`` with ``log_x``). A non-finite
    error counts as broken (the method gave no answer), at that sample's ``x``.
    """
    xs = np.asarray(x, dtype=float)
    es = np.asarray(error, dtype=float)
    if xs.shape != es.shape or xs.ndim != 1 or xs.size == 0:
        raise ValueError("x and error must be 1-D arrays of the same, non-zero length")
    order = np.argsort(xs, kind="stable")
    xs, es = xs[order], es[order]
    base = es[0] if baseline is None else float(baseline)
    if not np.isfinite(base) or base <= 0:
        raise ValueError(f"the baseline error must be positive and finite, not {base}")
    threshold = factor * base
    broken = ~np.isfinite(es) | (es >= threshold)
    if not broken.any():
        return None
    i = int(np.argmax(broken))
    if i == 0 or not np.isfinite(es[i]):
        return float(xs[i])
    x0, x1 = (np.log10(xs[i - 1]), np.log10(xs[i])) if log_x else (xs[i - 1], xs[i])
    xb = x0 + (threshold - es[i - 1]) / (es[i] - es[i - 1]) * (x1 - x0)
    return float(10.0**xb if log_x else xb)


def breakdown_point_below(
    x: ArrayLike, error: ArrayLike, reference: float, factor: float = 2.0, baseline: float | None = None,
    log_x: bool = False,
) -> float | None:
    """The stress ``x`` below ``reference`` at which ``error`` first reaches ``factor`` times its baseline,
    read from ``reference`` downwards (the error at ``reference`` unless ``baseline``), or None: the
    mirror of :func:`breakdown_point` for an axis that can be pushed both ways (``log_x``: ``x`` > 0)."""
    xs, es = np.asarray(x, dtype=float), np.asarray(error, dtype=float)
    below = xs <= reference
    if not below.any():
        raise ValueError(f"no sample at or below the reference {reference}")
    mirrored = 1.0 / xs[below] if log_x else -xs[below]
    base = es[below][np.argmax(xs[below])] if baseline is None else baseline
    point = breakdown_point(mirrored, es[below], factor, base, log_x)
    return None if point is None else (1.0 / point if log_x else -point)


def breakdown_points(
    x: ArrayLike, error: ArrayLike, reference: float | None = None, factor: float = 2.0,
    baseline: float | None = None, log_x: bool = False,
) -> tuple[float | None, float | None]:
    """The stress at which ``error`` first reaches ``factor`` times its baseline, read outwards from the
    least-stressed sample: ``(below, above)``. That sample is the one nearest ``reference`` on an axis pushed
    both ways (:func:`breakdown_point_below` under it, :func:`breakdown_point` over it), else the lowest ``x``
    (``below`` None); the baseline is its error unless given. (None, None) when the baseline is not a
    positive, finite error (its scene failed: no breakdown can be read)."""
    xs, es = np.asarray(x, dtype=float), np.asarray(error, dtype=float)
    order = np.argsort(xs, kind="stable")
    xs, es = xs[order], es[order]
    start = 0 if reference is None else int(np.argmin(np.abs(xs - reference)))
    base = float(es[start] if baseline is None else baseline)
    if not (np.isfinite(base) and base > 0):
        return None, None
    above = breakdown_point(xs[start:], es[start:], factor, base, log_x)
    below = (breakdown_point_below(xs[:start + 1], es[:start + 1], float(xs[start]), factor, base, log_x)
             if start > 0 else None)
    return below, above


def breakdown(
    x: Series,
    error: Series,
    *,
    x_name: str,
    x_unit: str,
    error_name: str,
    error_unit: str,
    factor: float = 2.0,
    baseline: float | Mapping[str, float] | None = None,
    log_x: bool = False,
    reference: float | None = None,
    title: str = "",
    out: PathLike | None = None,
) -> Figure:
    """Error against a stress (event noise rate, force, ...) per method, each method's
    breakdown point (:func:`breakdown_point`) marked on its threshold line.

    ``error`` is an array or a mapping from method name to arrays; ``x`` is shared or given
    per method the same way. Samples without a finite error are marked along the top edge.
    ``reference``: the unstressed ``x`` of an axis pushed both ways (its error the baseline unless
    given); the breakdown is then read from it outwards, below (:func:`breakdown_point_below`) and above.
    """
    errors = _named(error)
    xs = _named(x) if isinstance(x, Mapping) else dict.fromkeys(errors, np.asarray(x, dtype=float))
    if xs.keys() != errors.keys():
        raise ValueError(f"methods of x {list(xs)} differ from those of the errors {list(errors)}")
    fig = new_figure(6.4, 4.2)
    ax = fig.subplots()
    top = blended_transform_factory(ax.transData, ax.transAxes)
    for i, (name, e) in enumerate(errors.items()):
        color = CYCLE[i % len(CYCLE)]
        xm = xs[name]
        order = np.argsort(xm, kind="stable")
        base = baseline.get(name) if isinstance(baseline, Mapping) else baseline
        start = 0 if reference is None else int(np.argmin(np.abs(xm[order] - reference)))
        base_error = float(e[order][start] if base is None else base)
        measurable = bool(np.isfinite(base_error) and base_error > 0)  # no baseline (its scene failed): no breakdown
        low, point = breakdown_points(xm, e, reference, factor, base_error, log_x)
        threshold = factor * base_error
        where = (
            f"breaks at {point:.3g} {x_unit}".rstrip() if point is not None
            else f"no breakdown up to {np.max(xm):.3g} {x_unit}" if measurable else "no baseline error"
        )
        if start > 0 and measurable:
            sides = [f"{side} {v:.3g}" for side, v in (("below at", low), ("above at", point)) if v is not None]
            where = (f"breaks {', '.join(sides)} {x_unit}".rstrip() if sides
                     else f"no breakdown within {np.min(xm):.3g}-{np.max(xm):.3g} {x_unit}".rstrip())
        ax.plot(xm[order], e[order], marker="o", ms=4, color=color, label=f"{name}: {where}".lstrip(": "))
        if measurable:
            ax.axhline(threshold, color=color, ls=":", lw=1, alpha=0.8)
        failed = ~np.isfinite(e)
        if failed.any():
            ax.plot(xm[failed], np.full(failed.sum(), 0.97), "x", color=color, ms=7, transform=top, clip_on=False)
        for found in (low, point):
            if found is None:
                continue
            ax.axvline(found, color=color, ls="--", lw=1)
            if found not in xm[failed]:
                ax.plot([found], [threshold], marker="D", ms=8, color=color, markeredgecolor="black", zorder=4)
    if reference is not None:
        ax.axvline(reference, color="#555555", ls="-", lw=0.8, alpha=0.6, label=f"reference {reference:g} {x_unit}".rstrip())
    if log_x:
        ax.set_xscale("log")
    ax.set_xlabel(axis_label(x_name, x_unit))
    ax.set_ylabel(axis_label(error_name, error_unit))
    ax.grid(alpha=0.3)
    handles, _ = ax.get_legend_handles_labels()
    if any((~np.isfinite(e)).any() for e in errors.values()):
        handles.append(Line2D([], [], ls="", marker="x", color="#555555", label="no finite error (top edge)"))
    ax.legend(handles=handles, fontsize=8, title=f"dotted: {factor:g} x baseline error", title_fontsize=7)
    return _finish(fig, title, out)


# -- a recording over time ----------------------------------------------------------------------


def time_series(
    t_s: ArrayLike,
    measured: ArrayLike,
    predicted: ArrayLike,
    *,
    t_predicted_s: ArrayLike | None = None,
    axis_names: Sequence[str] = ("x", "y", "z"),
    quantity: str = "F",
    unit: str = "N",
    phases: Sequence[tuple[str, float, float]] = (),
    title: str = "",
    out: PathLike | None = None,
) -> Figure:
    """Measured and predicted values over time, one panel per axis, with the mean absolute
    error of the prediction against the measurement interpolated at the prediction's times.

    ``measured`` is (n,) or (n, k) at ``t_s``; ``predicted`` (m,) or (m, k) at
    ``t_predicted_s`` (default ``t_s``), in seconds on one clock. ``phases`` are
    ``(name, start_s, end_s)`` spans shaded behind the curves.
    """
    t_m = np.asarray(t_s, dtype=float)
    t_p = t_m if t_predicted_s is None else np.asarray(t_predicted_s, dtype=float)
    meas = np.asarray(measured, dtype=float).reshape(t_m.size, -1)
    pred = np.asarray(predicted, dtype=float).reshape(t_p.size, -1)
    if meas.shape[1] != pred.shape[1]:
        raise ValueError(f"{meas.shape[1]} measured axes for {pred.shape[1]} predicted")
    k = meas.shape[1]
    names = list(axis_names)[:k] if len(axis_names) >= k else [str(j) for j in range(k)]
    fig = new_figure(9.0, 1.0 + 2.0 * k)
    axes = fig.subplots(k, 1, sharex=True, squeeze=False)[:, 0]
    inside = (t_p >= t_m.min()) & (t_p <= t_m.max()) if t_m.size else np.zeros(t_p.size, bool)
    for j, (ax, name) in enumerate(zip(axes, names)):
        for p, (phase, start, end) in enumerate(phases):
            ax.axvspan(start, end, color="#eef1f5" if p % 2 else "#e2e8f0", lw=0, zorder=0)
            if j == 0:
                ax.annotate(
                    phase, ((start + end) / 2, 1.0), xycoords=("data", "axes fraction"), ha="center", va="bottom", fontsize=7
                )
        ax.plot(t_m, meas[:, j], color="#1d2430", lw=1.0, label="measured")
        ax.plot(t_p, pred[:, j], color=_color(name, j), lw=1.2, label="predicted")
        err = np.abs(pred[inside, j] - np.interp(t_p[inside], t_m, meas[:, j]))
        err = err[np.isfinite(err)]
        if err.size:
            ax.text(0.01, 0.95, f"MAE {err.mean():.3g} {unit}", transform=ax.transAxes, va="top", fontsize=8)
        ax.set_ylabel(axis_label(f"{quantity}{name}", unit))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right", ncol=2)  # each panel's own colours
    axes[-1].set_xlabel("time (s)")
    return _finish(fig, title, out)


def held_force(
    t_s: ArrayLike,
    ft_n: ArrayLike,
    target_n: ArrayLike,
    *,
    t_estimate_s: ArrayLike | None = None,
    estimate_n: ArrayLike | None = None,
    phases: Sequence[tuple[str, float, float]] = (),
    title: str = "",
    out: PathLike | None = None,
) -> Figure:
    """A force loop's run: the F/T's normal force (N, the reference) and the target it held at ``t_s`` (s; the
    target nan where nothing was held), with the pipeline's estimate at ``t_estimate_s`` if given; ``phases`` as
    ``(name, start_s, end_s)`` spans shaded behind the curves."""
    fig = new_figure(9.0, 3.2)
    ax = fig.subplots()
    for p, (phase, start, end) in enumerate(phases):
        ax.axvspan(start, end, color="#eef1f5" if p % 2 else "#e2e8f0", lw=0, zorder=0)
        ax.annotate(phase, ((start + end) / 2, 1.0), xycoords=("data", "axes fraction"), ha="center", va="bottom",
                    fontsize=7)
    ax.plot(np.asarray(t_s, float), np.asarray(ft_n, float), color="#1d2430", lw=1.0, label="F/T (reference)")
    ax.plot(np.asarray(t_s, float), np.asarray(target_n, float), color="#c2410c", lw=1.4, ls="--", label="target")
    if t_estimate_s is not None and estimate_n is not None:
        ax.plot(np.asarray(t_estimate_s, float), np.asarray(estimate_n, float), color=_color("z", 2), lw=1.1,
                label="event estimate")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(axis_label("|Fz|", "N"))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right", ncol=3)
    return _finish(fig, title, out)


# -- runtime --------------------------------------------------------------------------------------


def runtime_bars(
    stage_ms: Mapping[str, float | ArrayLike],
    *,
    budget_ms: float | None = 10.0,
    title: str = "",
    out: PathLike | None = None,
) -> Figure:
    """Latency per pipeline stage: the mean as a bar, whiskers to the 5th and 95th percentile
    when a stage has several samples, and the real-time budget as a dashed line."""
    names = list(stage_ms)
    samples = [np.asarray(stage_ms[n], dtype=float).ravel() for n in names]
    samples = [s[np.isfinite(s)] for s in samples]
    means = np.array([s.mean() if s.size else np.nan for s in samples])
    low = np.array([means[i] - np.percentile(s, 5) if s.size > 1 else 0.0 for i, s in enumerate(samples)])
    high = np.array([np.percentile(s, 95) - means[i] if s.size > 1 else 0.0 for i, s in enumerate(samples)])
    fig = new_figure(6.4, 1.2 + 0.45 * max(1, len(names)))
    ax = fig.subplots()
    y = np.arange(len(names))
    colors = [("#d62728" if budget_ms is not None and m > budget_ms else CYCLE[0]) for m in means]
    ax.barh(y, np.nan_to_num(means), xerr=np.vstack([low, high]), color=colors, alpha=0.8, capsize=3)
    for yi, m, h in zip(y, means, high):
        if np.isfinite(m):
            ax.annotate(f"{m:.3g} ms", (m + h, yi), xytext=(5, 0), textcoords="offset points", va="center", fontsize=8)
    if budget_ms is not None:
        ax.axvline(budget_ms, color="#d62728", ls="--", lw=1.2)
        ax.annotate(
            f"budget {budget_ms:g} ms ({1000 / budget_ms:.0f} Hz)", (budget_ms, 1.0), xycoords=("data", "axes fraction"),
            xytext=(0, 3), textcoords="offset points", ha="center", va="bottom", fontsize=8, color="#d62728",
        )  # fmt: skip
    ax.margins(x=0.18)
    ax.set_yticks(y, names)
    ax.invert_yaxis()
    ax.set_xlabel("latency per window (ms)")
    ax.set_ylabel("stage")
    ax.grid(axis="x", alpha=0.3)
    return _finish(fig, title, out)
