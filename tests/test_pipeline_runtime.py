"""The streaming runtime and `labrig run` on a short simulated indentation."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.indenters import Indenter
from labrig.pipeline import depth_sources, results, run_setup, runtime
from labrig.pipeline.windows import recording_windows
from labrig.recording import Recording
from labrig.sim.live import record_live
from labrig.sim.motion import probing_path


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory, rig: RigConfig, sphere: Indenter) -> Path:
    path = probing_path(rig, sphere, depth_mm=0.8, shear_mm=0.0, normal_speed_mm_s=5.0, wait_s=0.05)
    out = tmp_path_factory.mktemp("runtime") / "press.h5"
    record_live(out, rig, sphere, path, seed=3, realtime=False)
    return out


def _invoke(*args: str):  # type: ignore[no-untyped-def]
    from typer.testing import CliRunner

    from labrig.cli import app

    return CliRunner().invoke(app, ["run", *args])


def test_time_windows_tile_the_recording(recording: Path) -> None:
    with Recording(recording) as rec:
        end = rec.end_us()
        wins = list(recording_windows(rec, window_us=10_000))
        total = len(rec.events_between(0, end))
    assert len(wins) == -(-end // 10_000)
    assert all(w[1] == n[0] for w, n in itertools.pairwise(wins))
    assert sum(len(w[2]) for w in wins) == total
    assert all(((w[2]["t"] >= w[0]) & (w[2]["t"] < w[1])).all() for w in wins)


def test_count_windows_hold_a_fixed_number_of_events(recording: Path) -> None:
    with Recording(recording) as rec:
        wins = list(recording_windows(rec, window_us=None, window_events=5_000))
        total = len(rec.events_between(0, rec.end_us()))
    assert len(wins) == total // 5_000
    assert all(len(w[2]) == 5_000 for w in wins)
    assert all(w[0] <= w[1] <= n[0] for w, n in itertools.pairwise(wins))
    with pytest.raises(ValueError), Recording(recording) as rec:
        next(recording_windows(rec, window_us=10_000, window_events=5_000))


def test_threads_and_serial_give_the_same_forces(rig: RigConfig, recording: Path) -> None:
    with Recording(recording) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=None)
        out = []
        for concurrent in (False, True):
            pipe = runtime.Pipeline(setup, depth_sources.TruthDepth(rec))
            out.append(list(pipe.run(rec, window_events=20_000, concurrent=concurrent)))
    serial, threaded = out
    assert len(serial) == len(threaded) > 5
    for a, b in zip(serial, threaded, strict=True):
        assert (a.t0_us, a.t1_us, a.n_events) == (b.t0_us, b.t1_us, b.n_events)
        assert np.array_equal(a.forces_n, b.forces_n)
    peak = min(serial, key=lambda r: r.net_force_n[2])
    assert peak.net_force_n[2] < -1.0 and set(peak.seconds) == set(runtime.STAGES)


def test_setup_reads_the_fitted_modulus_and_calibrated_camera(rig: RigConfig, recording: Path, tmp_path: Path) -> None:
    (tmp_path / "gel.toml").write_text("youngs_modulus_mpa = 0.35\npoisson_ratio = 0.48\n")
    with Recording(recording) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=tmp_path)
        assert setup.youngs_modulus_mpa == 0.35 and setup.sources["modulus"].endswith("gel.toml")
        assert setup.sources["camera"].startswith("nominal camera")
        plain = run_setup.setup_for_recording(rec, calibration_dir=None)
        assert plain.youngs_modulus_mpa == rig.gel.youngs_modulus_mpa
        assert np.allclose(plain.rest_px, setup.rest_px)
        assert run_setup.setup_for_recording(rec, calibration_dir=tmp_path, youngs_modulus_mpa=0.5).youngs_modulus_mpa == 0.5


def test_labrig_run_writes_results_and_an_animation(recording: Path, tmp_path: Path) -> None:
    out, gif = tmp_path / "forces.h5", tmp_path / "view.gif"
    result = _invoke(str(recording), "--out", str(out), "--view", str(gif), "--view-every", "10",
                     "--calibration", str(tmp_path), "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["windows"] > 50 and summary["real_time_factor"] > 0 and summary["peak_normal_force_on_gel_n"] > 1.0
    data = results.load_result(out)
    m = 156
    assert data["forces_n"].shape == (summary["windows"], m, 3) and data["positions_px"].shape[1:] == (m, 2)
    assert np.allclose(data["net_force_n"], data["forces_n"].sum(axis=1), atol=1e-4)
    assert data["attrs"]["depth_source"] == "truth" and data["attrs"]["window_us"] == 10_000
    assert gif.read_bytes()[:6] == b"GIF89a"
    from PIL import Image

    assert Image.open(gif).n_frames >= 5


def test_labrig_run_at_1_khz_runs_depth_every_10_ms(recording: Path, tmp_path: Path) -> None:
    """--window-ms 1 --depth-every-ms 10: a result per millisecond, the depth map changing at most every 10 ms."""
    out = tmp_path / "khz.h5"
    result = _invoke(str(recording), "--window-ms", "1", "--depth-every-ms", "10", "--out", str(out),
                     "--calibration", str(tmp_path), "--json")
    assert result.exit_code == 0, result.output
    data = results.load_result(out)
    assert data["attrs"]["window_us"] == 1_000 and data["attrs"]["depth_every_us"] == 10_000
    assert np.all(np.diff(data["t0_us"]) == 1_000) and json.loads(result.output)["peak_normal_force_on_gel_n"] > 1.0


def test_labrig_run_rejects_bad_options(recording: Path, tmp_path: Path) -> None:
    for args, message in (((str(recording), "--window-ms", "10", "--window-events", "100"), "not both"),
                          ((str(recording), "--view", str(tmp_path / "a.mp4")), "GIF"),
                          ((str(tmp_path / "none.h5"),), "no such recording"),
                          ((str(recording), "--depth-every-ms", "0"), "--depth-every-ms must be positive")):
        result = _invoke(*args)
        assert result.exit_code != 0 and message in (result.output + str(result.exception))


def test_missing_markers_are_skipped_and_condensed(recording: Path) -> None:
    """Three markers flagged missing (one under the contact): never tracked, forces finite and the press's
    peak as with every marker (the depth network's input and the normal forces do not depend on them)."""
    from dataclasses import replace

    with Recording(recording) as rec:
        setup = run_setup.setup_for_recording(rec, calibration_dir=None)
        missing = np.zeros(len(setup.rest_px), bool)
        missing[[20, 84, 150]] = True
        runs = [list(runtime.Pipeline(s, depth_sources.TruthDepth(rec)).run(rec, window_us=10_000, concurrent=False))
                for s in (setup, replace(setup, missing=missing))]
    full, holed = runs
    assert not any(r.updated[missing].any() for r in holed)
    assert all(np.isfinite(r.forces_n).all() and np.isfinite(r.positions_px).all() for r in holed)
    peak_full = min(r.net_force_n[2] for r in full)
    peak_holed = min(r.net_force_n[2] for r in holed)
    assert peak_holed == pytest.approx(peak_full, rel=0.02) and peak_full < -1.0
