"""Contrast thresholds per grid cell (``labrig calibrate events``): the LED-ramp scene, the fit, its file, the
command, and the brightness channel they put in physical units."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from labrig.calibration.event_thresholds import fit_event_thresholds, thresholds_from_counts
from labrig.calibration.event_thresholds_file import (
    NOMINAL_THRESHOLD_LN,
    ContrastThresholds,
    load_event_thresholds,
    write_event_thresholds,
)
from labrig.config import RigConfig, Roi, rig_with
from labrig.errors import CalibrationError
from labrig.eventtypes import EVENT_DTYPE
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline import run_setup
from labrig.pipeline.brightness import BrightnessIntegrator, BrightnessParams, brightness_channel, signed_counts
from labrig.sim.calibration_scenes import LedRamps, record_led_ramps

#: A small ROI (the scene's cost goes with its pixels); the grid's cells are then about 2 x 2 pixels.
SMALL_ROI = {"roi.x0_px": 500, "roi.y0_px": 250, "roi.x1_px": 724, "roi.y1_px": 430}
SHORT_RAMPS = LedRamps(cycles=6)


def _labrig(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "labrig.cli", *map(str, args)], capture_output=True, text=True, timeout=120)


def _sensor(rig: RigConfig, on: float, off: float) -> RigConfig:
    return rig_with(rig, {**SMALL_ROI, "sim.events.threshold_on": on, "sim.events.threshold_off": off})


@pytest.fixture(scope="module")
def asymmetric_scene(rig: RigConfig, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, RigConfig]:
    """The LED-ramp scene on a camera less sensitive to ON than to OFF (0.30 / 0.20)."""
    sensor = _sensor(rig, 0.30, 0.20)
    path = tmp_path_factory.mktemp("events") / "ramps.h5"
    record_led_ramps(path, sensor, seed=3, ramps=SHORT_RAMPS)
    return path, sensor


@pytest.mark.parametrize(("c_on", "c_off"), [(0.22, 0.22), (0.30, 0.20), (0.15, 0.40)])
def test_the_counts_model_inverts(c_on: float, c_off: float) -> None:
    """Counts made by the model (n C = A - (C_on + C_off) / 2) give the thresholds back."""
    amplitude = np.log(3.0)
    n_on = (amplitude - (c_on + c_off) / 2) / c_on
    n_off = (amplitude - (c_on + c_off) / 2) / c_off
    got_on, got_off = thresholds_from_counts(n_on, n_off, amplitude)
    assert got_on == pytest.approx(c_on) and got_off == pytest.approx(c_off)


def test_the_scene_gives_each_polarity_its_threshold(asymmetric_scene: tuple[Path, RigConfig]) -> None:
    """The fit recovers 0.30 / 0.20 per cell (threshold spread 0.03 per pixel, four pixels a cell) and their
    ratio; counting events alone (one threshold for both) could not tell them apart."""
    path, sensor = asymmetric_scene
    fit = fit_event_thresholds(path, sensor.roi)
    assert fit.on_ln_median == pytest.approx(0.30, rel=0.04)
    assert fit.off_ln_median == pytest.approx(0.20, rel=0.04)
    assert fit.on_off_ratio == pytest.approx(1.5, rel=0.05)
    assert fit.thresholds.on_ln.shape == GRID_SHAPE and fit.cells_filled == 0
    assert fit.ramps_used == 2 * SHORT_RAMPS.cycles - 2  # the first cycle settles the references


def test_the_file_round_trips_and_refuses_a_malformed_map(asymmetric_scene: tuple[Path, RigConfig], tmp_path: Path) -> None:
    path, sensor = asymmetric_scene
    fit = fit_event_thresholds(path, sensor.roi)
    toml_path = write_event_thresholds(tmp_path / "events.toml", fit.thresholds, fit.summary(), {"recording": str(path)})
    back = load_event_thresholds(toml_path)
    assert np.allclose(back.on_ln, fit.thresholds.on_ln, rtol=1e-4) and np.allclose(back.off_ln, fit.thresholds.off_ln, rtol=1e-4)
    assert back.roi == sensor.roi
    with pytest.raises(CalibrationError, match="ROI"):
        back.check_roi(Roi(0, 0, 1280, 720))
    text = toml_path.read_text()
    toml_path.write_text(text.replace("grid_shape = [90, 112]", "grid_shape = [90, 111]"))
    with pytest.raises(CalibrationError, match="grid_shape"):
        load_event_thresholds(toml_path)
    toml_path.write_text(text.replace("[map]", "[maps]"))
    with pytest.raises(CalibrationError, match="malformed"):
        load_event_thresholds(toml_path)
    # the maps as a person might edit them (one line, a comment, a table after them) read the same through tomllib
    head, maps = text.split("[map]")
    on_rows = "[" + ", ".join("[" + ", ".join(f"{v:.5g}" for v in row) + "]" for row in back.on_ln) + "]"
    off_rows = maps.split("off_ln = ")[1]
    edited = f"{head}[map]\n# edited\non_ln = {on_rows}\noff_ln = {off_rows}\n[extra]\nnote = 1\n"
    toml_path.write_text(edited)
    again = load_event_thresholds(toml_path)
    np.testing.assert_array_equal(again.on_ln, back.on_ln)
    np.testing.assert_array_equal(again.off_ln, back.off_ln)
    toml_path.write_text(text.replace("    [", "    [1, ", 1))  # a row longer than the rest
    with pytest.raises(CalibrationError, match="malformed"):
        load_event_thresholds(toml_path)


def test_a_recording_without_the_ramps_is_refused_in_one_line(small_recording: Path) -> None:
    with pytest.raises(CalibrationError, match="not an event-response recording"):
        fit_event_thresholds(small_recording, Roi(276, 22, 1004, 694))


def test_the_command_writes_the_files_and_never_replaces_the_default_unasked(
        asymmetric_scene: tuple[Path, RigConfig], tmp_path: Path) -> None:
    path, sensor = asymmetric_scene
    folder = tmp_path / "cal"
    folder.mkdir()
    rig_file = folder / "rig.toml"
    rig_file.write_text(sensor.text)
    first = _labrig("calibrate", "events", path, "--rig", rig_file, "--plot", tmp_path / "thresholds.png", "--json")
    assert first.returncode == 0, first.stderr
    summary = json.loads(first.stdout)
    assert summary["path"] == str(folder / "events.toml")
    first_text = (folder / "events.toml").read_text()
    assert Path(summary["plot"]).stat().st_size > 10_000
    assert {"on_ln_median", "off_ln_median", "on_off_ratio", "pixels_rejected", "cells_filled",
            "dim_light_warning"} <= summary.keys()
    again = _labrig("calibrate", "events", path, "--rig", rig_file)
    assert again.returncode == 2 and "--force" in again.stderr and "Traceback" not in again.stderr
    assert len(again.stderr.strip().splitlines()) == 1
    forced = _labrig("calibrate", "events", path, "--rig", rig_file, "--force", "--json")
    assert forced.returncode == 0, forced.stderr
    assert json.loads(forced.stdout)["backup"] == str(folder / "events.toml.bak")
    assert (folder / "events.toml.bak").read_text() == first_text  # the previous calibration, kept
    setup = run_setup.setup_for_rig(sensor, calibration_dir=folder)
    assert setup.thresholds is not None and setup.sources["thresholds"] == str(folder / "events.toml")


def test_calibrated_counts_weigh_each_event_by_its_threshold() -> None:
    """An ON event counts C_on / 0.22 reference events, an OFF event C_off / 0.22; no thresholds: one each."""
    roi = Roi(276, 22, 1004, 694)
    on = np.full(GRID_SHAPE, 0.33, np.float32)
    off = np.full(GRID_SHAPE, 0.11, np.float32)
    thresholds = ContrastThresholds(on, off, roi, "test")
    ev = np.zeros(4, EVENT_DTYPE)
    ev["x"], ev["y"], ev["p"], ev["t"] = [600, 600, 600, 900], [300, 300, 300, 500], [1, 1, 0, 0], [1, 2, 3, 4]
    weighted = signed_counts(ev, roi, thresholds=thresholds)
    plain = signed_counts(ev, roi)
    assert plain.sum() == 0.0
    assert weighted.sum() == pytest.approx((2 * 0.33 - 2 * 0.11) / NOMINAL_THRESHOLD_LN, rel=1e-6)
    integrator = BrightnessIntegrator(roi, thresholds=thresholds)
    assert np.allclose(integrator.add_events(ev, 10), weighted)


def _pressed_change(rig: RigConfig, sphere, table, thresholds: ContrastThresholds | None) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The brightness channel after a sphere pressed 1 mm at the centre (held, no shear) on ``rig``."""
    from labrig.sim.motion import probing_path
    from labrig.sim.rig import VirtualRig

    vr = VirtualRig(rig, sphere, seed=5, table=table)
    path = probing_path(rig, sphere, depth_mm=1.0, shear_mm=0.0, wait_s=0.1, normal_speed_mm_s=3.0)
    hold_end = next(t1 for name, _t0, t1 in path.phases if name == "wait")
    integrator = BrightnessIntegrator(rig.roi, thresholds=thresholds)
    t = 0
    while t < hold_end:
        t = min(t + 50_000, int(hold_end))
        integrator.add_events(vr.advance(t, path).events, t)
    return brightness_channel(integrator.counts, integrator.pixels_per_cell, BrightnessParams())


def test_the_calibrated_channel_does_not_move_with_the_cameras_thresholds(rig: RigConfig, sphere, table) -> None:  # type: ignore[no-untyped-def]
    """The same press seen by a camera at 0.22 and one at 0.30 / 0.26: the event counts differ by the
    thresholds' ratio, the calibrated channel (each camera's own thresholds) does not."""
    reference = _pressed_change(rig, sphere, table, None)
    dull = rig_with(rig, {"sim.events.threshold_on": 0.30, "sim.events.threshold_off": 0.26})
    dent = np.abs(reference) > 0.3
    assert dent.sum() > 50
    counted = _pressed_change(dull, sphere, table, None)
    own = ContrastThresholds(np.full(GRID_SHAPE, 0.30, np.float32), np.full(GRID_SHAPE, 0.26, np.float32), rig.roi, "own")
    calibrated = _pressed_change(dull, sphere, table, own)

    def gain(channel: np.ndarray) -> float:
        return float(np.sum(channel[dent] * reference[dent]) / np.sum(reference[dent] ** 2))

    assert gain(counted) < 0.85  # fewer events for the same change
    assert gain(calibrated) == pytest.approx(1.0, abs=0.08)
