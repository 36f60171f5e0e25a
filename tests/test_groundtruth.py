"""Ground truth: closed forms vs published results and the numerical solver, projection, sidecar, CLI."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import h5py
import hdf5plugin
import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.dataset import sidecar_path
from labrig.errors import LabrigError
from labrig.groundtruth import (
    DepthTable,
    GroundTruthError,
    HertzModel,
    SneddonModel,
    choose_model,
    generate,
    load_groundtruth,
    write_sidecar,
)
from labrig.indenters import Indenter, load_indenter
from labrig.physics.mechanics.spectral import contact_modulus_mpa
from labrig.recording import Recording
from labrig.sim.truth_config import true_camera


@pytest.fixture(scope="module")
def probe(tmp_path_factory: pytest.TempPathFactory, rig: RigConfig, sphere: Indenter) -> Path:
    """A short simulated probing run of the sphere at (2, -1.5) mm: 1 mm deep, 0.5 mm shear."""
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    path = tmp_path_factory.mktemp("gt") / "probe.h5"
    tool = probing_path(rig, sphere, location_mm=(2.0, -1.5), depth_mm=1.0, shear_mm=0.5, normal_speed_mm_s=3.0,
                        shear_speed_mm_s=3.0, wait_s=0.1)
    record_live(path, rig, sphere, tool, realtime=False)
    return path


# ---------------------------------------------------------------------------------- closed forms


def test_hertz_matches_johnson(rig: RigConfig) -> None:
    gel = rig.gel
    e_star = contact_modulus_mpa(gel)
    model = HertzModel(6.0, gel)
    delta = 1.0
    force = model.force_n(delta)
    a = model.contact_radius_mm(delta)
    # Johnson (1985) eq. 4.22-4.23: a^3 = 3PR / 4E*, delta = a^2 / R, p0 = 3P / (2 pi a^2)
    assert a == pytest.approx((3 * force * 6.0 / (4 * e_star)) ** (1 / 3), rel=1e-12)
    r = np.array([0.0, a, 50 * a])
    uz = model.uz_radial(delta, r)
    assert uz[0] == pytest.approx(delta)
    assert uz[1] == pytest.approx(delta / 2)  # both branches meet at r = a
    assert uz[2] == pytest.approx(force / (np.pi * e_star * r[2]), rel=2e-3)  # Boussinesq far field


def test_sneddon_integrals_reproduce_punch_cone_and_hertz(rig: RigConfig) -> None:
    gel = rig.gel
    e_star = contact_modulus_mpa(gel)
    # flat punch without fillet: P = 2 a E* delta, uz = (2 delta / pi) asin(a / r) outside (Sneddon 1946)
    a = 3.0
    punch = SneddonModel(lambda r: np.where(r <= a, 0.0, np.inf), a, gel)
    delta = 0.4
    assert punch.force_n(delta) == pytest.approx(2 * a * e_star * delta, rel=2e-3)
    r = np.array([1.0, 4.0, 9.0])
    expected = np.where(r <= a, delta, 2 * delta / np.pi * np.arcsin(np.minimum(a / r, 1)))
    np.testing.assert_allclose(punch.uz_radial(delta, r), expected, rtol=3e-3)
    # cone of semi-angle alpha: delta = (pi/2) a cot(alpha), P = (2/pi) E* tan(alpha) delta^2 (Sneddon 1948)
    alpha = np.radians(70.0)
    cone = SneddonModel(lambda r: r / np.tan(alpha), 20.0, gel)
    delta = 1.0
    assert cone.contact_radius_mm(delta) == pytest.approx(2 * delta * np.tan(alpha) / np.pi, rel=1e-3)
    assert cone.force_n(delta) == pytest.approx(2 / np.pi * e_star * np.tan(alpha) * delta**2, rel=3e-3)
    # paraboloid: Hertz
    paraboloid = SneddonModel(lambda r: r**2 / 12.0, 6.0, gel)
    hertz = HertzModel(6.0, gel)
    assert paraboloid.force_n(1.0) == pytest.approx(hertz.force_n(1.0), rel=3e-3)
    np.testing.assert_allclose(paraboloid.uz_radial(1.0, r), hertz.uz_radial(1.0, r), atol=2e-3)


@pytest.mark.parametrize("name", ["sphere", "cylinder"])
def test_closed_forms_agree_with_the_numerical_solver(rig: RigConfig, tmp_path: Path, name: str) -> None:
    indenter = load_indenter(name)
    closed = SneddonModel.for_indenter(indenter, rig.gel)  # the exact profile (sphere cap, filleted punch)
    numerical = DepthTable.build(indenter, rig.gel, mode="halfspace", spacing_mm=0.1, size_mm=16.0, max_depth_mm=1.0,
                                 cache_dir=tmp_path)
    delta = 0.8
    assert numerical.force_n(delta) == pytest.approx(closed.force_n(delta), rel=0.02)
    x = np.linspace(0.0, 7.5, 16)
    uz_num, contact_num = numerical.fields(delta, x, np.zeros_like(x))
    uz_closed, contact_closed = closed.fields(delta, x, np.zeros_like(x))
    np.testing.assert_allclose(uz_num, uz_closed, atol=0.02 * delta)
    assert np.count_nonzero(contact_num != contact_closed) <= 1
    if name == "sphere":  # Hertz is the paraboloid: within 3 % of the sphere cap at this depth
        assert HertzModel(6.0, rig.gel).force_n(delta) == pytest.approx(closed.force_n(delta), rel=0.03)


def test_numerical_maps_are_bilinear_samples_of_the_table(rig: RigConfig, tmp_path: Path) -> None:
    from scipy import ndimage

    table = DepthTable.build(load_indenter("sphere"), rig.gel, mode="halfspace", spacing_mm=0.1, size_mm=8.0,
                             max_depth_mm=1.0, cache_dir=tmp_path)
    rng = np.random.default_rng(2)
    dx, dy = rng.uniform(-4.5, 4.5, (2, 30, 40))  # some beyond the table's 8 mm
    delta = 0.63
    uz, contact = table.fields(delta, dx, dy)
    i, w = table._bracket(delta)
    g = table.grid
    coords = np.stack([dy.ravel() / g.spacing_mm + g.ny // 2, dx.ravel() / g.spacing_mm + g.nx // 2])
    inside = ((coords >= 0) & (coords <= np.array([[g.ny - 1], [g.nx - 1]]))).all(axis=0)
    expected = sum(wk * ndimage.map_coordinates(table.uz[k].astype(np.float64), coords, order=1)
                   for k, wk in ((i, 1 - w), (i + 1, w)))
    mask = sum(wk * ndimage.map_coordinates(table.contact[k].astype(np.float64), coords, order=1)
               for k, wk in ((i, 1 - w), (i + 1, w)))
    touching = ((mask >= 0.5) & inside).reshape(dx.shape)
    assert np.array_equal(contact, touching)
    free = inside.reshape(dx.shape) & ~touching
    np.testing.assert_allclose(uz[free], expected.reshape(dx.shape)[free], rtol=1e-12, atol=1e-12)
    assert inside.sum() < inside.size and np.all(uz[~inside.reshape(dx.shape)] > 0)  # the half-space's far field


def test_model_choice_per_indenter(rig: RigConfig) -> None:
    assert choose_model(load_indenter("sphere"), rig.gel, "halfspace").method == "hertz"
    assert choose_model(load_indenter("cylinder"), rig.gel, "halfspace").method == "sneddon"
    assert choose_model(load_indenter("square"), rig.gel, "halfspace").method == "numerical"
    assert choose_model(load_indenter("sphere"), rig.gel, "layer").method == "numerical"
    with pytest.raises(ValueError, match="half-space"):
        choose_model(load_indenter("sphere"), rig.gel, "layer", "hertz")


# ---------------------------------------------------------------------------------- maps


def test_map_centre_is_where_the_indenter_is_in_the_image(probe: Path, rig: RigConfig) -> None:
    gt = generate(probe)
    assert gt.attrs["elastic_model"] == "layer" and gt.attrs["contact_model"] == "numerical"
    deepest = int(np.argmax(gt.indentation_mm))
    assert gt.indentation_mm[deepest] == pytest.approx(1.0, abs=0.03)
    mask = gt.contact_mask[deepest].astype(bool)
    rows, cols = np.nonzero(mask)
    centre = np.array([cols.mean(), rows.mean()])
    # the commanded location projected through the camera into the network grid

    px = true_camera(rig).project(np.array([[2.0, -1.5, 0.0]]))[0]
    roi = rig.roi
    cell = np.array([(px[0] - roi.x0_px + 0.5) * 112 / roi.width_px - 0.5, (px[1] - roi.y0_px + 0.5) * 90 / roi.height_px - 0.5])
    assert np.hypot(*(centre - cell)) < 2.0  # cells (0.27 mm): the nominal gel pose is 0.4 mm off the true one
    # and where the events are while pressing
    with Recording(probe) as rec:
        down = next(p for p in rec.phases() if p.name == "normal_down")
        ev = rec.events_between(down.t_end_us - 150_000, down.t_end_us)
    ex = (ev["x"] - roi.x0_px + 0.5) * 112 / roi.width_px - 0.5
    ey = (ev["y"] - roi.y0_px + 0.5) * 90 / roi.height_px - 0.5
    near = np.hypot(ex - centre[0], ey - centre[1]) < 25
    assert np.hypot(ex[near].mean() - centre[0], ey[near].mean() - centre[1]) < 2.0
    # depth inside the contact is the indenter's surface; the map peaks at the indentation
    assert gt.depth_mm[deepest].max() == pytest.approx(gt.indentation_mm[deepest], abs=0.01)
    assert gt.depth_norm.max() <= 1.0 and gt.depth_norm.min() >= 0.0


def test_layer_beats_halfspace_out_of_contact(probe: Path) -> None:
    with Recording(probe) as rec:
        truth = rec.stream("truth/depth")
    errors = {}
    for elastic in ("layer", "halfspace"):
        gt = generate(probe, elastic=elastic)
        idx = np.clip(np.searchsorted(truth["t_host_us"], gt.t_us, side="right") - 1, 0, None)
        true_depth, true_mask = truth["depth_mm"][idx], truth["contact_mask"][idx].astype(bool)
        active = gt.indentation_mm > 0.2
        err = np.abs(gt.depth_mm[active] - true_depth[active])
        errors[elastic] = float(err[~true_mask[active]].mean())
    assert errors["layer"] < 0.02 < errors["halfspace"]


# ---------------------------------------------------------------------------------- sidecar


def test_sidecar_round_trip(probe: Path, tmp_path: Path) -> None:
    gt = generate(probe, elastic="halfspace", rate_hz=50)
    out = write_sidecar(gt, tmp_path / "probe.gt.h5")
    assert sidecar_path(probe).name == "probe.gt.h5"
    loaded = load_groundtruth(out)
    assert len(loaded) == gt.t_us.size
    np.testing.assert_array_equal(loaded.t_us, gt.t_us)
    np.testing.assert_array_equal(loaded.depth_mm, gt.depth_mm)
    np.testing.assert_array_equal(loaded.contact_mask, gt.contact_mask)
    assert loaded.depth_mm.dtype == np.float32 and loaded.contact_mask.dtype == np.uint8
    assert loaded.depth_mm.shape[1:] == (90, 112) and loaded.grid_px.shape == (90, 112, 2)
    assert loaded.attrs["elastic_model"] == "halfspace" and loaded.attrs["contact_model"] == "hertz"
    assert loaded.attrs["youngs_modulus_mpa"] == pytest.approx(gt.attrs["youngs_modulus_mpa"])
    assert loaded.attrs["youngs_modulus_mpa"] == pytest.approx(0.4, rel=0.05)  # the rig's, or the fitted gel.toml's
    assert loaded.scale_mm == pytest.approx(2.5)
    from labrig.cache import sha256_of

    assert loaded.attrs["source_sha256"] == sha256_of(probe)
    assert json.loads(loaded.attrs["model_json"])["method"] == "hertz"
    with h5py.File(out) as f:
        assert f["depth_mm"].chunks == (1, 90, 112) and str(hdf5plugin.Zstd.filter_id) in f["depth_mm"]._filters
    # nearest in time: a window's last event 3 ms after a map picks that map
    i = len(loaded) // 2
    dt, depth, _mask, indentation = loaded.nearest(float(loaded.t_us[i]) + 3000)
    assert dt == -3000 and np.array_equal(depth, loaded.depth_mm[i]) and indentation == loaded.indentation_mm[i]
    assert list(loaded.nearest_index([loaded.t_us[0] - 10**6, loaded.t_us[-1] + 10**6])) == [0, len(loaded) - 1]
    assert loaded.normalised(i).min() >= 0.0 and loaded.normalised(i).max() <= 1.0


def test_load_groundtruth_refuses_other_files(probe: Path, tmp_path: Path) -> None:
    with pytest.raises(GroundTruthError, match="not a labrig ground-truth sidecar"):
        load_groundtruth(probe)
    with pytest.raises(GroundTruthError, match="no such"):
        load_groundtruth(tmp_path / "missing.gt.h5")


# ---------------------------------------------------------------------------------- CLI


def _run(*args: str):  # type: ignore[no-untyped-def]
    from typer.testing import CliRunner

    from labrig.cli import app

    return CliRunner().invoke(app, ["groundtruth", *args])


def test_cli_single_recording_then_current(probe: Path, tmp_path: Path) -> None:
    import shutil

    rec = tmp_path / "run.h5"
    shutil.copy(probe, rec)
    first = _run(str(rec), "--json", "--rate-hz", "50")
    assert first.exit_code == 0, first.output
    summary = json.loads(first.output)
    assert summary["written"] == 1 and summary["results"][0]["elastic_model"] == "layer"
    assert (tmp_path / "run.gt.h5").exists()
    second = json.loads(_run(str(rec), "--json", "--rate-hz", "50").output)
    assert second["current"] == 1 and second["written"] == 0
    third = json.loads(_run(str(rec), "--json", "--rate-hz", "50", "--model", "halfspace").output)
    assert third["written"] == 1 and third["results"][0]["contact_model"] == "hertz"


def test_cli_campaign_folder(probe: Path, tmp_path: Path) -> None:
    import shutil

    shutil.copy(probe, tmp_path / "a.h5")
    (tmp_path / "manifest.csv").write_text("id,split,status,file,sha256\na,train,complete,a.h5,\nb,val,pending,,\n")
    result = _run(str(tmp_path), "--json", "--rate-hz", "20")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["written"] == 1 and summary["not_complete_in_manifest"] == 1
    assert summary["results"][0]["split"] == "train"


def test_cli_campaign_folder_on_worker_processes(probe: Path, tmp_path: Path) -> None:
    """--workers 2: the same sidecars through the executor's local processes."""
    import shutil

    for name in ("a", "b"):
        shutil.copy(probe, tmp_path / f"{name}.h5")
    (tmp_path / "manifest.csv").write_text("id,split,status,file,sha256\na,train,complete,a.h5,\nb,val,complete,b.h5,\n")
    result = _run(str(tmp_path), "--json", "--rate-hz", "20", "--workers", "2")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["written"] == 2 and summary["failed"] == 0
    assert [r["split"] for r in summary["results"]] == ["train", "val"]
    assert (tmp_path / "a.gt.h5").exists() and (tmp_path / "b.gt.h5").exists()


@pytest.mark.parametrize(("make", "message"), [
    (lambda d: d, "no manifest.csv"),
    (lambda d: (d / "notes.txt").write_text("hello") and d / "notes.txt", "not an HDF5 file"),
    (lambda d: d / "missing.h5", "no such file"),
])
def test_cli_bad_inputs_are_clear_errors(tmp_path: Path, make, message: str) -> None:  # type: ignore[no-untyped-def]
    result = _run(str(make(tmp_path)))
    assert result.exit_code != 0
    assert isinstance(result.exception, LabrigError)
    assert message in str(result.exception)


def test_cli_hdf5_that_is_not_a_recording_and_bad_options(tmp_path: Path) -> None:
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = [1]
    result = _run(str(other))
    assert isinstance(result.exception, LabrigError) and "not a labrig recording" in str(result.exception)
    result = _run(str(other), "--model", "plate")
    assert isinstance(result.exception, LabrigError) and "--model" in str(result.exception)


def test_cli_uses_the_indenter_a_recording_carries_and_counts_failures(probe: Path, tmp_path: Path) -> None:
    """A lab's own height-map indenter needs no indenters file: the recording carries its definition.
    A recording with neither a definition nor a known name fails, and the command says so and exits 1."""
    import shutil

    from labrig.indenters import indenter_toml

    sphere = load_indenter("sphere")
    y, x = np.mgrid[-60:61, -60:61] * 0.1
    dome = dataclasses.replace(sphere, name="lab-dome", kind="heightmap", geometry={"file": "dome.npy", "spacing_mm": 0.1},
                               _heightmap=np.asarray(sphere.height_mm(x, y)))
    shutil.copy(probe, tmp_path / "dome.h5")
    shutil.copy(probe, tmp_path / "orphan.h5")
    with h5py.File(tmp_path / "dome.h5", "r+") as f:
        f.attrs["indenter"] = "lab-dome"
        f.attrs["indenter_definition"] = indenter_toml(dome)
    with h5py.File(tmp_path / "orphan.h5", "r+") as f:
        f.attrs["indenter"] = "lab-only"
        del f.attrs["indenter_definition"]
    (tmp_path / "manifest.csv").write_text("id,split,status,file,sha256\ndome,test,complete,dome.h5,\n"
                                           "orphan,test,complete,orphan.h5,\n")
    result = _run(str(tmp_path), "--json", "--rate-hz", "20", "--model", "halfspace")
    assert result.exit_code == 1, result.output
    summary = json.loads(result.stdout)
    by_name = {Path(r["recording"]).name: r for r in summary["results"]}
    assert by_name["dome.h5"]["status"] == "written" and by_name["dome.h5"]["contact_model"] == "numerical"
    assert by_name["orphan.h5"]["status"] == "failed" and "--indenters" in by_name["orphan.h5"]["reason"]
    assert summary["failed"] == 1 and "1 of 2 recordings failed" in result.stderr


def test_a_press_deeper_than_its_indenters_max_depth_gets_tables_that_reach_it(probe: Path, tmp_path: Path) -> None:
    """A pin's or a texture's contact comes at a depth, so a press can reach past the travel its protocol asked
    for, and past the indenter's ``max_depth_mm``: the tables are built as deep as the press went."""
    import shutil

    from labrig.groundtruth.generate import TABLE_REACH_STEP_MM
    from labrig.indenters import indenter_toml

    shallow = dataclasses.replace(load_indenter("sphere"), name="shallow-sphere", max_depth_mm=0.6)
    shutil.copy(probe, tmp_path / "deep.h5")
    with h5py.File(tmp_path / "deep.h5", "r+") as f:
        f.attrs["indenter"] = "shallow-sphere"
        f.attrs["indenter_definition"] = indenter_toml(shallow)
    gt = generate(tmp_path / "deep.h5", table_options={"cache_dir": tmp_path / "tables"})
    deepest = int(np.argmax(gt.indentation_mm))
    assert gt.indentation_mm[deepest] == pytest.approx(1.0, abs=0.03)
    assert gt.depth_mm[deepest].max() == pytest.approx(gt.indentation_mm[deepest], abs=0.01)
    reaches = {json.loads(str(np.load(p)["meta"]))["spec"]["max_depth_mm"] for p in (tmp_path / "tables").rglob("*.npz")}
    assert min(reaches) == pytest.approx(0.6)  # the indenter's, on which the depth at contact is found
    reach = max(reaches)
    assert reach >= gt.indentation_mm.max() and reach / TABLE_REACH_STEP_MM == pytest.approx(round(reach / TABLE_REACH_STEP_MM))
