"""Contact kinematics and the shared contact track: cheap forces equal the fields', sampling in order."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.indenters import Indenter, load_indenter
from labrig.physics.mechanics import ContactTable, ShearHistory
from labrig.sim.contact_track import ContactKinematics, ContactTrack
from labrig.sim.motion import true_gel_in_machine
from labrig.sim.truth_config import true_contact_table


def test_cheap_force_matches_the_fields_along_a_shear_loop(table: ContactTable) -> None:
    """The Masing sum of tabulated net forces is the traction field's sum (clipping aside)."""
    history_a, history_b = ShearHistory(), ShearHistory()
    for shift in [0.0, 0.1, 0.3, 0.6, 0.4, 0.0, -0.3, -0.6, -0.2]:
        vector = np.array([shift, 0.0]) * np.sqrt(0.5) + np.array([0.0, shift]) * np.sqrt(0.5)
        fields = table.fields(1.2, vector, history_a)
        terms, angle = table.shear_terms(vector, history_b)
        cheap = table.force_for_terms(1.2, terms, angle)
        traction_sum = fields.traction_mpa.sum(axis=(1, 2), dtype=np.float64) * table.grid.cell_area_mm2
        np.testing.assert_allclose(cheap, fields.force_n)
        assert np.abs(traction_sum - cheap[:2]).max() <= 0.01 * max(1.0, float(np.hypot(*cheap[:2])))


def test_pressure_centre_is_the_tip_for_a_sphere(table: ContactTable) -> None:
    np.testing.assert_allclose(table.pressure_centre_mm(1.0), 0.0, atol=1e-5)
    np.testing.assert_allclose(table.pressure_centre_mm(0.0), 0.0)


def _tool_at(rig: RigConfig, sphere: Indenter, x_mm: float, y_mm: float, depth_mm: float) -> np.ndarray:
    """Machine position of the tool reference that puts the tip at gel (x, y, -depth)."""
    pose = true_gel_in_machine(rig)
    return pose.apply(np.array([x_mm, y_mm, -depth_mm])) - np.asarray(sphere.tool_offset_mm)


def test_kinematics_anchor_shear_and_lift_off(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    kin = ContactKinematics(table, sphere.tool_offset_mm, true_gel_in_machine(rig).inverse())
    above = kin.step(0, _tool_at(rig, sphere, 1.0, 2.0, -0.5))
    assert not above.in_contact and above.depth_mm == 0.0
    pressed = kin.step(1000, _tool_at(rig, sphere, 1.0, 2.0, 1.0))
    assert pressed.in_contact
    np.testing.assert_allclose(pressed.anchor_mm, [1.0, 2.0], atol=1e-9)
    assert pressed.force_on_gel_n[2] < -3.0  # pressing is -z on the gel
    np.testing.assert_allclose(pressed.centre_of_pressure_mm[:2], [1.0, 2.0], atol=1e-9)
    sheared = kin.step(2000, _tool_at(rig, sphere, 1.1, 2.0, 1.0))
    assert sheared.force_on_gel_n[0] > 0.2  # the indenter drags the gel along +x
    np.testing.assert_allclose(sheared.anchor_mm, [1.0, 2.0], atol=1e-9)  # sticking, not slipping
    lifted = kin.step(3000, _tool_at(rig, sphere, 1.1, 2.0, -0.1))
    assert not lifted.in_contact
    again = kin.step(4000, _tool_at(rig, sphere, 1.1, 2.0, 1.0))
    np.testing.assert_allclose(again.force_on_gel_n[:2], 0.0, atol=1e-9)  # a fresh contact: no memory


def test_gross_slip_drags_the_anchor(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    kin = ContactKinematics(table, sphere.tool_offset_mm, true_gel_in_machine(rig).inverse())
    kin.step(0, _tool_at(rig, sphere, 0.0, 0.0, 1.0))
    state = kin.step(1000, _tool_at(rig, sphere, 3.0, 0.0, 1.0))
    assert state.anchor_mm is not None
    slip_mm = kin._slip_shift_mm(1.0)
    assert 0.1 < slip_mm < 3.0
    assert state.anchor_mm[0] == pytest.approx(3.0 - slip_mm)  # dragged to one slip shift behind the tip
    friction = table.friction
    assert abs(state.force_on_gel_n[0]) == pytest.approx(friction * abs(state.force_on_gel_n[2]), rel=0.02)


def _track(rig: RigConfig, sphere: Indenter, table: ContactTable) -> tuple[ContactTrack, list[int]]:
    """A track on a press-and-shear path that logs the times the path was asked for."""
    asked: list[int] = []
    start = _tool_at(rig, sphere, 0.0, 0.0, 0.0)
    bottom = _tool_at(rig, sphere, 0.0, 0.0, 1.5)

    def path(t_us: np.ndarray | int) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_us, dtype=np.float64))
        asked.extend(int(v) for v in t)
        w = np.clip(t / 1e6, 0, 1)[:, None]
        return start + w * (bottom - start)

    kin = ContactKinematics(table, sphere.tool_offset_mm, true_gel_in_machine(rig).inverse())
    return ContactTrack(kin, path), asked


def test_track_samples_in_order_and_answers_the_past_from_storage(
    rig: RigConfig, sphere: Indenter, table: ContactTable
) -> None:
    track, asked = _track(rig, sphere, table)
    for t in range(0, 1_000_001, 1250):  # the F/T twin, at 800 Hz
        track.sample(t)
    n = len(asked)
    past = track.sample(500_600)  # the renderer, behind: served from storage
    assert len(asked) == n
    assert past.t_us == 500_000  # the latest stored sample at or before
    force, _, _ = track.wrench_state(500_250)
    lo, hi = track.sample(500_000).force_on_gel_n[2], track.sample(501_250).force_on_gel_n[2]
    assert lo != hi and force[2] == pytest.approx(lo + 0.2 * (hi - lo))  # 500_250 is 1/5 of the way
    assert len(asked) == n  # interpolation never samples the path again
    later = track.first_after(500_000, 519_999)
    assert later.t_us == 518_750  # the latest stored sample in (500_000, 519_999]
    new = track.sample(1_200_000)
    assert new.t_us == 1_200_000 and len(asked) == n + 1


def test_track_is_safe_to_share_between_threads(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    track, _ = _track(rig, sphere, table)
    errors: list[BaseException] = []

    def reader(step: int) -> None:
        try:
            for t in range(0, 1_000_000, step):
                track.wrench_state(t)
        except BaseException as exc:  # pragma: no cover - the assertion reports it
            errors.append(exc)

    threads = [threading.Thread(target=reader, args=(step,)) for step in (1250, 7000)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout=30)
    assert not errors
    times = list(track._times)
    assert times == sorted(times) and len(set(times)) == len(times)


def test_a_ridge_shears_in_any_direction_through_a_table_per_direction(rig: RigConfig) -> None:
    """Non-axisymmetric indenters: a few degrees off a table's direction is served by it; 90 deg by its own."""
    ridge = load_indenter("ridge")
    base = true_contact_table(ridge, rig)
    built: list[float] = []

    def table_for(direction_deg: float) -> ContactTable:
        built.append(direction_deg)
        return true_contact_table(ridge, rig, direction_deg=direction_deg)

    pose = true_gel_in_machine(rig)
    for angle_deg, expect in ((0.6, []), (90.6, [90.0])):
        built.clear()
        kin = ContactKinematics(base, ridge.tool_offset_mm, pose.inverse(), table_for_direction=table_for)
        kin.step(0, _tool_at(rig, ridge, 0.0, 0.0, 0.6))
        u = np.array([np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))]) * 0.2
        state = kin.step(1000, _tool_at(rig, ridge, u[0], u[1], 0.6))
        assert built == expect
        shear = state.force_on_gel_n[:2]
        assert np.hypot(*shear) > 0.1
        along = shear @ (u / np.hypot(*u))
        assert along > 0.99 * np.hypot(*shear)  # the force follows the shear direction


def test_the_epoch_counts_the_kinematics_fresh_starts(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    """Contact made, a new shear axis (the old residual dropped) and lift-off each start an epoch; pressing and
    shearing along one axis do not (the fields may jump only between epochs: the rig solves on both sides)."""
    kin = ContactKinematics(table, sphere.tool_offset_mm, true_gel_in_machine(rig).inverse())
    epochs = [kin.step(t, _tool_at(rig, sphere, x, y, z)).epoch for t, (x, y, z) in enumerate([
        (0.0, 0.0, -0.5), (0.0, 0.0, 0.5), (0.0, 0.0, 1.0),  # above, then in contact: one start
        (0.1, 0.0, 1.0), (0.2, 0.0, 1.0), (0.1, 0.0, 1.0),  # shear along x and back: the same memory
        (0.1, 0.3, 1.0),  # clearly across the x axis: a new axis, the residual dropped
        (0.1, 0.3, -0.1),  # lifted off
    ])]
    assert epochs == [0, 1, 1, 1, 1, 1, 2, 3]
