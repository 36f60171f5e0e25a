"""Depth sources: the normal-displacement map (90 x 112 network grid, mm into the gel) of each window.

* :class:`TruthDepth`: the recording's ``/truth/depth`` at the window's end, between two solves linear in
  time as the sim moves its markers (:func:`truth_between`; virtual-rig recordings only);
* :class:`ModelDepth`: the ONNX depth network (:mod:`labrig.pipeline.depthnet`) on the SAE of the
  span it was trained on, ending at the window's end, and the state channels its card
  (:mod:`labrig.pipeline.model_card`) names (:mod:`labrig.pipeline.depth_inputs`), with the rest
  gate of :mod:`labrig.pipeline.rest_gate`; one class per design, chosen by the card
  (:func:`model_depth`): :class:`SaeNetworkDepth` (change only: the quiet-window hold of
  :mod:`labrig.pipeline.quiet`) and :class:`BrightnessNetworkDepth` (the brightness change since
  rest in its input).

:func:`depth_source` is the one place a run's source is built (``labrig run``, ``run --live``
and ``evaluate``).
"""

from __future__ import annotations

import logging
from abc import abstractmethod
from dataclasses import replace
from pathlib import Path
from typing import Protocol, TypeVar

import numpy as np
import numpy.typing as npt

from labrig import models
from labrig.errors import LabrigError
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.anchor import AnchorParams
from labrig.pipeline.brightness import LEAK_STEP_US, BrightnessIntegrator, dim_light_warning
from labrig.pipeline.depth_inputs import DisplacementRaster, gel_plane_displacement_mm, gel_plane_mm, network_input
from labrig.pipeline.depth_lane import DepthJob, DepthSteps, one_step
from labrig.pipeline.depthnet import DepthModel
from labrig.pipeline.model_card import ModelCard
from labrig.pipeline.quiet import QuietHold, QuietParams
from labrig.pipeline.rest_gate import RestGate, RestGateParams
from labrig.pipeline.run_setup import PipelineSetup
from labrig.recording import Recording

log = logging.getLogger(__name__)

DEFAULT_QUIET = QuietParams()
DEFAULT_REST_GATE = RestGateParams()
DEFAULT_ANCHOR = AnchorParams()
#: Tiles (rows x columns over the SAE grid) watched for motion with a noise-trained network.
NOISE_TILES = (6, 7)
T = TypeVar("T")


class DepthSource(Protocol):
    """Gives the normal-displacement map (90 x 112, mm into the gel) for a window.

    ``window_us``: the span the source's SAE covers, ending at the pipeline window's end
    (None: the pipeline window itself). ``depth_mm`` gets that span's SAE (None unless
    ``needs_sae``), its bounds and how many events fell in it. ``needs_counts``: the pipeline
    counts each window's signed events for :meth:`observe`. ``anchor``: the noise of the
    contact's location read from its maps (:mod:`labrig.pipeline.anchor`); None: exact maps, no filter.

    Per window the pipeline calls :meth:`observe`, then :meth:`depth_mm` (unless it keeps the last
    map). A source that subclasses this protocol inherits the defaults below.
    """

    name: str
    needs_sae: bool
    needs_counts: bool = False
    window_us: float | None = None
    anchor: AnchorParams | None = None

    def observe(self, positions_px: npt.NDArray[np.float64], rest_px: npt.NDArray[np.float64],
                counts: npt.NDArray[np.float32] | None, t1_us: int) -> None:
        """The tracked window ending at ``t1_us``: its marker positions (M, 2) px, the rest they are measured
        from (M, 2) px and, when ``needs_counts``, its signed event counts per grid cell (else None)."""
        return None

    def count_events(self, events: npt.NDArray) -> npt.NDArray[np.float32] | None:
        """A window's signed event counts per grid cell as :meth:`observe` takes them, when the source counts
        them its own way (every event once and in order); None: the front stage's
        :func:`~labrig.pipeline.brightness.signed_counts` with the setup's thresholds."""
        return None

    def depth_mm(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                 n_events: int) -> npt.NDArray[np.float32]: ...

    def depth_job(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                  n_events: int) -> DepthJob:
        """:meth:`depth_mm` as a job another thread may run (:mod:`labrig.pipeline.depth_lane`): whatever reads or
        changes this source's state is done now, in the caller, and the job only computes. By default all of
        :meth:`depth_mm` is done now."""
        depth = self.depth_mm(sae_grid, t0_us, t1_us, n_events)
        return lambda: depth

    def depth_steps(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                    n_events: int) -> DepthSteps:
        """:meth:`depth_job` in steps the caller runs one at a time (:class:`~labrig.pipeline.depth_lane.SteppedLane`):
        the state's work now, then the computation; a network cut by :meth:`split_network` runs one part per step.
        By default the job is one step."""
        return one_step(self.depth_job(sae_grid, t0_us, t1_us, n_events))

    def split_network(self, parts: int) -> int:
        """Cut the source's network into ``parts`` steps for :meth:`depth_steps`; the steps it will take (by
        default 1: no network)."""
        return 1

    def warm_up(self) -> None:
        """Pay the first run's costs (a network's buffers) now, leaving the source's state as it is. By default
        nothing."""
        return None


def truth_between(t_maps_us: npt.NDArray[np.int64], t_us: npt.ArrayLike
                  ) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp], npt.NDArray[np.float64]]:
    """The ``/truth/depth`` maps (times ``t_maps_us``, increasing) around each time: (before, after, weight of
    after). The maps are the sim's quasi-static solves and its markers move linearly in time between two of
    them, so the truth between is their linear blend; before the first map or after the last, that map."""
    t = np.asarray(t_us, dtype=np.float64)
    if len(t_maps_us) < 2:
        zero = np.zeros(np.shape(t), np.intp)
        return zero, zero, np.zeros(np.shape(t))
    after = np.clip(np.searchsorted(t_maps_us, t, side="right"), 1, len(t_maps_us) - 1)
    before = after - 1
    t0, t1 = t_maps_us[before].astype(np.float64), t_maps_us[after].astype(np.float64)
    return before, after, np.clip((t - t0) / (t1 - t0), 0.0, 1.0)


class TruthDepth(DepthSource):
    """The recording's ``/truth/depth`` at the window's end (:func:`truth_between`; virtual rig only).

    The sim's own maps locate the contact exactly: no anchor filter (``anchor`` None)."""

    name = "truth"
    needs_sae = False

    def __init__(self, recording: Recording) -> None:
        if "truth/depth" not in recording.streams or recording.rows("truth/depth") == 0:
            raise LabrigError(f"{recording.path}: no /truth/depth (only virtual-rig recordings have it); use --depth model")
        self.t_us = recording.column("truth/depth", "t_host_us")
        self.maps = np.asarray(recording.column("truth/depth", "depth_mm"), np.float32)  # ~40 kB per solve, loaded once

    def depth_mm(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                 n_events: int = 0) -> npt.NDArray[np.float32]:
        before, after, w = truth_between(self.t_us, t1_us)
        if w == 0.0:
            return self.maps[before]
        if w == 1.0:
            return self.maps[after]
        return (self.maps[before] * np.float32(1.0 - w) + self.maps[after] * np.float32(w)).astype(np.float32)


class ModelDepth(DepthSource):
    """The depth network (:class:`labrig.pipeline.depthnet.DepthModel`, ONNX) on the SAE of the
    window it was trained on (model card ``window_ms``) ending at each pipeline window's end,
    with the state channels its card names (:mod:`labrig.pipeline.depth_inputs`).

    What the networks share; :func:`model_depth` builds the one its card asks for: a
    :class:`SaeNetworkDepth`, which sees change only and keeps its last map through still windows,
    or a :class:`BrightnessNetworkDepth`, whose input holds the gel's state.

    ``setup``: the run's camera, ROI and markers (needed by a network that takes the displacement
    field or the brightness change). ``rest``: the rest gate (:mod:`labrig.pipeline.rest_gate`):
    once the tracked markers are back at rest the depth is exactly zero and the source forgets
    its state (:meth:`reset`); None: off.
    """

    needs_sae = True
    hold: QuietHold | None = None  # the quiet-window hold (None: every window goes to the network)
    integrator: BrightnessIntegrator | None = None  # the brightness change since rest (None: not an input)

    def __init__(self, model: DepthModel, setup: PipelineSetup | None, rest: RestGateParams | None) -> None:
        self.model = model
        self.card = model.card
        self.name = f"model:{model.name}"
        self.window_us: float | None = model.window_ms * 1000.0
        self.inputs = model.inputs
        self.anchor: AnchorParams | None = anchor_params_for(self.card)
        self.gate = RestGate(setup.observed if setup is not None else None, rest) if rest is not None else None
        self.raster: DisplacementRaster | None = None
        if "displacement" in self.inputs.kinds:
            if setup is None:
                raise LabrigError(f"{model.path} takes the markers' displacement field: build it with "
                                  "depth_sources.depth_source(..., setup=...)")
            self.raster = DisplacementRaster(setup.rest_px, setup.observed, setup.rig.roi)
        self.camera = setup.camera if setup is not None else None
        self.previous_norm = np.zeros(GRID_SHAPE, np.float32)
        self._positions_px: npt.NDArray[np.float64] | None = None
        self._rest_px: npt.NDArray[np.float64] | None = None
        self._rest_seen: npt.NDArray[np.float64] | None = None
        self._rest_mm: npt.NDArray[np.float64] | None = None
        self.at_rest = False

    def observe(self, positions_px: npt.NDArray[np.float64], rest_px: npt.NDArray[np.float64],
                counts: npt.NDArray[np.float32] | None, t1_us: int) -> None:
        self.markers(positions_px, rest_px)
        if counts is not None:
            self.counts(counts, t1_us)

    def count_events(self, events: npt.NDArray) -> npt.NDArray[np.float32] | None:
        return self.integrator.count(events) if self.integrator is not None else None

    def markers(self, positions_px: npt.NDArray[np.float64], rest_px: npt.NDArray[np.float64]) -> None:
        """This window's tracked marker positions (M, 2) px and the rest they are measured from."""
        self._positions_px, self._rest_px = positions_px, rest_px
        self.at_rest = self.gate(positions_px, rest_px) if self.gate is not None else False

    def counts(self, signed_counts: npt.NDArray[np.float32], t1_us: int) -> None:
        """This window's log-intensity change per grid cell in reference events
        (:func:`labrig.pipeline.brightness.signed_counts` with the setup's thresholds)."""
        if self.integrator is not None:
            self.integrator.add(signed_counts, t1_us)

    @abstractmethod
    def depth_mm(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                 n_events: int) -> npt.NDArray[np.float32]: ...

    def estimate(self, sae_grid: npt.NDArray[np.float32] | None) -> npt.NDArray[np.float32]:
        """The network's map for this window's SAE and state; it becomes the previous estimate."""
        return self._remember(self.model.depth_mm(self._input(sae_grid)))

    def _input(self, sae_grid: npt.NDArray[np.float32] | None) -> npt.NDArray[np.float32]:
        if sae_grid is None:
            raise ValueError(f"{self.name} needs the SAE: the pipeline must compute it (needs_sae)")
        return self.network_input(sae_grid)

    def _remember(self, depth: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """``depth`` becomes the previous estimate."""
        self.previous_norm = depth / np.float32(self.model.scale_mm)
        return depth

    def warm_up(self) -> None:
        """The network run twice on zeros, whole and in its parts (its state, the previous estimate, untouched)."""
        zeros = np.zeros((self.inputs.channels, *GRID_SHAPE), np.float32)
        for _ in range(2):
            self.model.depth_mm(zeros)
            for _ in self.model.depth_mm_steps(zeros):
                pass

    def split_network(self, parts: int) -> int:
        return self.model.split(parts)

    def network_input(self, sae_grid: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """The channels the card names for this window: the SAE, then the state."""
        if not self.inputs.stateful:
            return sae_grid
        bright = self.integrator.channel() if self.integrator is not None else None
        field = None
        if self.raster is not None:
            if self._positions_px is None or self._rest_px is None or self.camera is None:
                raise LabrigError(f"{self.model.name} takes the markers' displacement: the pipeline must call "
                                  "observe() before depth_mm()")
            if self._rest_px is not self._rest_seen:  # the rest changes only while the stream's first windows refine it
                self._rest_seen, self._rest_mm = self._rest_px, gel_plane_mm(self.camera, self._rest_px)
            field = self.raster(gel_plane_displacement_mm(self.camera, self._positions_px, self._rest_px, self._rest_mm))
        return network_input(self.inputs, sae_grid, field, self.previous_norm, bright)

    def reset(self, t_us: int | None = None) -> None:
        """Forget the previous estimate (the gel is at rest at ``t_us``)."""
        self.previous_norm = np.zeros(GRID_SHAPE, np.float32)


class SaeNetworkDepth(ModelDepth):
    """A network that does not see the brightness change since rest: the SAE (with, if its card
    says so, the markers' displacement and its previous map). A 10 ms SAE shows change, not
    state, so ``quiet``: windows at the noise floor keep the last active map
    (:mod:`labrig.pipeline.quiet`); None feeds every window to the network."""

    def __init__(self, model: DepthModel, setup: PipelineSetup | None, quiet: QuietParams | None,
                 rest: RestGateParams | None) -> None:
        super().__init__(model, setup, rest)
        self.hold = QuietHold(GRID_SHAPE, quiet) if quiet is not None else None

    def depth_mm(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                 n_events: int) -> npt.NDArray[np.float32]:
        hold = self.hold
        quiet = hold(n_events, t1_us - t0_us, sae_grid) if hold is not None else False  # every window feeds the floors
        if self.at_rest:
            self.reset(t1_us)
            return np.zeros(GRID_SHAPE, np.float32)
        if quiet and hold is not None:
            return hold.held_mm
        depth = self.estimate(sae_grid)
        return hold.update(depth) if hold is not None else depth

    def reset(self, t_us: int | None = None) -> None:
        """Forget the held map and the previous estimate (the gel is at rest at ``t_us``)."""
        super().reset(t_us)
        if self.hold is not None:
            self.hold.update(np.zeros(GRID_SHAPE, np.float32))


_WARNED: set[str] = set()


def _warn_once(message: str) -> None:
    if message not in _WARNED:
        _WARNED.add(message)
        log.warning(message)


class BrightnessNetworkDepth(ModelDepth):
    """A network that takes the brightness change since rest (:mod:`labrig.pipeline.brightness`),
    integrated here from each window's signed event counts (``needs_counts``). It sees the gel's
    state in every window, so it answers every window: no quiet hold."""

    needs_counts = True

    def __init__(self, model: DepthModel, setup: PipelineSetup | None, rest: RestGateParams | None) -> None:
        super().__init__(model, setup, rest)
        if setup is None:
            raise LabrigError(f"{model.path} takes the brightness change since rest: build it with "
                              "depth_sources.depth_source(..., setup=...)")
        self.integrator = BrightnessIntegrator(setup.rig.roi, self.inputs.brightness, thresholds=setup.thresholds)
        if self.inputs.brightness.reference_slope_gain is not None and (
                setup.thresholds is None or setup.thresholds.slope_gain is None):
            _warn_once(f"{model.path.name} reads the brightness under the reference light, and this camera's slope gain "
                       "is not measured: the reference light is assumed (measure it: `labrig calibrate events`)")
        dim = dim_light_warning(None if setup.thresholds is None else setup.thresholds.slope_gain)
        if dim is not None:
            _warn_once(f"{model.path.name}: {dim}")

    def depth_mm(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                 n_events: int) -> npt.NDArray[np.float32]:
        if self.at_rest:
            self.reset(t1_us)
            return np.zeros(GRID_SHAPE, np.float32)
        return self.estimate(sae_grid)

    def warm_up(self) -> None:
        """The network's warm-up, and a throwaway integrator's leak steps and channel (their first calls load what
        they use)."""
        super().warm_up()
        assert self.integrator is not None
        scratch = BrightnessIntegrator(self.integrator.roi, self.integrator.params, self.integrator.grid_shape,
                                       self.integrator.thresholds)
        counts = np.zeros(self.integrator.grid_shape, np.float32)
        for step in range(3):
            scratch.add(counts, step * LEAK_STEP_US)
        scratch.channel()

    def depth_job(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                  n_events: int) -> DepthJob:
        """The rest gate and the network's input (the SAE and a snapshot of the brightness state) now; the job
        runs the network."""
        if self.at_rest:
            self.reset(t1_us)
            zeros = np.zeros(GRID_SHAPE, np.float32)
            return lambda: zeros
        inputs = self._input(sae_grid)
        return lambda: self._remember(self.model.depth_mm(inputs))

    def depth_steps(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                    n_events: int) -> DepthSteps:
        """The rest gate and the network's input now (as :meth:`depth_job`); then the network, a part per step."""
        if self.at_rest:
            self.reset(t1_us)
            zeros = np.zeros(GRID_SHAPE, np.float32)
            return one_step(lambda: zeros)
        return self._network_steps(self._input(sae_grid))

    def _network_steps(self, inputs: npt.NDArray[np.float32]) -> DepthSteps:
        depth = yield from self.model.depth_mm_steps(inputs)
        return self._remember(depth)

    def reset(self, t_us: int | None = None) -> None:
        """Forget the previous estimate and the brightness change (the gel is at rest at ``t_us``)."""
        super().reset(t_us)
        if self.integrator is not None:
            self.integrator.reset(t_us)


def model_depth(path: str | Path, threads: int = 1, quiet: QuietParams | str | None = "auto", *,
                setup: PipelineSetup | None = None, rest: RestGateParams | str | None = "auto") -> ModelDepth:
    """The depth network at ``path`` (an ``.onnx`` with its card, or a bundled network's name:
    ``default``, ``sae-only``) as the source its card asks for.

    ``quiet``: the quiet hold of a network that does not see the brightness change (``"auto"``:
    :func:`quiet_params_for`; None: off); ``rest``: the rest gate (``"auto"``: :func:`rest_params_for`;
    None: off). ``setup``: the run's camera, ROI and markers (needed by a network with state channels).
    """
    model = DepthModel(models.model_path(path), threads=threads)
    gate = _setting(rest, rest_params_for(model.card), "rest")
    if model.card.sees_brightness:
        if _setting(quiet, None, "quiet") is not None:
            raise LabrigError(f"{model.name} sees the brightness change since rest: it answers every window, "
                              "a quiet hold does not apply")
        return BrightnessNetworkDepth(model, setup, gate)
    return SaeNetworkDepth(model, setup, _setting(quiet, quiet_params_for(model.card), "quiet"), gate)


def _setting(value: T | str | None, auto: T | None, what: str) -> T | None:
    """``value``, or ``auto`` for ``"auto"``."""
    if isinstance(value, str):
        if value != "auto":
            raise LabrigError(f"the {what} setting must be 'auto', None or its parameters, not {value!r}")
        return auto
    return value


def quiet_params_for(card: ModelCard) -> QuietParams | None:
    """The quiet-window gate for a network: the rate gate, plus per-tile activity when it was
    trained on noisy windows. A network trained clean draws dimples from a noisy SAE, so
    the more sensitive tile test would hand it more of them (measured in docs/evaluation.md).
    None (no hold) for a network that sees the brightness change since rest: the state is in its input."""
    if card.sees_brightness:
        return None
    return replace(DEFAULT_QUIET, tiles=NOISE_TILES) if card.noise_trained else DEFAULT_QUIET


def rest_params_for(card: ModelCard) -> RestGateParams | None:
    """The rest gate for a network: on for one that sees only the SAE (its quiet hold would keep a
    stale dent), off for one that sees the brightness change since rest. The gate reads the gel's
    rest from the markers alone, and a press at the gel's centre hardly moves them in the image
    (parallax only): the gate would zero the first 0.2-0.5 mm of such a press, and a light one
    whole. The brightness network's own input returns to rest with the gel; measured on the
    paper campaign's test split, it is better without the gate on every figure
    (docs/depthnet.md)."""
    if card.sees_brightness:
        return None
    return DEFAULT_REST_GATE


def anchor_params_for(card: ModelCard) -> AnchorParams:
    """The contact anchor's noise model for a network: its card's ``contact_anchor`` (fields of
    :class:`~labrig.pipeline.anchor.AnchorParams`) over the defaults, fitted for the bundled network."""
    return card.contact_anchor


def default_model_path(folder: str | Path = "models") -> Path:
    """The newest ``*.onnx`` with a model card in ``folder`` (your own trained networks), else the bundled one."""
    candidates = sorted(Path(folder).glob("*.onnx"), key=lambda p: p.stat().st_mtime)
    candidates = [p for p in candidates if p.with_suffix(".json").exists()]
    return candidates[-1] if candidates else models.bundled_model_path()


def depth_source(kind: str, setup: PipelineSetup, recording: Recording | None = None,
                 model_path: str | Path | None = None, threads: int = 1, quiet: QuietParams | str | None = "auto",
                 rest: RestGateParams | str | None = "auto") -> DepthSource:
    """The one builder of a run's depth source, for ``labrig run``, ``run --live`` and ``evaluate``.

    ``kind``: "truth" (the recording's /truth/depth; needs ``recording``) or "model" (the ONNX
    network ``model_path``, else the newest in models/, else the bundled one) with the run's
    ``setup``, the quiet hold and the rest gate (each ``"auto"``: as the network's card asks).
    """
    if kind == "truth":
        if recording is None:
            raise LabrigError("--depth truth needs a virtual-rig recording; a live camera has no true depth")
        return TruthDepth(recording)
    if kind == "model":
        return model_depth(model_path or default_model_path(), threads=threads, quiet=quiet, setup=setup, rest=rest)
    raise LabrigError(f"depth source must be 'truth' or 'model', not {kind!r}")
