"""The virtual rig recorded end to end: events, F/T, CNC, phases, triggers and truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labrig.config import load_rig
from labrig.indenters import load_indenter
from labrig.recording import Recording
from labrig.sim.live import FT_CLOCK_DRIFT_PPM, FT_CLOCK_ORIGIN_US, record_live
from labrig.sim.motion import probing_path
from labrig.sim.truth_config import sim_config


@pytest.fixture(scope="module")
def live_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rig = load_rig()
    sphere = load_indenter("sphere")
    path = probing_path(rig, sphere, depth_mm=0.6, shear_mm=0.3, normal_speed_mm_s=3.0, shear_speed_mm_s=3.0, wait_s=0.1)
    out = tmp_path_factory.mktemp("live") / "sphere.h5"
    result = record_live(out, rig, sphere, path, seed=3, realtime=False)
    assert result.recording.exit_status == "complete" and result.events > 10_000
    return out


def test_live_recording_holds_every_stream(live_recording: Path) -> None:
    with Recording(live_recording) as rec:
        assert rec.attrs["indenter"] == "sphere" and rec.attrs["extra_virtual_rig"]
        assert [p.name for p in rec.phases()][:2] == ["approach", "normal_down"]
        assert rec.rows("triggers") == rec.rows("trigger_out") == 9
        assert rec.rows("ft") > 0.95 * 800 * rec.phases()[-1].t_end_us / 1e6
        for stream in ("truth/markers", "truth/contact", "truth/marker_forces", "truth/depth"):
            assert rec.rows(stream) > 0
        depth = rec.column("truth/depth", "depth_mm")
        assert depth.shape[1:] == (90, 112) and 0.5 < depth.max() < 0.65
        # The F/T sensor feels the reaction of the gel's force: Fz up on the indenter.
        contact = rec.stream("truth/contact")
        assert rec.column("ft", "force_n")[:, 2].max() == pytest.approx(-contact["force_n"][:, 2].min(), rel=0.02)
        # The dense force field adds up to the net force.
        forces = rec.column("truth/marker_forces", "force_n")
        assert np.allclose(forces.sum(axis=1), contact["force_n"], atol=0.02 + 0.01 * np.abs(contact["force_n"]).max())


def test_live_recording_clocks_match_the_simulated_devices(live_recording: Path) -> None:
    rig = load_rig()
    world_us = np.linspace(0, 1.5e6, 200)
    with Recording(live_recording) as rec:
        camera = rec.clock_model("camera")
        assert camera.method == "triggers" and camera.n_triggers == 9
        cam = sim_config(rig).camera_clock
        camera_device = cam.origin_us + np.floor(world_us * (1 + cam.drift_ppm * 1e-6))
        assert np.abs(camera.to_host_us(camera_device) - world_us).max() <= 5.0
        ft = rec.clock_model("ft")
        ft_device = FT_CLOCK_ORIGIN_US + np.floor(world_us * (1 + FT_CLOCK_DRIFT_PPM * 1e-6))
        # Not paced: every chunk is "received" at its end, up to one chunk (10 ms) late.
        assert np.abs(ft.to_host_us(ft_device) - world_us).max() <= 10_000 + 50
