"""Contact shape: a footprint follows its yaw relative to the gel; a height map's tool axis can be set."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from labrig.config import RigConfig, rig_with
from labrig.frames import Pose, yaw_tilt_matrix
from labrig.groundtruth.contact import DepthTable
from labrig.groundtruth.turned import TurnedModel, lab_footprint_yaw_deg, turned_model
from labrig.indenters import Indenter, IndenterError, load_indenter, load_indenters
from labrig.physics.mechanics import ContactTable
from labrig.physics.mechanics.table_cache import table_key, table_spec
from labrig.sim.truth_config import sim_config, true_contact_table

#: A small, coarse table: enough to see a footprint's shape, seconds to build.
SMALL = {"spacing_mm": 0.2, "size_mm": 12.0, "max_depth_mm": 0.3, "shear_steps": 2}


def square_orientation_deg(mask: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray) -> float:
    """The turn of a square footprint's sides from the x axis, deg in (-45, 45], from its 4-fold moment."""
    x, y = np.meshgrid(x_mm, y_mm)
    z = (x + 1j * y)[mask]
    moment = np.sum(np.abs(z) ** 4 * np.exp(4j * np.angle(z)))
    turn = np.degrees(np.angle(-moment)) / 4  # a square's corners (r^4 weighs them) lie at 45 deg from its sides
    return float(45 - (45 - turn) % 90)


@pytest.fixture(scope="module")
def square_tables(rig: RigConfig, tmp_path_factory: pytest.TempPathFactory) -> tuple[ContactTable, ContactTable]:
    """(unturned, turned by 30 deg relative to the gel): the gel yawed by -30 deg in the CNC frame."""
    cache = tmp_path_factory.mktemp("tables")
    square = load_indenter("square")
    flat = ContactTable.build(square, sim_config(rig).gel, cache_dir=cache, **SMALL)
    turned = true_contact_table(square, rig_with(rig, {"sim.rig_pose.gel_yaw_deg": -30.0}), cache_dir=cache, **SMALL)
    return flat, turned


def test_a_square_turned_30_deg_from_the_gel_presses_a_footprint_turned_30_deg(
    square_tables: tuple[ContactTable, ContactTable],
) -> None:
    flat, turned = square_tables
    assert flat.yaw_deg == 0.0 and turned.yaw_deg == pytest.approx(30.0)
    a, b = flat.fields(0.3), turned.fields(0.3)
    assert square_orientation_deg(a.contact_mask, a.x_mm, a.y_mm) == pytest.approx(0.0, abs=1.5)
    assert square_orientation_deg(b.contact_mask, b.x_mm, b.y_mm) == pytest.approx(30.0, abs=1.5)
    # Same face, same force: only the footprint turned.
    assert b.contact_mask.sum() == pytest.approx(a.contact_mask.sum(), rel=0.1)  # edge cells of a 0.2 mm grid
    assert b.force_n[2] == pytest.approx(a.force_n[2], rel=0.06)  # a punch's edge on a coarse grid
    # The depth map is the unturned one turned by 30 deg (sampled back at the turned points).
    x, y = np.meshgrid(b.x_mm, b.y_mm)
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    spacing = b.x_mm[1] - b.x_mm[0]
    cols = (c * x + s * y - a.x_mm[0]) / spacing
    rows = (-s * x + c * y - a.y_mm[0]) / spacing
    back = ndimage.map_coordinates(a.depth_mm.astype(np.float64), [rows, cols], order=1, mode="nearest")
    box = np.hypot(x, y) < 5.0
    assert np.median(np.abs(b.depth_mm - back)[box]) < 0.01 * 0.3
    assert np.median(np.abs(b.depth_mm - a.depth_mm)[box]) > 5 * np.median(np.abs(b.depth_mm - back)[box])


def test_the_ground_truth_turns_the_square_as_the_sim_does(
    rig: RigConfig, square_tables: tuple[ContactTable, ContactTable], tmp_path: Path
) -> None:
    square = replace(load_indenter("square"), yaw_deg=30.0)
    gel_pose = Pose(yaw_tilt_matrix(0.0), np.zeros(3))
    assert lab_footprint_yaw_deg(square, gel_pose) == pytest.approx(30.0)
    table = DepthTable.build(square, sim_config(rig).gel, spacing_mm=0.2, size_mm=12.0, max_depth_mm=0.3, cache_dir=tmp_path)
    model = turned_model(table, square, gel_pose)
    assert isinstance(model, TurnedModel) and model.describe()["footprint_yaw_deg"] == pytest.approx(30.0)
    sim = square_tables[1].fields(0.3)
    x, y = np.meshgrid(sim.x_mm, sim.y_mm)
    _, mask = model.fields(0.3, x, y)
    _, unturned = table.fields(0.3, x, y)
    assert square_orientation_deg(mask, sim.x_mm, sim.y_mm) == pytest.approx(30.0, abs=1.5)
    overlap = np.sum(mask & sim.contact_mask) / np.sum(mask | sim.contact_mask)
    assert overlap > 0.9 and overlap > np.sum(unturned & sim.contact_mask) / np.sum(unturned | sim.contact_mask) + 0.1
    # An unturned indenter keeps the plain model.
    assert turned_model(table, load_indenter("square"), gel_pose) is table


def rig_footprint_yaw_deg(indenter: Indenter, rig: RigConfig) -> float:
    return indenter.footprint_yaw_deg(sim_config(rig).rig_pose.gel_yaw_deg)


def test_footprint_yaw_is_the_indenters_yaw_minus_the_gels_reduced_by_symmetry(rig: RigConfig) -> None:
    indenters = load_indenters()
    assert sim_config(rig).rig_pose.gel_yaw_deg == pytest.approx(0.6)
    assert rig_footprint_yaw_deg(indenters["square"], rig) == pytest.approx(-0.6)
    assert rig_footprint_yaw_deg(indenters["ridge"], rig) == pytest.approx(-0.6)
    assert rig_footprint_yaw_deg(indenters["sphere"], rig) == 0.0
    square = replace(indenters["square"], yaw_deg=120.6)
    assert rig_footprint_yaw_deg(square, rig) == pytest.approx(30.0)  # 120 deg = 30 deg for a square
    assert replace(indenters["ridge"], yaw_deg=200.0).footprint_yaw_deg(0.0) == pytest.approx(20.0)


def test_table_cache_keys_differ_by_yaw(rig: RigConfig, tmp_path: Path) -> None:
    indenters = load_indenters()
    # The virtual rig's tables (true_contact_table) take the yaw relative to the true gel, cached apart.
    turned = true_contact_table(indenters["square"], rig, cache_dir=tmp_path, **SMALL)
    unturned = true_contact_table(indenters["square"], rig, cache_dir=tmp_path, yaw_deg=0.0, **SMALL)
    assert turned.yaw_deg == pytest.approx(-0.6) and unturned.yaw_deg == 0.0
    assert turned.meta["key"] != unturned.meta["key"] and len(list(tmp_path.rglob("square-*.npz"))) == 2
    options = {"mode": "layer", "spacing_mm": 0.1, "size_mm": 24.0, "direction_deg": 0.0, "depth_step_mm": 0.05,
               "max_depth_mm": 1.5, "shear_depth_stride": 1, "shear_steps": 10}

    def key(indenter: Indenter, yaw: float) -> str:
        return table_key(table_spec(indenter, sim_config(rig).gel, yaw_deg=indenter.reduced_turn_deg(yaw), **options))

    square, sphere = indenters["square"], indenters["sphere"]
    assert len({key(square, yaw) for yaw in (0.0, 30.0, -0.6, 0.6)}) == 4
    assert key(square, 90.0) == key(square, 0.0)  # a square turned a quarter is the same square
    assert key(sphere, 30.0) == key(sphere, 0.0)
    # An unturned indenter's spec has no yaw: its cached tables keep their keys.
    assert "yaw_deg" not in table_spec(square, sim_config(rig).gel, **options)


# ------------------------------------------------------------------------------------- height-map axis


def write_ring(folder: Path, axis: str | None, load: bool = True) -> Indenter | None:
    """A torus ring (2.5 mm radius, 0.5 mm tube) on an 81 x 81 map at 0.1 mm (its centre is [4, 4] mm),
    in ``folder``/indenters.toml; loaded when ``load``."""
    y, x = (np.mgrid[0:81, 0:81] - 40) * 0.1
    tube = np.hypot(x, y) - 2.5
    with np.errstate(invalid="ignore"):
        height = np.where(np.abs(tube) < 0.5, 0.5 - np.sqrt(0.25 - tube**2), np.nan)
    np.save(folder / "ring.npy", height)
    key = "" if axis is None else f"axis_mm = {axis}\n"
    (folder / "indenters.toml").write_text(
        '[ring]\nkind = "heightmap"\nfile = "ring.npy"\nspacing_mm = 0.1\ntool_offset_mm = [0, 0, -40]\n'
        f"max_normal_force_n = 10\nmax_shear_force_n = 2\nmax_depth_mm = 0.3\n{key}"
    )
    return load_indenter("ring", folder / "indenters.toml") if load else None


def test_a_ring_with_its_axis_at_its_centre_presses_symmetric(rig: RigConfig, tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    centred = write_ring(tmp_path / "a", "[4.0, 4.0]")
    lowest = write_ring(tmp_path / "b", None)
    assert centred is not None and lowest is not None
    assert centred.axis_mm == (4.0, 4.0) and lowest.axis_mm is None
    assert centred.height_mm(2.5, 0.0) == pytest.approx(0.0) and np.isinf(centred.height_mm(0.0, 0.0))
    assert lowest.height_mm(0.0, 0.0) == pytest.approx(0.0)  # today's default: the tip is a point of the ring
    assert centred.footprint_radius_mm == pytest.approx(3.0, abs=0.05)  # the ring's outer edge, not the map's corner
    table = ContactTable.build(centred, sim_config(rig).gel, cache_dir=tmp_path, **SMALL)
    old = ContactTable.build(lowest, sim_config(rig).gel, cache_dir=tmp_path, **SMALL)
    assert table.meta["key"] != old.meta["key"]
    f = table.fields(0.2)
    assert f.contact_mask.sum() > 50 and not f.contact_mask[len(f.y_mm) // 2, len(f.x_mm) // 2]  # a ring, hole inside
    for flipped in (f.depth_mm[:, ::-1], f.depth_mm[::-1, :], f.depth_mm.T):
        assert np.max(np.abs(flipped - f.depth_mm)) < 1e-3 * 0.2
    assert np.hypot(*table.pressure_centre_mm(0.2)) < 0.01
    assert np.hypot(*old.pressure_centre_mm(0.2)) == pytest.approx(2.5, abs=0.1)  # off the ring's centre
    assert old.fields(0.2).force_n[2] == pytest.approx(f.force_n[2], rel=0.05)
    # The ground truth presses the ring about the same axis.
    truth = DepthTable.build(centred, sim_config(rig).gel, spacing_mm=0.2, size_mm=12.0, max_depth_mm=0.3, cache_dir=tmp_path)
    x, y = np.meshgrid(f.x_mm, f.y_mm)
    uz, mask = truth.fields(0.2, x, y)
    assert np.array_equal(mask, mask[::-1, ::-1]) and np.sum(mask & f.contact_mask) / np.sum(mask | f.contact_mask) > 0.95
    assert np.max(np.abs(uz - uz[::-1, ::-1])) < 1e-3 * 0.2


RING_ENTRY = ('[ring]\nkind = "heightmap"\nfile = "ring.npy"\nspacing_mm = 0.1\ntool_offset_mm = [0, 0, -40]\n'
              "max_normal_force_n = 10\nmax_shear_force_n = 2\nmax_depth_mm = 0.3\n")
SPHERE_ENTRY = ('[ball]\nkind = "sphere"\nradius_mm = 6\ntool_offset_mm = [0, 0, -40]\nmax_normal_force_n = 10\n'
                "max_shear_force_n = 2\nmax_depth_mm = 1\n")


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (RING_ENTRY + "axis_mm = [4.0]\n", "axis_mm must be [x, y] in mm"),
        (RING_ENTRY + 'axis_mm = ["a", 1]\n', "axis_mm must be [x, y] in mm"),
        (RING_ENTRY + "axis_mm = [9.0, 4.0]\n", "lies outside the height map (x 0 to 8 mm"),
        (RING_ENTRY + "axis_mm = [4.0, -0.1]\n", "lies outside the height map"),
        (RING_ENTRY + 'yaw_deg = "north"\n', "yaw_deg must be a number of degrees"),
        (SPHERE_ENTRY + "axis_mm = [0, 0]\n", "unknown key 'axis_mm'"),
        (SPHERE_ENTRY + "yaw_deg = true\n", "yaw_deg must be a number"),
    ],
)
def test_bad_axis_and_yaw_keys_say_what_is_wrong(tmp_path: Path, body: str, message: str) -> None:
    write_ring(tmp_path, None)
    path = tmp_path / "indenters.toml"
    path.write_text(body)
    with pytest.raises(IndenterError, match=message.replace("[", r"\[").replace("(", r"\(")) as info:
        load_indenters(path)
    assert "\n" not in str(info.value)


def test_a_height_map_without_any_surface_is_refused(tmp_path: Path) -> None:
    np.save(tmp_path / "ring.npy", np.full((5, 5), np.nan))
    (tmp_path / "indenters.toml").write_text(RING_ENTRY)
    with pytest.raises(IndenterError, match="no finite height"):
        load_indenters(tmp_path / "indenters.toml")


def test_the_cli_reports_a_bad_axis_in_one_line(tmp_path: Path) -> None:
    write_ring(tmp_path, "[40.0, 4.0]", load=False)
    result = subprocess.run(
        [sys.executable, "-m", "labrig.cli", "sim", "probe", str(tmp_path / "x.h5"), "--indenter", "ring",
         "--indenters", str(tmp_path / "indenters.toml")],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "axis_mm [40.0, 4.0] lies outside the height map" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_ground_truth_maps_of_a_recording_follow_the_indenters_yaw(rig: RigConfig, tmp_path: Path) -> None:
    """`generate` turns the labels by the indenter's yaw (as the recording carries it) minus the registered gel yaw."""
    from labrig.groundtruth import generate
    from labrig.indenters import load_indenters
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    (tmp_path / "indenters.toml").write_text(
        '[square]\nkind = "square"\nside_mm = 5.0\nfillet_mm = 0.3\nyaw_deg = 30.6\ntool_offset_mm = [0.0, 0.0, -40.0]\n'
        "max_normal_force_n = 22.0\nmax_shear_force_n = 5.0\nmax_depth_mm = 1.5\n"
    )
    options = {"spacing_mm": 0.2, "size_mm": 12.0, "cache_dir": str(tmp_path)}
    turns = []
    for square in (load_indenter("square"), load_indenters(tmp_path / "indenters.toml")["square"]):
        recording = tmp_path / f"square-{square.yaw_deg}.h5"
        tool = probing_path(rig, square, location_mm=(1.0, -1.0), depth_mm=0.6, shear_mm=0.0, normal_speed_mm_s=3.0,
                            wait_s=0.05)
        record_live(recording, rig, square, tool, realtime=False)
        gt = generate(recording, table_options=options)
        deepest = int(np.argmax(gt.indentation_mm))
        mask = gt.contact_mask[deepest].astype(bool)
        offset = gt.grid_gel_mm[..., :2] - gt.anchor_gel_mm[deepest]
        z = (offset[..., 0] + 1j * offset[..., 1])[mask]
        turns.append(float(np.degrees(np.angle(-np.sum(np.abs(z) ** 4 * np.exp(4j * np.angle(z))))) / 4))
        assert mask.sum() > 300
    assert turns[0] == pytest.approx(-0.6, abs=1.5)  # the registered gel yaw, 0.6 deg
    assert turns[1] == pytest.approx(30.0, abs=1.5)
