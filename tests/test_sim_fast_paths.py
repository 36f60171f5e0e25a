"""The virtual rig's fast paths give what the plain paths give: compiled sensor passes, cached timeline
rows, the one-wrench cross product, batched F/T rows, reused contact solves, steps over a still image,
and the F/T rate's arithmetic on Python floats (table lookups, one position, the sensor's wrench)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labrig.config import RigConfig
from labrig.devices.bota_stream import FtSample
from labrig.devices.motion_profile import MachineLimits, MotionTimeline, Segment, SegmentTable, make_block
from labrig.frames import wrench_about
from labrig.indenters import Indenter
from labrig.physics.mechanics import ContactTable, ShearHistory
from labrig.physics.mechanics.stiffening import stiffening_factor
from labrig.physics.mechanics.table_build import to_mindlin
from labrig.protocol.routing import put_ft, put_ft_rows
from labrig.recording import Recording, RecordingMetadata, RecordingWriter
from labrig.sim import _render_kernels as _k
from labrig.sim.events import EventParams, EventSensor
from labrig.sim.motion import PiecewiseLinearPath, probing_path
from labrig.sim.rig import VirtualRig

finite = st.floats(-1e4, 1e4, allow_nan=False)


def _leak_reference(s: EventSensor, cand: np.ndarray, t1: int) -> tuple[np.ndarray, np.ndarray]:
    """The leak of quiet pixels as numpy rounds over all candidates (the model of EventSensor._quiet_leak)."""
    out_pix, out_t = [], []
    while True:
        t = s._t_start_us + (s.c_on[cand] + s.reference[cand] - s.log_filtered[cand]) / s._k[cand]
        due_at = t <= t1
        if not due_at.any():
            break
        due, t = cand[due_at], t[due_at]
        t_int = np.floor(t + 1e-6).astype(np.int64)
        ok = t >= s.last_event_us[due] + s._refractory_us
        s.reference[due] += s.c_on[due]
        s._hi[due] = s.reference[due] + s.c_on[due] - 1e-9  # the band moves with R (outside_band)
        s._lo[due] = s.reference[due] - s.c_off[due] + 1e-9
        s.last_event_us[due[ok]] = t_int[ok]
        out_pix.append(due[ok])
        out_t.append(t_int[ok])
        cand = due
    if not out_pix:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    return np.concatenate(out_pix), np.concatenate(out_t)


def _sensor(seed: int, leak_hz: float = 40.0) -> EventSensor:
    rng = np.random.default_rng(seed)
    params = EventParams(leak_rate_hz=leak_hz, shot_noise_rate_hz=0.0)
    s = EventSensor(params, 40, 30, rng.random(1200), seed=seed)
    s._start_epoch(0, 1000)
    s.log_filtered += rng.normal(0, 0.05, s.size)  # some pixels pushed towards their threshold
    s.last_event_us[rng.random(s.size) < 0.3] = 20_000  # some within their refractory period
    return s


@pytest.mark.parametrize("seed", range(6))
def test_compiled_quiet_leak_gives_the_numpy_rounds_events_and_state(seed: int) -> None:
    fast, slow = _sensor(seed), _sensor(seed)
    cand = np.flatnonzero(np.random.default_rng(seed + 100).random(fast.size) < 0.5)
    fast._leak_candidates = cand.copy()
    t1 = 60_000  # long enough for some pixels to leak twice, inside the epoch; no input, no noise: leak only
    events = fast.step(0, t1, [], [])
    pix, pol, t = events["y"].astype(np.int64) * fast.width + events["x"], events["p"], events["t"]
    ref_pix, ref_t = _leak_reference(slow, cand, t1)
    assert pix.size > 10 and np.all(pol == 1)
    got = sorted(zip(pix.tolist(), t.tolist()))
    assert got == sorted(zip(ref_pix.tolist(), ref_t.tolist()))
    for name in ("reference", "last_event_us", "_hi", "_lo"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)


@pytest.mark.parametrize("leak_hz", [0.05, 30.0])
def test_compiled_epoch_leak_candidates_match_numpy(leak_hz: float) -> None:
    s = _sensor(3, leak_hz)
    to_end = 2_000.0  # us: some pixels reach their band's top by then, others not
    expected = np.flatnonzero(s.log_filtered + s._k * to_end >= s._hi)
    assert 0 < expected.size < s.size
    cand = np.empty(s.size, np.int64)
    m = _k.epoch_leak_candidates(s._k, to_end, s.log_filtered, s._hi, cand)
    np.testing.assert_array_equal(cand[:m], expected)


@pytest.mark.parametrize("seed", range(4))
def test_the_time_free_band_holds_every_crossing_of_the_epoch(seed: int) -> None:
    """A pixel inside its band (outside_band false) has no crossing anywhere in the epoch: D = Lf - R + k (t - t_start)
    stays inside (-C_off, C_on) from the epoch's start to its end, for values on both sides of the band's edges."""
    s = _sensor(seed, 0.5)  # a band narrower by the leak over the epoch, not empty
    rng = np.random.default_rng(seed)
    to_start, to_end = s._epoch_start_us - s._t_start_us, s._epoch_end_us - s._t_start_us
    # Values spread around both edges, some within rounding of them.
    y = np.where(rng.random(s.size) < 0.5, s._hi - s._k * to_end, s._lo - s._k * to_start)
    y += rng.normal(0, 1e-3, s.size) * (rng.random(s.size) < 0.5) + rng.normal(0, 1e-12, s.size)
    inside = np.array([not _k.outside_band(y[i], s._hi[i], s._lo[i], s._k[i], to_end, to_start) for i in range(s.size)])
    assert 0 < inside.sum() < s.size
    for to_t in (to_start, to_end):
        d = y - s.reference + s._k * to_t
        assert np.all(d[inside] < s.c_on[inside]) and np.all(d[inside] > -s.c_off[inside])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 5e5), st.floats(0, 2e6), finite, finite, st.floats(0, 50), st.floats(-500, 500)),
                min_size=1, max_size=12),
       st.lists(st.floats(-1e6, 1e7), min_size=1, max_size=20))
def test_one_time_on_the_timeline_is_the_vectorised_position(rows: list[tuple[float, ...]], times: list[float]) -> None:
    table, t = SegmentTable((0.5, -1.0, 2.0)), 0.0
    for gap, duration, x, z, v0, accel in rows:
        t += gap
        table.append(Segment(t, duration, (x, 1.0, z), (0.6, 0.0, -0.8), v0, accel))
        t += duration
    segments = table.with_extra([])
    vectorised = table.positions_of_rows(segments, np.array(times))
    for i, time_us in enumerate(times):
        np.testing.assert_array_equal(table.positions_of_rows(segments, time_us)[0], vectorised[i])


def _force_reference(table: ContactTable, depth: float, terms: tuple[tuple[float, float], ...], angle: float) -> np.ndarray:
    """The net force as numpy arrays (the model of ContactTable.force_xyz_for_terms)."""
    from labrig.physics.mechanics.tables import _bracket as bracket
    from labrig.physics.mechanics.tables import _lerp as lerp

    shear = np.zeros(2)
    for w, s in terms:
        if s == 0 or w == 0:
            continue
        j, v = bracket(table.shear_depths_mm, depth)
        for row, wr in ((j, 1 - v), (j + 1, v)):
            if wr == 0 or row >= len(table.shear_rows) or table.slip_shift_mm[row] <= 0:
                continue
            k, f = bracket(to_mindlin(table.fractions), float(to_mindlin(min(abs(s) / table.slip_shift_mm[row], 1.0))))
            shear += w * (wr * np.sign(s) * lerp(table.shear_force_n[row], k, f))
    if angle:
        c, s_ = np.cos(angle), np.sin(angle)
        shear = np.array([c * shear[0] - s_ * shear[1], s_ * shear[0] + c * shear[1]])
    row, weight = bracket(table.depths_mm, depth)
    factor = stiffening_factor(depth, table.meta["spec"]["gel"]["thickness_mm"], table.stiffening)
    return np.array([shear[0], shear[1], float(lerp(table.normal_force_n, row, weight))]) * factor


@settings(max_examples=150, deadline=None)
@given(st.floats(0.0, 1.9), st.lists(st.tuples(st.sampled_from([1.0, 2.0]), st.floats(-1.0, 1.0)), min_size=1, max_size=4),
       st.floats(-3.0, 3.0))
def test_the_tables_float_lookups_are_the_array_lookups(table: ContactTable, depth: float,
                                                         terms: list[tuple[float, float]], angle: float) -> None:
    expected = _force_reference(table, depth, tuple(terms), angle) if depth > 0 else np.zeros(3)
    np.testing.assert_allclose(table.force_for_terms(depth, tuple(terms), angle), expected, rtol=1e-12, atol=1e-12)
    slips = table.slip_shift_mm
    assert table.slip_shift_at(depth) == pytest.approx(float(np.interp(depth, table.shear_depths_mm[: len(slips)], slips)),
                                                     rel=1e-12, abs=1e-15)
    if depth > 0:
        i = min(int(np.searchsorted(table.depths_mm, depth, side="right")) - 1, len(table.depths_mm) - 2)
        w = (depth - table.depths_mm[i]) / (table.depths_mm[i + 1] - table.depths_mm[i])
        centre = table._pressure_centres_mm[i] * (1 - w) + table._pressure_centres_mm[i + 1] * w
        np.testing.assert_allclose(table.pressure_centre_mm(depth), centre, rtol=1e-9, atol=1e-12)


def test_a_vector_shift_resolves_as_its_components(table: ContactTable) -> None:
    history = ShearHistory()
    for shift in (0.1, 0.3, -0.2):
        vector = shift * np.array([np.cos(0.4), np.sin(0.4)])
        along, angle = table._resolve_shift(vector, history)
        assert along == pytest.approx(shift, rel=1e-12)
        assert angle == pytest.approx(0.4, rel=1e-12)
    assert table._resolve_shift((0.0, 0.0), None) == (0.0, 0.0)
    with pytest.raises(ValueError, match="one axis"):
        table._resolve_shift((0.0, 0.3), history)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(finite, finite, st.floats(-50, 0), st.floats(10, 3000)), min_size=1, max_size=5),
       st.lists(st.floats(-1e5, 2e7), min_size=1, max_size=20))
def test_one_position_on_the_motion_timeline_is_the_vectorised_one(moves: list[tuple[float, ...]],
                                                                    times: list[float]) -> None:
    limits = MachineLimits()
    timeline = MotionTimeline(limits, (0.0, 0.0, 0.0), 0.0)
    for x, y, z, feed in moves:
        block = make_block(timeline.tail_mm, (x / 100, y / 100, z), feed, limits)
        if block is not None:
            timeline.append(block, timeline.t_us)
            timeline.start(timeline.t_us)
    vectorised = timeline.positions_at(np.array(times))
    for i, t in enumerate(times):
        assert timeline.position_at(t) == tuple(vectorised[i])


def test_batched_ft_rows_are_the_rows_put_one_by_one(tmp_path) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(5)
    samples = [FtSample(int(i * 1250) % (1 << 32), 10**12 + i * 1_250_000 + int(rng.integers(0, 999)),
                        tuple(rng.normal(size=3).tolist()), tuple(rng.normal(size=3).tolist()), int(i % 3),
                        24.0 + float(rng.random())) for i in range(150)]  # type: ignore[arg-type]
    paths = []
    for name, batched in (("one.h5", False), ("batched.h5", True)):
        writer = RecordingWriter(tmp_path / name, RecordingMetadata(indenter="sphere")).open()
        writer.t0_host_ns = 10**12
        if batched:
            assert put_ft_rows(writer, samples[:64]) and put_ft_rows(writer, samples[64:]) and put_ft_rows(writer, [])
        else:
            assert all(put_ft(writer, s) for s in samples)
        paths.append(writer.close().path)
    with Recording(paths[0]) as one, Recording(paths[1]) as batched:
        a, b = one.stream("ft"), batched.stream("ft")
        assert len(a["t_host_us"]) == 150
        for column in a:
            np.testing.assert_array_equal(a[column], b[column], err_msg=column)


def test_a_contact_solved_again_reuses_its_fields(rig: RigConfig, sphere: Indenter, table: ContactTable) -> None:
    vr = VirtualRig(rig, sphere, seed=2, table=table)
    path = probing_path(rig, sphere, depth_mm=1.0, shear_mm=0.5)
    vr.advance(int(path.phases[1][2]), path)  # to the end of normal down
    state = vr.track.sample(vr.t_us) if vr.track is not None else None
    assert state is not None and state.in_contact
    first, again = vr.solve(state), vr.solve(state)
    assert again.fields is first.fields and again.markers_mm is first.markers_mm
    fresh = VirtualRig(rig, sphere, seed=2, table=table).solve(state)  # nothing cached
    np.testing.assert_array_equal(fresh.markers_mm, first.markers_mm)
    np.testing.assert_array_equal(fresh.marker_forces_n, first.marker_forces_n)


def test_zero_traction_fields_are_what_the_convolution_gives(table: ContactTable) -> None:
    fields = table.fields_for_terms(1.0, ((1.0, 0.0),))
    convolved = table._tangential_convolver()(np.zeros((2, *table.box.shape), np.float32))
    assert fields.ux_mm.dtype == convolved.dtype
    np.testing.assert_array_equal(fields.ux_mm, convolved[0])
    np.testing.assert_array_equal(fields.uy_mm, convolved[1])


def test_a_still_image_takes_one_sensor_step_per_chunk_and_no_render(rig: RigConfig, sphere: Indenter,
                                                                     table: ContactTable) -> None:
    vr = VirtualRig(rig, sphere, seed=4, table=table, max_solve_interval_us=15_000)
    hold = probing_path(rig, sphere).position_mm[:1]  # above the gel
    still = PiecewiseLinearPath(np.array([0.0, 1.0]), np.repeat(hold, 2, axis=0))
    steps: list[tuple[int, int]] = []
    step = vr.sensor.step

    def counted(t0: int, t1: int, *args: object, **kwargs: object) -> np.ndarray:
        steps.append((t0, t1))
        return step(t0, t1, *args, **kwargs)  # type: ignore[arg-type]

    vr.sensor.step = counted  # type: ignore[method-assign]
    outs = [vr.advance(t, still) for t in range(10_000, 400_001, 10_000)]
    assert len(steps) == 40  # the solves every 15 ms do not split the 10 ms chunks
    assert sum(o.renders for o in outs) == 1  # the first render; the image never changes after it
    assert sum(len(o.solves) for o in outs) >= 20  # the contact is still solved (the truth's rows)
    assert sum(o.events.size for o in outs) > 0  # shot noise and leak go on
    t = np.concatenate([o.truth_t_us for o in outs])
    np.testing.assert_array_equal(t, np.arange(t.size) * 1000)


@pytest.fixture(scope="module")
def still_rig(rig: RigConfig, sphere: Indenter, table: ContactTable) -> VirtualRig:
    return VirtualRig(rig, sphere, seed=1, table=table)


@settings(max_examples=100, deadline=None)
@given(st.tuples(finite, finite, finite), st.tuples(finite, finite, finite), st.tuples(finite, finite, finite))
def test_the_sensors_wrench_is_the_rotated_reaction(still_rig: VirtualRig, force: tuple[float, ...],
                                                    cop: tuple[float, ...], tip: tuple[float, ...]) -> None:
    vr = still_rig
    on_indenter = -np.asarray(force)
    torque = wrench_about(on_indenter, cop, np.asarray(tip) + vr.ft_origin_from_tip_mm)
    got_force, got_torque = vr.ft_wrench_of(force, cop, tip)
    np.testing.assert_allclose(got_force, vr.ft_axes_in_gel.T @ on_indenter, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(got_torque, vr.ft_axes_in_gel.T @ torque, rtol=1e-12, atol=1e-9)


def _clear_noise_reference(pix: np.ndarray, t: np.ndarray, n_pix: np.ndarray, n_t: np.ndarray, n_last: np.ndarray,
                           r: int) -> np.ndarray:
    """Which noise events keep clear of their pixel's other events, as numpy passes (the model of clear_noise)."""
    keep = n_t >= n_last + r
    mark = np.zeros(max(pix.max(initial=0), n_pix.max(initial=0)) + 1, np.int64)
    mark[n_pix] = -1
    near = mark[pix] == -1
    all_pix, all_t = np.concatenate([pix[near], n_pix]), np.concatenate([t[near], n_t])
    is_noise = np.concatenate([np.zeros(int(near.sum()), bool), np.ones(n_pix.size, bool)])
    order = np.lexsort((all_t, all_pix))
    sp, st_ = all_pix[order], all_t[order]
    gap_prev = np.full(sp.size, np.iinfo(np.int64).max)
    gap_next = gap_prev.copy()
    same = sp[1:] == sp[:-1]
    gap_prev[1:][same] = (st_[1:] - st_[:-1])[same]
    gap_next[:-1][same] = (st_[1:] - st_[:-1])[same]
    clear = np.empty(sp.size, bool)
    clear[order] = (gap_prev >= r) & (gap_next >= r)
    return keep & clear[is_noise]


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 40), st.integers(1, 30), st.integers(0, 2**31), st.sampled_from([1, 50, 300]))
def test_compiled_noise_clearance_is_the_numpy_passes(n_signal: int, n_noise: int, seed: int, r: int) -> None:
    rng = np.random.default_rng(seed)
    pixels = 12  # few pixels: many events share one
    pix, t = rng.integers(0, pixels, n_signal), rng.integers(1000, 2000, n_signal)
    n_pix, n_t = rng.integers(0, pixels, n_noise), rng.integers(1000, 2000, n_noise)
    n_last = np.where(rng.random(n_noise) < 0.3, n_t - rng.integers(0, 2 * r + 1, n_noise), -(2**62))
    keep = np.empty(n_noise, bool)
    kept = _k.clear_noise(pix, t, n_pix, n_t, n_last, r, np.full(pixels, 7, np.int64), keep)
    expected = _clear_noise_reference(pix, t, n_pix, n_t, n_last, r)
    np.testing.assert_array_equal(keep, expected)
    assert kept == int(expected.sum())


@settings(max_examples=60, deadline=None)
@given(st.integers(2, 30), st.integers(2, 30), st.integers(0, 2**31), st.floats(0.0, 0.5))
def test_compiled_slope_and_its_box_are_the_numpy_passes(nx: int, ny: int, seed: int, tol: float) -> None:
    from labrig.sim.shading import DepthField, slope_of

    rng = np.random.default_rng(seed)
    x, y = np.linspace(-1.0, 2.0, nx), np.linspace(0.5, 1.7, ny)
    depth = rng.normal(0, 0.05, (ny, nx)) * (rng.random((ny, nx)) < 0.3)
    field = DepthField(x, y, depth)
    expected = slope_of(depth, (x[-1] - x[0]) / (nx - 1), (y[-1] - y[0]) / (ny - 1))
    np.testing.assert_array_equal(field.slope, expected)
    assert field.slope_bbox_mm(tol) == field.node_box_mm(expected > tol)


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 60), st.booleans(), st.booleans())
def test_compiled_rim_luminance_and_composition_are_the_numpy_passes(seed: int, n: int, led_on: bool, with_block: bool
                                                                     ) -> None:
    """The renderer's scattered pixels (marker rims): distinct touched canvas pixels get their luminance, those in
    the ROI outside the re-shaded block are composed and kept where they changed: as the numpy passes did."""
    rng = np.random.default_rng(seed)
    ch, cw, pad = 14, 16, 3  # canvas, and the ROI inside it
    h, w = ch - 2 * pad, cw - 2 * pad
    canvas_to_roi = np.full(ch * cw, -1, np.int64)
    roi_to_canvas = ((np.arange(h)[:, None] + pad) * cw + pad + np.arange(w)[None, :]).ravel()
    canvas_to_roi[roi_to_canvas] = np.arange(h * w)
    touched = rng.integers(0, ch * cw, n)  # overlapping markers repeat pixels
    cov = rng.uniform(-0.2, 1.6, ch * cw)
    membrane, marker, cov_max = 0.1, 0.8, 1.3
    lum = rng.random(ch * cw)
    shade = rng.uniform(0.5, 2.0, h * w)
    reported = rng.random(h * w)
    reported[::3] = np.minimum(shade[::3] * lum[roi_to_canvas[::3]], 1.0)  # some pixels unchanged
    block = (2, 7, 1, 4) if with_block else (0, 0, 0, 0)
    # The numpy passes.
    lum_ref, reported_ref = lum.copy(), reported.copy()
    last = np.zeros(ch * cw, np.int64)  # each distinct pixel at its last occurrence, in list order
    last[touched] = np.arange(n)
    distinct = touched[last[touched] == np.arange(n)]
    lum_ref[distinct] = membrane + np.clip(cov[distinct], 0.0, cov_max) * (marker - membrane)
    pixels = canvas_to_roi[distinct]
    pixels = pixels[pixels >= 0]
    y, x = np.divmod(pixels, w)
    pixels = pixels[~((y >= block[2]) & (y < block[3]) & (x >= block[0]) & (x < block[1]))]
    new = np.minimum(shade[pixels] * lum_ref[roi_to_canvas[pixels]], 1.0) if led_on else np.zeros(pixels.size)
    old = reported_ref[pixels]
    moved = np.abs(new - old) > (old + new + 1e-3) * 1e-4
    reported_ref[pixels[moved]] = new[moved]
    # The compiled ones.
    outside = np.empty(n, np.int64)
    k = _k.touch_luminance(touched, np.zeros(ch * cw, np.int64), cov, membrane, marker, cov_max, lum, canvas_to_roi,
                           block, w, outside)
    np.testing.assert_array_equal(lum, lum_ref)
    np.testing.assert_array_equal(outside[:k], pixels)
    out_pix, out_val = np.empty(k, np.int64), np.empty(k)
    m = _k.compose_list(outside, k, roi_to_canvas, lum, shade, reported, led_on, 1e-4, out_pix, out_val)
    np.testing.assert_array_equal(out_pix[:m], pixels[moved])
    np.testing.assert_array_equal(out_val[:m], new[moved])
    np.testing.assert_array_equal(reported, reported_ref)
