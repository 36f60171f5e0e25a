"""Rig registration on a gel other than the default, a touch-off the others disagree with, a poor fit.

The thick-gel rig (issue 36): a copy of calibration/rig.toml with a softer, thicker gel (E 0.25 MPa,
nu 0.49, 5 mm), its surface 1 mm further from the camera and 1 mm higher for the CNC, and the gel
calibration `labrig calibrate gel` gave on it. Four touch-offs on the virtual rig (about a minute);
the rest is offline. The sim's truth ([sim.rig_pose]) is read here only, to compare.
"""

from __future__ import annotations

import dataclasses
import json
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from labrig.calibration.fits import reject_outliers
from labrig.calibration.gel import gel_model
from labrig.calibration.registration import OUTLIER_MIN_RESIDUAL_MM, OUTLIER_RATIO, Press, solve_registration
from labrig.calibration.registration_file import REFUSE_RESIDUAL_RMS_MM, RigRegistration
from labrig.config import DEFAULT_RIG, RigConfig, load_rig
from labrig.errors import CalibrationError
from labrig.frames import yaw_tilt_matrix
from labrig.indenters import Indenter, load_indenters
from labrig.physics.camera import CameraModel
from labrig.physics.geometry import nominal_gel_in_machine
from labrig.protocol.calibration_runs import TOUCHOFF_LOCATIONS, require_usable_fit, touchoff_locations
from labrig.protocol.session import RigSession
from labrig.protocol.touchoff import press
from labrig.sim.motion import true_gel_in_machine
from labrig.sim.truth_config import sim_config, true_camera

DEPTHS = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0)
LOCATIONS = TOUCHOFF_LOCATIONS[:4]
#: The thick gel's rig file: the default's with these lines changed (nominal and truth alike).
THICK_GEL_EDITS = {
    "thickness_mm = 4.0": "thickness_mm = 5.0",
    "youngs_modulus_mpa = 0.4\n": "youngs_modulus_mpa = 0.25\n",
    "poisson_ratio = 0.48": "poisson_ratio = 0.49",
    "gel_origin_machine_mm = [-100.0, -100.0, -90.0]": "gel_origin_machine_mm = [-100.0, -100.0, -89.0]",
    "gel_to_camera_translation_mm = [0.12, -0.08, 30.0]": "gel_to_camera_translation_mm = [0.12, -0.08, 31.0]",
    "gel_origin_machine_mm = [-99.65, -100.20, -90.12]": "gel_origin_machine_mm = [-99.65, -100.20, -89.12]",
}
#: What `labrig calibrate gel` fitted on the thick-gel rig (seed 0).
THICK_GEL_CALIBRATION = ("youngs_modulus_mpa = 0.251107\npoisson_ratio = 0.49\nthickness_mm = 5\n"
                         "stiffening = 0.578604\nstiffening_fitted = true\n")
#: Tolerances against the truth: origin per axis (mm), yaw (deg). The touch-offs run in real time, so on a
#: loaded machine the contact is detected a few um deeper or shallower (6.9 um in z seen in a clean-clone CI
#: run); the outlier these tests plant is 0.76 mm off.
ORIGIN_TOLERANCE_MM = 0.01
YAW_TOLERANCE_DEG = 0.05


@pytest.fixture(scope="module")
def thick_rig(tmp_path_factory: pytest.TempPathFactory) -> RigConfig:
    text = Path(DEFAULT_RIG).read_text()
    for old, new in THICK_GEL_EDITS.items():
        assert old in text, old
        text = text.replace(old, new)
    folder = tmp_path_factory.mktemp("thick-gel")
    (folder / "rig.toml").write_text(text)
    (folder / "gel.toml").write_text(THICK_GEL_CALIBRATION)
    return load_rig(folder / "rig.toml")


@pytest.fixture(scope="module")
def sphere() -> Indenter:
    return load_indenters()["sphere"]


@pytest.fixture(scope="module")
def thick_presses(thick_rig: RigConfig, sphere: Indenter, tmp_path_factory: pytest.TempPathFactory) -> list[Press]:
    out = tmp_path_factory.mktemp("thick-touchoffs")
    nominal = nominal_gel_in_machine(thick_rig)
    directions = [90.0 * i for i in range(len(LOCATIONS))]
    with RigSession.for_rig(thick_rig, sphere, shear_directions_deg=directions) as session:
        return [press(session, thick_rig, sphere, nominal, loc, DEPTHS, shear_mm=0.3, shear_direction_deg=direction,
                      record_to=out / f"touch-{i}.h5")
                for i, (loc, direction) in enumerate(zip(LOCATIONS, directions, strict=True))]


@pytest.fixture(scope="module")
def camera(thick_rig: RigConfig) -> CameraModel:
    return true_camera(thick_rig)


def _solve(presses: list[Press], rig: RigConfig, sphere: Indenter, camera: CameraModel) -> RigRegistration:
    return solve_registration(presses, rig, sphere, camera, "sim truth", gel=gel_model(rig))


def _assert_truth(reg: RigRegistration, rig: RigConfig) -> None:
    truth = true_gel_in_machine(rig)
    error = reg.gel_in_machine.translation_mm - truth.translation_mm
    assert np.abs(error).max() < ORIGIN_TOLERANCE_MM, error
    assert reg.yaw_tilt_deg[0] == pytest.approx(sim_config(rig).rig_pose.gel_yaw_deg, abs=YAW_TOLERANCE_DEG)


def _displaced(p: Press, along_mm: float) -> Press:
    """The press with its machine contact point moved ``along_mm`` across the gel (tangentially about its
    centre): a touch-off whose position was lost, or whose contact was located that far off."""
    loc = np.array(p.location_mm)
    tangent = np.r_[-loc[1], loc[0], 0.0] / np.hypot(*loc)
    return dataclasses.replace(p, contact_tool_mm=p.contact_tool_mm + along_mm * tangent)


def test_thick_gel_registration_recovers_the_truth(thick_rig: RigConfig, sphere: Indenter, camera: CameraModel,
                                                   thick_presses: list[Press], tmp_path: Path) -> None:
    reg = _solve(thick_presses, thick_rig, sphere, camera)
    _assert_truth(reg, thick_rig)
    assert reg.surface_gel is not None and reg.surface_gel.thickness_mm == 5.0
    assert reg.surface_gel.source.endswith("gel.toml") and reg.surface_gel.stiffening == pytest.approx(0.5786, abs=1e-4)
    quality = reg.quality
    assert quality.verdict == "good" and quality.points_rejected == 0, quality
    assert quality.residual_rms_mm < 0.015
    saved = tomllib.loads(reg.save(tmp_path / "rig-registration.toml").read_text())
    assert saved["residuals"]["fit_quality"] == "good" and saved["residuals"]["points_used"] == len(LOCATIONS)
    assert saved["surface_gel"]["thickness_mm"] == 5.0
    summary = json.loads(json.dumps(reg.summary()))
    assert {"residual_rms_mm", "residual_max_mm", "worst_point", "points_rejected", "fit_quality",
            "surface_gel"} <= set(summary)


def test_a_touch_off_the_others_disagree_with_is_dropped(thick_rig: RigConfig, sphere: Indenter, camera: CameraModel,
                                                         thick_presses: list[Press], tmp_path: Path) -> None:
    # 0.76 mm across the gel at one corner: the signature (one point ~0.6 mm off, yaw ~1.4-1.8
    # deg) when all four are fitted.
    corrupted = list(thick_presses)
    corrupted[1] = _displaced(thick_presses[1], 0.76)
    reg = _solve(corrupted, thick_rig, sphere, camera)
    _assert_truth(reg, thick_rig)
    assert [p.rejected for p in reg.points] == [False, True, False, False]
    assert reg.points[1].rejected_residual_mm == pytest.approx(0.76, abs=0.05)
    quality = reg.quality
    assert quality.verdict == "poor" and quality.points_rejected == 1 and quality.points_used == 3
    assert re.search(r"touch-off 1 at \(7.0, -6.0\) mm dropped: 7[4-8]\d um", quality.message()), quality.message()
    require_usable_fit(reg, tmp_path)  # a warning, not a refusal
    saved = tomllib.loads(reg.save(tmp_path / "rig-registration.toml").read_text())
    assert saved["residuals"]["points_rejected"] == 1 and saved["points"][1]["rejected"] is True


def test_a_camera_calibrated_on_another_gel_is_refused(thick_rig: RigConfig, sphere: Indenter,
                                                       thick_presses: list[Press], tmp_path: Path) -> None:
    # The default gel's camera (surface 30 mm from the lens, not 31): every contact 3 % off in scale.
    stale = true_camera(load_rig())
    reg = _solve(thick_presses, thick_rig, sphere, stale)
    quality = reg.quality
    assert quality.verdict == "refused" and quality.residual_rms_mm > REFUSE_RESIDUAL_RMS_MM, quality
    with pytest.raises(CalibrationError, match=r"rig registration refused: \d+ um rms over 4 touch-offs, worst .*"
                                               r"yaw .* deg; rms above 100 um.*extrinsics.toml"):
        require_usable_fit(reg, tmp_path)


def test_reject_outliers_drops_only_the_inconsistent_point() -> None:
    rng = np.random.default_rng(1)
    gel = np.array([[*loc, 0.0] for loc in TOUCHOFF_LOCATIONS[:5]])
    rotation = yaw_tilt_matrix(0.6, (0.15, -0.1))
    machine = gel @ rotation.T + np.array([-99.65, -100.2, -89.12]) + rng.normal(0, 0.003, gel.shape)
    kept, dropped = reject_outliers(gel, machine, min_residual_mm=OUTLIER_MIN_RESIDUAL_MM, ratio=OUTLIER_RATIO,
                                    min_points=3)
    assert kept.all() and dropped == []
    machine[3] += np.array([0.3, -0.4, 0.0])
    kept, dropped = reject_outliers(gel, machine, min_residual_mm=OUTLIER_MIN_RESIDUAL_MM, ratio=OUTLIER_RATIO,
                                    min_points=3)
    assert kept.tolist() == [True, True, True, False, True]
    assert [d.index for d in dropped] == [3] and dropped[0].residual_mm == pytest.approx(0.5, abs=0.02)


def test_touch_off_count_is_checked() -> None:
    assert touchoff_locations(5) == TOUCHOFF_LOCATIONS[:5]
    with pytest.raises(CalibrationError, match="3 to 9"):
        touchoff_locations(2)
