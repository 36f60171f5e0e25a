"""The imperfect sensor in the rig file: printed markers, camera delivery, F/T drops, the true gel."""

from __future__ import annotations

import socket
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from labrig.config import ConfigError, RigConfig, load_rig, parse_rig, rig_with
from labrig.indenters import Indenter
from labrig.physics.mechanics import ContactTable
from labrig.sim.bota_twin import BotaTwin, BotaTwinParams
from labrig.sim.delivery import HOT_EPOCH_US, BurstSchedule, HotPixels
from labrig.sim.evk4_twin import Evk4Twin
from labrig.sim.imperfections import SimMarkers, printed_markers
from labrig.sim.motion import true_gel_in_machine
from labrig.sim.rig import VirtualRig
from labrig.sim.truth_config import sim_config, true_contact_table

N = 12 * 13


# -- the rig file ----------------------------------------------------------------------------------


def test_the_default_rig_is_the_ideal_sensor(rig: RigConfig) -> None:
    assert sim_config(rig).gel == rig.gel and sim_config(rig).markers.ideal
    assert sim_config(rig).camera_delivery.burst_period_ms == 0 and sim_config(rig).camera_delivery.hot_pixels == 0
    assert sim_config(rig).ft.drop_probability == 0


def test_a_partial_sim_gel_takes_the_rest_from_the_nominal_gel(rig: RigConfig) -> None:
    changed = rig_with(rig, {"sim.gel.youngs_modulus_mpa": 0.55, "sim.gel.friction": 0.8})
    assert sim_config(changed).gel == replace(rig.gel, youngs_modulus_mpa=0.55, friction=0.8)
    assert changed.gel == rig.gel  # what the lab knows is unchanged
    assert "[sim.gel]" in changed.text


def test_the_sim_builds_its_tables_from_the_true_gel(rig: RigConfig, sphere: Indenter,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    seen = []
    monkeypatch.setattr(ContactTable, "build", classmethod(lambda cls, indenter, gel, **kw: seen.append(gel)))
    true_contact_table(sphere, rig_with(rig, {"sim.gel.youngs_modulus_mpa": 0.55}))
    assert seen[0].youngs_modulus_mpa == 0.55


@pytest.mark.parametrize(
    ("snippet", "message"),
    [
        ("[sim.markers]\nposition_error = 0.1\n", r"\[sim\.markers\] unknown key 'position_error'; allowed: seed, "),
        ("[sim.markers]\nposition_error_mm = 0.9\n", r"position_error_mm must be in \[0, 0\.5\] mm"),
        ("[sim.markers]\nposition_error_mm = [[0.1, 0.0]]\n", r"lists 1 \[dx, dy\] pairs; give one per marker \(156\)"),
        ("[sim.markers]\nposition_error_mm = [[0.1]]\n", r"a list of \[dx, dy\] pairs, not \[0\.1\]"),
        ("[sim.markers]\nposition_error_mm = \"big\"\n", r"must be a number \(mm std\) or a list"),
        ("[sim.markers]\ndiameter_variation = 0.7\n", r"diameter_variation must be in \[0, 0\.5\]"),
        ("[sim.markers]\ncontrast_variation = -0.1\n", r"contrast_variation must be in \[0, 0\.5\]"),
        ("[sim.markers]\nmissing = [3, 156]\n", r"marker index 156 is outside 0\.\.155"),
        ("[sim.markers]\nmissing = [3, 3]\n", r"missing lists a marker twice"),
        ("[sim.markers]\nmissing = [\"a\"]\n", r"missing must be a list of marker indices"),
        ("[sim.markers]\nmissing_count = 2.5\n", r"missing_count must be a whole number"),
        ("[sim.markers]\nmissing = [0]\nmissing_count = 155\n", r"missing_count must be in \[0, 154\]"),
        ("[sim.camera_delivery]\nburst_period_ms = 5.0\nburst_jitter_ms = 8.0\n", r"must not exceed burst_period_ms"),
        ("[sim.camera_delivery]\nburst_period_ms = -1\n", r"must be >= 0"),
        ("[sim.camera_delivery]\nhot_pixels = 10000000\n", r"hot_pixels must be in \[0, 489216\]"),
        ("[sim.camera_delivery]\nhot_pixel_rate_hz = 0\n", r"hot_pixel_rate_hz must be in \(0, 3000\]"),
        ("[sim.ft]\ndrop_probability = 1.0\n", r"\[sim\.ft\] drop_probability must be in \[0, 1\)"),
        ("[sim.ft]\ndrop_probability = true\n", r"drop_probability must be a number"),
        ("[sim.gel]\nyoungs_modulus_mpa = -1\n", r"\[sim\.gel\] youngs_modulus_mpa must be positive"),
        ("[sim.gel]\nstiffness = 1\n", r"\[sim\.gel\] unknown key 'stiffness'"),
    ],
)
def test_bad_knobs_say_what_is_wrong_in_one_line(rig: RigConfig, snippet: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as info:
        sim_config(parse_rig(rig.text + "\n" + snippet, Path("bad.toml")))
    text = str(info.value)
    assert text.startswith("bad.toml: ") and "\n" not in text


# -- printed markers -------------------------------------------------------------------------------


def test_printed_markers_are_seeded_and_each_knob_draws_on_its_own(rig: RigConfig) -> None:
    nominal = rig.markers.rest_positions_mm()
    spec = SimMarkers(seed=4, position_error_mm=0.05, missing=(0, 17), missing_count=3)
    a, b = printed_markers(spec, nominal, 0.5), printed_markers(spec, nominal, 0.5)
    assert np.array_equal(a.rest_mm, b.rest_mm) and np.array_equal(a.printed, b.printed)
    error = a.rest_mm[:, :2] - nominal[:, :2]
    assert 0.04 < error.std() < 0.06 and np.all(a.rest_mm[:, 2] == 0)
    assert a.missing.size == 5 and {0, 17} <= set(a.missing.tolist())
    more = printed_markers(replace(spec, contrast_variation=0.2, diameter_variation=0.1), nominal, 0.5)
    assert np.array_equal(more.rest_mm, a.rest_mm) and np.array_equal(more.printed, a.printed)
    assert 0.05 < np.std(more.diameter_mm / 0.5) < 0.15 and 0.1 < np.std(more.contrast) < 0.3
    other = printed_markers(replace(spec, seed=5), nominal, 0.5)
    assert not np.array_equal(other.rest_mm, a.rest_mm)


def test_an_explicit_list_places_each_marker(rig: RigConfig) -> None:
    offsets = [[0.01 * (i % 7), -0.02 * (i % 3)] for i in range(N)]
    changed = rig_with(rig, {"sim.markers.position_error_mm": tuple(tuple(o) for o in offsets)})
    printed = printed_markers(sim_config(changed).markers, rig.markers.rest_positions_mm(), 0.5)
    assert np.allclose(printed.rest_mm[:, :2] - rig.markers.rest_positions_mm()[:, :2], offsets)


@pytest.fixture(scope="module")
def imperfect(rig: RigConfig, sphere: Indenter, table: ContactTable) -> VirtualRig:
    changed = rig_with(rig, {"sim.markers.seed": 2, "sim.markers.position_error_mm": 0.1,
                             "sim.markers.diameter_variation": 0.15, "sim.markers.contrast_variation": 0.3,
                             "sim.markers.missing": (20, 77), "sim.markers.missing_count": 2})
    return VirtualRig(changed, sphere, table=table)


def _window(vr: VirtualRig, centre_px: np.ndarray, half: int = 14) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ROI image around a sensor-pixel centre: (intensity, x, y) of its pixels."""
    roi = vr.rig.roi
    cx, cy = int(np.rint(centre_px[0])) - roi.x0_px, int(np.rint(centre_px[1])) - roi.y0_px
    image = vr.renderer.image[cy - half : cy + half + 1, cx - half : cx + half + 1]
    y, x = np.mgrid[cy - half : cy + half + 1, cx - half : cx + half + 1]
    return image, x + roi.x0_px, y + roi.y0_px


def test_the_camera_sees_the_markers_as_printed(imperfect: VirtualRig) -> None:
    vr = imperfect
    printed = vr.printed.markers
    centres = vr.camera.project(printed.rest_mm)
    membrane = sim_config(vr.rig).lighting.membrane_level
    for i in printed.missing:
        image, _, _ = _window(vr, centres[i], 3)
        assert np.allclose(image, membrane)  # never printed: bare membrane
    lighting, checked = sim_config(vr.rig).lighting, 0
    for i in np.flatnonzero(printed.printed)[:40]:
        image, x, y = _window(vr, centres[i])
        weight = image - membrane
        assert np.hypot((weight * x).sum() / weight.sum() - centres[i][0],
                        (weight * y).sum() / weight.sum() - centres[i][1]) < 0.05  # drawn at the printed centre
        brightest = min(membrane + printed.contrast[i] * (lighting.marker_level - membrane), 1.0) - membrane
        assert weight.max() == pytest.approx(brightest, rel=1e-6)  # its own ink (a saturated pixel stays at 1)
        jacobian = vr.camera.jacobian_px_per_mm(printed.rest_mm[i : i + 1])[0, :, :2]
        area_px = np.pi * (printed.diameter_mm[i] / 2) ** 2 * abs(np.linalg.det(jacobian))
        if brightest < 1.0 - membrane:  # unsaturated: the image sums to the marker's area times its ink
            assert weight.sum() / brightest == pytest.approx(area_px, rel=0.02)  # its own diameter
            checked += 1
    assert checked > 20


def test_the_truth_describes_the_printed_markers(imperfect: VirtualRig, rig: RigConfig, sphere: Indenter) -> None:
    vr = imperfect
    missing = vr.printed.markers.missing
    surface = true_gel_in_machine(rig).apply(np.zeros(3)) - np.asarray(sphere.tool_offset_mm)
    state = vr.kinematics.step(0, surface + np.array([0.3, 0.2, -1.0]))
    solve = vr.solve(state)
    forces = solve.marker_forces_n
    assert np.isnan(forces[missing]).all() and not np.isnan(np.delete(forces, missing, axis=0)).any()
    assert np.allclose(np.nansum(forces, axis=0), solve.force_on_gel_n, rtol=1e-6, atol=1e-6)  # the cells still tile
    near = np.argsort(np.linalg.norm(vr.rest_mm[:, :2] - [0.3, 0.2], axis=1))[:12]
    assert np.abs(solve.markers_mm[near] - vr.rest_mm[near]).max() > 0.1  # displaced from the printed rest
    out = vr.advance(3000, lambda t: np.repeat(surface[None] + [0, 0, 5.0], np.size(t), axis=0))
    assert np.isnan(out.truth_markers_px[:, missing]).all()
    kept = np.delete(np.arange(N), missing)
    assert np.allclose(out.truth_markers_mm[0, kept], vr.rest_mm[kept], atol=1e-6)
    nominal = rig.markers.rest_positions_mm()
    assert 0.05 < np.std(out.truth_markers_mm[0, kept, :2] - nominal[kept, :2]) < 0.15


# -- camera delivery -------------------------------------------------------------------------------


def test_hot_pixels_fire_at_their_rate_whatever_the_chunking(rig: RigConfig) -> None:
    hot_rig = rig_with(rig, {"sim.camera_delivery.hot_pixels": 25, "sim.camera_delivery.hot_pixel_rate_hz": 400.0})
    hot = HotPixels(hot_rig, seed=3)
    assert len(hot) == 25 and len(set(zip(hot.x.tolist(), hot.y.tolist()))) == 25
    whole = hot.events(0, 2 * HOT_EPOCH_US + 50_000)
    parts = np.concatenate([hot.events(0, 37_000), hot.events(37_000, 150_001), hot.events(150_001, 250_000)])
    assert np.array_equal(whole, parts) and np.all(np.diff(whole["t"]) >= 0)
    assert whole.size == pytest.approx(25 * 400 * 0.25, rel=0.15)
    assert not np.array_equal(whole, HotPixels(hot_rig, seed=4).events(0, 250_000))  # when they fire: the run's seed
    assert HotPixels(hot_rig, seed=9).x.tolist() == hot.x.tolist()  # which pixels are hot: the sensor's


def test_the_rig_adds_hot_pixel_events(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    changed = rig_with(rig, {"sim.camera_delivery.hot_pixels": 10, "sim.camera_delivery.hot_pixel_rate_hz": 1000.0})
    far = true_gel_in_machine(rig).apply(np.zeros(3)) - np.asarray(sphere.tool_offset_mm) + np.array([0, 0, 20.0])
    def hold(t: object) -> np.ndarray:
        return np.repeat(far[None], np.size(t), axis=0)
    plain = VirtualRig(rig, sphere, table=table, seed=1).advance(100_000, hold).events
    hot = VirtualRig(changed, sphere, table=table, seed=1).advance(100_000, hold).events
    expected = HotPixels(changed, seed=1).events(0, 100_000)
    assert hot.size == plain.size + expected.size and np.all(np.diff(hot["t"]) >= 0)
    def at(ev: np.ndarray) -> np.ndarray:
        return np.isin(ev["y"].astype(int) * 2000 + ev["x"], expected["y"].astype(int) * 2000 + expected["x"])
    assert np.array_equal(hot[~at(hot)], plain[~at(plain)])  # the other pixels' events are untouched


def test_burst_releases_follow_the_period_and_jitter() -> None:
    bursts = BurstSchedule(20_000, 5_000, seed=1)
    t = np.arange(0, 1_000_000, 777)
    release = np.array([bursts.release_after(int(x)) for x in t])
    assert np.all(release >= t) and np.all(np.diff(release) >= 0)
    assert np.all(release % 20_000 < 5_000) and np.all(release - t < 25_000)
    assert len(set((release % 20_000).tolist())) > 10  # jittered
    assert BurstSchedule(20_000, 0).release_after(20_001) == 40_000


def test_record_live_delivers_camera_bursts_and_drops_ft_samples(rig: RigConfig, sphere: Indenter, table: ContactTable,
                                                                 tmp_path: Path) -> None:
    from labrig.recording import Recording
    from labrig.sim.live import FT_RATE_HZ, record_live
    from labrig.sim.motion import probing_path

    changed = rig_with(rig, {"sim.camera_delivery.burst_period_ms": 40.0, "sim.camera_delivery.burst_jitter_ms": 6.0,
                             "sim.ft.drop_probability": 0.25})
    path = probing_path(changed, sphere, depth_mm=0.3, shear_mm=0.0, normal_speed_mm_s=10.0, wait_s=0.0, approach_mm=0.1)
    counts = []
    for name in ("a.h5", "b.h5"):
        vr = VirtualRig(changed, sphere, table=table, seed=5)
        result = record_live(tmp_path / name, changed, sphere, path, seed=5, realtime=False, virtual_rig=vr)
        with Recording(result.recording.path) as rec:
            packets = rec.column("event_packets", "t_host_us")
            ft = rec.column("ft", "t_device_us")
            counts.append((packets.tolist(), ft.tolist(), rec.rows("events")))
    assert counts[0] == counts[1]  # deterministic
    packets = np.array(counts[0][0])
    assert np.all(packets % 40_000 < 6_000) and np.unique(packets).size < packets.size  # several chunks per burst
    assert counts[0][2] == result.events  # every event delivered
    samples = np.arange(0, path.duration_us, 1e6 / FT_RATE_HZ).size
    assert 0.6 * samples < len(counts[0][1]) < 0.9 * samples


def test_the_evk4_twin_holds_chunks_until_their_burst(tmp_path: Path) -> None:
    from labrig.eventtypes import EVENT_DTYPE

    hold_us = 300_000
    twin = Evk4Twin(tmp_path / "evk4.sock", release_at=lambda t: t + hold_us).start()
    try:
        client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        client.connect(str(twin.path))
        assert twin.wait_connected(2.0)
        header = b""
        while not header.endswith(b"% end\n"):
            header += client.recv(1)
        events = np.zeros(100, EVENT_DTYPE)
        events["x"], events["t"] = np.arange(100), np.arange(100) * 10
        fed = time.monotonic()
        assert twin.feed(events)
        client.settimeout(5.0)
        assert client.recv(1 << 16)
        assert time.monotonic() - fed >= hold_us / 1e6 - 0.01
        client.close()
    finally:
        twin.close()


def test_the_live_world_wires_bursts_and_drops(rig: RigConfig, sphere: Indenter, tmp_path: Path) -> None:
    from labrig.sim.world import LiveWorld

    changed = rig_with(rig, {"sim.camera_delivery.burst_period_ms": 10.0, "sim.ft.drop_probability": 0.1})
    world = LiveWorld(changed, sphere, camera_socket=tmp_path / "evk4.sock")
    assert world.evk4 is not None and world.evk4.release_at is not None
    assert world.bota.params.drop_probability == 0.1
    world._origin_us = 1_000_000
    assert world.evk4.release_at(1_000_001) == 1_010_000


def test_the_bota_twin_drops_frames_but_keeps_its_clock() -> None:
    from labrig.devices.bota_protocol import FilterSetup, Frame, decode_all

    def frames(p: float) -> list[Frame]:
        twin = BotaTwin(BotaTwinParams(boot_delay_us=10_000, filter=FilterSetup(64), drop_probability=p, seed=3))
        data = b"".join(twin.transmit(t) for t in range(0, 1_010_001, 500))
        return [e for e in decode_all(data) if isinstance(e, Frame)]

    full, lossy = frames(0.0), frames(0.2)
    assert len(lossy) == pytest.approx(0.8 * len(full), rel=0.1)
    kept = {f.t_device_us for f in lossy}
    assert kept < {f.t_device_us for f in full}  # the same device times, some missing
    same = [f for f in full if f.t_device_us in kept]
    assert [f.force_n for f in same] == [f.force_n for f in lossy]  # the other samples are unchanged


def test_a_rig_file_on_disk_with_every_knob(tmp_path: Path) -> None:
    text = load_rig().text + (
        "\n[sim.markers]\nseed = 1\nposition_error_mm = 0.05\nmissing = [5]\nmissing_count = 2\n"
        "diameter_variation = 0.1\ncontrast_variation = 0.1\n"
        "\n[sim.camera_delivery]\nburst_period_ms = 20.0\nburst_jitter_ms = 2.0\nhot_pixels = 4\n"
        "\n[sim.ft]\ndrop_probability = 0.01\n\n[sim.gel]\nyoungs_modulus_mpa = 0.45\n")
    path = tmp_path / "rig.toml"
    path.write_text(text)
    rig = load_rig(path)
    assert sim_config(rig).markers.missing == (5,) and sim_config(rig).camera_delivery.hot_pixels == 4
    assert sim_config(rig).gel.youngs_modulus_mpa == 0.45 and rig.gel.youngs_modulus_mpa == 0.4
