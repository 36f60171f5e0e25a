"""Indenters as data and the rig configuration: shapes, validation, clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labrig.config import ConfigError, load_rig
from labrig.indenters import IndenterError, load_indenter, load_indenters
from labrig.sim.truth_config import sim_config


def test_default_indenters_have_the_paper_shapes() -> None:
    indenters = load_indenters()
    assert set(indenters) == {"sphere", "cylinder", "square", "ridge"}
    sphere, cylinder, square, ridge = (indenters[n] for n in ("sphere", "cylinder", "square", "ridge"))
    # Sphere of radius 6 mm: a cap of height R - sqrt(R^2 - r^2).
    assert sphere.height_mm(3.0, 0.0) == pytest.approx(6 - np.sqrt(27))
    assert sphere.height_mm(0.0, 0.0) == 0.0 and np.isinf(sphere.height_mm(6.5, 0.0))
    # Flat faces, filleted edges, nothing past the rim.
    assert cylinder.height_mm(2.5, 0.0) == 0.0 and 0 < cylinder.height_mm(2.9, 0.0) < 0.3
    assert np.isinf(cylinder.height_mm(3.1, 0.0))
    assert square.height_mm(2.0, 2.0) == 0.0 and np.isinf(square.height_mm(2.6, 0.0))
    assert 0 < square.height_mm(2.4, 2.4) < 0.3 and np.isinf(square.height_mm(2.45, 2.45))
    # Ridge: a round bar 2 mm wide along x, 12 mm long, with round ends.
    assert ridge.height_mm(4.0, 0.0) == 0.0 and ridge.height_mm(0.0, 0.5) == pytest.approx(1 - np.sqrt(0.75))
    assert np.isinf(ridge.height_mm(0.0, 1.1)) and np.isinf(ridge.height_mm(6.1, 0.0))


def test_a_height_map_indenter_needs_no_code(tmp_path: Path) -> None:
    y, x = np.mgrid[-20:21, -20:21] * 0.1
    np.save(tmp_path / "cone.npy", np.hypot(x, y) * 0.5)
    (tmp_path / "indenters.toml").write_text(
        '[cone]\nkind = "heightmap"\nfile = "cone.npy"\nspacing_mm = 0.1\ntool_offset_mm = [0, 0, -40]\n'
        "max_normal_force_n = 10\nmax_shear_force_n = 2\nmax_depth_mm = 1\n"
    )
    cone = load_indenter("cone", tmp_path / "indenters.toml")
    assert cone.height_mm(1.0, 0.0) == pytest.approx(0.5)
    assert cone.height_mm(0.55, 0.0) == pytest.approx(0.275)
    assert np.isinf(cone.height_mm(2.5, 0.0))


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ('[a]\nkind = "blob"\n', "kind must be one of"),
        ('[a]\nkind = "sphere"\nradius_mm = 6\n', "missing 'tool_offset_mm'"),
        ('[a]\nkind = "sphere"\nradius = 6\n', "unknown key 'radius'"),
        ('[a]\nkind = "sphere"\nradius_mm = -1\ntool_offset_mm = [0,0,0]\nmax_normal_force_n = 1\n'
         "max_shear_force_n = 1\nmax_depth_mm = 1\n", "positive number of mm"),
        ("[a\n", "not valid TOML"),
    ],
)
def test_bad_indenter_files_say_what_is_wrong(tmp_path: Path, body: str, message: str) -> None:
    path = tmp_path / "indenters.toml"
    path.write_text(body)
    with pytest.raises(IndenterError, match=message):
        load_indenters(path)


def test_unknown_indenter_lists_the_known_ones() -> None:
    with pytest.raises(IndenterError, match="sphere, cylinder, square, ridge"):
        load_indenter("banana")


def test_default_rig_config_is_consistent() -> None:
    rig = load_rig()
    markers = rig.markers.rest_positions_mm()
    assert markers.shape == (156, 3)
    assert np.ptp(markers[:, 0]) == pytest.approx(24.0) and np.ptp(markers[:, 1]) == pytest.approx(22.0)
    # About 28 px per mm at the membrane: a 0.5 mm marker is about 14 px across.
    depth_mm = sim_config(rig).camera.gel_to_camera_translation_mm[2]
    assert sim_config(rig).camera.fx_px / depth_mm == pytest.approx(28.0, rel=0.02)
    assert rig.roi.width_px > 24 * 28 and rig.roi.height_px > 22 * 28


def test_bad_rig_config_names_the_field(tmp_path: Path) -> None:
    text = load_rig().text.replace("poisson_ratio = 0.48", "poisson_ratio = 0.7")
    (tmp_path / "rig.toml").write_text(text)
    with pytest.raises(ConfigError, match=r"\[gel\] poisson_ratio"):
        load_rig(tmp_path / "rig.toml")
    (tmp_path / "rig.toml").write_text(load_rig().text.replace("[roi]", "[roi]\nzoom = 2"))
    with pytest.raises(ConfigError, match="unknown key 'zoom'"):
        load_rig(tmp_path / "rig.toml")


def test_an_indenter_definition_round_trips_through_its_own_toml(tmp_path: Path) -> None:
    """What a recording stores (indenter_toml) gives back the same shape and limits, a height map inline."""
    from labrig.indenters import indenter_from_toml, indenter_toml

    y, x = np.mgrid[-20:21, -25:26] * 0.1
    heights = np.hypot(x, y) * 0.5
    heights[0, 0] = np.inf  # no surface there
    np.save(tmp_path / "cone.npy", heights)
    (tmp_path / "indenters.toml").write_text(
        '[cone]\nkind = "heightmap"\nfile = "cone.npy"\nspacing_mm = 0.1\ntool_offset_mm = [0, 0.5, -40]\n'
        "max_normal_force_n = 10\nmax_shear_force_n = 2\nmax_depth_mm = 1\n"
    )
    lab = load_indenters(tmp_path / "indenters.toml")
    xs, ys = np.meshgrid(np.linspace(-3, 3, 23), np.linspace(-3, 3, 19))
    for original in (*load_indenters().values(), lab["cone"]):
        copy = indenter_from_toml(indenter_toml(original), "run.h5")
        assert (copy.name, copy.kind, copy.tool_offset_mm, copy.max_depth_mm, copy.max_normal_force_n,
                copy.max_shear_force_n) == (original.name, original.kind, original.tool_offset_mm, original.max_depth_mm,
                                            original.max_normal_force_n, original.max_shear_force_n)
        np.testing.assert_array_equal(copy.height_mm(xs, ys), original.height_mm(xs, ys))
        assert copy.footprint_radius_mm == original.footprint_radius_mm
    with pytest.raises(IndenterError, match=r"run\.h5: an indenter definition holds one indenter"):
        indenter_from_toml(indenter_toml(lab["cone"]) + "[b]\n", "run.h5")
