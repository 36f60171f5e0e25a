"""A pipeline result (labrig run --out) as a ROS 2 bag: the force field, net force, depth map and tracks."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from cli_runner import run_labrig as run

from labrig.pipeline import results
from labrig.pipeline.ros2_messages import point_cloud_columns
from labrig.recording.ros2 import messages as M
from labrig.recording.ros2 import topics

pytest.importorskip("rosbags")

MP = pytest.MonkeyPatch
Cap = pytest.CaptureFixture[str]


@pytest.fixture(scope="module")
def result(sphere_press: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from typer.testing import CliRunner

    from labrig.cli import app

    out = tmp_path_factory.mktemp("result") / "forces.h5"
    done = CliRunner().invoke(app, ["run", str(sphere_press), "--out", str(out), "--out-depth", "--json"])
    assert done.exit_code == 0, done.output
    return out


def test_a_result_exports_as_force_field_net_force_depth_and_tracks(result: Path, sphere_press: Path, tmp_path: Path,
                                                                    monkeypatch: MP, capsys: Cap) -> None:
    from rosbags.rosbag2 import Reader

    from labrig.recording import Recording

    bag = tmp_path / "forces.mcap"
    code, out, err = run(monkeypatch, capsys, "export", result, "--bag", bag, "--json")
    assert code == 0, err
    summary = json.loads(out)
    data = results.load_result(result)
    n, m = data["forces_n"].shape[:2]
    assert summary["windows"] == n and summary["markers"] == m == 156 and summary["depth_maps"]
    with Recording(sphere_press) as rec:
        t0 = int(rec.attrs["t0_host_ns"])
    store = M.typestore()
    got: dict[str, list[object]] = {}
    stamps: dict[str, list[int]] = {}
    with Reader(bag) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {topics.FORCE_FIELD: M.POINT_CLOUD2, topics.NET_FORCE: M.WRENCH_STAMPED,
                         topics.TRACKS: M.POINT_CLOUD2, topics.DEPTH: M.IMAGE}
        for connection, log_ns, raw in reader.messages():
            msg = store.deserialize_cdr(raw, connection.msgtype)
            got.setdefault(connection.topic, []).append(msg)
            stamps.setdefault(connection.topic, []).append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
            assert stamps[connection.topic][-1] == log_ns
    assert all(len(v) == n for v in got.values())
    assert stamps[topics.FORCE_FIELD] == [t0 + int(t) * 1000 for t in data["t1_us"]]
    i = int(np.argmax(np.abs(data["net_force_n"][:, 2])))  # the deepest press
    field = point_cloud_columns(got[topics.FORCE_FIELD][i])
    assert got[topics.FORCE_FIELD][i].header.frame_id == topics.GEL_FRAME
    places_m = (data["rest_mm"] + data["displacement_mm"][i]) / 1000
    assert np.allclose(np.stack([field["x"], field["y"], field["z"]], axis=1), places_m, atol=1e-7)
    assert np.allclose(np.stack([field["fx"], field["fy"], field["fz"]], axis=1), data["forces_n"][i], atol=1e-5)
    net = got[topics.NET_FORCE][i].wrench
    assert np.allclose([net.force.x, net.force.y, net.force.z], data["net_force_n"][i]) and net.force.z < -1.0
    moment = np.cross(places_m.astype(np.float64), data["forces_n"][i].astype(np.float64)).sum(axis=0)
    assert np.allclose([net.torque.x, net.torque.y, net.torque.z], moment, atol=1e-6)
    image = got[topics.DEPTH][i]
    assert image.encoding == "32FC1" and (image.height, image.width, image.step) == (90, 112, 448)
    assert np.array_equal(np.asarray(image.data, np.uint8).view("<f4").reshape(90, 112), data["depth_mm"][i])
    tracks = point_cloud_columns(got[topics.TRACKS][i])
    assert np.allclose(np.stack([tracks["u"], tracks["v"]], axis=1), data["positions_px"][i], atol=1e-3)
    assert np.array_equal(tracks["updated"].astype(bool), data["updated"][i].astype(bool))


def test_a_result_without_rest_points_says_to_run_again(result: Path, tmp_path: Path, monkeypatch: MP, capsys: Cap) -> None:
    old = tmp_path / "old.h5"
    old.write_bytes(result.read_bytes())
    with h5py.File(old, "r+") as f:
        del f["rest_mm"]
    code, _, err = run(monkeypatch, capsys, "export", old, "--bag", tmp_path / "old.mcap")
    assert code == 2 and "run `labrig run REC --out` again" in " ".join(err.split())
    assert not (tmp_path / "old.mcap").exists()
