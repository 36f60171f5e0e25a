"""Training inputs that carry the gel's state: the tracker's displacement field and a perturbed previous map.

**Displacement field.** The channels come from running the pipeline's own markers' stage
(:class:`labrig.pipeline.marker_stage.MarkerStage`: its tracker and the rest refinement, 10 ms
windows ending at each window's end, the recording's calibration) over
the whole recording once, cached under ``$LABRIG_CACHE/tracks`` (:mod:`labrig.cache`), not
from the virtual rig's ``/truth/markers``: a real recording has no true markers, and the
tracker's errors (lag in fast motion, drift that survives a shear, markers that slip) are
not Gaussian noise; the network must learn to read what it will be given. A window's field
is the tracked positions interpolated at the window's end, back-projected to the gel plane
and rasterised with the same :class:`~labrig.pipeline.depth_inputs.DisplacementRaster` the
depth source uses.

**Previous map.** The ground truth nearest the previous window's last event (one window
earlier; for a share of the windows up to 30 windows earlier), perturbed so that the network
does not trust it blindly and its own errors do not compound at run time
(:class:`PreviousAugment`): zeroed for a share of the windows (the start of a stream, the
rest gate), otherwise scaled, shifted by whole grid cells and given Gaussian noise. Fed only
the truth, a network learns to copy the channel and its errors compound in closed loop, so the
trainer also feeds it its own answers (:func:`self_feed`).

**Brightness change since rest.** The events' polarities integrated per grid cell
(:class:`~labrig.pipeline.brightness.BrightnessIntegrator`, weighted by the calibration's contrast
thresholds as a run weighs them), stepped over the whole recording in 10 ms windows from its start,
as a run steps it, and kept at every step
(:class:`BrightnessTrack`, cached under ``$LABRIG_CACHE/brightness`` and memory-mapped); a
window's channel is the step before its end plus the window's own events after that step. A
network trained under the reference light (``BrightnessParams.reference_slope_gain``) reads each
recording's slope gain from its sensor's ``events.toml`` ``[shading]``, as a run does.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.cache import cache_folder, cache_key, sha256_of
from labrig.calibration.event_thresholds_file import ContrastThresholds
from labrig.errors import LabrigError
from labrig.executor import run_tasks
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline import run_setup, tracking
from labrig.pipeline.brightness import BrightnessIntegrator, BrightnessParams
from labrig.pipeline.depth_inputs import DisplacementRaster, InputSpec, gel_plane_displacement_mm, network_input
from labrig.pipeline.marker_stage import MarkerStage
from labrig.pipeline.rest import RestParams
from labrig.pipeline.sae import UNET_SHAPE, crop_from_unet
from labrig.pipeline.windows import recording_windows
from labrig.recording import Recording
from labrig.training.shift import shifted

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
#: The tracker's windows over a recording (us).
TRACK_WINDOW_US = 10_000
TRACKS_VERSION = 2
BRIGHTNESS_VERSION = 2
#: The most times a batch's previous-map channel is replaced by the network's own answer (:func:`self_feed`).
SELF_FEED_MAX = 2


@dataclass(frozen=True)
class PreviousAugment:
    """How the previous map is chosen and perturbed.

    With ``p_stale`` it is the truth from 2 to ``max_lag_windows`` windows earlier instead of one
    (a map that may show another state: the dent before a release, nothing before a press), so
    the network checks it against the SAE and the displacement rather than copying it. Then it
    is zeroed with ``p_zero``, else scaled by a factor in ``[1 - scale, 1 + scale]``, shifted up
    to ``shift_cells`` cells per axis and given noise of ``noise`` (normalised depth units)
    standard deviation; clipped to [0, 1].
    """

    p_zero: float = 0.25
    scale: float = 0.4
    shift_cells: int = 2
    noise: float = 0.02
    p_stale: float = 0.3
    max_lag_windows: int = 30

    def lag_windows(self, rng: np.random.Generator) -> int:
        """How many windows back the previous map is taken from."""
        return int(rng.integers(2, self.max_lag_windows + 1)) if rng.uniform() < self.p_stale else 1

    def __call__(self, previous: F32, rng: np.random.Generator) -> F32:
        if rng.uniform() < self.p_zero:
            return np.zeros_like(previous)
        out = previous * np.float32(rng.uniform(1.0 - self.scale, 1.0 + self.scale))
        dr, dc = (int(v) for v in rng.integers(-self.shift_cells, self.shift_cells + 1, 2))
        out = shifted(out, dr, dc)
        out = out + rng.normal(0.0, self.noise, out.shape).astype(np.float32)
        return np.clip(out, 0.0, 1.0).astype(np.float32)

    def describe(self) -> dict[str, float]:
        return {"p_zero": self.p_zero, "scale": self.scale, "shift_cells": self.shift_cells, "noise": self.noise,
                "p_stale": self.p_stale, "max_lag_windows": self.max_lag_windows}


@dataclass(frozen=True)
class Tracks:
    """The tracker over one recording: window ends (N,) host us, positions (N, M, 2) px, the rest (M, 2) px."""

    t_us: npt.NDArray[np.int64]
    positions_px: F64
    rest_px: F64

    def at(self, t_us: float) -> F64:
        """(M, 2) positions linearly interpolated at ``t_us`` (the rest before the first window)."""
        k = int(np.searchsorted(self.t_us, t_us))
        if k == 0:
            return self.rest_px
        if k >= len(self.t_us):
            return self.positions_px[-1]
        a, b = self.t_us[k - 1], self.t_us[k]
        w = (t_us - a) / max(float(b - a), 1.0)
        return (1.0 - w) * self.positions_px[k - 1] + w * self.positions_px[k]


def track_recording(path: str | Path, calibration_dir: str | Path | None, cache_root: str | Path | None = None) -> Tracks:
    """The pipeline's tracker over the whole recording (10 ms windows), cached by the file's SHA-256 and the setup."""
    path = Path(path)
    with Recording(path) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=calibration_dir)
        params = tracking.TrackerParams(marker_diameter_px=tracking.marker_diameter_px(setup.rig, setup.camera))
        key = cache_key({"recording": sha256_of(path), "rest_px": np.round(setup.rest_px, 4).tolist(),
                         "observed": setup.observed.tolist(), "tracker": repr(params), "window_us": TRACK_WINDOW_US,
                         "rest": repr(RestParams()), "version": TRACKS_VERSION})
        cached = cache_folder("tracks", cache_root) / f"{key}.npz"
        if cached.exists():
            with np.load(cached) as data:
                return Tracks(data["t_us"], data["positions_px"], data["rest_px"])
        markers = MarkerStage.for_setup(setup, params, RestParams())
        ends, positions = [], []
        for t0, t1, events in recording_windows(rec, window_us=TRACK_WINDOW_US):
            p, _ = markers.update(events, t0, t1)
            ends.append(t1)
            positions.append(p.copy())
    if not ends:
        raise LabrigError(f"{path}: no camera windows to track")
    tracks = Tracks(np.asarray(ends, np.int64), np.asarray(positions, np.float64), np.asarray(markers.rest_px, np.float64))
    cached.parent.mkdir(parents=True, exist_ok=True)
    tmp = cached.with_name(f".{cached.stem}.tmp.npz")
    np.savez(tmp, t_us=tracks.t_us, positions_px=tracks.positions_px, rest_px=tracks.rest_px)
    tmp.replace(cached)
    return tracks


@dataclass(frozen=True)
class BrightnessTrack:
    """The integrated signed counts (reference events) of one recording at every 10 ms step: step ends
    ``t_us`` (N,) host us, ``counts`` (N, 90, 112) float16 (memory-mapped), the ROI, the integrator's
    settings and the event calibration that weighs the events and holds the light's slope gain (None: nominal)."""

    t_us: npt.NDArray[np.int64]
    counts: npt.NDArray[np.float16]
    roi: Any
    params: BrightnessParams
    thresholds: ContrastThresholds | None = None

    def window_end(self, t_end_us: float) -> float:
        """A training window's end: ``t_end_us``, or with the dead band undone (``params.dead_band``) the nearest step
        end, where the cached counts hold exactly what the run-time integrator holds (its pixels' polarity memory
        is not cached, so a window ending between steps would count its events without it)."""
        if not self.params.dead_band or not len(self.t_us):
            return t_end_us
        k = int(np.clip(np.searchsorted(self.t_us, t_end_us), 1, len(self.t_us) - 1)) if len(self.t_us) > 1 else 0
        if k > 0 and abs(t_end_us - self.t_us[k - 1]) <= abs(self.t_us[k] - t_end_us):
            k -= 1
        return float(self.t_us[k])

    def channel_at(self, t_end_us: float, events: npt.NDArray) -> F32:
        """The brightness channel at ``t_end_us``: the last step at or before it plus ``events``
        (the window's, host us) after that step."""
        k = int(np.searchsorted(self.t_us, t_end_us, side="right")) - 1
        integrator = BrightnessIntegrator(self.roi, self.params, thresholds=self.thresholds)
        if k >= 0:
            integrator.add(np.asarray(self.counts[k], np.float32), float(self.t_us[k]))
            events = events[events["t"] >= self.t_us[k]] if len(events) else events
        integrator.add_events(events, t_end_us)
        return integrator.channel()


def brightness_recording(path: str | Path, params: BrightnessParams, calibration_dir: str | Path | None,
                         cache_root: str | Path | None = None) -> BrightnessTrack:
    """:class:`BrightnessTrack` of a recording, cached by the file's SHA-256, its ROI, the contrast
    thresholds and the settings."""
    path = Path(path)
    with Recording(path) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=calibration_dir)
        roi, thresholds = setup.rig.roi, setup.thresholds
        key = cache_key({"recording": sha256_of(path), "roi": [roi.x0_px, roi.y0_px, roi.x1_px, roi.y1_px],
                         "params": repr(replace(params, reference_slope_gain=None)),  # the counts do not depend on it
                         "window_us": TRACK_WINDOW_US, "version": BRIGHTNESS_VERSION,
                         "thresholds": thresholds.digest() if thresholds is not None else "nominal"})
        folder = cache_folder("brightness", cache_root)
        times, counts = folder / f"{key}.t.npy", folder / f"{key}.counts.npy"
        if not (times.exists() and counts.exists()):
            ends, steps = _integrated_steps(rec, roi, params, thresholds)
            folder.mkdir(parents=True, exist_ok=True)
            for target, array in ((counts, steps), (times, ends)):
                tmp = target.with_name(f".{target.stem}.{os.getpid()}.tmp.npy")
                np.save(tmp, array)
                tmp.replace(target)
    return BrightnessTrack(np.load(times), np.load(counts, mmap_mode="r"), roi, params, thresholds)


def integrated_noise(track: BrightnessTrack, t_end_us: float, rate_hz: float, rng: np.random.Generator) -> F32:
    """(90, 112) what background noise at ``rate_hz`` per pixel (half ON, half OFF, independent) adds to the
    brightness channel by ``t_end_us``: per cell a leaky random walk, Gaussian with variance
    ``rate P tau / 2 (1 - exp(-2 T / tau))`` events (P pixels per cell, T the time since the track's start),
    each weighing its cell's reference-event weight (the thresholds', else 1), in the channel's units. Its
    mean, zero, needs no median."""
    params = track.params
    integrator = BrightnessIntegrator(track.roi, params)
    elapsed_s = max(float(t_end_us - (track.t_us[0] - TRACK_WINDOW_US)), 0.0) * 1e-6
    tau_s = params.rest_tau_s or params.tau_s  # a gated leak holds noise at its quiet cells' time constant
    variance = rate_hz * integrator.pixels_per_cell * tau_s / 2.0 * (1.0 - np.exp(-2.0 * elapsed_s / tau_s))
    std = np.sqrt(variance) / integrator.pixels_per_cell / params.scale_events_per_px
    if track.thresholds is not None:
        on_weight, off_weight = track.thresholds.reference_weights
        std = std * np.sqrt(0.5 * (on_weight**2 + off_weight**2)).reshape(GRID_SHAPE)
    return (rng.normal(0.0, std, GRID_SHAPE)).astype(np.float32)


def _integrated_steps(rec: Any, roi: Any, params: BrightnessParams, thresholds: ContrastThresholds | None
                      ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float16]]:
    """The integrator stepped over the recording's 10 ms windows (``recording_windows``' tiling from 0):
    window ends (N,) and the integrated counts (N, 90, 112) float16 after each, from one read of
    each 10 s slice of events rather than one read per window."""
    end = rec.end_us()
    n = -(-end // TRACK_WINDOW_US)
    if n <= 0:
        raise LabrigError(f"{rec.path}: no camera windows to integrate")
    ends = np.minimum((np.arange(n, dtype=np.int64) + 1) * TRACK_WINDOW_US, end)
    integrator = BrightnessIntegrator(roi, params, thresholds=thresholds)
    out = np.empty((n, *GRID_SHAPE), np.float16)
    per_slice = 1000
    for first in range(0, n, per_slice):
        last = min(first + per_slice, n)
        events = rec.events_between(first * TRACK_WINDOW_US, min(last * TRACK_WINDOW_US, end))
        window = events["t"] // TRACK_WINDOW_US - first
        if len(window) > 1 and (np.diff(window) < 0).any():  # device times may step back a little
            order = np.argsort(window, kind="stable")
            events, window = events[order], window[order]
        bounds = np.searchsorted(window, np.arange(last - first + 1))
        for k in range(last - first):
            integrator.add_events(events[bounds[k]:bounds[k + 1]], float(ends[first + k]))
            out[first + k] = integrator.counts
    return ends, out


class StateChannels:
    """The state channels of one recording's training windows (after the SAE, in the spec's order)."""

    def __init__(self, recording: str | Path, spec: InputSpec, calibration_dir: str | Path | None,
                 augment: PreviousAugment | None = None, cache_root: str | Path | None = None) -> None:
        self.spec = spec
        self.augment = augment or PreviousAugment()
        self.tracks: Tracks | None = None
        self.raster: DisplacementRaster | None = None
        self.brightness: BrightnessTrack | None = None
        if "brightness" in spec.kinds:
            self.brightness = brightness_recording(recording, spec.brightness, calibration_dir, cache_root)
        if "displacement" in spec.kinds:
            with Recording(recording) as rec:
                setup = run_setup.setup_for_recording(rec, calibration_dir=calibration_dir)
            self.camera = setup.camera
            self.raster = DisplacementRaster(setup.rest_px, setup.observed, setup.rig.roi)
            self.tracks = track_recording(recording, calibration_dir, cache_root)

    def window_end(self, t_end_us: float) -> float:
        """Where a training window meant to end at ``t_end_us`` ends (:meth:`BrightnessTrack.window_end`)."""
        return self.brightness.window_end(t_end_us) if self.brightness is not None else t_end_us

    def __call__(self, t_end_us: float, previous_at: Callable[[int], F32] | None, rng: np.random.Generator,
                 events: npt.NDArray | None = None, noise_hz: float = 0.0) -> F32:
        """(channels - 2, 96, 112): the displacement field at ``t_end_us``, the perturbed previous map and the
        brightness change (``events``: the window's own, ending at ``t_end_us``; ``noise_hz``: the window's
        background-noise augmentation, whose integrated count :func:`integrated_noise` adds).

        ``previous_at(lag_windows)``: the normalised true map that many windows before this one."""
        field = None
        if self.raster is not None and self.tracks is not None:
            field = self.raster(gel_plane_displacement_mm(self.camera, self.tracks.at(t_end_us), self.tracks.rest_px))
        previous = None
        if "previous" in self.spec.kinds:
            assert previous_at is not None
            previous = self.augment(previous_at(self.augment.lag_windows(rng)), rng)
        bright = None
        if self.brightness is not None:
            assert events is not None, "the brightness channel needs the window's events"
            bright = self.brightness.channel_at(t_end_us, events)
            if noise_hz > 0:
                bright = bright + integrated_noise(self.brightness, t_end_us, noise_hz, rng)
        return network_input(self.spec, np.zeros((2, *UNET_SHAPE), np.float32), field, previous, bright)[2:]


def self_feed(model: Any, x: Any, channel: int, steps: int) -> Any:
    """``x`` with its previous-map channel replaced ``steps`` times by the network's own answer (no gradient).

    At run time the previous map is the network's own last estimate, errors included; fed only
    the (perturbed) truth, a network learns to trust it and its errors compound in closed loop
    (measured: the depth ran to the top of the scale within a press). Fed its own answer, it
    learns to correct it. The answer stands in for the previous window's (10 ms earlier)."""
    import torch
    import torch.nn.functional as functional

    if steps == 0:
        return x
    x = x.clone()
    with torch.no_grad():
        for _ in range(steps):
            own = crop_from_unet(model(x)[:, 0]).clamp(0.0, 1.0)
            rows = x.shape[-2] - own.shape[-2]
            x[:, channel] = functional.pad(own, (0, 0, rows // 2, rows - rows // 2))
    return x


@dataclass(frozen=True)
class StateTask:
    """One recording whose state channels to build and cache ahead of training (plain values: a task)."""

    recording: str
    inputs: dict[str, Any]  # the input spec's card (:meth:`InputSpec.to_card`)
    calibration_dir: str | None


def build_state(task: StateTask) -> int:
    """Build ``task``'s state channels (the tracker's tracks, the brightness steps), filling their caches;
    returns how many 10 ms steps the recording has."""
    channels = StateChannels(task.recording, InputSpec.from_card({"inputs": task.inputs}), task.calibration_dir)
    steps = channels.brightness.t_us if channels.brightness is not None else (
        channels.tracks.t_us if channels.tracks is not None else np.zeros(0))
    return len(steps)


def prepare_states(recordings: list[Path], spec: InputSpec, calibration_dir: str | Path | None, *,
                   workers: int | None) -> None:
    """Build every recording's state channels in parallel (``workers`` processes; None: one per core) so that
    training samples from warm caches: a campaign's first pass would otherwise integrate each recording whole,
    one after another, in the sampler's process."""
    if not spec.stateful or not recordings:
        return
    tasks = [StateTask(str(path), spec.to_card(), None if calibration_dir is None else str(calibration_dir))
             for path in recordings]
    run_tasks(build_state, tasks, workers=workers, use_cache=False)
