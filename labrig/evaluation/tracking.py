"""Marker tracking on one recording: the paper's lost tracks (Table I) and, on the virtual rig, the true error.

The paper's metric (section "Marker tracking evaluation", after Evetac): probing sequences
start and end with the gel at rest, so a marker whose tracked position ends more than
15 px (about one marker diameter) from where it started is a lost track. The virtual rig
also records every marker's true image position (``/truth/markers``, 1 kHz), so there the
tracker's error is measured directly at each window's end, and a track counts as lost by
the truth when that error exceeds 15 px at any time (it may have recovered by the end,
which the start-end proxy cannot see).

Missing markers (never printed) are skipped by every tracker: the calibration says which
(``observed``, :attr:`labrig.pipeline.run_setup.PipelineSetup.observed`; with ``rest="rig"``
the rig's printed markers, as any calibration would find them). The sim's truth has NaN rows
for them, so the true errors leave them out and count them (``markers_missing``); lost tracks
are counted over the observed markers only (an unobserved marker's position is an estimate
from its neighbours, not a track).

:func:`track_recording` is a pure task for :func:`labrig.executor.run_tasks`;
:func:`table_lost_tracks` turns its results into Table I rows (mean and std over recordings).

Settings map onto the trackers as follows. ``patch_scale`` is the patch side in marker
diameters (the paper's 1x-5x); for the circle-fit baseline it sets the annulus' outer
radius to the same half side (``outer_radius = patch_scale`` marker radii); Evetac's
published tracker has a fixed ring band and ignores it (:data:`FIXED_BAND_TRACKERS`).
``refine`` switches the grid-aware refinement: lambda 0.2 or 0 for the paper's tracker, the
neighbour springs (gain 0.1 or 0) for the circle fit, Evetac's springs on or off.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.config import DEFAULT_CALIBRATION_DIR, load_rig
from labrig.errors import LabrigError
from labrig.pipeline.evetac import EvetacParams, EvetacTracker
from labrig.pipeline.marker_stage import MarkerStage, MarkerTracker
from labrig.pipeline.run_setup import rig_from_recording, setup_for_recording
from labrig.pipeline.tracking import (
    CircleFitParams,
    CircleFitTracker,
    Tracker,
    TrackerParams,
    marker_diameter_px,
)
from labrig.pipeline.windows import recording_windows
from labrig.recording import Recording
from labrig.sim.imperfections import printed_markers
from labrig.sim.truth_config import sim_config, true_camera

Array = npt.NDArray[np.float64]

LOST_PX = 15.0  # the paper's threshold: start-end drift (px) above which a track is lost
PAPER_LAMBDA = 0.2  # the paper's refinement weight
CIRCLE_FIT_SPRING = 0.1  # the circle-fit baseline's neighbour-spring gain when refined
TRACKERS = ("paper", "paper-published", "circle-fit", "evetac")
FIXED_BAND_TRACKERS = frozenset({"evetac"})  # trackers that ignore ``patch_scale``
REST_SOURCES = ("calibration", "rig")
TABLE_PATCH_SCALES = (1.0, 2.0, 3.0, 4.0, 5.0)


@dataclass(frozen=True)
class TrackingTask:
    """One recording, one tracker setting. Windows: ``window_us`` long (default 10 ms) or ``window_events`` each.

    ``tracker``: "paper" (the bundled tracker with its event gates), "paper-published" (no gate,
    no two-polarity test, no polarity guard: the tracker as the paper describes it), "circle-fit" (a circle-fit
    baseline, formerly "evetac") or "evetac" (Evetac's published tracker, :mod:`labrig.pipeline.evetac`).
    ``rest``: where the markers' rest pixels come from: "calibration" (the extrinsics the
    recording names, else ``calibration_dir``'s, as ``labrig run`` resolves them; the rig's
    camera when there are none) or "rig" (the rig's own camera model).
    """

    recording: str
    tracker: str = "paper"
    patch_scale: float = 3.0
    refine: bool = True
    window_us: int | None = 10_000
    window_events: int | None = None
    rest: str = "calibration"
    calibration_dir: str | None = DEFAULT_CALIBRATION_DIR
    lost_px: float = LOST_PX


@dataclass(frozen=True)
class TruthErrors:
    """A track (W windows, M markers) against the sim's marker truth at the window ends; None without truth."""

    has_truth: bool
    error_median_px: float | None  # over every marker and window
    error_p95_px: float | None
    error_max_px: float | None
    error_max_per_marker_px: Array | None  # (M,)
    lost_by_truth: int | None  # markers ever more than ``lost_px`` off
    t1_us: npt.NDArray[np.int64] | None  # (W,) window ends, host us
    window_error_p95_px: Array | None  # (W,)
    truth_end_offset_max_px: float | None  # how far the true markers end from where they started
    markers_missing: int | None = None  # markers without truth (never printed: NaN rows), left out of the above

    @classmethod
    def absent(cls) -> TruthErrors:
        return cls(False, None, None, None, None, None, None, None, None, None)


@dataclass(frozen=True)
class TrackingResult:
    """One tracker setting on one recording (W windows, M markers): lost tracks, drift, timing and,
    on the virtual rig, the true error (the :class:`TruthErrors` fields, None on hardware)."""

    recording: str
    tracker: str
    patch_scale: float
    refine: bool
    window_us: int | None
    window_events: int | None
    rest_source: str  # where the markers' rest pixels came from
    marker_diameter_px: float
    n_windows: int
    n_markers: int
    markers_unobserved: int  # markers the tracker skipped (missing in the calibration)
    drift_px: Array  # (M,) |end - start| of each track, px
    lost_tracks: int  # observed tracks with drift above ``lost_px``
    drift_max_px: float
    track_ms_median: float  # the tracker's update per window, ms
    track_ms_p95: float
    has_truth: bool
    error_median_px: float | None
    error_p95_px: float | None
    error_max_px: float | None
    error_max_per_marker_px: Array | None
    lost_by_truth: int | None
    t1_us: npt.NDArray[np.int64] | None
    window_error_p95_px: Array | None
    truth_end_offset_max_px: float | None
    markers_missing: int | None


def tracker_for(task: TrackingTask, rest_px: Array, diameter_px: float,
                observed: npt.ArrayLike | None = None) -> MarkerTracker:
    """The tracker ``task`` asks for, starting at ``rest_px`` (M, 2) with markers ``diameter_px`` wide;
    ``observed`` (M,): False for markers to skip (missing), None: all tracked."""
    if task.patch_scale <= 0:
        raise LabrigError(f"patch_scale must be positive (a multiple of the marker diameter), not {task.patch_scale}")
    if task.tracker == "evetac":
        return EvetacTracker(rest_px, EvetacParams(marker_diameter_px=diameter_px, springs=bool(task.refine)), observed)
    if task.tracker == "circle-fit":
        spring = CIRCLE_FIT_SPRING if task.refine else 0.0
        params = CircleFitParams(marker_diameter_px=diameter_px, outer_radius=float(task.patch_scale), spring=spring)
        return CircleFitTracker(rest_px, params, observed)
    lam = PAPER_LAMBDA if task.refine else 0.0
    base = TrackerParams(marker_diameter_px=diameter_px, patch_scale=float(task.patch_scale), refine_lambda=lam)
    if task.tracker == "paper":
        return Tracker(rest_px, base, observed)
    if task.tracker == "paper-published":
        published = replace(base, gate_diameters=None, min_each_polarity=0, polarity_guard=None, lopsided_ratio=None,
                            lag_noise_px=None)
        return Tracker(rest_px, published, observed)
    raise LabrigError(f"tracker must be one of {', '.join(TRACKERS)}, not {task.tracker!r}")


def track_recording(task: TrackingTask | Mapping[str, Any]) -> TrackingResult:
    """Track ``task.recording`` window by window; lost tracks, drift and (virtual rig) true errors."""
    task = task if isinstance(task, TrackingTask) else TrackingTask(**task)
    with Recording(task.recording) as rec:
        rig, camera, rest_px, rest_source, observed = rest_pixels(rec, task.rest, task.calibration_dir)
        diameter = marker_diameter_px(rig, camera)
        markers = MarkerStage(tracker_for(task, rest_px, diameter, observed))  # the rest held: trackers compared alike
        ends, positions, seconds = [], [], []
        for t0, t1, events in recording_windows(rec, window_us=task.window_us, window_events=task.window_events):
            tic = time.perf_counter()
            p, _ = markers.update(events, t0, t1)
            seconds.append(time.perf_counter() - tic)
            ends.append(t1)
            positions.append(p)
        truth = _truth_markers(rec)
    if not positions:
        raise LabrigError(f"{task.recording}: no tracking windows (the recording has no events?)")
    track = np.asarray(positions)  # (W, M, 2)
    drift = np.linalg.norm(track[-1] - rest_px, axis=1)
    ms = np.asarray(seconds) * 1e3
    truth_fields = truth_errors(track, np.asarray(ends, np.float64), truth, task.lost_px)
    return TrackingResult(
        recording=str(task.recording), tracker=task.tracker, patch_scale=float(task.patch_scale), refine=bool(task.refine),
        window_us=task.window_us, window_events=task.window_events, rest_source=rest_source,
        marker_diameter_px=float(diameter), n_windows=len(track), n_markers=track.shape[1], drift_px=drift,
        markers_unobserved=int((~observed).sum()), lost_tracks=int((drift[observed] > task.lost_px).sum()),
        drift_max_px=float(drift[observed].max()),
        track_ms_median=float(np.median(ms)), track_ms_p95=float(np.percentile(ms, 95)),
        **{f.name: getattr(truth_fields, f.name) for f in fields(TruthErrors)})


track_recording.cache_version = "9"  # type: ignore[attr-defined]  # 9: the marker diameter through the rest's camera; 8: neighbours' moves; 7: lopsided gates follow neighbours, lag correction; 6: the paper tracker's polarity guard


def rest_pixels(rec: Any, rest: str, calibration_dir: str | None) -> tuple[Any, Any, Array, str, npt.NDArray[np.bool_]]:
    """(rig, camera, rest pixels (M, 2), where they came from, observed (M,)) for an open recording; see
    :class:`TrackingTask`.

    "calibration": the run's camera and rest pixels (:func:`labrig.pipeline.run_setup.setup_for_recording`)
    and its present markers; "rig": the virtual rig's true camera and lattice, and its printed markers
    (``[sim.markers]``: what a calibration of that rig would find missing)."""
    if rest == "calibration":
        setup = setup_for_recording(rec, calibration_dir=calibration_dir)
        return setup.rig, setup.camera, np.asarray(setup.rest_px, np.float64), setup.sources["camera"], setup.observed
    if rest == "rig":
        carried = rig_from_recording(rec)
        rig = carried or load_rig()
        printed = printed_markers(sim_config(rig).markers, rig.markers.rest_positions_mm(), rig.markers.diameter_mm).printed
        camera = true_camera(rig)
        return (rig, camera, camera.project(rig.markers.rest_positions_mm()),
                "rig camera (" + ("the recording's rig" if carried else str(rig.path)) + ")", np.asarray(printed, bool))
    raise LabrigError(f"rest must be one of {', '.join(REST_SOURCES)}, not {rest!r}")


def _truth_markers(rec: Any) -> tuple[Array, Array] | None:
    """(t_us (T,), position_px (T, M, 2)) of ``/truth/markers``, or None on a recording without it."""
    if "truth/markers" not in rec.streams or rec.rows("truth/markers") == 0:
        return None
    t = rec.column("truth/markers", "t_host_us").astype(np.float64)
    return t, rec.column("truth/markers", "position_px").astype(np.float64)


def truth_at(t_truth_us: Array, truth_px: Array, t_us: Array) -> Array:
    """True positions (W, M, 2) px at times ``t_us`` (W,), linear between the truth's samples (held at the ends)."""
    upper = np.clip(np.searchsorted(t_truth_us, t_us), 1, max(len(t_truth_us) - 1, 1))
    lower = upper - 1
    span = np.maximum(t_truth_us[upper] - t_truth_us[lower], 1e-9)
    w = np.clip((t_us - t_truth_us[lower]) / span, 0.0, 1.0)[:, None, None]
    return truth_px[lower] + w * (truth_px[upper] - truth_px[lower])


def truth_errors(track_px: Array, t1_us: Array, truth: tuple[Array, Array] | None, lost_px: float) -> TruthErrors:
    """The true errors of a track (W, M, 2) px at window ends ``t1_us`` (W,); :meth:`TruthErrors.absent` without truth."""
    if truth is None:
        return TruthErrors.absent()
    t_truth, truth_px = truth
    if truth_px.shape[1] != track_px.shape[1]:
        raise LabrigError(f"/truth/markers has {truth_px.shape[1]} markers, the tracker {track_px.shape[1]}")
    present = np.isfinite(truth_px).all(axis=(0, 2))  # (M,) markers with truth: a missing marker's rows are NaN
    if not present.any():
        raise LabrigError("/truth/markers has no marker with a finite position")
    error = np.linalg.norm(track_px[:, present] - truth_at(t_truth, truth_px[:, present], t1_us), axis=2)  # (W, M')
    per_marker = np.full(track_px.shape[1], np.nan)
    per_marker[present] = error.max(axis=0)
    return TruthErrors(
        has_truth=True, error_median_px=float(np.median(error)), error_p95_px=float(np.percentile(error, 95)),
        error_max_px=float(error.max()), error_max_per_marker_px=per_marker,
        lost_by_truth=int((per_marker[present] > lost_px).sum()), t1_us=t1_us.astype(np.int64),
        window_error_p95_px=np.percentile(error, 95, axis=1),
        truth_end_offset_max_px=float(np.linalg.norm(truth_px[-1, present] - truth_px[0, present], axis=1).max()),
        markers_missing=int((~present).sum()))


# -- Table I ------------------------------------------------------------------------------------------


def table_tasks(recordings: Iterable[str], *, patch_scales: Sequence[float] = TABLE_PATCH_SCALES,
                refine: Sequence[bool] = (True, False), **settings: Any) -> list[TrackingTask]:
    """Every (recording, refinement, patch scale) of Table I as tasks; ``settings`` are other TrackingTask fields."""
    known = {f.name for f in fields(TrackingTask)} - {"recording", "patch_scale", "refine"}
    unknown = set(settings) - known
    if unknown:
        raise LabrigError(f"unknown tracking settings {sorted(unknown)}; use {sorted(known)}")
    return [TrackingTask(str(path), patch_scale=float(scale), refine=r, **settings)
            for path in recordings for r in refine for scale in patch_scales]


def table_lost_tracks(results: Iterable[TrackingResult | None]) -> list[dict[str, Any]]:
    """Table I rows: per (tracker, window, refinement, patch scale), lost tracks per sequence over recordings.

    Row keys: ``tracker``, ``window_us``, ``window_events``, ``refine``, ``patch_scale``,
    ``recordings`` (count), ``lost_mean``, ``lost_std`` (population std over recordings, tracks);
    ``lost_by_truth_mean``, ``lost_by_truth_std``, ``error_p95_px_mean`` (mean of the
    recordings' p95 true error, px) over the recordings with truth (None if none has it);
    ``track_ms_median`` (median over recordings of the per-recording median, ms). Failed tasks
    (None) are skipped. Rows are sorted by tracker, window, refinement first, then patch scale.
    """
    groups: dict[tuple[Any, ...], list[TrackingResult]] = {}
    for r in results:
        if r is not None:
            key = (r.tracker, r.window_us, r.window_events, bool(r.refine), float(r.patch_scale))
            groups.setdefault(key, []).append(r)
    rows = []
    for key in sorted(groups, key=lambda k: (k[0], k[1] or 0, k[2] or 0, not k[3], k[4])):
        group = groups[key]
        lost = np.array([r.lost_tracks for r in group], np.float64)
        with_truth = [r for r in group if r.has_truth]
        by_truth = np.array([r.lost_by_truth for r in with_truth], np.float64)
        p95 = np.array([r.error_p95_px for r in with_truth], np.float64)
        rows.append({
            "tracker": key[0], "window_us": key[1], "window_events": key[2], "refine": key[3], "patch_scale": key[4],
            "recordings": len(group), "lost_mean": float(lost.mean()), "lost_std": float(lost.std()),
            "lost_by_truth_mean": float(by_truth.mean()) if with_truth else None,
            "lost_by_truth_std": float(by_truth.std()) if with_truth else None,
            "error_p95_px_mean": float(p95.mean()) if with_truth else None,
            "track_ms_median": float(np.median([r.track_ms_median for r in group])),
        })
    return rows
