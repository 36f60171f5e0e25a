"""``events.toml``: the camera's contrast thresholds per grid cell, and their loader.

An event fires each time a pixel's log intensity moves by its contrast threshold, ON and OFF
each their own: :class:`ContrastThresholds` holds both, in ln units, per cell of the network
grid (:mod:`labrig.physics.grid`, the cells of :func:`labrig.pipeline.sae.sae_grid`) over the
ROI they were measured on. ``events.toml`` holds the summary and the maps themselves (``[map]``
``on_ln``, ``off_ln``: rows of the grid, 5 significant digits), so the file travels alone like
every other calibration file. Without one every event counts as one of a sensor at
:data:`NOMINAL_THRESHOLD_LN` (the pipeline's thresholds are then None).

The file may also hold the membrane's shading response (``[shading]`` ``slope_gain``: how much
brighter the membrane looks per unit of surface slope, :mod:`labrig.calibration.slope_response`),
fitted from a press of known depth; without it the light is taken as the reference light.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import re
import tomllib
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from labrig import __version__
from labrig.calibration.files import save_text_atomic, toml_table
from labrig.config import Roi
from labrig.errors import CalibrationError

F32 = npt.NDArray[np.float32]

#: The IMX636's nominal contrast threshold, ln units (25 % Weber contrast: ln 1.25 = 0.223), and the
#: reference sensor's: the unit of the brightness channel's reference events.
NOMINAL_THRESHOLD_LN = 0.22
EVENTS_FORMAT_VERSION = 1
EVENTS_FILE = "events.toml"


@dataclass(frozen=True, eq=False)
class ContrastThresholds:
    """ON and OFF contrast thresholds ``on_ln``, ``off_ln`` (rows, cols) float32, ln intensity per event,
    per cell of the network grid over ``roi`` (sensor px); ``source``: where they came from; ``slope_gain``
    (dimensionless; None: not measured): the membrane's shading response of the same sensor."""

    on_ln: F32
    off_ln: F32
    roi: Roi
    source: str = "nominal"
    slope_gain: float | None = None

    def __post_init__(self) -> None:
        if self.on_ln.shape != self.off_ln.shape or self.on_ln.ndim != 2:
            raise CalibrationError(f"{self.source}: the ON and OFF threshold maps must be 2-D of one shape")
        if not (np.isfinite(self.on_ln).all() and np.isfinite(self.off_ln).all()
                and (self.on_ln > 0).all() and (self.off_ln > 0).all()):
            raise CalibrationError(f"{self.source}: every contrast threshold must be finite and positive; "
                                   "recalibrate with `labrig calibrate events`")
        if self.slope_gain is not None and not (np.isfinite(self.slope_gain) and self.slope_gain > 0):
            raise CalibrationError(f"{self.source}: the slope gain must be a positive number, not {self.slope_gain!r}; "
                                   "recalibrate with `labrig calibrate events`")

    @cached_property
    def reference_weights(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Flat per-cell weights of an ON and an OFF event in reference events: ``C_on / C_nominal`` and
        ``-C_off / C_nominal`` (:data:`NOMINAL_THRESHOLD_LN`)."""
        return (self.on_ln.ravel().astype(np.float64) / NOMINAL_THRESHOLD_LN,
                -self.off_ln.ravel().astype(np.float64) / NOMINAL_THRESHOLD_LN)

    def digest(self) -> str:
        """A short SHA-256 of the maps and the ROI (cache keys)."""
        h = hashlib.sha256(np.ascontiguousarray(self.on_ln).tobytes() + np.ascontiguousarray(self.off_ln).tobytes())
        h.update(repr((self.roi.x0_px, self.roi.y0_px, self.roi.x1_px, self.roi.y1_px)).encode())
        return h.hexdigest()[:16]

    def check_roi(self, roi: Roi) -> None:
        """Refuse a run whose ROI is not the one the thresholds were measured on."""
        mine = (self.roi.x0_px, self.roi.y0_px, self.roi.x1_px, self.roi.y1_px)
        theirs = (roi.x0_px, roi.y0_px, roi.x1_px, roi.y1_px)
        if mine != theirs:
            raise CalibrationError(f"{self.source}: measured on the ROI {mine}, the rig's is {theirs}; "
                                   "recalibrate with `labrig calibrate events`")


def write_event_thresholds(path: str | Path, thresholds: ContrastThresholds, summary: dict[str, Any],
                           provenance: dict[str, Any]) -> Path:
    """Write ``events.toml`` (``summary``: the [thresholds], [scene] and [quality] figures, and [shading] when
    the slope response was fitted) with its maps, through a temporary file."""
    roi = thresholds.roi

    def rows(values: F32) -> str:
        return "[\n" + "".join("    [" + ", ".join(f"{v:.5g}" for v in row) + "],\n" for row in values) + "]"

    text = (
        "# Contrast thresholds per network-grid cell, fitted by `labrig calibrate events` (labrig.calibration.event_thresholds)\n"
        "# from the LED ring dimmed and brightened along ramps; ln intensity per event. docs/calibration.md.\n"
        f"format_version = {EVENTS_FORMAT_VERSION}\n"
        f'date = "{_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")}"\n'
        f'labrig_version = "{__version__}"\n\n'
        + toml_table("thresholds", {**summary["thresholds"], "grid_shape": list(thresholds.on_ln.shape)})
        + "\n" + toml_table("roi", {"x0_px": roi.x0_px, "y0_px": roi.y0_px, "x1_px": roi.x1_px, "y1_px": roi.y1_px})
        + "\n" + toml_table("scene", summary["scene"])
        + "\n" + toml_table("quality", summary["quality"])
        + ("\n" + toml_table("shading", summary["shading"]) if summary.get("shading") else "")
        + "\n" + toml_table("source", provenance)
        + f"\n[map]  # per cell, row-major over the ROI: the ON and OFF thresholds, ln\non_ln = {rows(thresholds.on_ln)}\n"
        + f"off_ln = {rows(thresholds.off_ln)}\n"
    )
    return save_text_atomic(path, text)


_MAP_TABLE = re.compile(r"^\[map\][^\n]*\n(?P<body>(?:[^\[\n][^\n]*\n|\s*\[[^\n]*\n|\][^\n]*\n?)*)\Z", re.M)
_MAP_ARRAY = re.compile(r"^(on_ln|off_ln) = \[\n((?:    \[[^\]\n]*\],\n)*)\]$", re.M)
_NUMBER_SEPARATORS = str.maketrans("[],", "   ")


def _parse(text: str) -> dict[str, Any]:
    """The file as TOML; the two maps, when the file ends with ``[map]`` as :func:`write_event_thresholds` writes
    it, read by numpy (tomllib takes about 0.3 s over 20,000 numbers), else by tomllib like the rest."""
    table = _MAP_TABLE.search(text)
    arrays = {m.group(1): m.group(2) for m in _MAP_ARRAY.finditer(table.group("body"))} if table else {}
    if table is None or set(arrays) != {"on_ln", "off_ln"}:
        return tomllib.loads(text)
    data = tomllib.loads(text[:table.start()])
    try:
        data["map"] = {name: [np.array(line.translate(_NUMBER_SEPARATORS).split(), np.float32)
                              for line in body.splitlines()] for name, body in arrays.items()}
    except ValueError:
        return tomllib.loads(text)
    return data


def load_event_thresholds(path: str | Path) -> ContrastThresholds:
    """The thresholds of an ``events.toml``."""
    path = Path(path)
    try:
        data = _parse(path.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"{path}: no event calibration; run `labrig calibrate events`") from None
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(f"{path}: not valid TOML ({exc})") from None
    version = data.get("format_version")
    if version != EVENTS_FORMAT_VERSION:
        raise CalibrationError(f"{path}: format_version {version!r} is not one this labrig reads "
                               f"({EVENTS_FORMAT_VERSION}); recalibrate with `labrig calibrate events`")
    try:
        r, shape = data["roi"], tuple(int(v) for v in data["thresholds"]["grid_shape"])
        roi = Roi(int(r["x0_px"]), int(r["y0_px"]), int(r["x1_px"]), int(r["y1_px"]))
        on = np.asarray(data["map"]["on_ln"], np.float32)
        off = np.asarray(data["map"]["off_ln"], np.float32)
        shading = data.get("shading")
        slope_gain = None if shading is None else float(shading["slope_gain"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: missing or malformed key {exc}; recalibrate with `labrig calibrate events`") from None
    if on.shape != shape or off.shape != shape:
        raise CalibrationError(f"{path}: [map] on_ln and off_ln must be {shape} (grid_shape), not {on.shape} and "
                               f"{off.shape}; recalibrate with `labrig calibrate events`")
    return ContrastThresholds(on, off, roi, str(path), slope_gain)
