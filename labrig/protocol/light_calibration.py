"""The light's slope response, measured as a lab would: one press of known depth, its ground truth, the fit.

The calibration press (``protocols/slope-press.toml``, :data:`SLOPE_PRESS_PROTOCOL`): the standard
sphere at the gel's centre, 1.2 mm below contact, held 1 s, no shear. Its ground truth
(:func:`labrig.groundtruth.generate.generate`, from the rig's calibration, never the simulator's
truth) gives the surface slope per grid cell at every map; the events, summed per cell and
weighted by the camera's contrast thresholds, give the log-intensity change at the same instants;
:func:`labrig.calibration.slope_response.slope_response_of` finds the slope gain. The same press
and the same fit serve a lab's recording (``labrig calibrate events --press REC``), the virtual
rig's (:func:`record_slope_press`) and each camera a varied campaign gives its recordings
(:mod:`labrig.protocol.virtual_campaign`).
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from labrig.calibration.event_thresholds_file import ContrastThresholds, load_event_thresholds, write_event_thresholds
from labrig.calibration.slope_response import SlopeResponse, slope_response_of
from labrig.config import RigConfig
from labrig.errors import CalibrationError, LabrigError
from labrig.groundtruth.generate import generate
from labrig.indenters import Indenter
from labrig.protocol.files import PROTOCOLS_DIR, load_protocol
from labrig.protocol.runner import RunResult
from labrig.protocol.virtual_run import record_virtual

#: The calibration press: a sphere at the centre, 1.2 mm deep, held 1 s, no shear, from 1 mm above the surface.
SLOPE_PRESS_PROTOCOL = PROTOCOLS_DIR / "slope-press.toml"


def record_slope_press(out: str | Path, rig: RigConfig, indenter: Indenter, seed: int = 0) -> RunResult:
    """Record the calibration press (:data:`SLOPE_PRESS_PROTOCOL`) with ``indenter`` (the standard sphere) on the
    virtual rig ``rig`` in virtual time."""
    spec = load_protocol(SLOPE_PRESS_PROTOCOL)
    return record_virtual(spec, out, rig, indenter, seed=seed, protocol_toml=SLOPE_PRESS_PROTOCOL.read_text())


def measure_slope_response(press: str | Path, roi: Any, thresholds: ContrastThresholds | None,
                           calibration_dir: str | Path | None = None, rig_path: str | Path | None = None
                           ) -> SlopeResponse:
    """The slope gain of the light that recorded ``press`` (a probing recording of a known indenter), from its
    ground truth (``calibration_dir``, ``rig_path``: as ``labrig groundtruth`` takes them) and its events
    weighted by ``thresholds`` (None: nominal) over the network grid on ``roi``."""
    try:
        gt = generate(press, calibration_dir=calibration_dir, rig_path=rig_path)
    except LabrigError as exc:
        raise CalibrationError(f"{press}: no ground truth for the slope fit: {exc}") from None
    return slope_response_of(press, roi, thresholds, gt.t_us, gt.depth_mm, gt.indentation_mm, gt.grid_gel_mm)


def write_slope_response(events_path: str | Path, response: SlopeResponse, press: str | Path) -> Path:
    """Rewrite ``events.toml`` with its ``[shading]`` section set to ``response`` (the press named as its source)."""
    path = Path(events_path)
    thresholds = load_event_thresholds(path)
    data = tomllib.loads(path.read_text())
    summary = {"thresholds": {k: v for k, v in data["thresholds"].items() if k != "grid_shape"},
               "scene": data.get("scene", {}), "quality": data.get("quality", {}),
               "shading": {**response.summary(), "press": str(press)}}
    return write_event_thresholds(path, thresholds, summary, data.get("source", {}))
