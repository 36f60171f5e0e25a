"""The live world: real drivers over ptys move the virtual rig's indenter and read its wrench."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from labrig.config import load_rig
from labrig.devices.bota import BotaSensor, BotaSettings
from labrig.devices.camera import open_camera
from labrig.devices.grbl import Grbl
from labrig.indenters import load_indenter
from labrig.physics.geometry import nominal_gel_in_machine
from labrig.sim.world import LiveWorld


class Camera:
    """Collects what the world hands to the camera."""

    def __init__(self) -> None:
        self.events = 0
        self.triggers: list[tuple[int, int]] = []

    def __call__(self, events: np.ndarray, triggers: list[tuple[int, int]]) -> None:
        self.events += len(events)
        self.triggers += triggers


@pytest.fixture(scope="module")
def world() -> Iterator[tuple[LiveWorld, Camera]]:
    camera = Camera()
    with LiveWorld(load_rig(), load_indenter("sphere"), seed=2, camera_sink=camera) as w:
        yield w, camera


def _surface_tool_mm(w: LiveWorld) -> np.ndarray:
    """Work position of the tool that touches the gel centre (nominal pose, unhomed machine)."""
    rig = w.rig.rig
    surface = nominal_gel_in_machine(rig).apply(np.zeros(3)) - np.asarray(w.rig.indenter.tool_offset_mm)
    return surface - np.asarray(w.grbl.physical_offset_mm)


def _offset(base: np.ndarray, dx: float, dy: float, dz: float) -> list[float]:
    return (base + np.array([dx, dy, dz])).tolist()


def test_drivers_press_the_gel_and_feel_its_force(world: tuple[LiveWorld, Camera]) -> None:
    w, camera = world
    grbl = Grbl(w.paths["grbl"])
    bota = BotaSensor(w.paths["bota"], char_gap_s=0.0)
    try:
        grbl.connect()
        bota.connect(boot_timeout_s=5)
        bota.configure(BotaSettings())
        bota.start()
        contact = _surface_tool_mm(w)
        grbl.move_to(*_offset(contact, 0, 0, 1.0), feed_mm_min=1200, wait=True)
        free = np.mean([s.force_n for s in bota.wait_samples(80)], axis=0)
        grbl.set_output(True)
        grbl.move_to(*_offset(contact, 0, 0, -1.2), feed_mm_min=120, wait=True)
        pressed = np.mean([s.force_n for s in bota.wait_samples(160)], axis=0)
        truth = w.rig.ft_wrench(w.track.sample(w.now_world_us()))[0]
        grbl.move_to(*_offset(contact, 0.5, 0, -1.2), feed_mm_min=60, wait=True)
        sheared = np.mean([s.force_n for s in bota.wait_samples(160)], axis=0)
        grbl.set_output(False)
        grbl.move_to(*_offset(contact, 0, 0, 3.0), feed_mm_min=1200, wait=True)
        deadline = time.monotonic() + 20  # the renderer runs behind the host clock: let it pass M9
        while len(camera.triggers) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        bota.close()
        grbl.close()
    load = pressed - free  # the twin's bias cancels
    assert 3.0 < load[2] < 15.0  # pressing 1.2 mm (less the pose error) into the layer
    assert load[2] == pytest.approx(truth[2], abs=0.05)  # the sensor measures the rig's wrench
    assert sheared[0] - free[0] < -0.5  # the gel holds the indenter back against +x
    assert camera.events > 1000
    assert [p for _, p in camera.triggers] == [1, 0]  # M8 and M9 reached the camera's trigger input
    assert w.error is None and w.server.error is None


def test_sim_serve_prints_devices_that_drivers_open(tmp_path: Path) -> None:
    """`labrig sim serve` in its own process; GRBL and the camera opened by their real drivers."""
    links = tmp_path / "links"
    proc = subprocess.Popen(
        [sys.executable, "-m", "labrig.cli", "sim", "serve", "--seconds", "30", "--json", "--links", str(links),
         "--camera-socket", str(tmp_path / "evk4.sock")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        assert proc.stdout is not None
        lines = [json.loads(proc.stdout.readline()) for _ in range(3)]
        devices = {line["device"]: line["path"] for line in lines}
        assert set(devices) == {"grbl", "bota", "evk4"}
        assert (links / "grbl").resolve() == Path(devices["grbl"]).resolve()
        grbl = Grbl(str(links / "grbl"))
        camera = open_camera("sim", path=devices["evk4"])
        try:
            assert grbl.connect().state == "Idle"
            camera.open()
            camera.start()
            grbl.set_output(True)
            triggers, events, deadline = [], 0, time.monotonic() + 10
            while not triggers and time.monotonic() < deadline:
                chunk = camera.read(timeout_s=0.5)
                if chunk is not None:
                    events += chunk.events.size
                    triggers += chunk.triggers["p"].tolist()
            assert triggers == [1]  # M8 became a rising edge in the camera's EVT3 stream
            assert events > 0  # pixel noise at rest
        finally:
            camera.close()
            grbl.close()
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "stats" in json.loads(out.strip().splitlines()[-1])
    assert not (links / "grbl").exists()  # links removed on exit
