"""Depth sources: the normal-displacement map (90 x 112 network grid, mm into the gel) of each window.

* :class:`TruthDepth`: the recording's ``/truth/depth`` at the window's end, between two solves linear in
  time as the sim moves its markers (:func:`truth_between`; virtual-rig recordings only);
* :class:`ModelDepth`: the ONNX depth network (:mod:`labrig.pipeline.depthnet`) on the SAE of the
  span it was trained on, ending at the window's end, and the state channels its card names
  (:mod:`labrig.pipeline.depth_inputs`), with the quiet-window hold of
  :mod:`labrig.pipeline.quiet` and the rest gate of :mod:`labrig.pipeline.rest_gate`.

:func:`depth_source` is the one place a run's source is built (``labrig run``, ``run --live``
and ``evaluate``).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from labrig import models
from labrig.errors import LabrigError
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.anchor import AnchorParams
from labrig.pipeline.brightness import BrightnessIntegrator
from labrig.pipeline.depth_inputs import DisplacementRaster, gel_plane_displacement_mm, gel_plane_mm, network_input
from labrig.pipeline.depthnet import DepthModel
from labrig.pipeline.quiet import QuietHold, QuietParams
from labrig.pipeline.rest_gate import RestGate, RestGateParams
from labrig.pipeline.run_setup import PipelineSetup
from labrig.recording import Recording

DEFAULT_QUIET = QuietParams()
DEFAULT_REST_GATE = RestGateParams()
DEFAULT_ANCHOR = AnchorParams()
#: Tiles (rows x columns over the SAE grid) watched for motion with a noise-trained network.
NOISE_TILES = (6, 7)


class DepthSource(Protocol):
    """Gives the normal-displacement map (90 x 112, mm into the gel) for a window.

    ``window_us``: the span the source's SAE covers, ending at the pipeline window's end
    (None: the pipeline window itself). ``depth_mm`` gets that span's SAE (None unless
    ``needs_sae``), its bounds and how many events fell in it. ``anchor``: the noise of the
    contact's location read from its maps (:mod:`labrig.pipeline.anchor`); None: exact maps, no filter.
    """

    name: str
    needs_sae: bool
    window_us: float | None
    anchor: AnchorParams | None

    def depth_mm(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                 n_events: int) -> npt.NDArray[np.float32]: ...


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


class TruthDepth:
    """The recording's ``/truth/depth`` at the window's end (:func:`truth_between`; virtual rig only)."""

    name = "truth"
    needs_sae = False
    window_us: float | None = None
    anchor: AnchorParams | None = None  # the sim's own maps locate the contact exactly

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


class ModelDepth:
    """The depth network (:class:`labrig.pipeline.depthnet.DepthModel`, ONNX) on the SAE of the
    window it was trained on (model card ``window_ms``) ending at each pipeline window's end,
    with the state channels its card names (:mod:`labrig.pipeline.depth_inputs`).

    ``path``: an ``.onnx`` with its card, or a bundled network's name (``default``,
    ``sae-only``). ``setup``: the run's camera, ROI and markers (needed by a network that
    takes the displacement field). ``quiet``: windows at the noise floor keep the last active
    map (:mod:`labrig.pipeline.quiet`); ``"auto"`` also watches each SAE tile for motion when
    the network was trained with background-noise augmentation (:func:`quiet_params_for`);
    None feeds every window to the network. ``rest``: the rest gate
    (:mod:`labrig.pipeline.rest_gate`): once the tracked markers are back at rest the depth
    is exactly zero, the held map and the previous estimate are cleared; None turns it off;
    ``"auto"`` (:func:`rest_params_for`) keeps it for the networks that need it.

    The pipeline calls :meth:`markers` with each window's tracked positions before
    :meth:`depth_mm` (``needs_markers``), and, for a network that takes the brightness change
    since rest (``needs_counts``), :meth:`counts` with each window's signed event counts.
    Such a network sees the gel's state in every window, so it answers every window: the
    quiet hold, which keeps an SAE-only network's last map through still windows, is off.
    """

    needs_sae = True
    needs_markers = True

    def __init__(self, path: str | Path, threads: int = 1, quiet: QuietParams | str | None = "auto", *,
                 setup: PipelineSetup | None = None, rest: RestGateParams | str | None = "auto") -> None:
        self.model = DepthModel(models.model_path(path), threads=threads)
        self.name = f"model:{self.model.name}"
        self.window_us: float | None = self.model.window_ms * 1000.0
        self.inputs = self.model.inputs
        self.needs_counts = "brightness" in self.inputs.kinds
        self.anchor: AnchorParams | None = anchor_params_for(self.model.card)
        if quiet == "auto":
            quiet = quiet_params_for(self.model.card)
        assert not isinstance(quiet, str), f"quiet must be QuietParams, None or 'auto', not {quiet!r}"
        self.hold = QuietHold(GRID_SHAPE, quiet) if quiet is not None else None
        if rest == "auto":
            rest = rest_params_for(self.model.card)
        assert not isinstance(rest, str), f"rest must be RestGateParams, None or 'auto', not {rest!r}"
        self.gate = RestGate(setup.observed if setup is not None else None, rest) if rest is not None else None
        self.raster: DisplacementRaster | None = None
        if "displacement" in self.inputs.kinds:
            if setup is None:
                raise LabrigError(f"{self.model.path} takes the markers' displacement field: build it with "
                                  "depth_sources.depth_source(..., setup=...)")
            self.raster = DisplacementRaster(setup.rest_px, setup.observed, setup.rig.roi)
        self.integrator: BrightnessIntegrator | None = None
        if self.needs_counts:
            if setup is None:
                raise LabrigError(f"{self.model.path} takes the brightness change since rest: build it with "
                                  "depth_sources.depth_source(..., setup=...)")
            self.integrator = BrightnessIntegrator(setup.rig.roi, self.inputs.brightness, thresholds=setup.thresholds)
        self.camera = setup.camera if setup is not None else None
        self.previous_norm = np.zeros(GRID_SHAPE, np.float32)
        self._positions_px: npt.NDArray[np.float64] | None = None
        self._rest_px: npt.NDArray[np.float64] | None = None
        self._rest_seen: npt.NDArray[np.float64] | None = None
        self._rest_mm: npt.NDArray[np.float64] | None = None
        self.at_rest = False

    def markers(self, positions_px: npt.NDArray[np.float64], rest_px: npt.NDArray[np.float64]) -> None:
        """This window's tracked marker positions (M, 2) px and the rest they are measured from."""
        self._positions_px, self._rest_px = positions_px, rest_px
        self.at_rest = self.gate(positions_px, rest_px) if self.gate is not None else False

    def counts(self, signed_counts: npt.NDArray[np.float32], t1_us: int) -> None:
        """This window's log-intensity change per grid cell in reference events
        (:func:`labrig.pipeline.brightness.signed_counts` with the setup's thresholds)."""
        if self.integrator is not None:
            self.integrator.add(signed_counts, t1_us)

    def depth_mm(self, sae_grid: npt.NDArray[np.float32] | None, t0_us: int, t1_us: int,
                 n_events: int) -> npt.NDArray[np.float32]:
        assert sae_grid is not None
        quiet = self.hold(n_events, t1_us - t0_us, sae_grid) if self.hold is not None else False  # every window feeds the floors
        if self.at_rest:
            self.reset(t1_us)
            return np.zeros(GRID_SHAPE, np.float32)
        if quiet:
            assert self.hold is not None
            return self.hold.held_mm
        depth = self.model.depth_mm(self.network_input(sae_grid))
        self.previous_norm = depth / np.float32(self.model.scale_mm)
        return self.hold.update(depth) if self.hold is not None else depth

    def network_input(self, sae_grid: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """The channels the card names for this window: the SAE, then the state."""
        if not self.inputs.stateful:
            return sae_grid
        bright = self.integrator.channel() if self.integrator is not None else None
        field = None
        if self.raster is not None:
            if self._positions_px is None or self._rest_px is None or self.camera is None:
                raise LabrigError(f"{self.model.name} takes the markers' displacement: the pipeline must call "
                                  "markers() before depth_mm()")
            if self._rest_px is not self._rest_seen:  # the rest changes only while the stream's first windows refine it
                self._rest_seen, self._rest_mm = self._rest_px, gel_plane_mm(self.camera, self._rest_px)
            field = self.raster(gel_plane_displacement_mm(self.camera, self._positions_px, self._rest_px, self._rest_mm))
        return network_input(self.inputs, sae_grid, field, self.previous_norm, bright)

    def reset(self, t_us: int | None = None) -> None:
        """Forget the held map, the previous estimate and the brightness change (the gel is at rest at ``t_us``)."""
        self.previous_norm = np.zeros(GRID_SHAPE, np.float32)
        if self.integrator is not None:
            self.integrator.reset(t_us)
        if self.hold is not None:
            self.hold.update(np.zeros(GRID_SHAPE, np.float32))


def quiet_params_for(card: dict[str, Any]) -> QuietParams | None:
    """The quiet-window gate for a network: the rate gate, plus per-tile activity when it was
    trained on noisy windows. A network trained clean draws dimples from a noisy SAE, so
    the more sensitive tile test would hand it more of them (measured in docs/evaluation.md).
    None (no hold) for a network that sees the brightness change since rest: the state is in its input."""
    if _sees_brightness(card):
        return None
    noise_trained = bool((card.get("augmentation") or {}).get("background_noise"))
    return replace(DEFAULT_QUIET, tiles=NOISE_TILES) if noise_trained else DEFAULT_QUIET


def rest_params_for(card: dict[str, Any]) -> RestGateParams | None:
    """The rest gate for a network: on for one that sees only the SAE (its quiet hold would keep a
    stale dent), off for one that sees the brightness change since rest. The gate reads the gel's
    rest from the markers alone, and a press at the gel's centre hardly moves them in the image
    (parallax only): the gate would zero the first 0.2-0.5 mm of such a press, and a light one
    whole. The brightness network's own input returns to rest with the gel; measured on the
    paper campaign's test split, it is better without the gate on every figure
    (docs/depthnet.md)."""
    if _sees_brightness(card):
        return None
    return DEFAULT_REST_GATE


def anchor_params_for(card: dict[str, Any]) -> AnchorParams:
    """The contact anchor's noise model for a network: its card's ``contact_anchor`` (fields of
    :class:`~labrig.pipeline.anchor.AnchorParams`) over the defaults, fitted for the bundled network."""
    fields = card.get("contact_anchor") or {}
    try:
        return replace(DEFAULT_ANCHOR, **fields)
    except TypeError as e:
        raise LabrigError(f"model card: contact_anchor has an unknown field ({e}); "
                          f"use {sorted(AnchorParams.__dataclass_fields__)}") from e


def _sees_brightness(card: dict[str, Any]) -> bool:
    """The card's network takes the brightness change since rest (its state is in its input)."""
    return "brightness" in ((card.get("inputs") or {}).get("kinds") or [])


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
        return ModelDepth(model_path or default_model_path(), threads=threads, quiet=quiet, setup=setup, rest=rest)
    raise LabrigError(f"depth source must be 'truth' or 'model', not {kind!r}")
