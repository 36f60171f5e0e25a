"""Camera calibration from events on the virtual rig, scored against the sim's true camera (`true_camera(rig)`)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from labrig.calibration.extrinsics import associate_grid, calibrate_extrinsics, write_extrinsics
from labrig.calibration.files import Intrinsics, load_camera, load_extrinsics, load_intrinsics
from labrig.calibration.intrinsics import IntrinsicsResult, calibrate_intrinsics, intrinsics_from_result, write_intrinsics
from labrig.config import RigConfig, load_rig
from labrig.errors import CalibrationError
from labrig.frames import rotvec_to_matrix
from labrig.physics.camera import CameraModel, distort_normalized
from labrig.sim.calibration_scenes import record_led_blink, record_target_scene
from labrig.sim.truth_config import true_camera

N_VIEWS = 10


@pytest.fixture(scope="module")
def rig() -> RigConfig:
    return load_rig()


@pytest.fixture(scope="module")
def truth(rig: RigConfig) -> CameraModel:
    return true_camera(rig)


@pytest.fixture(scope="module")
def scenes(rig: RigConfig, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The two scene recordings, made once for the module."""
    root = tmp_path_factory.mktemp("calibration")
    target = record_target_scene(root / "target.h5", rig, n_views=N_VIEWS, seed=0).path
    led = record_led_blink(root / "led.h5", rig, seed=0).path
    return {"target": target, "led": led, "root": root}


@pytest.fixture(scope="module")
def intrinsics_result(scenes: dict[str, Path]) -> IntrinsicsResult:
    return calibrate_intrinsics(scenes["target"])


@pytest.fixture(scope="module")
def intrinsics(intrinsics_result: IntrinsicsResult, scenes: dict[str, Path]) -> Intrinsics:
    path = write_intrinsics(intrinsics_result, scenes["root"] / "intrinsics.toml")
    return load_intrinsics(path)


def test_intrinsics_recover_the_true_camera(intrinsics: Intrinsics, intrinsics_result: IntrinsicsResult,
                                            truth: CameraModel) -> None:
    for key in ("fx_px", "fy_px", "cx_px", "cy_px"):
        assert getattr(intrinsics, key) == pytest.approx(getattr(truth, key), rel=0.005), key
    assert intrinsics_result.rms_px < 0.3
    assert intrinsics.n_views >= 8


def test_distortion_error_over_the_gel_region_is_below_a_tenth_of_a_pixel(intrinsics: Intrinsics, truth: CameraModel,
                                                                          rig: RigConfig) -> None:
    roi = rig.roi
    u, v = np.meshgrid(np.linspace(roi.x0_px, roi.x1_px - 1, 30), np.linspace(roi.y0_px, roi.y1_px - 1, 30))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    normalized = truth.pixels_to_normalized(pixels)
    # The recovered distortion applied through the true pinhole: only the distortion's error remains.
    distorted = distort_normalized(normalized, intrinsics.distortion)
    mapped = np.stack([truth.fx_px * distorted[:, 0] + truth.cx_px, truth.fy_px * distorted[:, 1] + truth.cy_px], axis=1)
    assert np.linalg.norm(mapped - pixels, axis=1).max() < 0.1


def test_extrinsics_with_the_recovered_intrinsics(scenes: dict[str, Path], intrinsics: Intrinsics, truth: CameraModel,
                                                  rig: RigConfig) -> None:
    result = calibrate_extrinsics(scenes["led"], intrinsics, rig.markers)
    true_r = truth.gel_to_camera.rotation
    r = rotvec_to_matrix(result.rotvec_rad)
    angle = np.degrees(np.arccos(np.clip((np.trace(true_r.T @ r) - 1) / 2, -1, 1)))
    assert angle < 0.1
    t, true_t = result.translation_mm, np.asarray(truth.gel_to_camera_translation_mm)
    assert np.abs(t[:2] - true_t[:2]).max() < 0.05
    assert t[2] == pytest.approx(true_t[2], rel=0.005)
    assert result.detected.all() and result.mean_error_px <= 0.3
    # The file round-trips, and the calibrated camera projects the markers where the true one does.
    path = write_extrinsics(result, scenes["root"] / "extrinsics.toml", intrinsics)
    loaded = load_extrinsics(path)
    assert loaded.mean_error_px == pytest.approx(result.mean_error_px)
    camera = load_camera(intrinsics.path, path)  # type: ignore[arg-type]
    rest = rig.markers.rest_positions_mm()
    assert np.abs(camera.project(rest) - truth.project(rest)).max() < 0.3
    np.testing.assert_allclose(loaded.rest_px, camera.project(loaded.rest_gel_mm), atol=1e-6)


def test_extrinsics_at_four_times_the_event_noise(scenes: dict[str, Path], intrinsics: Intrinsics, truth: CameraModel,
                                                 rig: RigConfig) -> None:
    """Threshold spread 0.12 on 0.22: membrane pixels as bright as markers; the targets still hold."""
    led = record_led_blink(scenes["root"] / "led-x4.h5", rig, seed=1, noise_scale=4.0).path
    result = calibrate_extrinsics(led, intrinsics, rig.markers, nominal_rotvec_rad=rig.camera.nominal_rotvec_rad)
    r = rotvec_to_matrix(result.rotvec_rad)
    angle = np.degrees(np.arccos(np.clip((np.trace(truth.gel_to_camera.rotation.T @ r) - 1) / 2, -1, 1)))
    assert angle < 0.1
    t, true_t = result.translation_mm, np.asarray(truth.gel_to_camera_translation_mm)
    assert np.abs(t[:2] - true_t[:2]).max() < 0.05
    assert t[2] == pytest.approx(true_t[2], rel=0.005)
    assert result.detected.sum() >= 0.9 * len(result.detected) and result.mean_error_px <= 0.3


def test_association_with_many_weaker_spurious_blobs(truth: CameraModel, rig: RigConfig) -> None:
    rest = rig.markers.rest_positions_mm()
    rng = np.random.default_rng(5)
    px = truth.project(rest) + rng.normal(0, 0.3, (len(rest), 2))
    noise = rng.uniform([250, 0], [1030, 720], (120, 2))  # as many noise peaks as markers, over and around the grid
    points = np.vstack([px, noise])
    strength = np.concatenate([rng.uniform(5, 12, len(px)), rng.uniform(3, 6, len(noise))])
    labels, spurious = associate_grid(points, Intrinsics.from_camera(truth), rig.markers.rows, rig.markers.cols,
                                      strength=strength)
    assert spurious == len(points) - (labels[:, 0] >= 0).sum()
    near = np.linalg.norm(noise[:, None] - px[None], axis=2).min(axis=1) < 14  # a noise peak on a marker may take it
    assert (labels[: len(px), 0] >= 0).sum() >= len(px) - near.sum()
    assert (labels[len(px) :, 0] >= 0).sum() <= near.sum()


def test_association_survives_a_missing_and_a_spurious_blob_and_a_turned_grid(truth: CameraModel, rig: RigConfig) -> None:
    rest = rig.markers.rest_positions_mm()
    intr = Intrinsics.from_camera(truth)
    rng = np.random.default_rng(3)
    for turn_deg in (0.0, 90.0, 180.0, 33.0):
        pose = truth.gel_to_camera
        spin = rotvec_to_matrix([0.0, 0.0, np.radians(turn_deg)])
        px = truth.project_camera((rest @ spin.T) @ pose.rotation.T + pose.translation_mm)
        px = px + rng.normal(0, 0.1, px.shape)
        keep = np.ones(len(px), bool)
        keep[17] = False  # a missing marker
        points = np.vstack([px[keep], [[20.0, 30.0]], px[40] + [21.0, 17.0]])  # spurious blobs, one inside the grid
        labels, spurious = associate_grid(points, intr, rig.markers.rows, rig.markers.cols)
        assert (labels[:, 0] >= 0).sum() == len(px) - 1
        assert spurious == 2


def test_bad_inputs_say_what_was_found_and_what_is_needed(scenes: dict[str, Path], intrinsics: Intrinsics,
                                                          rig: RigConfig, tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match=r"\d+ (marker blobs found|of \d+ blobs matched).*need (at least )?\d+"):
        calibrate_extrinsics(scenes["target"], intrinsics, rig.markers)  # no marker grid in a target scene
    with pytest.raises(CalibrationError, match=r"found in \d+ of \d+ views; need at least 20"):
        calibrate_intrinsics(scenes["target"], min_views=20)
    from labrig.recording import RecordingMetadata, RecordingWriter

    empty = tmp_path / "quiet.h5"
    with RecordingWriter(empty, RecordingMetadata()) as writer:
        writer.put_events([1, 2], [3, 4], [1, 0], [100, 200], 1000)
    with pytest.raises(CalibrationError, match="no LED blink found"):
        calibrate_extrinsics(empty, intrinsics, rig.markers)


def test_intrinsics_file_records_its_source(intrinsics: Intrinsics, intrinsics_result: IntrinsicsResult) -> None:
    import tomllib

    data = tomllib.loads(Path(intrinsics.path).read_text())  # type: ignore[arg-type]
    assert data["source"]["recording_sha256"] == intrinsics_result.recording_sha256
    assert len(data["intrinsics"]["per_view_rms_px"]) == data["intrinsics"]["n_views"]
    assert intrinsics_from_result(intrinsics_result).fx_px == pytest.approx(intrinsics.fx_px)


def test_cli_calibrate_intrinsics_and_extrinsics(scenes: dict[str, Path], tmp_path: Path) -> None:
    import json

    from typer.testing import CliRunner

    from labrig.cli import app

    runner = CliRunner()
    target = tmp_path / "target.h5"
    shutil.copy(scenes["target"], target)
    res = runner.invoke(app, ["calibrate", "intrinsics", str(target), "--out", str(tmp_path / "i.toml"), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["views_used"] >= 8
    res = runner.invoke(app, ["calibrate", "extrinsics", str(scenes["led"]), "--intrinsics", str(tmp_path / "i.toml"),
                              "--out", str(tmp_path / "e.toml"), "--plot", str(tmp_path / "e.png"), "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["markers_detected"] == 156 and (tmp_path / "e.png").stat().st_size > 0
    res = runner.invoke(app, ["calibrate", "extrinsics", str(target), "--intrinsics", str(tmp_path / "i.toml"),
                              "--out", str(tmp_path / "bad.toml")])
    assert isinstance(res.exception, CalibrationError) and "12x13" in str(res.exception)  # main() exits 2 on it


def test_cli_extrinsics_reports_the_markers_as_printed(scenes: dict[str, Path], intrinsics: Intrinsics,
                                                       tmp_path: Path) -> None:
    """A perfect gel: no marker missing, every measured centre on its nominal site within the calibration's
    accuracy (well under a pixel), and the residual map drawn beside the file."""
    import json

    from typer.testing import CliRunner

    from labrig.cli import app

    res = CliRunner().invoke(app, ["calibrate", "extrinsics", str(scenes["led"]), "--intrinsics", str(intrinsics.path),
                                   "--out", str(tmp_path / "e.toml"), "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["markers_missing"] == [] and summary["residual_max_px"] < 0.5 and summary["residual_max_mm"] < 0.02
    assert len(summary["worst_residuals"]) == 5 and Path(summary["residual_map"]) == tmp_path / "e-residuals.png"
    assert (tmp_path / "e-residuals.png").stat().st_size > 10_000
    loaded = load_extrinsics(tmp_path / "e.toml")
    assert loaded.format_version == 2 and np.abs(loaded.marker_map.rest_px - loaded.rest_px).max() < 0.5
    table = CliRunner().invoke(app, ["calibrate", "extrinsics", str(scenes["led"]), "--intrinsics", str(intrinsics.path),
                                     "--out", str(tmp_path / "t.toml")])
    assert table.exit_code == 0 and "missing markers" in table.stdout and "none" in table.stdout
