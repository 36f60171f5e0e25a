"""Procedural indenter shapes: families drawn from seeds, named in indenters files, carried by recordings."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labrig.indenter_shapes import FAMILIES, MAX_RELIEF_MM, draw_shape
from labrig.indenters import DEFAULT_INDENTERS, IndenterError, indenter_from_toml, indenter_toml, load_indenters

SHAPES = DEFAULT_INDENTERS.parent / "shapes.toml"


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_a_family_draws_one_shape_per_seed_with_its_tip_at_zero(family: str) -> None:
    a, again, other = draw_shape(family, 3), draw_shape(family, 3), draw_shape(family, 4)
    np.testing.assert_array_equal(a.heights_mm, again.heights_mm)
    assert a.parameters == again.parameters and a.parameters != other.parameters
    finite = a.heights_mm[np.isfinite(a.heights_mm)]
    assert finite.min() == 0.0 and finite.max() <= MAX_RELIEF_MM
    assert finite.size > 300  # a real footprint, not a few samples
    assert not np.isfinite(a.heights_mm).all() or family in ("edge", "textured")


def test_the_families_are_the_shapes_they_say() -> None:
    annulus = draw_shape("annulus", 0)
    centre = annulus.heights_mm.shape[0] // 2
    ring = annulus.parameters["centre_radius_mm"]
    assert np.isinf(annulus.heights_mm[centre, centre])  # open in the middle
    assert annulus.heights_mm[centre, centre + round(ring / annulus.spacing_mm)] < 0.01  # its lowest circle
    pins = draw_shape("pins", 0)
    assert len(pins.parameters["pins_xy_radius_lift_mm"]) >= 2
    lowest = [draw_shape("flat", seed) for seed in range(6)]
    for flat in lowest:  # a flat face: many samples at the tip's height
        assert (flat.heights_mm < 1e-9).sum() * flat.spacing_mm**2 > 1.0
    assert len({round(f.parameters["fillet_mm"], 3) for f in lowest}) == 6
    with pytest.raises(ValueError, match="unknown shape family 'blob'"):
        draw_shape("blob", 0)


def test_the_shapes_file_extends_the_standard_indenters_and_holds_seeds_out() -> None:
    indenters = load_indenters(SHAPES)
    standard = load_indenters()
    assert set(standard) < set(indenters)
    procedural = [name for name in indenters if name not in standard]
    assert len(procedural) == 30 and all(indenters[n].kind == "heightmap" for n in procedural)
    held_out = {n for n in procedural if int(n.rsplit("-", 1)[1]) >= 100}
    assert len(held_out) == 10 and {n.rsplit("-", 1)[0] for n in held_out} == set(FAMILIES)
    shape = indenters["annulus-100"]
    assert shape.axis_mm == (5.0, 5.0)  # the tool axis at the map's centre: the ring pressed round its location
    assert 2.0 < shape.footprint_radius_mm < 4.5  # the farthest sample with a surface, not the map's corner


def test_a_recording_carries_a_procedural_shape_as_its_height_map() -> None:
    shape = load_indenters(SHAPES)["pins-1"]
    copy = indenter_from_toml(indenter_toml(shape), "run.h5")
    xs, ys = np.meshgrid(np.linspace(-4, 4, 31), np.linspace(-4, 4, 29))
    np.testing.assert_array_equal(copy.height_mm(xs, ys), shape.height_mm(xs, ys))
    assert copy.axis_mm == shape.axis_mm and copy.footprint_radius_mm == shape.footprint_radius_mm


LIMITS = "tool_offset_mm = [0, 0, -40]\nmax_normal_force_n = 10\nmax_shear_force_n = 2\nmax_depth_mm = 1\n"


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ('[a]\nkind = "procedural"\nfamily = "blob"\nseed = 1\n' + LIMITS, "family must be one of annulus"),
        ('[a]\nkind = "procedural"\nfamily = "pins"\nseed = -1\n' + LIMITS, "seed must be a whole number"),
        ('[a]\nkind = "procedural"\nfamily = "pins"\nseed = 1\naxis_mm = [1, 1]\n' + LIMITS, "leave out axis_mm"),
        ('extends = 3\n[a]\nkind = "sphere"\nradius_mm = 6\n' + LIMITS, "extends must name another indenters file"),
        ('extends = "indenters.toml"\n', "leads back to itself"),
        ('extends = "missing.toml"\n', "no such indenter file"),
    ],
)
def test_bad_procedural_and_extending_files_say_what_is_wrong(tmp_path: Path, body: str, message: str) -> None:
    path = tmp_path / "indenters.toml"
    path.write_text(body)
    with pytest.raises(IndenterError, match=message):
        load_indenters(path)


def test_an_extending_file_cannot_redefine_a_name(tmp_path: Path) -> None:
    (tmp_path / "mine.toml").write_text(f'extends = "{DEFAULT_INDENTERS}"\n[sphere]\nkind = "sphere"\nradius_mm = 4\n'
                                        + LIMITS)
    with pytest.raises(IndenterError, match=r"\[sphere\] is already defined"):
        load_indenters(tmp_path / "mine.toml")


def test_a_campaign_names_its_indenters_file(tmp_path: Path) -> None:
    from labrig.config import DEFAULT_RIG, load_rig
    from labrig.protocol import load_campaign
    from labrig.protocol.files import campaign_indenters_file
    from labrig.protocol.spec import ProtocolError

    campaign = DEFAULT_INDENTERS.parent / "shape-check.toml"
    assert campaign_indenters_file(campaign) == SHAPES
    plan = load_campaign(campaign, load_rig(DEFAULT_RIG), load_indenters(SHAPES))
    assert {p.spec.indenter for p in plan.plans} >= {"sphere", "edge-100", "textured-101"}
    assert {p.split for p in plan.plans} == {"test"}
    bad = tmp_path / "bad.toml"
    bad.write_text('[campaign]\nname = "bad"\nindenters = "nowhere.toml"\n[[group]]\nindenters = ["sphere"]\n'
                   "locations_mm = [[0.0, 0.0]]\ndepth_mm = [0.5]\n")
    with pytest.raises(ProtocolError, match=r"campaign\.indenters: must name an indenters file"):
        load_campaign(bad, None, load_indenters())
