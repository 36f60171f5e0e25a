"""Virtual-time campaigns: the recording's shape, determinism across processes and a Dask cluster,
the manifest's made_by column, resuming."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

CAMPAIGN = """
[campaign]
name = "vt"
seed = 5
protocol = "quick.toml"

[[group]]
indenters = ["sphere"]
locations_mm = [[0.0, 0.0], [2.0, -1.0]]
depth_mm = [0.6]
"""

QUICK = """
[probe]
indenter = "sphere"
[approach]
start_height_mm = 0.3
speed_mm_s = 1.0
max_travel_mm = 1.5
[normal]
depth_mm = 0.6
speed_mm_s = 2.0
[wait]
duration_s = 0.05
[shear]
distance_mm = 0.3
speed_mm_s = 2.0
[retract]
height_mm = 0.5
"""

#: Wall-clock attributes: the only ones two identical recordings may differ in.
WALL_CLOCK_ATTRS = {"created", "ended"}


def _labrig(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "labrig.cli", *args], capture_output=True, text=True, timeout=600)


def _manifest(out: Path) -> list[dict[str, str]]:
    with (out / "manifest.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _contents(path: Path) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    arrays: dict[str, np.ndarray] = {}
    attrs: dict[str, object] = {}
    with h5py.File(path, "r") as f:
        def visit(name: str, obj: h5py.HLObject) -> None:
            for key, value in obj.attrs.items():
                attrs[f"{name}@{key}"] = value
            if isinstance(obj, h5py.Dataset) and not name.startswith("recording/commits"):
                arrays[name] = obj[()]
        f.visititems(visit)
        attrs.update({f"@{k}": v for k, v in f.attrs.items() if k not in WALL_CLOCK_ATTRS})
    return arrays, attrs


@pytest.fixture()
def campaign_file(tmp_path: Path) -> Path:
    (tmp_path / "quick.toml").write_text(QUICK)
    (tmp_path / "vt.toml").write_text(CAMPAIGN)
    return tmp_path / "vt.toml"


def test_virtual_time_recordings_are_identical_in_a_process_and_on_a_dask_cluster(campaign_file: Path, tmp_path: Path) -> None:
    """The same campaign and seed give the same recording: every array and every attribute but
    the wall-clock ones, whether recorded by the CLI in its process or by a Dask worker."""
    distributed = pytest.importorskip("dask.distributed")
    from labrig.config import load_rig
    from labrig.indenters import DEFAULT_INDENTERS, load_indenters
    from labrig.protocol import load_campaign
    from labrig.protocol.campaign import Manifest
    from labrig.protocol.virtual_campaign import pending_tasks, run_virtual_campaign

    here = tmp_path / "here"
    done = _labrig("campaign", str(campaign_file), "--out", str(here), "--virtual-time", "--limit", "1", "--json")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["recorded"] == 1 and summary["made_by"] == "virtual-time" and summary["simulated_s"] > 1.0
    rows = _manifest(here)
    assert [r["made_by"] for r in rows] == ["virtual-time", ""] and rows[0]["status"] == "complete"

    rig = load_rig()
    indenters = load_indenters()
    campaign = load_campaign(campaign_file, rig, indenters)
    there = tmp_path / "there"
    there.mkdir()
    manifest = Manifest(there, campaign)
    tasks = pending_tasks(campaign, manifest, there, rig_path=rig.path, indenters_path=DEFAULT_INDENTERS, limit=1)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        outcomes = run_virtual_campaign(campaign, manifest, tasks, workers=None, scheduler=cluster.scheduler_address)
    assert [o.status for o in outcomes] == ["complete"]
    assert _manifest(there)[0]["sha256"] == outcomes[0].sha256

    a_arrays, a_attrs = _contents(here / "vt-000.h5")
    b_arrays, b_attrs = _contents(there / "vt-000.h5")
    assert a_arrays.keys() == b_arrays.keys() and a_attrs.keys() == b_attrs.keys()
    for name, value in a_arrays.items():
        np.testing.assert_array_equal(value, b_arrays[name], err_msg=name)
    for name, value in a_attrs.items():
        np.testing.assert_array_equal(np.asarray(value), np.asarray(b_attrs[name]), err_msg=name)
    assert a_arrays["streams/events/x"].size > 1000
    assert a_attrs["@extra_made_by"] == "virtual-time" and a_attrs["@exit_status"] == "complete"


def test_virtual_time_recording_looks_like_a_through_driver_one(campaign_file: Path, tmp_path: Path) -> None:
    """Phases with trigger edges at their starts, F/T at 800 Hz on the sensor's drifting clock with
    its bias tared away, CNC status at 10 Hz following trapezoids, the G-code conversation."""
    from labrig.config import load_rig
    from labrig.indenters import indenter_from_toml, load_indenters
    from labrig.protocol import load_campaign
    from labrig.protocol.virtual_run import record_virtual
    from labrig.recording import Recording

    rig, indenters = load_rig(), load_indenters()
    plan = load_campaign(campaign_file, rig, indenters).plans[1]
    result = record_virtual(plan.spec, tmp_path / "one.h5", rig, indenters["sphere"], seed=2)
    assert result.exit_status == "complete", result.reason
    assert result.phases == ["approach", "normal_down", "wait", "shear", "wait", "shear_opposite", "wait", "normal_up",
                             "retract"]
    with Recording(result.path) as rec:
        phases = rec.phases()
        assert rec.rows("trigger_out") == len(phases) == rec.rows("triggers")
        ft = rec.stream("ft")
        host = ft["t_host_us"].astype(np.int64)
        rate_hz = (host.size - 1) * 1e6 / (host[-1] - host[0])
        assert 700 < rate_hz < 900
        device = ft["t_device_us"].astype(np.int64)
        assert np.all(np.diff(device) == 1250)  # the sensor's own clock, one period per sample
        quiet = ft["force_n"][: 50]
        assert np.all(np.abs(quiet.mean(axis=0)) < 0.05) and 0.005 < quiet[:, 2].std() < 0.05  # tared, noisy
        assert float(np.abs(ft["force_n"][:, 2]).max()) > 0.5  # pressed
        cnc = rec.stream("cnc")
        assert 8 < 1e6 / np.median(np.diff(cnc["t_host_us"].astype(np.int64))) < 12
        assert {b"Idle", b"Run", b"Jog"} <= set(cnc["state"].tolist())
        feeds = cnc["feed_mm_min"]
        assert 0 < np.min(feeds[feeds > 0]) < 120  # caught accelerating or decelerating on the trapezoids
        lines = rec.stream("gcode")["line"].tolist()
        assert any(line.startswith(b"$J=") for line in lines) and b"M8" in lines and b"M9" in lines
        assert rec.attrs["extra_made_by"] == "virtual-time"
        # ground truth needs no file
        assert indenter_from_toml(str(rec.attrs["indenter_definition"]), "recording") == indenters["sphere"]
        assert rec.clock_model("camera").method == "triggers"
