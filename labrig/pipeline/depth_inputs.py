"""The depth network's input contract: which channels it takes, and how the gel's state becomes channels.

A 10 ms SAE shows change, not state: a still dent makes no events. The tracker integrates
every marker's motion since rest, and the last depth estimate remembers the dent, so a
network may take, beside the SAE, channels that carry the state. The model card's
``inputs`` names them in order (absent: ``["sae"]``, the paper's network):

* ``sae`` (2 channels): the polarity-separated SAE of :func:`labrig.pipeline.sae.sae_grid`;
* ``displacement`` (2 channels): the markers' in-plane displacement since rest, x then y,
  on the gel plane z = 0 (each tracked and rest pixel back-projected through the camera),
  in units of ``displacement_scale_mm``, rasterised onto the 90 x 112 network grid by
  :class:`DisplacementRaster`;
* ``previous`` (1 channel): the source's previous depth estimate, normalised by the card's
  ``scale_mm`` (zeros at the start of a stream and at rest);
* ``brightness`` (1 channel): the membrane's brightness change since rest, the events'
  polarities integrated per grid cell (:mod:`labrig.pipeline.brightness`; the card's
  ``inputs.brightness`` holds its leak, unit and clip).

Every channel is zero-padded to 96 x 112 like the SAE (:func:`labrig.pipeline.sae.pad_for_unet`).
Training and inference build the channels with the same functions here.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig.config import Roi
from labrig.errors import LabrigError
from labrig.physics.camera import CameraModel
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.brightness import REFERENCE_SLOPE_GAIN, BrightnessParams
from labrig.pipeline.displacement import grid_coordinates
from labrig.pipeline.sae import UNET_SHAPE

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

#: Each input kind and its channels.
CHANNELS = {"sae": 2, "displacement": 2, "previous": 1, "brightness": 1}
#: The named input sets (``labrig train --inputs``), the comparison's variants.
INPUT_SETS = {"sae": ("sae",), "sae+disp": ("sae", "displacement"), "sae+disp+prev": ("sae", "displacement", "previous"),
              "sae+bright": ("sae", "brightness"), "sae+bright+disp": ("sae", "brightness", "displacement"),
              "sae+bright-hold": ("sae", "brightness"), "sae+bright-band": ("sae", "brightness")}
#: The brightness change integrated with the gated leak: a press held as long as it lasts
#: (:class:`~labrig.pipeline.brightness.BrightnessParams` ``rest_tau_s``; the held cells' own leak, 10 h, is
#: longer than any press), its cells counting events only while the press moves (``moving_ratio``: a still
#: press's events are noise), started again once a press is undone (``release_fraction``), under the reference
#: light (the camera's measured slope gain divided out); the other sets keep one 30 s leak and the light as it is.
HOLD_BRIGHTNESS = BrightnessParams(tau_s=36_000.0, rest_tau_s=0.5, floor_events_per_px=0.3, release_fraction=0.5,
                                   release_s=0.2, moving_ratio=2.0, reference_slope_gain=REFERENCE_SLOPE_GAIN)
#: The same, counted with the pixels' dead band undone (:mod:`labrig.pipeline.dead_band`): a press undone leaves
#: no ghost of its last band, which a dim light expressed under the reference light would magnify; with no ghost
#: to keep out, the hold's floor sits lower, holding the shallow flanks a dim light brightens less; and only a
#: brightening is expressed under the reference light (a marker's darkening is not the shading's).
BAND_BRIGHTNESS = replace(HOLD_BRIGHTNESS, dead_band=True, floor_events_per_px=0.12, brightening_only=True)
INPUT_BRIGHTNESS = {"sae+bright-hold": HOLD_BRIGHTNESS, "sae+bright-band": BAND_BRIGHTNESS}
#: Gel-plane displacement (mm) that makes one unit of a displacement channel.
DEFAULT_DISPLACEMENT_SCALE_MM = 1.0


@dataclass(frozen=True)
class InputSpec:
    """The channels a depth network takes, in order, the displacement channels' unit (mm) and the
    brightness channel's settings."""

    kinds: tuple[str, ...] = ("sae",)
    displacement_scale_mm: float = DEFAULT_DISPLACEMENT_SCALE_MM
    brightness: BrightnessParams = field(default_factory=BrightnessParams)

    def __post_init__(self) -> None:
        unknown = [k for k in self.kinds if k not in CHANNELS]
        if unknown or not self.kinds or self.kinds[0] != "sae" or len(set(self.kinds)) != len(self.kinds):
            raise LabrigError(f"depth-network inputs must start with sae and use each of {', '.join(CHANNELS)} "
                              f"at most once, not {list(self.kinds)}")
        if self.displacement_scale_mm <= 0:
            raise LabrigError("the displacement scale must be a positive number of mm")

    @classmethod
    def named(cls, name: str) -> InputSpec:
        """One of :data:`INPUT_SETS` (``sae``, ``sae+disp``, ``sae+disp+prev``, ``sae+bright``, ...), with its
        brightness settings (:data:`INPUT_BRIGHTNESS`, else the defaults)."""
        if name not in INPUT_SETS:
            raise LabrigError(f"--inputs must be one of {', '.join(INPUT_SETS)}, not {name!r}")
        return cls(INPUT_SETS[name], brightness=INPUT_BRIGHTNESS.get(name, BrightnessParams()))

    @classmethod
    def from_card(cls, card: dict[str, Any]) -> InputSpec:
        """The card's ``inputs`` (absent: the SAE alone, the cards written before inputs were named)."""
        inputs = card.get("inputs")
        if inputs is None:
            return cls()
        if not isinstance(inputs, dict) or not isinstance(inputs.get("kinds"), list):
            raise LabrigError(f"model card {card.get('name', '?')}: 'inputs' must hold a list of 'kinds'")
        return cls(tuple(str(k) for k in inputs["kinds"]),
                   float(inputs.get("displacement_scale_mm", DEFAULT_DISPLACEMENT_SCALE_MM)),
                   BrightnessParams.from_card(inputs.get("brightness")))

    def to_card(self) -> dict[str, Any]:
        card: dict[str, Any] = {"kinds": list(self.kinds), "channels": self.channels,
                                "displacement_scale_mm": self.displacement_scale_mm,
                                "description": "sae: OFF, ON; displacement: markers' gel-plane dx, dy since rest / "
                                               "displacement_scale_mm, rasterised on the grid; previous: last estimate / "
                                               "scale_mm; brightness: signed events per pixel since rest, leaky, less "
                                               "the median, / scale_events_per_px, clipped"}
        if "brightness" in self.kinds:
            card["brightness"] = self.brightness.to_card()
        return card

    @property
    def channels(self) -> int:
        return sum(CHANNELS[k] for k in self.kinds)

    @property
    def name(self) -> str:
        exact = [n for n in INPUT_SETS if InputSpec.named(n) == self]
        same_kinds = [n for n, kinds in INPUT_SETS.items() if kinds == self.kinds]
        return (exact or same_kinds or ["+".join(self.kinds)])[0]

    def channel_of(self, kind: str) -> int | None:
        """Index of the first channel of ``kind`` in the stacked input, None when the spec lacks it."""
        if kind not in self.kinds:
            return None
        return sum(CHANNELS[k] for k in self.kinds[:self.kinds.index(kind)])

    @property
    def stateful(self) -> bool:
        """Takes more than the SAE (needs the tracker's markers or its own last map)."""
        return len(self.kinds) > 1


class DisplacementRaster:
    """Markers' displacements (M, 2) onto the network grid: a normalised Gaussian splat.

    Each cell takes the Gaussian-weighted mean of the observed markers' values, weights by
    the cell's distance (grid cells) to each marker's rest on the grid, ``sigma`` the
    lattice pitch times ``sigma_pitch``. Missing markers have no weight, so their
    neighbours fill in; cells beyond the lattice take the nearest markers' values. The
    (cells x markers) weights are built once per rest.
    """

    def __init__(self, rest_px: npt.ArrayLike, observed: npt.ArrayLike | None, roi: Roi,
                 grid_shape: tuple[int, int] = GRID_SHAPE, sigma_pitch: float = 0.6) -> None:
        rest = np.asarray(rest_px, np.float64).reshape(-1, 2)
        self.observed = np.ones(len(rest), bool) if observed is None else np.asarray(observed, bool).reshape(-1)
        if self.observed.shape != (len(rest),) or not self.observed.any():
            raise LabrigError("the displacement raster needs one observed flag per marker and one observed marker")
        self.grid_shape = grid_shape
        rc = grid_coordinates(rest[self.observed], roi, grid_shape)
        pitch = _pitch(rc)
        sigma = max(sigma_pitch * pitch, 0.5)
        rows, cols = np.mgrid[0:grid_shape[0], 0:grid_shape[1]]
        cells = np.stack([rows.ravel(), cols.ravel()], axis=1).astype(np.float64)
        d2 = ((cells[:, None, :] - rc[None, :, :]) ** 2).sum(-1)
        logw = -d2 / (2.0 * sigma**2)
        logw -= logw.max(axis=1, keepdims=True)  # far cells: the nearest markers dominate, no underflow
        w = np.exp(logw)
        w[w < 1e-6] = 0.0
        self.weights = (w / w.sum(axis=1, keepdims=True)).astype(np.float32)  # (cells, observed markers)

    def __call__(self, values: npt.ArrayLike) -> F32:
        """(2, rows, cols) float32 of per-marker values (M, 2); missing markers' values are ignored."""
        v = np.asarray(values, np.float32).reshape(-1, 2)[self.observed]
        v = np.nan_to_num(v, nan=0.0)
        return np.ascontiguousarray((self.weights @ v).T.reshape(2, *self.grid_shape))


def _pitch(rc: F64) -> float:
    """Median nearest-neighbour distance between points (grid cells)."""
    if len(rc) < 2:
        return 1.0
    d2 = ((rc[:, None, :] - rc[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    return float(np.median(np.sqrt(d2.min(axis=1))))


def gel_plane_mm(camera: CameraModel, pixels: npt.ArrayLike) -> F64:
    """(M, 2) where the pixels (M, 2) see the gel plane z = 0 (gel frame, mm)."""
    return camera.backproject_to_plane(np.asarray(pixels, np.float64).reshape(-1, 2), 0.0)[:, :2]


def gel_plane_displacement_mm(camera: CameraModel, positions_px: npt.ArrayLike, rest_px: npt.ArrayLike,
                              rest_mm: F64 | None = None) -> F64:
    """(M, 2) in-plane displacement on the gel plane z = 0 (gel frame, mm): tracked minus rest, both back-projected
    (``rest_mm``: the rest's :func:`gel_plane_mm`, when already known)."""
    return gel_plane_mm(camera, positions_px) - (gel_plane_mm(camera, rest_px) if rest_mm is None else rest_mm)


def network_input(spec: InputSpec, sae: npt.ArrayLike, displacement: npt.ArrayLike | None = None,
                  previous_norm: npt.ArrayLike | None = None, brightness: npt.ArrayLike | None = None) -> F32:
    """The stacked, padded input (channels, 96, 112) for ``spec`` from its parts on the 90 x 112 grid.

    ``displacement``: (2, 90, 112) in mm (divided here by the spec's scale); ``previous_norm``:
    (90, 112) normalised depth; ``brightness``: (90, 112) the channel of
    :func:`labrig.pipeline.brightness.brightness_channel`. A part the spec names must be given.
    """
    out = np.zeros((spec.channels, *UNET_SHAPE), np.float32)
    top = (UNET_SHAPE[0] - GRID_SHAPE[0]) // 2  # the zero padding of :func:`~labrig.pipeline.sae.pad_for_unet`
    channel = 0
    for kind in spec.kinds:
        if kind == "sae":
            part = np.asarray(sae, np.float32)
        elif kind == "displacement":
            if displacement is None:
                raise LabrigError("this depth network takes the markers' displacement field; none was given")
            part = np.asarray(displacement, np.float32) / np.float32(spec.displacement_scale_mm)
        elif kind == "brightness":
            if brightness is None:
                raise LabrigError("this depth network takes the brightness change since rest; none was given")
            part = np.asarray(brightness, np.float32)[None]
        else:
            if previous_norm is None:
                raise LabrigError("this depth network takes its previous depth map; none was given")
            part = np.asarray(previous_norm, np.float32)[None]
        rows = slice(top, top + GRID_SHAPE[0]) if part.shape[-2] == GRID_SHAPE[0] else slice(None)
        out[channel:channel + len(part), rows] = part
        channel += len(part)
    return out
