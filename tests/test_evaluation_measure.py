"""Evaluation measurements on a simulated recording: windows, the F/T sensor in the gel frame, depth and force errors."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from labrig.config import RigConfig
from labrig.evaluation import tables
from labrig.evaluation.depth import DepthTask, evaluate_depth, per_map_errors_mm
from labrig.evaluation.forces import ForceTask, evaluate_forces
from labrig.evaluation.measured import ft_axes_in_gel, measured_force_on_gel_n
from labrig.indenters import Indenter
from labrig.pipeline.windows import window_ends_us
from labrig.recording import Recording
from labrig.training import depth_errors_mm


@pytest.fixture(scope="module")
def probe(tmp_path_factory: pytest.TempPathFactory, rig: RigConfig, sphere: Indenter) -> Path:
    """A short simulated sphere probe (1 mm, 0.5 mm shear) with its ground-truth sidecar."""
    from labrig.dataset import sidecar_path
    from labrig.groundtruth import generate, write_sidecar
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    out = tmp_path_factory.mktemp("evaluation") / "probe.h5"
    path = probing_path(rig, sphere, depth_mm=1.0, shear_mm=0.5, normal_speed_mm_s=3.0, shear_speed_mm_s=3.0, wait_s=0.1)
    record_live(out, rig, sphere, path, seed=3, realtime=False)
    write_sidecar(generate(out, rate_hz=100), sidecar_path(out))
    return out


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from labrig.pipeline.depthnet import build_unet, export_onnx

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("model") / "w2.onnx"
    export_onnx(build_unet(width=2).eval(), path, {"name": "w2", "scale_mm": 2.5, "window_ms": 10.0,
                                                   "loss": {"name": "contact"}, "architecture": {"width": 2}})
    return path


def test_count_windows_hold_the_given_number_of_events(probe: Path) -> None:
    with Recording(probe) as rec:
        t0, t1 = window_ends_us(rec, window_events=5_000)
        assert len(t0) == (rec.n_events - 1) // 5_000 and np.all(t1 > t0) and np.all(t0[1:] == t1[:-1])
        counts = [len(rec.events_between(a, b)) for a, b in zip(t0[:5], t1[:5])]
        assert all(abs(c - 5_000) <= 50 for c in counts)  # rows out of time order shift a few events
        f0, f1 = window_ends_us(rec, window_events=None, window_us=10_000)
        assert np.all(f1 - f0 == 10_000) and f1[-1] <= rec.end_us()


def test_ft_sensor_in_the_gel_frame_matches_the_sims_force_on_the_gel(probe: Path) -> None:
    with Recording(probe) as rec:
        rotation, _source = ft_axes_in_gel(rec, calibration_dir=None)
        truth = rec.stream("truth/contact")
        t = truth["t_host_us"][::5]
        measured = measured_force_on_gel_n(rec, t - 5_000, t + 5_000, rotation)
    true = truth["force_n"][::5].astype(np.float64)
    pressing = true[:, 2] < -0.5
    assert pressing.sum() > 10
    assert np.median(np.abs(measured[pressing] - true[pressing]), axis=0).max() < 0.15  # N: sensor noise, window mean
    assert np.all(np.sign(measured[pressing, 2]) == -1)  # the force on the gel presses into it


def test_forces_with_the_true_depth_follow_the_ft_sensor(probe: Path) -> None:
    r = evaluate_forces(ForceTask(str(probe), "truth", window_events=None, window_us=20_000, calibration_dir=None))
    p = r.probing
    assert p.sum() > 20 and r.depth_source == "truth"
    peak = int(np.argmin(r.measured_n[:, 2]))
    assert r.measured_n[peak, 2] < -2.0
    assert abs(r.predicted_n[peak, 2] / r.measured_n[peak, 2] - 1) < 0.25
    assert np.nanmean(r.marker_mae_n[p], axis=0).max() < 0.05  # N per marker against the sim's field
    err = r.contact_error_px[p]
    err = err[np.isfinite(err).all(1)]
    assert len(err) > 10 and np.median(np.linalg.norm(err, axis=1)) < 10.0  # px; the sphere is 6 mm, 1 mm deep
    rows = {row["axis"]: row for row in tables.table3([r])}
    assert rows["total"]["force_mae_n"] >= rows["z"]["force_mae_n"] > 0
    assert set(r.stage_ms) >= {"track", "depth", "forces"} and r.total_ms > 0


def test_depth_errors_of_a_network_per_window(probe: Path, tiny_model: Path) -> None:
    r = evaluate_depth(DepthTask(str(probe), str(tiny_model), window_events=None, window_us=50_000))
    w = len(r.t_us)
    assert w > 10 and r.window_ms == 10.0
    for key in ("total_mm", "noncontact_mm", "true_max_mm", "gt_offset_us"):
        assert getattr(r, key).shape == (w,)
    assert np.isfinite(r.contact_mm).sum() > 3 and np.nanmax(np.abs(r.gt_offset_us)) <= 10_000
    row = tables.depth_row([r])
    assert row["windows"] == w and row["total_mm"] > 0


def test_per_map_errors_agree_with_the_training_metric() -> None:
    rng = np.random.default_rng(0)
    pred, true = rng.random((6, 9, 11)), rng.random((6, 9, 11))
    contact = rng.random((6, 9, 11)) > 0.7
    contact[2] = False
    mine = per_map_errors_mm(pred, true, contact)
    theirs = depth_errors_mm(pred, true, contact)
    assert np.mean(mine["total_mm"]) == pytest.approx(theirs["total_mm"], abs=1e-5)
    assert np.nanmean(mine["contact_mm"]) == pytest.approx(theirs["contact_mm"], abs=1e-5)
    assert np.isnan(mine["contact_mm"][2])


def test_table3_on_hand_made_results() -> None:
    result = SimpleNamespace(predicted_n=np.array([[1.0, 0.0, -5.0], [0.0, 2.0, -10.0], [9.0, 9.0, 9.0]]),
                             measured_n=np.array([[0.5, 0.0, -4.0], [0.0, 1.0, -12.0], [0.0, 0.0, 0.0]]),
                             contact_error_px=np.array([[3.0, 4.0], [np.nan, np.nan], [100.0, 100.0]]),
                             probing=np.array([True, True, False]))
    rows = {row["axis"]: row for row in tables.table3([result])}
    assert rows["x"]["force_mae_n"] == pytest.approx(0.25)
    assert rows["y"]["force_mae_n"] == pytest.approx(0.5)
    assert rows["z"]["force_mae_n"] == pytest.approx(1.5)
    assert rows["total"]["force_mae_n"] == pytest.approx((np.sqrt(0.25 + 1) + np.sqrt(1 + 4)) / 2)
    assert rows["total"]["position_mae_px"] == pytest.approx(5.0) and rows["z"]["position_mae_px"] is None
    by_range = [row for row in tables.force_by_range([result]) if row["axis"] == "z" and row["windows"]]
    assert [row["range_n"] for row in by_range] == ["2-5", "10-15"]
    assert by_range[1]["under_prediction_n"] == pytest.approx(2.0)  # predicted 10 N against 12 N: 2 N under


def test_force_errors_per_indenter_pool_each_indenters_recordings() -> None:
    def result(indenter: str, error_z: float, windows: int) -> SimpleNamespace:
        return SimpleNamespace(predicted_n=np.tile([0.0, 0.0, -5.0 + error_z], (windows, 1)),
                               measured_n=np.tile([0.0, 0.0, -5.0], (windows, 1)),
                               contact_error_px=np.tile([3.0, 4.0], (windows, 1)), probing=np.ones(windows, bool),
                               indenter=indenter)

    rows = tables.force_by_indenter([result("sphere", 1.0, 2), result("edge-100", 3.0, 4), result("sphere", 2.0, 2)])
    assert [(r["indenter"], r["recordings"]) for r in rows] == [("sphere", 2), ("edge-100", 1)]
    assert rows[0]["force_z_mae_n"] == pytest.approx(1.5) and rows[1]["force_z_mae_n"] == pytest.approx(3.0)
    assert rows[0]["force_x_mae_n"] == 0.0 and rows[1]["position_total_mae_px"] == pytest.approx(5.0)


def test_layer_labels_beat_the_half_space_out_of_contact(probe: Path) -> None:
    from labrig.evaluation.groundtruth_error import GroundTruthErrorTask, evaluate_groundtruth

    layer = evaluate_groundtruth(GroundTruthErrorTask(str(probe), "layer"))
    halfspace = evaluate_groundtruth(GroundTruthErrorTask(str(probe), "halfspace"))
    assert layer.frames > 20 and layer.method and halfspace.elastic == "halfspace"
    assert layer.mae_noncontact_mm < 0.03 < 0.05 < halfspace.mae_noncontact_mm  # docs/groundtruth.md
    assert halfspace.mae_noncontact_mm > 5 * layer.mae_noncontact_mm
    assert layer.mae_contact_mm < 0.15 and layer.mask_iou > 0.5


def test_force_truth_leaves_missing_markers_out_and_counts_them() -> None:
    """A missing marker's column of the sim's field is NaN: the net force sums the others, the MAE averages them."""
    from labrig.evaluation.forces import _truth

    field = np.array([[[1.0, 0.0, 2.0], [np.nan] * 3, [0.0, 1.0, 4.0]]] * 2)  # (T=2, M=3, 3)
    columns = {"t_host_us": np.array([0, 1000]), "force_n": field}
    rec = SimpleNamespace(streams={"truth/marker_forces"}, rows=lambda name: 2,
                          column=lambda name, col: columns[col])
    predicted = np.array([[[1.0, 0.0, 1.0], [50.0, 50.0, 50.0], [0.0, 1.0, 4.0]]])  # the missing marker's guess: ignored
    net, mae, missing = _truth(rec, np.array([900]), predicted)  # type: ignore[arg-type]
    assert missing == 1
    np.testing.assert_allclose(net, [[1.0, 1.0, 6.0]])
    np.testing.assert_allclose(mae, [[0.0, 0.0, 0.5]])
