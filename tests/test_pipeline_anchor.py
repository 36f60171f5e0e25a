"""The contact's anchor: held through a shallow release, following a slip, reset between contacts."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from labrig.config import RigConfig
from labrig.eventtypes import EVENT_DTYPE
from labrig.models import bundled_model_path
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline import depth_sources, run_setup, runtime
from labrig.pipeline.anchor import AnchorFilter, AnchorParams
from labrig.pipeline.model_card import ModelCard

TRUE_MM = np.array([1.5, -2.0])


def _core(rng: np.random.Generator, peak_mm: float, params: AnchorParams, at_mm: np.ndarray = TRUE_MM) -> np.ndarray:
    """A window's dent core: the true anchor plus the noise the filter expects at ``peak_mm``."""
    return at_mm + rng.normal(0.0, params.measurement_sigma_mm(peak_mm), 2)


def test_a_shallow_release_keeps_the_anchor_the_deep_press_found() -> None:
    params = AnchorParams()
    rng = np.random.default_rng(3)
    press = np.r_[np.linspace(0.05, 1.5, 15), np.full(20, 1.5), np.linspace(1.5, 0.05, 25)]  # down, hold, up
    raw, filtered = [], []
    kf = AnchorFilter(params)
    for peak in press:
        z = _core(rng, peak, params)
        raw.append(np.linalg.norm(z - TRUE_MM))
        filtered.append(np.linalg.norm(kf.update(z, peak, 0.02) - TRUE_MM))
    release = slice(35 + 15, None)  # the last ten windows: dents under 0.6 mm
    assert np.mean(filtered[release]) < 0.25 * np.mean(raw[release])
    assert np.mean(filtered[release]) < 0.05  # mm: the hold's error, not the shallow cores'


def test_a_slipping_contact_is_followed_within_a_few_windows() -> None:
    params = AnchorParams()
    rng = np.random.default_rng(4)
    kf = AnchorFilter(params)
    for _ in range(30):
        kf.update(_core(rng, 1.2, params), 1.2, 0.02)
    slipped = TRUE_MM + np.array([0.8, 0.0])  # gross slip: the contact is dragged 0.8 mm
    errors = [np.linalg.norm(kf.update(_core(rng, 1.2, params, slipped), 1.2, 0.02) - slipped) for _ in range(8)]
    assert errors[0] > 0.5  # one improbable core is not yet a slip
    assert max(errors[3:]) < 3 * params.floor_mm


def test_a_lone_outlier_is_bounded_and_no_dent_ends_the_contact() -> None:
    params = AnchorParams()
    kf = AnchorFilter(params)
    for _ in range(20):
        kf.update(TRUE_MM, 1.0, 0.02)
    after = kf.update(TRUE_MM + np.array([0.0, 3.0]), 1.0, 0.02)  # one core 3 mm off, a deep map's
    assert np.linalg.norm(after - TRUE_MM) < 0.2
    np.testing.assert_allclose(kf.update(TRUE_MM, 1.0, 0.02), TRUE_MM, atol=0.2)
    assert kf.update(None, 0.0, 0.02) is None and kf.anchor_mm is None
    elsewhere = np.array([-4.0, 3.0])
    np.testing.assert_array_equal(kf.update(elsewhere, 0.3, 0.02), elsewhere)  # a new contact starts from its core


def test_a_surer_core_far_from_a_shaky_anchor_is_a_new_contact() -> None:
    """A faint dimple before the press (a noise dent, 0.05 mm) starts an anchor the filter barely trusts;
    the press's first core, 5 mm away and surer, is taken at once, not bounded as an outlier."""
    kf = AnchorFilter()
    kf.update(np.array([-3.0, 2.0]), 0.05, 0.02)
    np.testing.assert_array_equal(kf.update(TRUE_MM, 0.4, 0.02), TRUE_MM)
    sure = AnchorFilter()  # the same far core against a sure anchor is one outlier, bounded
    for _ in range(10):
        sure.update(np.array([-3.0, 2.0]), 1.0, 0.02)
    assert np.linalg.norm(sure.update(TRUE_MM, 0.4, 0.02) - np.array([-3.0, 2.0])) < 0.5


class _Dents(depth_sources.DepthSource):
    """A depth source that replays maps, with the bundled network's anchor noise."""

    name = "dents"
    needs_sae = False
    window_us = None

    def __init__(self, maps: list[np.ndarray], anchor: AnchorParams | None) -> None:
        self.maps, self.anchor, self.k = maps, anchor, 0

    def depth_mm(self, sae_grid: Any, t0_us: int, t1_us: int, n_events: int) -> np.ndarray:
        self.k += 1
        return self.maps[self.k - 1]


def _dent(row: int, col: int, peak_mm: float) -> np.ndarray:
    rr, cc = np.indices(GRID_SHAPE)
    return (peak_mm * np.exp(-((rr - row) ** 2 + (cc - col) ** 2) / 18.0)).astype(np.float32)


@pytest.fixture(scope="module")
def setup(rig: RigConfig) -> run_setup.PipelineSetup:
    return run_setup.setup_for_rig(rig, calibration_dir=None)


def test_the_pipeline_reports_the_filtered_anchor_and_forgets_it_at_rest(setup: run_setup.PipelineSetup) -> None:
    residue = np.zeros(GRID_SHAPE, np.float32)
    residue[70:74, 90:94] = 0.08  # the release's last shallow map, its core far from the press
    shallow = _dent(40, 50, 0.1) + residue
    maps = [_dent(40, 50, 1.0)] * 10 + [_dent(40, 50, 0.3), shallow, np.zeros(GRID_SHAPE, np.float32), _dent(20, 30, 0.8)]
    empty = np.zeros(0, EVENT_DTYPE)

    def run(anchor: AnchorParams | None) -> list[runtime.WindowResult]:
        pipe = runtime.Pipeline(setup, _Dents(maps, anchor))
        return [pipe.process(10_000 * k, 10_000 * (k + 1), empty) for k in range(len(maps))]

    raw, filtered = run(None), run(AnchorParams())
    deep = raw[9].contact_px
    assert np.linalg.norm(raw[11].contact_px - deep) > 20  # the shallow core alone is pulled to the residue
    assert np.linalg.norm(filtered[11].contact_px - deep) < 3  # the anchor holds
    assert np.isnan(filtered[12].contact_px).all()  # no dent: no contact
    np.testing.assert_allclose(filtered[13].contact_px, raw[13].contact_px)  # a new press starts from its own core


def test_networks_carry_the_anchor_noise_and_the_truth_needs_none(setup: run_setup.PipelineSetup) -> None:
    source = depth_sources.depth_source("model", setup, model_path=bundled_model_path())
    assert source.anchor == depth_sources.DEFAULT_ANCHOR
    card = {"contact_anchor": {"floor_mm": 0.1}}
    assert depth_sources.anchor_params_for(_card(card)).floor_mm == 0.1
    with pytest.raises(depth_sources.LabrigError, match="contact_anchor"):
        depth_sources.anchor_params_for(_card({"contact_anchor": {"floor": 0.1}}))
    assert depth_sources.TruthDepth.anchor is None


def _card(sections: dict[str, Any]) -> ModelCard:
    """A model card with these sections (and the scale every card has)."""
    return ModelCard.from_json({"format": "labrig.depthnet", "scale_mm": 2.5, **sections})
