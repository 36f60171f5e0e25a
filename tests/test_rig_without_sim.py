"""A real rig's file holds no simulator truth: the lab's rig type has no ``sim``, a rig file
without ``[sim.*]`` sections is valid and the real-data commands (run, groundtruth, calibrate,
a hardware run's checks) run on it, and no module outside the simulator (and the layers that
open it) reads the simulator's truth."""

from __future__ import annotations

import ast
import dataclasses
import json
import logging
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from labrig.calibration import gel as gel_module
from labrig.calibration.files import camera_model
from labrig.config import DEFAULT_RIG, ConfigError, RigConfig, load_rig, rig_with
from labrig.indenters import Indenter
from labrig.physics.camera import CameraModel
from labrig.protocol.files import check_spec
from labrig.protocol.spec import ProbeSpec
from labrig.sim.calibration_scenes import record_led_blink
from labrig.sim.truth_config import sim_config, true_camera

LABRIG = Path(__file__).resolve().parent.parent / "labrig"
#: The packages that open the virtual rig and may read its truth (through labrig.sim.truth_config).
SIMULATOR_USERS = ("sim", "protocol", "evaluation", "cli", "live")


def without_sim(text: str) -> str:
    """A rig file's text without its ``[sim.*]`` sections (commented-out ones too)."""
    kept, keep = [], True
    for line in text.splitlines(keepends=True):
        header = re.match(r"^\s*#?\s*\[([^\[\]]+)\]", line)
        if header:
            keep = not header.group(1).strip().startswith("sim.")
        if keep:
            kept.append(line)
    return "".join(kept)


@pytest.fixture()
def lab_rig(tmp_path: Path) -> Path:
    """calibration/rig.toml without its [sim.*] sections, alone in a folder (no calibration files)."""
    path = tmp_path / "lab" / "rig.toml"
    path.parent.mkdir()
    path.write_text(without_sim(DEFAULT_RIG.read_text()))
    assert "[sim." not in path.read_text()
    return path


def test_the_rig_type_holds_no_simulator_truth(rig: RigConfig) -> None:
    assert "sim" not in {f.name for f in dataclasses.fields(RigConfig)}
    assert not hasattr(rig, "sim")


def test_a_rig_file_without_sim_sections_is_valid(lab_rig: Path, rig: RigConfig) -> None:
    lab = load_rig(lab_rig)
    assert (lab.gel, lab.markers, lab.camera, lab.roi, lab.rig, lab.mechanics) == (
        rig.gel, rig.markers, rig.camera, rig.roi, rig.rig, rig.mechanics)
    with pytest.raises(ConfigError) as info:
        sim_config(lab)  # the simulator needs its truth, and says so in one line
    assert "[sim.*]" in str(info.value) and "\n" not in str(info.value)


def test_the_nominal_camera_is_the_lens_and_sensor(rig: RigConfig) -> None:
    nominal = CameraModel.nominal(rig)
    assert nominal.fx_px == nominal.fy_px == pytest.approx(4.08e3 / 4.86)
    assert (nominal.cx_px, nominal.cy_px) == (639.5, 359.5) and nominal.distortion == (0.0,) * 5
    assert nominal.gel_to_camera_translation_mm == (0.0, 0.0, 30.0)
    assert nominal != true_camera(rig)  # the truth is for the simulator alone
    unstated = dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, focal_length_mm=None))
    with pytest.raises(ConfigError, match="focal_length_mm"):
        CameraModel.nominal(unstated)


def test_the_uncalibrated_fallback_is_the_nominal_camera_said_once(lab_rig: Path,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
    lab = rig_with(load_rig(lab_rig), {"camera.focal_length_mm": 4.11})  # a nominal camera not warned about yet
    with caplog.at_level(logging.WARNING):
        camera, source = camera_model(lab)
        again, _ = camera_model(lab)
    assert camera == again == CameraModel.nominal(lab) and source.startswith("nominal camera")
    said = [r.getMessage() for r in caplog.records if "nominal camera" in r.getMessage()]
    assert len(said) == 1 and "\n" not in said[0]


def test_the_gel_fit_takes_the_labs_contact_model(lab_rig: Path, sphere: Indenter,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    lab = rig_with(load_rig(lab_rig), {"mechanics.mode": "halfspace", "mechanics.grid_spacing_mm": 0.25})
    built = []
    monkeypatch.setattr(gel_module.ContactTable, "build", lambda indenter, gel, **options: built.append(options))
    gel_module.contact_table(sphere, lab)
    assert built[0]["mode"] == "halfspace" and built[0]["spacing_mm"] == 0.25


def test_a_hardware_rig_without_sim_sections_checks_its_protocol(lab_rig: Path) -> None:
    lab = load_rig(lab_rig)
    hardware = rig_with(lab, {"devices.grbl_port": "/dev/ttyUSB0", "devices.bota_port": "/dev/ttyUSB1",
                              "devices.camera": "metavision"})
    assert check_spec(ProbeSpec(indenter="sphere", location_mm=(0.0, 0.0), depth_mm=0.5), hardware, None) == []
    with pytest.raises(ConfigError, match=r"\[sim\.\*\]"):  # the embedded virtual rig needs the truth
        check_spec(ProbeSpec(indenter="sphere", location_mm=(0.0, 0.0), depth_mm=0.5), lab, None)


def labrig(*args: str | Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "labrig.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, cwd=cwd)


@pytest.mark.slow
def test_run_and_groundtruth_on_a_rig_without_sim_sections(lab_rig: Path, small_recording: Path) -> None:
    folder = lab_rig.parent
    recording = shutil.copy(small_recording, folder / "small.h5")
    ran = labrig("run", recording, "--rig", lab_rig, "--calibration", folder, "--window-ms", "100", "--depth", "model",
                 "--json", cwd=folder)
    assert ran.returncode == 0, ran.stderr
    assert json.loads(ran.stdout)["sources"]["camera"].startswith("nominal camera")
    assert len([line for line in ran.stderr.splitlines() if "nominal camera" in line]) == 1
    truth = labrig("groundtruth", recording, "--rig", lab_rig, "--calibration", folder, "--json", cwd=folder)
    assert truth.returncode == 0, truth.stderr
    result = json.loads(truth.stdout)["results"][0]
    assert result["status"] == "written" and result["camera_source"].startswith("nominal camera")


@pytest.mark.slow
def test_calibrate_from_a_recording_on_a_rig_without_sim_sections(lab_rig: Path, rig: RigConfig) -> None:
    folder = lab_rig.parent
    blink = folder / "blink.h5"
    record_led_blink(blink, rig)  # the scene comes from the virtual rig; the calibration sees only the lab's file
    intrinsics = DEFAULT_RIG.parent / "intrinsics.toml"
    done = labrig("calibrate", "extrinsics", blink, "--rig", lab_rig, "--intrinsics", intrinsics,
                  "--out", folder / "extrinsics.toml", "--json", cwd=folder)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["markers_detected"] == rig.markers.rows * rig.markers.cols


def _reads_simulator_truth(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, code) of each read of the simulator's truth, in line order: ``x.sim`` (not the module
    ``labrig.sim``), ``x["sim"]``, ``x.get("sim")``, and imports of the simulator's config modules."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module in ("labrig.sim.truth_config", "labrig.sim.imperfections"):
            found.append((node.lineno, f"from {node.module} import ..."))
        elif _is_sim_read(node):
            found.append((node.lineno, ast.unparse(node)))
    return sorted(found)


def _is_sim_read(node: ast.AST) -> bool:
    if isinstance(node, ast.Attribute):
        return node.attr == "sim" and not (isinstance(node.value, ast.Name) and node.value.id == "labrig")
    if isinstance(node, ast.Subscript):
        return isinstance(node.slice, ast.Constant) and node.slice.value == "sim"
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get" and node.args:
        return isinstance(node.args[0], ast.Constant) and node.args[0].value == "sim"
    return False


def test_the_scan_finds_a_read_of_the_truth() -> None:
    code = 'import labrig.sim\nx = rig.sim.camera\ny = data["sim"]\nz = data.get("sim", {})\nlabrig.sim.rig\n'
    assert [line for line, _ in _reads_simulator_truth(ast.parse(code))] == [2, 3, 4]


def test_no_module_outside_the_simulator_reads_its_truth() -> None:
    readers = []
    for path in sorted(LABRIG.rglob("*.py")):
        package = path.relative_to(LABRIG).parts[0]
        if package in SIMULATOR_USERS:
            continue
        readers += [f"{path.relative_to(LABRIG.parent)}:{line}: {what}"
                    for line, what in _reads_simulator_truth(ast.parse(path.read_text()))]
    assert readers == []
