"""The virtual rig end to end: events, forces, truth samples, stepping, clocks and triggers."""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np
import pytest

from labrig.config import RigConfig, rig_with
from labrig.frames import wrench_about
from labrig.indenters import Indenter
from labrig.physics.mechanics import ContactTable
from labrig.sim.motion import PiecewiseLinearPath, probing_path
from labrig.sim.optics import RenderUpdate
from labrig.sim.rig import TRUTH_MARKER_INTERVAL_US, RigOutput, Solve, VirtualRig
from labrig.sim.shading import DepthField
from labrig.sim.truth_config import sim_config

CHUNK_US = 100_000


def noiseless(rig: RigConfig) -> RigConfig:
    """The rig with the pixels' leak and shot noise off."""
    return rig_with(rig, {"sim.events.leak_rate_hz": 0.0, "sim.events.shot_noise_rate_hz": 0.0})


@dataclass
class Run:
    """The standard sequence on a noiseless rig, with every render's markers in image pixels."""

    rig: VirtualRig
    path: PiecewiseLinearPath
    outputs: list[RigOutput] = field(default_factory=list)
    render_px: list[np.ndarray] = field(default_factory=list)

    @property
    def events(self) -> np.ndarray:
        return np.concatenate([o.events for o in self.outputs])

    @property
    def solves(self) -> list[Solve]:
        return [s for o in self.outputs for s in o.solves]

    def phase(self, index: int) -> tuple[str, float, float]:
        return self.path.phases[index]

    def solves_in(self, index: int) -> list[Solve]:
        _, t0, t1 = self.phase(index)
        return [s for s in self.solves if t0 <= s.t_us <= t1]


@pytest.fixture(scope="module")
def standard(rig: RigConfig, sphere: Indenter, table: ContactTable) -> Run:
    vr = VirtualRig(noiseless(rig), sphere, seed=1, table=table)
    run = Run(vr, probing_path(rig, sphere, depth_mm=1.5, shear_mm=1.0))
    render = vr.renderer.render

    def spy(markers_mm: np.ndarray, depth: DepthField | None = None, *, led: float | None = None) -> RenderUpdate:
        run.render_px.append(vr.camera.project(markers_mm))
        return render(markers_mm, depth, led=led)

    vr.renderer.render = spy  # type: ignore[method-assign,assignment]
    total = int(run.path.duration_us)
    for t_end in range(CHUNK_US, total + CHUNK_US, CHUNK_US):
        run.outputs.append(vr.advance(min(t_end, total), run.path))
    return run


def test_a_rig_at_rest_without_noise_makes_no_events(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    vr = VirtualRig(noiseless(rig), sphere, seed=3, table=table)
    hold = probing_path(rig, sphere)  # starts 0.5 mm above the gel: hold its first point
    still = PiecewiseLinearPath(np.array([0.0, 1.0]), np.repeat(hold.position_mm[:1], 2, axis=0))
    out = vr.advance(300_000, still)
    assert out.events.size == 0
    assert out.renders > 0 and all(s.depth_mm == 0 for s in out.solves)


def test_events_come_with_motion(standard: Run) -> None:
    events = standard.events
    assert np.all(np.diff(events["t"]) >= 0)

    def rate(t0: float, t1: float) -> float:
        return np.count_nonzero((events["t"] >= t0) & (events["t"] < t1)) / ((t1 - t0) * 1e-6)

    motion = ("normal_down", "shear", "shear_opposite", "normal_up")
    moving = [rate(t0, t1) for name, t0, t1 in standard.path.phases if name in motion]
    # Markers move linearly between solves, and solves come up to 50 ms apart once the tool is still, so a stop
    # or a start is spread over one solve interval: look inside each wait, from 0.1 s after the stop to 60 ms
    # before the start.
    waiting = [rate(t0 + 100_000, t1 - 60_000) for name, t0, t1 in standard.path.phases if name == "wait"]
    whole_waits = [rate(t0, t1) for name, t0, t1 in standard.path.phases if name == "wait"]
    assert min(moving) > 50_000  # events per second, no noise
    assert max(waiting) < 0.01 * min(moving)
    assert max(whole_waits) < 0.25 * min(moving)


def test_normal_force_at_full_depth_matches_the_table(standard: Run, table: ContactTable) -> None:
    wait = standard.solves_in(2)  # after Normal Down, 1.5 mm deep
    assert wait and all(s.depth_mm == pytest.approx(1.5, abs=1e-9) for s in wait)
    expected = table.fields(1.5, 0.0).force_n[2]
    assert 10.5 < expected < 11.3  # N, sphere 1.5 mm into the default gel, stiffening 0.6
    for s in wait:
        assert -s.force_on_gel_n[2] == pytest.approx(expected, rel=1e-9)  # pressing: -z on the gel
        assert abs(s.force_on_gel_n[0]) < 1e-3 * expected


def test_shear_force_rises_then_unloads_by_masing(standard: Run, table: ContactTable) -> None:
    fx = [s.force_on_gel_n[0] for s in standard.solves_in(3)]  # Shear, +1 mm along gel x
    assert np.all(np.diff(fx) >= -1e-9) and fx[-1] > 1.0
    peak = table.fields(1.5, 1.0).force_n[0]  # monotonic loading from zero
    held = [s.force_on_gel_n[0] for s in standard.solves_in(4)]
    assert held == pytest.approx([peak] * len(held), rel=1e-6)
    # Shear Opposite back to zero shift: F(0) = F(s_max) - 2 F(s_max / 2), a small reversed force that stays
    # (locked-in traction) through the last Wait, until the indenter lifts off.
    back = [s for s in standard.solves if standard.phase(5)[2] <= s.t_us <= standard.phase(6)[2]]
    masing = peak - 2 * table.fields(1.5, 0.5).force_n[0]
    mu_p = table.friction * table.fields(1.5, 0.0).force_n[2]
    assert back and all(s.force_on_gel_n[0] == pytest.approx(masing, abs=2e-3 * mu_p) for s in back)
    assert -0.1 * peak < back[0].force_on_gel_n[0] < 0
    lifted = [s for s in standard.solves if s.t_us >= standard.phase(8)[1] + 100_000]
    assert lifted and all(s.force_on_gel_n[0] == 0 and s.depth_mm == 0 for s in lifted)


def test_ft_wrench_is_the_reaction_about_the_sensor(standard: Run) -> None:
    vr = standard.rig
    solves = standard.solves_in(3)
    for s in (solves[0], solves[len(solves) // 2], solves[-1]):
        force, torque = vr.ft_wrench(s)
        assert np.linalg.norm(force) == pytest.approx(np.linalg.norm(s.force_on_gel_n), rel=1e-12)
        axes = vr.ft_axes_in_gel  # F/T axes in the gel frame: gel = axes @ ft
        np.testing.assert_allclose(axes @ force, -s.force_on_gel_n, atol=1e-12)
        lever_m = (s.centre_of_pressure_mm - (s.tip_gel_mm + vr.ft_origin_from_tip_mm)) * 1e-3
        np.testing.assert_allclose(axes @ torque, np.cross(lever_m, -s.force_on_gel_n), atol=1e-12)
        np.testing.assert_allclose(torque, axes.T @ wrench_about(-s.force_on_gel_n, s.centre_of_pressure_mm,
                                                                 s.tip_gel_mm + vr.ft_origin_from_tip_mm), atol=1e-15)


def test_truth_markers_are_sampled_at_1khz_and_project_consistently(standard: Run) -> None:
    t = np.concatenate([o.truth_t_us for o in standard.outputs])
    np.testing.assert_array_equal(t, np.arange(t.size) * TRUTH_MARKER_INTERVAL_US)
    assert t[-1] >= standard.path.duration_us - TRUTH_MARKER_INTERVAL_US
    mm = np.concatenate([o.truth_markers_mm for o in standard.outputs])
    px = np.concatenate([o.truth_markers_px for o in standard.outputs])
    assert mm.shape == (t.size, 156, 3) and px.shape == (t.size, 156, 2)
    camera = standard.rig.camera
    projected = camera.project(mm.reshape(-1, 3).astype(np.float64)).reshape(px.shape)
    assert np.abs(projected - px).max() < 1e-3  # px; the samples are float32
    assert np.ptp(mm[:, :, 2]) > 0.5  # the markers were pressed in during the run


def test_markers_move_at_most_a_fifth_of_a_pixel_between_renders(standard: Run) -> None:
    px = np.array(standard.render_px)
    step = np.hypot(*np.moveaxis(np.diff(px, axis=0), -1, 0)).max(axis=1)
    assert len(px) == sum(o.renders for o in standard.outputs) > 500
    assert step.max() <= 0.2 * 1.01
    assert step.max() > 0.15  # the bound is what sets the render rate while moving


def test_solves_sit_on_both_sides_of_each_contact_edge(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    """Where the contact begins or ends between two solves, the rig solves at the contact track's adjacent samples
    (the F/T twin's, 800 Hz) on either side, not across the edge: lifting off lets go of the residual shear at once,
    so the true markers would otherwise glide back over a whole solve interval."""
    vr = VirtualRig(noiseless(rig), sphere, seed=1, table=table)
    path = probing_path(rig, sphere, depth_mm=1.0, shear_mm=0.8)
    track = vr.bind(path)
    solves: list[Solve] = []
    for t in range(0, int(path.duration_us) + 1, 1250):  # the F/T twin samples the track; the renderer lags 30 ms
        track.sample(t)
        if t - 30_000 >= vr.t_us + 10_000:
            solves += vr.advance(t - 30_000, path).solves
    edges = [(a, b) for a, b in pairwise(solves) if (a.anchor_mm is None) != (b.anchor_mm is None)]
    assert len(edges) == 2  # the contact begins, and ends
    assert [b.t_us - a.t_us for a, b in edges] == [1250, 1250]
    lift_off = edges[1][0]
    assert lift_off.anchor_mm is not None and lift_off.depth_mm < 0.01  # the last sample still touching


def test_same_seed_same_events(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    path = probing_path(rig, sphere, depth_mm=0.6, shear_mm=0.2)

    def events(seed: int) -> bytes:
        vr = VirtualRig(rig, sphere, seed=seed, table=table)
        return np.concatenate([vr.advance(t, path).events for t in (200_000, 450_000, 600_000)]).tobytes()

    first = events(5)
    assert len(first) > 1000
    assert events(5) == first
    assert events(6) != first


def test_camera_clock_applies_offset_and_drift(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    vr = VirtualRig(rig, sphere, table=table)
    clock = sim_config(rig).camera_clock
    t = np.array([0, 1_000_000, 60_000_000])
    expected = clock.origin_us + np.floor(t * (1 + clock.drift_ppm * 1e-6)).astype(np.int64)
    np.testing.assert_array_equal(vr.camera_time_us(t), expected)
    assert vr.camera_time_us(1_000_000) - vr.camera_time_us(0) == 1_000_000 + round(clock.drift_ppm)
    assert vr.camera_time_us(0) == clock.origin_us


def test_trigger_edges_come_back_with_the_next_output(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    vr = VirtualRig(noiseless(rig), sphere, table=table)
    path = probing_path(rig, sphere)
    vr.trigger(5_000, 1)
    vr.trigger(25_000, 0)
    out = vr.advance(50_000, path)
    assert out.triggers == [(5_000, 1), (25_000, 0)]
    assert vr.advance(60_000, path).triggers == []


def test_led_blink_makes_every_marker_fire(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    """The extrinsic-calibration scene: LED off then on, gel at rest."""
    vr = VirtualRig(rig, sphere, seed=5, table=table)
    idle = probing_path(rig, sphere, depth_mm=0.5, shear_mm=0.0)
    still = lambda t: idle(np.zeros_like(np.atleast_1d(t)))  # noqa: E731  (tool held above the gel)
    vr.set_led(False, 20_000)
    vr.set_led(True, 60_000)
    events = vr.advance(100_000, still).events
    off = events[(events["p"] == 0) & (events["t"] >= 20_000) & (events["t"] < 30_000)]
    on = events[(events["p"] == 1) & (events["t"] >= 60_000) & (events["t"] < 70_000)]
    quiet = events[(events["t"] >= 35_000) & (events["t"] < 55_000)]
    assert len(off) > 20 * len(quiet) and len(on) > 20 * len(quiet)
    centres = np.rint(vr.camera.project(vr.rest_mm)).astype(int)
    # Every marker blinks: each has events within a few pixels of its centre.
    for events_of_kind in (off, on):
        counts = np.zeros((rig.camera.height_px, rig.camera.width_px), np.int64)
        np.add.at(counts, (events_of_kind["y"], events_of_kind["x"]), 1)
        near = [counts[y - 3 : y + 4, x - 3 : x + 4].sum() for x, y in centres]
        assert min(near) > 0
    with pytest.raises(ValueError):
        vr.set_led(False, 10_000)
