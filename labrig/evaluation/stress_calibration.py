"""What a lab would calibrate before a stressed run: the extrinsics of an imperfectly printed gel, and the
contrast thresholds and the light's slope response of a sensor whose biases or light changed.

On a gel whose markers sit off their lattice sites or are missing, the pipeline must not be
told by the sim where they are: it learns it as a lab does, from an extrinsic calibration of
that gel. :func:`calibrate_printed_markers` records the LED ring blinking on the stressed
virtual rig (:func:`labrig.sim.calibration_scenes.record_led_blink`), calibrates the
extrinsics with the lab's intrinsics (:func:`labrig.calibration.extrinsics.calibrate_extrinsics`),
and writes a calibration folder: the lab's other files (intrinsics, gel, rig registration)
with this extrinsics.toml, whose marker map (measured rest positions, missing markers) the
pipeline then reads like any other. The sim's truth only scores the calibration afterwards
(:class:`MarkerCalibration`: missing markers found, rest error); nothing of it reaches the
pipeline.
"""

from __future__ import annotations

import shutil
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from labrig.calibration.event_thresholds import fit_event_thresholds
from labrig.calibration.event_thresholds_file import write_event_thresholds
from labrig.calibration.files import load_intrinsics
from labrig.calibration.slope_response import slope_response_of
from labrig.config import RigConfig
from labrig.dataset import sidecar_path
from labrig.errors import LabrigError
from labrig.evaluation.stress_scene import StressScene, record_scene, stressed_rig
from labrig.groundtruth.sidecar import load_groundtruth
from labrig.indenters import DEFAULT_INDENTERS
from labrig.sim.calibration_scenes import record_led_blink, record_led_ramps
from labrig.sim.imperfections import printed_markers
from labrig.sim.truth_config import sim_config, true_camera

EXTRINSICS = "extrinsics.toml"
EVENTS = "events.toml"
#: The calibration press's protocol (``labrig.protocol.light_calibration`` plays it through the procedure).
SLOPE_PRESS_PROTOCOL = DEFAULT_INDENTERS.parent / "slope-press.toml"


def calibration_press(scene: StressScene) -> StressScene:
    """``scene``'s sensor pressed as the calibration press: the protocol file's indenter, depth, speed and hold,
    no shear, and none of the scene's faults of timing or position."""
    press = tomllib.loads(SLOPE_PRESS_PROTOCOL.read_text())
    return replace(scene, indenter=press["probe"]["indenter"], depth_mm=press["normal"]["depth_mm"],
                   speed_mm_s=press["normal"]["speed_mm_s"], wait_s=press["wait"]["duration_s"], shear_mm=0.0,
                   dead_side_mm=0.0, sync_age_min=None, burst_period_ms=0.0, position_error_mm=0.0)


@dataclass(frozen=True)
class MarkerCalibration:
    """A calibration folder for a stressed gel and how well its marker map matches the printed markers."""

    directory: str  # the lab's calibration files with this gel's extrinsics.toml
    missing_true: tuple[int, ...]  # markers never printed (the sim's truth, for scoring only)
    missing_found: tuple[int, ...]  # markers the calibration found missing
    rest_error_rms_px: float  # measured rest of the printed markers against their true image positions, px
    residual_rms_mm: float  # the calibration's own report: measured less nominal on the gel, mm

    @property
    def found_all(self) -> bool:
        """Every missing marker found, and no printed one called missing."""
        return set(self.missing_true) == set(self.missing_found)


def calibrate_printed_markers(rig: RigConfig, calibration_dir: str | Path | None, out_dir: str | Path,
                              seed: int = 0) -> MarkerCalibration:
    """Calibrate the extrinsics of ``rig``'s gel as printed into ``out_dir`` (module docstring).

    ``calibration_dir`` supplies the intrinsics and the other files; every ``*.toml`` of it but
    the extrinsics is copied. ``seed``: the LED-blink scene's.
    """
    from labrig.calibration.extrinsics import calibrate_extrinsics, write_extrinsics

    source = Path(calibration_dir) if calibration_dir is not None else None
    if source is None or not (source / "intrinsics.toml").exists():
        raise LabrigError("the marker stress axes calibrate the printed gel as a lab would and need the camera's "
                          f"intrinsics: {source or 'no calibration folder'} has no intrinsics.toml "
                          "(run `labrig calibrate intrinsics`, or pass --calibration with one)")
    out = _calibration_copy(source, out_dir, but=EXTRINSICS)
    intrinsics = load_intrinsics(out / "intrinsics.toml")
    recording = out / "led-blink.h5"
    record_led_blink(recording, rig, seed=seed, overwrite=True)
    result = calibrate_extrinsics(recording, intrinsics, rig.markers, nominal_rotvec_rad=rig.camera.nominal_rotvec_rad)
    write_extrinsics(result, out / EXTRINSICS, intrinsics)
    recording.unlink()
    marker_map = result.marker_map
    printed = printed_markers(sim_config(rig).markers, rig.markers.rest_positions_mm(), rig.markers.diameter_mm)
    true_px = true_camera(rig).project(printed.rest_mm)
    both = printed.printed & ~marker_map.missing
    error = np.linalg.norm(marker_map.rest_px[both] - true_px[both], axis=1)
    summary = marker_map.summary(0)
    return MarkerCalibration(str(out), tuple(int(i) for i in printed.missing), tuple(marker_map.missing_indices),
                             float(np.sqrt(np.mean(error**2))) if error.size else float("nan"),
                             float(summary["residual_rms_mm"]))  # type: ignore[arg-type]


def calibrate_event_response(scene: StressScene, calibration_dir: str | Path | None, out_dir: str | Path) -> str:
    """Calibrate the contrast thresholds of the stressed camera and the slope response of its light into
    ``out_dir`` as a lab would after changing its biases or its light: the LED ramps
    (:func:`labrig.sim.calibration_scenes.record_led_ramps`,
    :func:`labrig.calibration.event_thresholds.fit_event_thresholds`), then the calibration press
    (``protocols/slope-press.toml``'s sphere, depth, speed and hold, recorded as a stress scene on the same
    sensor) against its ground truth (:func:`labrig.calibration.slope_response.slope_response_of`). The
    other ``*.toml`` of ``calibration_dir`` (or of ``out_dir`` when it is already a calibrated copy)
    stay. Returns ``out_dir``."""
    rig = stressed_rig(scene)
    out = _calibration_copy(Path(calibration_dir) if calibration_dir is not None else None, out_dir, but=EVENTS)
    recording = out / "led-ramps.h5"
    record_led_ramps(recording, rig, seed=scene.seed, overwrite=True)
    fit = fit_event_thresholds(recording, rig.roi)
    recording.unlink()
    press = out / "slope-press.h5"
    record_scene(calibration_press(scene), press)
    gt = load_groundtruth(sidecar_path(press))
    response = slope_response_of(press, rig.roi, fit.thresholds, gt.t_us, gt.depth_mm, gt.indentation_mm,
                                 gt.grid_gel_mm)
    summary = {**fit.summary(), "shading": {**response.summary(), "press": "stress scene"}}
    write_event_thresholds(out / EVENTS, fit.thresholds, summary, {"recording": "stress scene", "seed": scene.seed})
    press.unlink()
    sidecar_path(press).unlink()
    return str(out)


def _calibration_copy(source: Path | None, out_dir: str | Path, *, but: str) -> Path:
    """``out_dir`` (made) holding every ``*.toml`` of ``source`` but ``but``, the file about to be calibrated;
    files already there (an earlier calibration of the same scene) are kept."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if source is not None and source.resolve() != out.resolve():
        for path in source.glob("*.toml"):
            if path.name != but and not (out / path.name).exists():
                shutil.copy2(path, out / path.name)
    return out
