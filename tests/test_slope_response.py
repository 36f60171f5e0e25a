"""The light's slope response (``labrig calibrate events --press``): the slope of a depth map, the fit, the
file, the calibration press on the virtual rig, and the brightness channel it puts under the reference light."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from labrig.calibration.event_thresholds_file import ContrastThresholds, load_event_thresholds
from labrig.calibration.slope_response import fit_slope_gain, surface_slope
from labrig.config import DEFAULT_CALIBRATION_DIR, RigConfig, rig_with
from labrig.errors import CalibrationError
from labrig.indenters import Indenter
from labrig.physics.grid import GRID_SHAPE
from labrig.physics.mechanics import ContactTable
from labrig.pipeline import run_setup
from labrig.pipeline.brightness import (
    REFERENCE_SLOPE_GAIN,
    BrightnessIntegrator,
    BrightnessParams,
    brightness_channel,
    reference_light,
)
from labrig.protocol.light_calibration import measure_slope_response, record_slope_press, write_slope_response

CALIBRATION = Path(DEFAULT_CALIBRATION_DIR)


def _grid(rows: int = 30, cols: int = 40, angle_rad: float = 0.4, sx: float = 0.11, sy: float = 0.07) -> np.ndarray:
    """A rotated, anisotropic grid of gel points (rows, cols, 2), mm."""
    i, j = np.mgrid[0:rows, 0:cols].astype(np.float64)
    u, v = j * sx, i * sy
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.stack([c * u - s * v + 3.0, s * u + c * v - 1.0], axis=-1)


def test_the_slope_of_a_plane_is_its_gradient_on_any_grid() -> None:
    xy = _grid()
    depth = 0.3 * xy[..., 0] - 0.4 * xy[..., 1] + 2.0
    assert np.allclose(surface_slope(depth, xy), 0.5, atol=1e-9)
    with pytest.raises(CalibrationError, match="must be"):
        surface_slope(depth, xy[:, :-1])


def _dome(xy: np.ndarray, centre: tuple[float, float], depth_mm: float, radius_mm: float = 1.2) -> np.ndarray:
    r2 = (xy[..., 0] - centre[0]) ** 2 + (xy[..., 1] - centre[1]) ** 2
    return depth_mm * np.exp(-r2 / radius_mm**2)


@pytest.mark.parametrize("gain", [1.0, 2.3, 4.0])
def test_the_fit_finds_the_gain_of_a_noisy_shading(gain: float) -> None:
    xy = _grid(60, 80, sx=0.08, sy=0.08)
    depth = np.stack([_dome(xy, (5.0, 1.5), d) for d in (0.5, 0.9, 1.3)])
    slope = np.stack([surface_slope(d, xy) for d in depth])
    rng = np.random.default_rng(0)
    change = np.log1p(gain * slope) + rng.normal(0.0, 0.05, slope.shape)
    fit = fit_slope_gain(change, depth, xy)
    assert fit.slope_gain == pytest.approx(gain, rel=0.03)
    assert fit.rms_ln == pytest.approx(0.05, rel=0.15) and fit.maps == 3 and fit.cells > 200


def test_the_fit_refuses_a_press_too_shallow_or_events_that_do_not_follow_it() -> None:
    xy = _grid(60, 80, sx=0.08, sy=0.08)
    shallow = _dome(xy, (5.0, 1.5), 0.01)[None]
    with pytest.raises(CalibrationError, match="sloped the membrane in"):
        fit_slope_gain(np.zeros_like(shallow), shallow, xy)
    deep = _dome(xy, (5.0, 1.5), 1.0)[None]
    with pytest.raises(CalibrationError, match="ran to its bound"):
        fit_slope_gain(np.zeros_like(deep), deep, xy)
    with pytest.raises(CalibrationError, match="one shape"):
        fit_slope_gain(np.zeros((1, 5, 5)), deep, xy)


def test_the_reference_light_turns_one_lights_shading_into_the_others() -> None:
    slope = np.linspace(0.0, 1.5, 50)
    for gain in (1.0, 3.7):
        assert np.allclose(reference_light(np.log1p(gain * slope), gain, 2.3), np.log1p(2.3 * slope), atol=1e-5)
    change = np.array([-0.4, 0.0, 0.7])
    assert np.allclose(reference_light(change, 2.3, 2.3), change, atol=1e-6)
    assert reference_light(np.array([-3.0]), 1.0, 4.0, floor_ln=-2.5)[0] == pytest.approx(-2.5)  # 1 + 4(e^-3 - 1) < 0


def test_brightening_only_leaves_a_markers_darkening_as_it_is() -> None:
    """A darkening is a marker leaving its place: the shading cannot make it, and one light's does not scale it."""
    change = np.array([-2.0, -0.3, 0.0, 0.4])
    for gain in (1.0, 4.0):
        converted = reference_light(change, gain, 2.4, brightening_only=True)
        assert np.allclose(converted[:2], change[:2]) and converted[2] == 0.0
        assert converted[3] == pytest.approx(np.log1p((2.4 / gain) * np.expm1(0.4)), rel=1e-5)
        assert not np.allclose(reference_light(change, gain, 2.4)[:2], change[:2])  # the shading's model scales them
    params = BrightnessParams(reference_slope_gain=2.4, brightening_only=True, dead_band=True)
    assert BrightnessParams.from_card(params.to_card()) == params


def test_the_channel_changes_the_light_only_when_the_network_and_the_calibration_both_ask() -> None:
    counts = np.zeros(GRID_SHAPE, np.float32)
    counts[40:50, 50:60] = 30.0
    plain = BrightnessParams(tau_s=3600.0)
    referenced = BrightnessParams(tau_s=3600.0, reference_slope_gain=REFERENCE_SLOPE_GAIN)
    base = brightness_channel(counts, 10.0, plain)
    assert np.array_equal(brightness_channel(counts, 10.0, plain, slope_gain=1.0), base)
    assert np.array_equal(brightness_channel(counts, 10.0, referenced, slope_gain=None), base)
    dimmer = brightness_channel(counts, 10.0, referenced, slope_gain=2 * REFERENCE_SLOPE_GAIN)
    assert 0.4 < dimmer[45, 55] / base[45, 55] < 0.6 and dimmer[0, 0] == 0.0
    assert BrightnessParams.from_card(referenced.to_card()) == referenced
    assert "reference_slope_gain" not in plain.to_card()


# -- the calibration press on the virtual rig ------------------------------------------------------------

#: The slope gain of the dim light the press is recorded under (the reference sensor's is 2.5).
DIM_GAIN = 1.5


@pytest.fixture(scope="module")
def dim_press(rig: RigConfig, sphere: Indenter, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, RigConfig]:
    """The calibration press recorded under a light of slope gain DIM_GAIN."""
    dim = rig_with(rig, {"sim.lighting.slope_gain": DIM_GAIN})
    path = tmp_path_factory.mktemp("light") / "press.h5"
    assert record_slope_press(path, dim, sphere, seed=2).exit_status == "complete"
    return path, dim


def test_the_press_measures_the_lights_gain_against_the_reference_sensors(dim_press: tuple[Path, RigConfig]) -> None:
    """The fit's model is not the renderer's exactly, so the measured gains are compared as a ratio: the dim
    light's over the shipped calibration's (the reference light, measured by the same press)."""
    path, dim = dim_press
    reference = load_event_thresholds(CALIBRATION / "events.toml")
    assert reference.slope_gain is not None
    fit = measure_slope_response(path, dim.roi, reference, CALIBRATION)
    assert fit.slope_gain / reference.slope_gain == pytest.approx(DIM_GAIN / 2.5, rel=0.06)
    assert fit.rms_ln < 0.2


def _pressed_channel(rig: RigConfig, sphere: Indenter, table: ContactTable, slope_gain: float) -> np.ndarray:
    """The channel under the reference light after a sphere pressed 1 mm at the centre on ``rig``."""
    from labrig.sim.motion import probing_path
    from labrig.sim.rig import VirtualRig

    vr = VirtualRig(rig, sphere, seed=5, table=table)
    path = probing_path(rig, sphere, depth_mm=1.0, shear_mm=0.0, wait_s=0.1, normal_speed_mm_s=3.0)
    hold_end = next(t1 for name, _t0, t1 in path.phases if name == "wait")
    own = ContrastThresholds(np.full(GRID_SHAPE, 0.22, np.float32), np.full(GRID_SHAPE, 0.22, np.float32), rig.roi,
                             "own", slope_gain)
    params = BrightnessParams(tau_s=3600.0, reference_slope_gain=REFERENCE_SLOPE_GAIN)
    integrator = BrightnessIntegrator(rig.roi, params, thresholds=own)
    t = 0
    while t < hold_end:
        t = min(t + 50_000, int(hold_end))
        integrator.add_events(vr.advance(t, path).events, t)
    return integrator.channel()


def test_under_the_reference_light_two_lights_give_one_channel(rig: RigConfig, sphere: Indenter,
                                                                table: ContactTable) -> None:
    """The same press under the reference light and a dim one: the raw channels differ by the lights' ratio,
    the channels under the reference light (each light's gain divided out) do not."""
    dim = rig_with(rig, {"sim.lighting.slope_gain": DIM_GAIN})
    reference = _pressed_channel(rig, sphere, table, 2.5)
    dent = np.abs(reference) > 0.3
    assert dent.sum() > 50
    raw = _pressed_channel(dim, sphere, table, REFERENCE_SLOPE_GAIN)  # the dim light taken as the reference
    corrected = _pressed_channel(dim, sphere, table, DIM_GAIN)

    def gain(channel: np.ndarray) -> float:
        return float(np.sum(channel[dent] * reference[dent]) / np.sum(reference[dent] ** 2))

    assert gain(raw) < 0.8
    assert gain(corrected) == pytest.approx(1.0, abs=0.1)


def _labrig(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "labrig.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


def test_the_command_fits_a_labs_press_into_events_toml(dim_press: tuple[Path, RigConfig], tmp_path: Path) -> None:
    path, dim = dim_press
    folder = tmp_path / "cal"
    shutil.copytree(CALIBRATION, folder)
    (folder / "rig.toml").write_text(dim.text)
    events = folder / "events.toml"
    thresholds_before = load_event_thresholds(events)
    missing = _labrig("calibrate", "events", "--press", tmp_path / "nope.h5", "--rig", folder / "rig.toml",
                      "--out", tmp_path / "x.toml")
    assert missing.returncode == 2 and "nope.h5" in missing.stderr and "Traceback" not in missing.stderr
    written = write_slope_response(events, measure_slope_response(path, dim.roi, thresholds_before, folder), path)
    loaded = load_event_thresholds(written)
    reference = load_event_thresholds(CALIBRATION / "events.toml").slope_gain
    assert loaded.slope_gain is not None and reference is not None
    assert loaded.slope_gain / reference == pytest.approx(DIM_GAIN / 2.5, rel=0.06)
    assert np.array_equal(loaded.on_ln, thresholds_before.on_ln) and loaded.digest() == thresholds_before.digest()
    setup = run_setup.setup_for_rig(dim, calibration_dir=folder)
    assert setup.thresholds is not None and setup.thresholds.slope_gain == loaded.slope_gain
    assert setup.sources["slope_gain"].startswith(f"{loaded.slope_gain:.3g} (")
    text = events.read_text()
    events.write_text(text.replace(f"slope_gain = {loaded.slope_gain:.5g}", "slope_gain = -1.0"))
    with pytest.raises(CalibrationError, match="slope gain must be a positive number"):
        load_event_thresholds(events)
