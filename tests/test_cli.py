"""`labrig inspect` and `labrig recover` as a user runs them (a real subprocess)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

SUMMARY_KEYS = {
    "duration_s", "events", "event_rate_hz", "ft_samples", "phases", "exit_status", "dropped", "warnings", "clock",
    "ft_sensor_fx_min_n", "ft_sensor_fx_max_n", "ft_sensor_fz_min_n", "ft_sensor_fz_max_n", "force_on_gel_x_min_n",
    "force_on_gel_z_min_n", "force_on_gel_z_max_n", "force_on_gel_ft_axes", "quality", "quality_reasons",
}


def labrig(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "labrig.cli", *map(str, args)], capture_output=True, text=True, timeout=120)


def test_inspect_prints_a_summary_and_json(small_recording: Path, tmp_path: Path) -> None:
    text = labrig("inspect", small_recording)
    assert text.returncode == 0, text.stderr
    assert "complete" in text.stdout and "normal_down" in text.stdout and "triggers" in text.stdout

    plot = tmp_path / "overview.png"
    result = labrig("inspect", small_recording, "--json", "--plot", plot)
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert set(summary) >= SUMMARY_KEYS
    assert summary["exit_status"] == "complete" and summary["dropped"] == {} and summary["warnings"] == []
    assert summary["events"] > 1_000_000 and summary["ft_samples"] == 2400
    assert 2.9 < summary["duration_s"] < 3.1
    assert summary["ft_sensor_fz_min_n"] < -10 < summary["ft_sensor_fz_max_n"]
    assert summary["force_on_gel_z_min_n"] == pytest.approx(-summary["ft_sensor_fz_max_n"], abs=0.2)  # the opposite
    assert [p["name"] for p in summary["phases"]][:2] == ["approach", "normal_down"]
    assert summary["clock"]["camera"]["method"] == "triggers"
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and plot.stat().st_size > 20_000


def newer_schema(path: Path, source: Path) -> Path:
    shutil.copy(source, path)
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = "2.0"
    return path


def plain_hdf5(path: Path, _: Path) -> Path:
    with h5py.File(path, "w") as f:
        f["data"] = [1, 2, 3]
    return path


def truncated(path: Path, source: Path) -> Path:
    data = source.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


BAD_FILES = {
    "missing": (lambda p, s: p, "no such file"),
    "directory": (lambda p, s: (p.mkdir(), p)[1], "is a directory"),
    "empty": (lambda p, s: (p.write_bytes(b""), p)[1], "empty"),
    "text": (lambda p, s: (p.write_text("x,y,p,t\n1,2,0,5\n"), p)[1], "not an HDF5 file"),
    "truncated": (truncated, "truncated"),
    "plain-hdf5": (plain_hdf5, "not a labrig recording"),
    "newer-schema": (newer_schema, "newer than this labrig reads"),
}


@pytest.mark.parametrize("kind", sorted(BAD_FILES))
def test_bad_input_gives_one_line_and_exit_2(kind: str, small_recording: Path, tmp_path: Path) -> None:
    make, expected = BAD_FILES[kind]
    path = make(tmp_path / f"{kind}.h5", small_recording)
    result = labrig("inspect", path)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:")
    assert expected in result.stderr


def test_recover_refuses_a_finalized_recording(small_recording: Path) -> None:
    result = labrig("recover", small_recording)
    assert result.returncode == 2 and "already finalized" in result.stderr and "Traceback" not in result.stderr


def test_sim_probe_records_a_run_and_reports_json(tmp_path: Path) -> None:
    out = tmp_path / "probe.h5"
    result = labrig("sim", "probe", out, "--depth-mm", "0.4", "--shear-mm", "0.1", "--speed-mm-s", "4", "--wait-s", "0.05",
                    "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["exit_status"] == "complete" and summary["events"] > 1000
    assert {"sim_duration_s", "wall_s", "real_time_factor", "event_rate_hz", "max_lag_ms"} <= set(summary)
    inspected = json.loads(labrig("inspect", out, "--json").stdout)
    assert inspected["ft_sensor_fz_max_n"] > 0.5 and [p["name"] for p in inspected["phases"]][1] == "normal_down"
    # One convention: inspect's force on the gel (gel frame) presses as the pipeline's does, Fz < 0.
    assert inspected["force_on_gel_z_min_n"] < -0.5 < inspected["force_on_gel_z_max_n"] + 1.0
    ran = json.loads(labrig("run", out, "--json").stdout)
    assert ran["peak_net_force_on_gel_n"][2] < -0.5
    assert ran["peak_net_force_on_gel_n"][2] == pytest.approx(inspected["force_on_gel_z_min_n"], rel=0.5)


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--indenter", "banana"], "unknown indenter"),
        (["--depth-mm", "7"], "max_depth_mm"),
        (["--x-mm", "40"], "off the gel"),
        (["--speed-mm-s", "0"], "must be positive"),
    ],
)
def test_sim_probe_rejects_bad_input(tmp_path: Path, args: list[str], expected: str) -> None:
    result = labrig("sim", "probe", tmp_path / "x.h5", *args)
    assert result.returncode == 2 and expected in result.stderr and "Traceback" not in result.stderr


def one_error_line(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), result.stderr
    return lines[0]


def test_output_paths_in_the_way_are_one_line_before_any_work(small_recording: Path, tmp_path: Path) -> None:
    a_file = tmp_path / "taken"
    a_file.write_text("not a folder")
    assert "--out" in one_error_line(labrig("campaign", "protocols/demo.toml", "--out", a_file))
    assert "is a file, not a folder" in one_error_line(labrig("inspect", small_recording, "--plot", a_file / "x.png"))
    assert "is a folder" in one_error_line(labrig("groundtruth", small_recording, "--plot", tmp_path))


def test_a_plot_into_a_missing_folder_makes_the_folder(small_recording: Path, tmp_path: Path) -> None:
    plot = tmp_path / "new" / "deeper" / "overview.png"
    result = labrig("inspect", small_recording, "--plot", plot)
    assert result.returncode == 0, result.stderr
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("kind", ["intrinsics", "extrinsics", "events", "rig", "gel"])
def test_calibrate_never_replaces_the_calibration_beside_the_rig_unasked(kind: str, tmp_path: Path) -> None:
    """Refused before anything is recorded or fitted: the default target exists and neither --out nor --force."""
    from labrig.config import DEFAULT_RIG

    shutil.copy(DEFAULT_RIG, tmp_path / "rig.toml")
    default = {"rig": "rig-registration.toml"}.get(kind, f"{kind}.toml")
    (tmp_path / default).write_text("# a lab's calibration\n")
    line = one_error_line(labrig("calibrate", kind, "--rig", tmp_path / "rig.toml"))
    assert str(tmp_path / default) in line and "--out" in line and "--force" in line
    assert (tmp_path / default).read_text() == "# a lab's calibration\n"


def test_run_refuses_a_result_file_that_is_not_hdf5_and_names_the_rig_it_used(small_recording: Path,
                                                                             tmp_path: Path) -> None:
    line = one_error_line(labrig("run", small_recording, "--out", tmp_path / "res.csv"))
    assert "HDF5" in line and ".h5" in line and not (tmp_path / "res.csv").exists()
    result = labrig("run", small_recording, "--depth", "model", "--json")
    assert result.returncode == 0, result.stderr
    rig = json.loads(result.stdout)["sources"]["rig"]
    assert rig.startswith(str(small_recording)) or Path(rig).exists()  # never a deleted temporary copy


def test_run_with_a_model_runs_the_model_and_says_so(small_recording: Path) -> None:
    """``--model`` alone means the network, also on a virtual-rig recording that holds its true depth."""
    result = labrig("run", small_recording, "--model", "default", "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["depth_source"] != "truth"
    line = one_error_line(labrig("run", small_recording, "--depth", "truth", "--model", "default"))
    assert "--model" in line and "--depth truth" in line
