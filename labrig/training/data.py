"""Training samples from a campaign: random event windows as SAEs, with the ground truth nearest in time.

The paper's sampling: pick a recording and a time at random, accumulate the following
window (10 ms by default) into a polarity-separated SAE normalised to [0, 1]
(:func:`labrig.pipeline.sae.sae_grid`, padded to 96 x 112), and take the ground-truth map
nearest in time to the window's last event. Times are host microseconds throughout:
:meth:`Recording.events_between` maps the camera's device clock to the recording's host
base, the base of the sidecar's ``t_host_us``.

Times are drawn uniformly over the recording's probing phases (``normal_down`` to
``normal_up``) widened by :data:`PHASE_MARGIN_S` before and ``after_s`` (the same by default) after,
intersected with the span of its ground truth and with the camera's stream: the approach and
retract (seconds of an undeformed gel at rest with hardly any events) would otherwise fill most
windows, while the margins still show the network the gel at rest. The gel leaves the indenter
about 0.1 s after ``normal_up`` ends, and the brightness change since rest then holds what its
events did not bring back (the pixels' threshold quantisation, their leak's bias: about one event
per pixel); a longer ``after_s`` shows the network more of that released gel, which it must read as
flat. ``phases="all"`` uses the whole recording.
Where a camera stream stopped early (a stalled camera) there are no events, not even noise,
beside a dented gel: such windows taught the network to draw a dimple from nothing.

**Background-noise augmentation** (:class:`NoiseAugment`): a share of the windows get extra
noise events, uniform over the ROI's pixels and the window, at a rate drawn log-uniformly
per window. A network trained at one sensor's noise level draws dimples from a noisier
sensor's SAE (the stress suite's event-noise axis); a real sensor's background rate
varies with the sensor, its biases, the light and the temperature.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import hdf5plugin  # noqa: F401  (registers the sidecars' zstd filter)
import numpy as np
import numpy.typing as npt

from labrig.config import DEFAULT_CALIBRATION_DIR, Roi
from labrig.dataset import SPLITS, Dataset, require_groundtruth
from labrig.errors import LabrigError
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.depth_inputs import InputSpec
from labrig.pipeline.sae import pad_for_unet, sae_grid
from labrig.recording import EVENT_DTYPE, Recording
from labrig.training.crop import CropAugment
from labrig.training.shift import ShiftAugment
from labrig.training.state_data import StateChannels

SAE_ONLY = InputSpec()
PROBING_PHASES = ("normal_down", "wait", "shear", "shear_opposite", "normal_up")
#: Margin around the probing phases (s): windows of the gel at rest, no contact, few events.
PHASE_MARGIN_S = 0.3
#: Events of the sampled spans a campaign keeps in memory (bytes): random windows over hundreds of recordings
#: would otherwise each cost a compressed read.
PRELOAD_BUDGET_BYTES = 6 << 30


@dataclass(frozen=True)
class NoiseAugment:
    """Extra background noise for a ``fraction`` of the windows: rate log-uniform in
    ``[min_hz, max_hz]`` events per pixel per second, uniform over the ROI's pixels."""

    max_hz: float
    min_hz: float = 0.02
    fraction: float = 0.5

    def __post_init__(self) -> None:
        if not 0.0 < self.min_hz <= self.max_hz:
            raise LabrigError(f"noise rates must satisfy 0 < {self.min_hz} <= {self.max_hz} Hz per pixel")
        if not 0.0 <= self.fraction <= 1.0:
            raise LabrigError("the noisy share of the windows must be within [0, 1]")

    def draw_hz(self, rng: np.random.Generator) -> float:
        """The extra rate for one window (0 for the clean share)."""
        if rng.uniform() >= self.fraction:
            return 0.0
        return float(np.exp(rng.uniform(np.log(self.min_hz), np.log(self.max_hz))))

    def describe(self) -> dict[str, float]:
        return {"min_hz": self.min_hz, "max_hz": self.max_hz, "fraction": self.fraction}


def background_noise(roi: Roi, t0_us: float, t1_us: float, rate_hz: float,
                     rng: np.random.Generator) -> npt.NDArray:
    """Noise events (``EVENT_DTYPE``, sorted in time) at ``rate_hz`` per pixel over ``roi`` and
    ``[t0_us, t1_us)``: Poisson count, uniform pixel, time and polarity."""
    mean = rate_hz * roi.width_px * roi.height_px * max(t1_us - t0_us, 0.0) * 1e-6
    n = int(rng.poisson(mean)) if mean > 0 else 0
    events = np.zeros(n, EVENT_DTYPE)
    events["x"] = rng.integers(roi.x0_px, roi.x1_px, n)
    events["y"] = rng.integers(roi.y0_px, roi.y1_px, n)
    events["p"] = rng.integers(0, 2, n)
    events["t"] = np.sort(rng.integers(int(t0_us), max(int(t1_us), int(t0_us) + 1), n))
    return events


@dataclass
class Sample:
    """One training example: network input, normalised target, contact mask (all numpy)."""

    sae: npt.NDArray[np.float32]      # (C, 96, 112), padded: the SAE, then the state channels the inputs name
    target: npt.NDArray[np.float32]   # (90, 112), depth / scale_mm clipped to [0, 1]
    contact: npt.NDArray[np.uint8]    # (90, 112)
    t_last_us: float
    dt_gt_us: float
    recording: int


class Source:
    """One recording and its sidecar: lazy map reads (one compressed chunk per map)."""

    def __init__(self, recording: Path, sidecar: Path, split: str, phases: str = "probing",
                 after_s: float = PHASE_MARGIN_S) -> None:
        self.path = recording
        self.sidecar = sidecar
        self.split = split
        self.rec = Recording(recording)
        self.gt = h5py.File(sidecar, "r")
        self.t_gt = self.gt["t_host_us"][:]
        if self.t_gt.size == 0:
            raise LabrigError(f"{sidecar} holds no maps; regenerate it with `labrig groundtruth`")
        attrs = self.gt.attrs
        self.scale_mm = float(attrs["scale_mm"])
        self.elastic_model = str(attrs.get("elastic_model", ""))
        self.indenter = str(attrs.get("indenter", self.rec.attrs.get("indenter", "")))
        x0, y0, x1, y1 = (int(v) for v in attrs["roi_px"])
        self.roi = Roi(x0, y0, x1, y1)
        self.span_us = self._span(phases, after_s)
        self._events: npt.NDArray | None = None  # the span's events, once preloaded
        self._t_max: npt.NDArray = np.zeros(0, np.int64)  # their running maximum time (host us)
        self._back_step_us = 0.0

    @property
    def preloaded(self) -> bool:
        """Whether the sampled span's events are held in memory (:meth:`preload`)."""
        return self._events is not None

    def preload(self, window_us: float) -> int:
        """Read the events of the sampled span (and one window past it) into memory, in the file's order; their
        size in bytes."""
        if self._events is None:
            events = self.rec.events_between(self.span_us[0], self.span_us[1] + window_us)
            t = np.ascontiguousarray(events["t"])
            self._t_max = np.maximum.accumulate(t)  # device times may step back a little
            self._back_step_us = float((self._t_max - t).max()) if len(t) else 0.0
            self._events = events
        return int(self._events.nbytes + self._t_max.nbytes)

    def events_between(self, t0_us: float, t1_us: float) -> npt.NDArray:
        """Events with host time in ``[t0_us, t1_us)`` in the file's order (as
        :meth:`Recording.events_between`): from memory when preloaded and within the span."""
        held = self._events
        if held is None or t0_us < self.span_us[0] or (len(held) and t1_us > self._t_max[-1] + 1):
            return self.rec.events_between(t0_us, t1_us)
        # Integer keys: a float key would make numpy convert the whole column to float first.
        i0 = int(np.searchsorted(self._t_max, np.int64(np.ceil(t0_us)), side="left"))
        i1 = int(np.searchsorted(self._t_max, np.int64(np.ceil(t1_us + self._back_step_us)), side="left"))
        rows = held[i0:i1]
        if self._back_step_us:
            rows = rows[(rows["t"] >= t0_us) & (rows["t"] < t1_us)]
        return rows

    def _span(self, phases: str, after_s: float) -> tuple[float, float]:
        t0, t1 = float(self.t_gt[0]), float(self.t_gt[-1])
        if phases == "probing":
            chosen = [p for p in self.rec.phases() if p.name in PROBING_PHASES]
            if chosen:
                t0 = max(t0, chosen[0].t_start_us - PHASE_MARGIN_S * 1e6)
                t1 = min(t1, chosen[-1].t_end_us + after_s * 1e6)
        elif phases != "all":
            raise LabrigError(f"phases must be 'probing' or 'all', not {phases!r}")
        events_end = self.rec.events_end_us()
        t1 = min(t1, float(events_end) if events_end is not None else t0)
        if t1 <= t0:
            raise LabrigError(f"{self.path}: its probing phases, its ground truth and its camera events do not overlap")
        return t0, t1

    def nearest(self, t_us: float) -> int:
        i = int(np.clip(np.searchsorted(self.t_gt, t_us), 1, self.t_gt.size - 1)) if self.t_gt.size > 1 else 0
        if i > 0 and abs(t_us - self.t_gt[i - 1]) <= abs(self.t_gt[i] - t_us):
            i -= 1
        return i

    def window(self, t0_us: float, window_us: float, index: int = -1,
               noise: npt.NDArray | None = None, state: StateChannels | None = None,
               rng: np.random.Generator | None = None, noise_hz: float = 0.0) -> Sample:
        """The SAE of ``[t0, t0 + window)`` and the map nearest to its last event (window end if none).

        ``noise``: extra events in the window (augmentation); they do not move the ground
        truth's time, which follows the recording's own last event (``noise_hz``: their rate, which the
        brightness channel's own noise follows). ``state``: the state
        channels (:mod:`labrig.training.state_data`) appended to the SAE; their previous map is
        the one nearest the previous window's last event (or one further back), perturbed with ``rng``.
        """
        events = self.events_between(t0_us, t0_us + window_us)
        own_events = events
        t_last = float(events["t"].max()) if len(events) else t0_us + window_us
        if noise is not None and len(noise):
            events = np.concatenate([events, noise.astype(events.dtype)])
            events = events[np.argsort(events["t"], kind="stable")]
        sae = pad_for_unet(sae_grid(events, t0_us, t0_us + window_us, self.roi, GRID_SHAPE))
        i = self.nearest(t_last)
        depth = self.gt["depth_mm"][i]
        target = np.clip(depth / np.float32(self.scale_mm), 0.0, 1.0).astype(np.float32)
        if state is not None:
            def previous(lag_windows: int) -> npt.NDArray[np.float32]:
                k = self.nearest(t_last - lag_windows * window_us)
                return np.clip(self.gt["depth_mm"][k] / np.float32(self.scale_mm), 0.0, 1.0).astype(np.float32)

            sae = np.concatenate([sae, state(t0_us + window_us, previous, rng or np.random.default_rng(), own_events,
                                             noise_hz)])
        return Sample(sae, target, self.gt["contact_mask"][i].astype(np.uint8), t_last,
                      float(self.t_gt[i]) - t_last, index)

    def close(self) -> None:
        self.gt.close()
        self.rec.close()


@dataclass
class CampaignData:
    """The complete recordings of one or more campaign folders that have current sidecars, by split."""

    folder: Path
    sources: dict[str, list[Source]] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)
    folders: list[Path] = field(default_factory=list)  # every folder, ``folder`` first

    @property
    def scale_mm(self) -> float:
        scales = {s.scale_mm for group in self.sources.values() for s in group}
        if len(scales) > 1:
            raise LabrigError(f"{self.folder}: sidecars use different scales {sorted(scales)}; "
                              "regenerate them with one --scale-mm")
        return scales.pop()

    def counts(self) -> dict[str, int]:
        return {k: len(self.sources.get(k, [])) for k in SPLITS}

    def describe(self) -> dict[str, Any]:
        """Training-data section of the model card."""
        models = sorted({s.elastic_model for g in self.sources.values() for s in g})
        folders = self.folders or [self.folder]
        return {
            "campaign": str(self.folder), "campaign_name": self.folder.name, "split_counts": self.counts(),
            "campaigns": [str(f) for f in folders],
            "split_counts_by_campaign": {str(f): {k: sum(s.path.parent.resolve() == f.resolve() for s in self.sources.get(k, []))
                                                 for k in SPLITS} for f in folders},
            "recordings": {k: [s.path.name for s in self.sources.get(k, [])] for k in SPLITS},
            "indenters": sorted({s.indenter for g in self.sources.values() for s in g}),
            "groundtruth_model": models, "scale_mm": self.scale_mm, "skipped": self.skipped,
        }

    def close(self) -> None:
        for group in self.sources.values():
            for s in group:
                s.close()


def open_campaign(folder: str | Path | Sequence[str | Path], phases: str = "probing",
                  after_s: float = PHASE_MARGIN_S) -> CampaignData:
    """Pair each complete recording of a campaign folder's manifest with its ``NAME.gt.h5``, by split.

    Several folders (e.g. the paper campaign and a training campaign) pool their recordings
    split by split; each keeps its own split assignment. A recording without a split (or an
    unknown one) trains. A missing sidecar is an error that says to run ``labrig groundtruth
    DATA/`` first; a recording that cannot be used is skipped.
    """
    folders = [Path(f) for f in ([folder] if isinstance(folder, (str, Path)) else folder)]
    if not folders:
        raise LabrigError("no campaign folder to train on")
    data = CampaignData(folders[0], folders=folders)
    for one in folders:
        recordings = Dataset.open(one).require()
        require_groundtruth(recordings, one)
        for recording in recordings:
            split = recording.split if recording.split in SPLITS else "train"
            try:
                data.sources.setdefault(split, []).append(Source(recording.path, recording.sidecar, split, phases,
                                                                      after_s))
            except LabrigError as exc:
                data.skipped.append(f"{recording.path.name}: {exc}")
    if not data.sources.get("train"):
        raise LabrigError(f"{folder}: no usable recording in the train split")
    data.scale_mm  # noqa: B018  (checks that all scales agree)
    return data


class WindowSampler:
    """Random windows from a list of sources, with a seeded generator whose state can be saved.

    Iterating yields :class:`Sample` s forever; :meth:`batch` stacks them as numpy
    arrays; :meth:`state` / :meth:`set_state` capture the generator for resume. ``shift``: each window
    moved across the grid (:mod:`labrig.training.shift`), else where it was recorded; ``crop``: then cut to a
    patch that holds its contact (:mod:`labrig.training.crop`), else the whole grid. ``preload``: the
    recordings' sampled spans read into memory, up to :data:`PRELOAD_BUDGET_BYTES` in all, as they are first drawn.
    """

    def __init__(self, sources: list[Source], window_us: float, seed: int, noise: NoiseAugment | None = None,
                 inputs: InputSpec = SAE_ONLY, calibration_dir: str | Path | None = DEFAULT_CALIBRATION_DIR,
                 shift: ShiftAugment | None = None, crop: CropAugment | None = None, preload: bool = False) -> None:
        if not sources:
            raise LabrigError("no recordings to sample from")
        self.sources = sources
        self.window_us = float(window_us)
        self.noise = noise
        self.rng = np.random.default_rng(seed)
        self.inputs = inputs
        self.calibration_dir = calibration_dir
        self.shift = shift
        self.crop = crop
        self._preload_left = PRELOAD_BUDGET_BYTES if preload else 0
        self._state: dict[int, StateChannels] = {}

    def state_channels(self, k: int) -> StateChannels | None:
        """Source ``k``'s state channels (built, and its tracks cached, on first use); None for the SAE alone."""
        if not self.inputs.stateful:
            return None
        if k not in self._state:
            self._state[k] = StateChannels(self.sources[k].path, self.inputs, self.calibration_dir)
        return self._state[k]

    def sample(self) -> Sample:
        k = int(self.rng.integers(len(self.sources)))
        src = self.sources[k]
        if self._preload_left > 0 and not src.preloaded:
            self._preload_left -= src.preload(self.window_us)
        t0, t1 = src.span_us
        start = float(self.rng.uniform(t0, max(t0, t1 - self.window_us)))
        state = self.state_channels(k)
        if state is not None:
            start = state.window_end(start + self.window_us) - self.window_us
        extra, rate_hz = None, 0.0
        if self.noise is not None:
            rate_hz = self.noise.draw_hz(self.rng)
            extra = background_noise(src.roi, start, start + self.window_us, rate_hz, self.rng) if rate_hz else None
        sample = src.window(start, self.window_us, k, extra, state, self.rng, rate_hz)
        if self.shift is not None:
            sample = self.shift.apply(sample, *self.shift.draw(self.rng))
        if self.crop is not None:
            sample = self.crop.apply(sample, *self.crop.draw(self.rng, sample.contact))
        return sample

    def __iter__(self) -> Iterator[Sample]:
        while True:
            yield self.sample()

    def batch(self, size: int) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.uint8]]:
        samples = [self.sample() for _ in range(size)]
        return (np.stack([s.sae for s in samples]), np.stack([s.target for s in samples]),
                np.stack([s.contact for s in samples]))

    def state(self) -> dict[str, Any]:
        return dict(self.rng.bit_generator.state)

    def set_state(self, state: dict[str, Any]) -> None:
        self.rng.bit_generator.state = state


def torch_dataset(sampler: WindowSampler) -> Any:
    """The sampler as a :class:`torch.utils.data.IterableDataset` of (sae, target, contact) tensors."""
    import torch
    from torch.utils.data import IterableDataset

    class Windows(IterableDataset):  # type: ignore[type-arg]
        def __iter__(self):  # type: ignore[no-untyped-def]
            for s in sampler:
                yield torch.from_numpy(s.sae), torch.from_numpy(s.target), torch.from_numpy(s.contact)

    return Windows()


def fixed_set(sources: list[Source], window_us: float, n: int, seed: int, inputs: InputSpec = SAE_ONLY,
              calibration_dir: str | Path | None = DEFAULT_CALIBRATION_DIR) -> tuple[npt.NDArray, ...]:
    """``n`` windows drawn once with their own seed (validation): arrays input (SAE and state channels), target, contact."""
    return WindowSampler(sources, window_us, seed, inputs=inputs, calibration_dir=calibration_dir).batch(n)
