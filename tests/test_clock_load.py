"""Clock fits on a loaded host: late host stamps, jittered trigger edges, early bursts.

The scene (labrig.testing.loaded_clock) is the virtual rig's camera with two
CPU-bound processes beside the recorder on 2 cores: packets at least 31 ms
late with a floor that moves by 0.8 ms between phases, the renderer behind by
up to 1.6 s for 60 % of the run, heavy-tailed late packets; 5 of the 9 trigger
edges handled 0.1-25 ms late. Targets (the issue "The camera clock under
load"): drift within 10 ppm of the truth up to +-500 ppm, residual against the
truth within 50 us.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.clock import ClockModel, ManualClock
from labrig.clock_fit import DRIFT_BOUND_PPM, UNKNOWN_LATEST_US, OnlineClockFit, fit_lower_envelope, fit_triggers
from labrig.recording import Recording, RecordingWriter
from labrig.testing.loaded_clock import LoadedCameraScene

DRIFT_TARGET_PPM = 10.0
RESIDUAL_TARGET_US = 50.0


def residual_us(model: ClockModel, scene: LoadedCameraScene) -> float:
    """Largest |model - truth| over the recording, us."""
    device = scene.device_us(np.linspace(0, scene.duration_s * 1e6, 2000))
    return float(np.abs(model.to_host_us(device) - scene.true_host_us(device)).max())


@pytest.mark.parametrize("drift_ppm", [-500.0, -300.0, 35.0, 300.0, 500.0])
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_trigger_edges_pin_the_drift_when_most_are_late(drift_ppm: float, seed: int) -> None:
    scene = LoadedCameraScene(drift_ppm=drift_ppm, seed=seed)
    envelope = fit_lower_envelope(*scene.packets())
    model = fit_triggers(*scene.trigger_pairs(), fallback=envelope)
    error = model.drift_ppm - scene.model_drift_ppm
    assert model.method == "triggers" and model.n_trigger_pairs == 9 and model.n_triggers >= 3
    assert abs(error) <= DRIFT_TARGET_PPM
    assert abs(error) <= model.drift_uncertainty_ppm < 3 * DRIFT_TARGET_PPM
    assert residual_us(model, scene) <= RESIDUAL_TARGET_US
    # Measured here: 4 ppm and 48 us at worst over these 20 scenes.
    assert abs(error) <= 5.0 and residual_us(model, scene) <= 48.0


@pytest.mark.parametrize("drift_ppm", [-500.0, 300.0])
def test_envelope_finds_the_floor_under_late_stretches(drift_ppm: float) -> None:
    """The renderer behind from 3 s to 18 s of 21 s, half the prompt packets late by a
    heavy-tailed amount: the floor at the ends holds the drift to the target."""
    scene = LoadedCameraScene(drift_ppm=drift_ppm, behind_s=((3.0, 18.0),), floor_shift_us=0.0, late_packet_fraction=0.5)
    device, receive = scene.packets()
    model = fit_lower_envelope(device, receive)
    error = model.drift_ppm - scene.model_drift_ppm
    assert abs(error) <= DRIFT_TARGET_PPM
    # Stated conservatively: a floor as thick as this one (150 us of jitter) may wander unseen.
    assert abs(error) <= model.drift_uncertainty_ppm <= 100.0
    assert model.residual_max_us > 1e6 and (receive - model.to_host_us(device)).min() >= -1e-6


def test_envelope_uncertainty_says_when_the_floor_is_short() -> None:
    """Prompt packets only in the first 4 s (as on the virtual rig at -500 ppm under load): the
    hull edge under the mean device time joins a prompt pair to a late one, 22,000 ppm off. The
    drift stays bounded, and its stated uncertainty covers the error instead of hiding it."""
    scene = LoadedCameraScene(drift_ppm=-500.0, behind_s=((4.0, 25.0),), seed=3)
    model = fit_lower_envelope(*scene.packets())
    assert abs(model.drift_ppm) <= DRIFT_BOUND_PPM
    assert abs(model.drift_ppm - scene.model_drift_ppm) <= model.drift_uncertainty_ppm
    assert model.drift_uncertainty_ppm > DRIFT_TARGET_PPM


def test_envelope_stays_within_the_bound_and_says_when_the_pairs_lie_beyond_it() -> None:
    device = np.arange(0, 20_000_000, 10_000, dtype=np.int64)
    receive = device + (device * 5000e-6).astype(np.int64) + 1000  # 5000 ppm: no crystal
    model = fit_lower_envelope(device, receive)
    assert abs(model.drift_ppm) <= DRIFT_BOUND_PPM < model.drift_uncertainty_ppm
    assert (receive - model.to_host_us(device)).min() >= -1e-6  # still below every pair


@settings(max_examples=30, deadline=None)
@given(drift_ppm=st.floats(-1500, 1500), seed=st.integers(0, 2**16), behind_start_s=st.floats(0, 15))
def test_envelope_stays_below_every_pair_within_the_bound(drift_ppm: float, seed: int, behind_start_s: float) -> None:
    scene = LoadedCameraScene(drift_ppm=drift_ppm, seed=seed, behind_s=((behind_start_s, behind_start_s + 5.0),))
    device, receive = scene.packets()
    model = fit_lower_envelope(device, receive)
    assert abs(model.drift_ppm) <= DRIFT_BOUND_PPM
    assert (receive - model.to_host_us(device)).min() >= -1e-6


def test_online_fit_never_reports_an_absurd_drift_after_an_early_burst() -> None:
    """The first packets a few microseconds of device time apart, stamped 40 us apart by a busy
    host: their slope is 13 (1.2e7 ppm). The live model stays bounded, says it knows nothing
    yet, and converges as the recording goes on."""
    scene = LoadedCameraScene(drift_ppm=300.0, burst_packets=6, behind_s=((8.0, 12.0),), floor_shift_us=0.0)
    device, receive = scene.packets()
    online = OnlineClockFit()
    drifts, uncertainties = [], []
    for chunk in [np.arange(2), np.arange(2, 6), *np.array_split(np.arange(6, device.size), 60)]:
        online.add(device[chunk], receive[chunk])
        model = online.model
        assert model is not None
        drifts.append(model.drift_ppm)
        uncertainties.append(model.drift_uncertainty_ppm)
    assert max(abs(d) for d in drifts) <= DRIFT_BOUND_PPM
    assert uncertainties[0] == np.inf and uncertainties[1] == np.inf
    final = online.refit()
    assert final is not None and abs(final.drift_ppm - scene.model_drift_ppm) <= final.drift_uncertainty_ppm
    assert final.drift_uncertainty_ppm < 3 * DRIFT_TARGET_PPM


def write_scene(path: Path, scene: LoadedCameraScene) -> None:
    """The scene as a recording: packets of three events, the edges seen and the edges sent."""
    device, receive = scene.packets()
    edges_device, edges_stamp = scene.trigger_pairs()
    polarity = (np.arange(edges_device.size) % 2 == 0).astype(np.uint8)
    with RecordingWriter(path, clock=ManualClock()) as writer:
        for d, h in zip(device.tolist(), receive.tolist()):
            writer.put_events([1, 2, 3], [4, 5, 6], [0, 1, 0], [d - 2, d - 1, d], h)
        writer.put("triggers", t_device_us=edges_device, polarity=polarity, channel=np.zeros(polarity.size, np.uint8))
        writer.put("trigger_out", t_host_us=edges_stamp, polarity=polarity,
                   t_latest_host_us=np.full(polarity.size, UNKNOWN_LATEST_US))


@pytest.mark.parametrize("drift_ppm", [-500.0, 300.0])
def test_finalized_recording_stores_a_robust_camera_model_with_its_quality(tmp_path: Path, drift_ppm: float) -> None:
    scene = LoadedCameraScene(drift_ppm=drift_ppm, seed=4)
    write_scene(tmp_path / "loaded.h5", scene)
    with Recording(tmp_path / "loaded.h5") as rec:
        camera = rec.clock_model("camera")
        attrs = dict(rec.file["clock/camera"].attrs)
    assert camera.method == "triggers" and camera.n_trigger_pairs == 9
    assert abs(camera.drift_ppm - scene.model_drift_ppm) <= DRIFT_TARGET_PPM
    assert residual_us(camera, scene) <= RESIDUAL_TARGET_US
    assert np.isfinite(attrs["drift_uncertainty_ppm"]) and np.isfinite(attrs["trigger_spread_us"])
    assert abs(attrs["online_drift_ppm"]) <= DRIFT_BOUND_PPM and "online_drift_uncertainty_ppm" in attrs


def test_clock_models_of_older_files_read_with_unknown_quality(tmp_path: Path) -> None:
    old = {"device_ref_us": 1.0, "host_ref_us": 2.0, "drift_ppm": 35.0, "method": "triggers-offset", "n_pairs": 10,
           "n_triggers": 9, "residual_p50_us": 1.0, "residual_p99_us": 2.0, "residual_max_us": 3.0}
    model = ClockModel.from_attrs(old)
    assert model.drift_ppm == 35.0 and model.drift_uncertainty_ppm == np.inf and model.n_trigger_pairs == 0
    import h5py

    with h5py.File(tmp_path / "attrs.h5", "w") as f:
        group = f.create_group("camera")
        for key, value in model.to_attrs().items():
            group.attrs[key] = value
    with h5py.File(tmp_path / "attrs.h5", "r") as f:
        assert ClockModel.from_attrs(dict(f["camera"].attrs)) == model


def test_latest_times_bound_the_offset_from_above_without_moving_the_line() -> None:
    """Edges stamped before they happen (send + wire) and answered after: the line stays on the
    earliest stamps (the answers' way back is slow and variable), and the truth lies between the
    line and its stated bound above it."""
    rng = np.random.default_rng(4)
    n, drift_ppm = 40, 250.0
    true_host = np.sort(rng.uniform(0, 20e6, n))
    device = 5e9 + true_host * (1 + drift_ppm * 1e-6)
    wake = rng.uniform(40, 90, n)  # every edge lags its stamp by the host's wake-up ...
    wake[rng.choice(n, 12, replace=False)] += rng.uniform(500, 8000, 12)  # ... some by much more
    earliest = true_host - wake
    latest = true_host + rng.uniform(300, 3000, n)  # the answer's way back: slow and variable
    alone = fit_triggers(device, earliest)
    bounded = fit_triggers(device, earliest, latest_host_us=latest)
    offset = np.median(true_host - bounded.to_host_us(device))
    assert bounded.host_ref_us == alone.host_ref_us and bounded.drift_ppm == alone.drift_ppm
    assert 0 < offset < 100 and offset <= bounded.offset_bound_us < 400
    assert np.isinf(alone.offset_bound_us)
    unknown = fit_triggers(device, earliest, latest_host_us=np.full(n, UNKNOWN_LATEST_US))
    assert unknown == alone


def test_latest_times_refuse_a_line_through_late_edges_that_line_up() -> None:
    """The signature of a through-driver run on a loaded host: the five last edges handled late
    by amounts that grow 229 ppm of their time, so they line up tighter than the four prompt
    ones and the fit took their line (-264 ppm against the true -35, 390 us off at the start),
    with a prompt edge answered before that line says it happened. Each edge's latest time
    (its answer) refuses that line; the prompt edges carry the fit."""
    true_host = 1e6 + np.array([0.0, 0.3, 0.6, 0.9, 1.8, 2.1, 2.4, 2.7, 3.0]) * 1e6
    device = 5e9 + true_host * (1 + 35e-6)
    wake = np.array([50.0, 62.0, 45.0, 70.0, 0, 0, 0, 0, 0])
    wake[4:] = 20 + 229e-6 * (true_host[4:] - true_host[4])
    earliest = true_host - wake
    latest = true_host + np.array([300.0, 450.0, 900.0, 380.0, 600.0, 700.0, 500.0, 800.0, 650.0])
    fooled = fit_triggers(device, earliest)
    assert fooled.drift_ppm == pytest.approx(-264.0, abs=1.0) and np.abs(fooled.to_host_us(device) - true_host).max() > 300
    model = fit_triggers(device, earliest, latest_host_us=latest)
    true_drift = (1 / (1 + 35e-6) - 1) * 1e6
    assert model.method == "triggers" and model.n_triggers == 4
    assert abs(model.drift_ppm - true_drift) <= model.drift_uncertainty_ppm
    assert np.abs(model.to_host_us(device) - true_host).max() <= 60.0
    assert np.isfinite(model.offset_bound_us) and (true_host - model.to_host_us(device)).max() <= model.offset_bound_us


def test_a_file_without_latest_trigger_times_refits_as_before(tmp_path: Path) -> None:
    """Files written before ``trigger_out.t_latest_host_us`` existed refit with the bound unknown."""
    import h5py

    from labrig.recording.finalize import fit_clock_models
    from labrig.recording.layout import stream_group

    scene = LoadedCameraScene(drift_ppm=100.0, seed=2)
    write_scene(tmp_path / "new.h5", scene)
    with h5py.File(tmp_path / "new.h5", "r+") as f:
        with_column = fit_clock_models(f)["camera"]
        del stream_group(f, "trigger_out")["t_latest_host_us"]
        without = fit_clock_models(f)["camera"]
    assert without == with_column and np.isinf(without.offset_bound_us)
