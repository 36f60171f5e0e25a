"""Training the depth network: losses, the paper's sampling, a short run, resume, the CLI."""

from __future__ import annotations

import itertools
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from labrig.config import RigConfig
from labrig.errors import LabrigError
from labrig.training import TrainConfig, contact_aware_l1, depth_errors_mm, output_paths, train, uniform_l1
from labrig.training.crop import CropAugment
from labrig.training.data import PHASE_MARGIN_S, WindowSampler, open_campaign, torch_dataset
from labrig.training.shift import ShiftAugment, shifted
from labrig.training.trainer import COSINE_FLOOR, DEFAULT_SHIFT_CELLS


@pytest.fixture(scope="session")
def campaign(tmp_path_factory: pytest.TempPathFactory, sphere_press: Path) -> Path:
    """A tiny campaign folder: one short simulated probe (~1 s) as a train and a val recording, with sidecars."""
    from labrig.dataset import sidecar_path
    from labrig.groundtruth import generate, write_sidecar

    folder = tmp_path_factory.mktemp("campaign")
    shutil.copy(sphere_press, folder / "a.h5")
    write_sidecar(generate(folder / "a.h5", rate_hz=100), sidecar_path(folder / "a.h5"))
    shutil.copy(folder / "a.h5", folder / "b.h5")
    shutil.copy(folder / "a.gt.h5", folder / "b.gt.h5")
    (folder / "manifest.csv").write_text("id,split,status,file,sha256\n"
                                         "a,train,complete,a.h5,\nb,val,complete,b.h5,\nc,test,pending,,\n")
    return folder


# ----------------------------------------------------------------------------------------- losses


def test_contact_aware_loss_equals_its_formula_on_a_hand_example() -> None:
    pred = torch.tensor([[[0.5, 0.0], [0.2, 0.1]], [[0.0, 0.0], [0.0, 0.4]]])
    target = torch.tensor([[[0.3, 0.0], [0.0, 0.0]], [[0.0, 0.0], [0.0, 0.0]]])
    contact = torch.tensor([[[1, 0], [1, 0]], [[0, 0], [0, 0]]], dtype=torch.uint8)
    # map 0: contact |0.2| and |0.2| -> 0.2; non-contact 0 and 0.1 -> 0.05. map 1: no contact; non-contact 0.4/4 = 0.1
    l_c, l_nc = 0.2, (0.05 + 0.1) / 2
    assert float(contact_aware_l1(pred, target, contact)) == pytest.approx(0.5 * l_c + 0.5 * l_nc)
    assert float(contact_aware_l1(pred, target, contact, lambda_c=0.8)) == pytest.approx(0.8 * l_c + 0.2 * l_nc)
    assert float(uniform_l1(pred, target)) == pytest.approx((0.2 + 0.2 + 0.1 + 0.4) / 8)
    # a small contact weighs as much as a large one: scaling the contact area leaves the loss alone
    big = torch.ones(1, 4, 4)
    small = torch.zeros(1, 4, 4)
    small[0, 0, 0] = 1
    assert float(contact_aware_l1(big * 0.3, big, big)) == pytest.approx(float(contact_aware_l1(small * 0.3 + (1 - small),
                                                                                                 small + (1 - small), small)))


def test_contact_aware_loss_has_gradients() -> None:
    pred = torch.zeros(2, 3, 3, requires_grad=True)
    contact = torch.zeros(2, 3, 3)
    contact[0, 1, 1] = 1
    contact_aware_l1(pred, torch.ones(2, 3, 3), contact).backward()
    assert pred.grad is not None and float(pred.grad[0, 1, 1]) < 0 and float(pred.grad[1, 0, 0]) < 0


def test_depth_errors_per_map_in_and_out_of_contact() -> None:
    true = np.zeros((2, 2, 2))
    pred = np.array([[[1.0, 0.0], [0.0, 0.2]], [[0.1, 0.1], [0.1, 0.1]]])
    contact = np.array([[[1, 0], [0, 0]], [[0, 0], [0, 0]]])
    e = depth_errors_mm(pred, true, contact)
    assert e["total_mm"] == pytest.approx((0.3 + 0.1) / 2, abs=1e-5)
    assert e["contact_mm"] == pytest.approx(1.0, abs=1e-5) and e["n_contact_maps"] == 1
    assert e["noncontact_mm"] == pytest.approx((0.2 / 3 + 0.1) / 2, abs=1e-5)


# ----------------------------------------------------------------------------------------- sampling


def test_sampling_windows_and_nearest_ground_truth(campaign: Path) -> None:
    data = open_campaign(campaign)
    try:
        assert data.counts() == {"train": 1, "val": 1, "test": 0} and data.scale_mm == 2.5
        src = data.sources["train"][0]
        phases = {p.name: p for p in src.rec.phases()}
        margin = PHASE_MARGIN_S * 1e6
        assert src.span_us[0] >= phases["normal_down"].t_start_us - margin
        assert src.span_us[1] <= phases["normal_up"].t_end_us + margin
        a, b = WindowSampler(data.sources["train"], 10_000, seed=3), WindowSampler(data.sources["train"], 10_000, seed=3)
        state = a.state()
        s1 = [a.sample() for _ in range(4)]
        assert all(np.array_equal(x.sae, b.sample().sae) for x in s1)  # same seed, same windows
        a.set_state(state)
        assert np.array_equal(a.sample().target, s1[0].target)  # the state restores the sequence
        for s in s1:
            assert s.sae.shape == (2, 96, 112) and s.target.shape == (90, 112) and s.contact.shape == (90, 112)
            assert s.sae.min() >= 0.0 and s.sae.max() <= 1.0 and not s.sae[:, :3].any() and not s.sae[:, 93:].any()
            assert s.target.min() >= 0.0 and s.target.max() <= 1.0
            assert abs(s.dt_gt_us) <= 5_000  # 100 Hz maps: at most half a period from the last event
            assert s.sae.max() > 0.5 or not s.contact.any()  # in contact the markers move: events
        # the target is the map nearest the window's last event
        s = s1[0]
        i = int(np.argmin(np.abs(src.t_gt - s.t_last_us)))
        assert np.allclose(s.target, np.clip(src.gt["depth_mm"][i] / 2.5, 0, 1))
        x, y, c = next(iter(torch_dataset(WindowSampler(data.sources["train"], 5_000, seed=0))))
        assert x.shape == (2, 96, 112) and y.shape == (90, 112) and c.dtype == torch.uint8
    finally:
        data.close()


def test_windows_can_be_drawn_further_into_the_released_gel(campaign: Path, tmp_path: Path) -> None:
    default, none = open_campaign(campaign), open_campaign(campaign, after_s=0.0)
    try:
        a, b = default.sources["train"][0], none.sources["train"][0]
        end = {p.name: p for p in a.rec.phases()}["normal_up"].t_end_us
        assert a.span_us[0] == b.span_us[0] and b.span_us[1] == pytest.approx(end)
        # this short recording's ground truth stops before the default margin does
        assert a.span_us[1] == pytest.approx(min(end + PHASE_MARGIN_S * 1e6, a.t_gt[-1]))
        assert a.span_us[1] > end
    finally:
        default.close()
        none.close()
    card = train(campaign, TrainConfig(steps=1, after_release_s=0.6, val_every=0, **TINY), tmp_path / "r",
                 show_progress=False)
    assert "--after-release-s 0.6" in card["reproduce"] and "0.6 s after Normal Up" in card["sampling"]
    with pytest.raises(LabrigError, match="--after-release-s"):
        TrainConfig(after_release_s=-1.0).check()


def test_missing_ground_truth_says_what_to_run(campaign: Path, tmp_path: Path) -> None:
    shutil.copy(campaign / "a.h5", tmp_path / "a.h5")
    (tmp_path / "manifest.csv").write_text("id,split,status,file,sha256\na,train,complete,a.h5,\n")
    with pytest.raises(LabrigError, match=r"run `labrig groundtruth .*` first"):
        open_campaign(tmp_path)
    with pytest.raises(LabrigError, match=r"manifest\.csv"):
        open_campaign(tmp_path / "a.h5")


# ----------------------------------------------------------------------------------------- training

TINY = {"width": 4, "batch_size": 4, "lr": 3e-3, "val_windows": 8, "threads": 1}


def pressed_window(src: Any) -> Any:
    """The window (10 ms) of a source that ends with Normal Down: the deepest press, in contact."""
    phases = {p.name: p for p in src.rec.phases()}
    window = src.window(phases["normal_down"].t_end_us - 10_000, 10_000)
    assert window.contact.any()
    return window


def test_short_run_lowers_the_loss_and_writes_a_loadable_model(campaign: Path, tmp_path: Path) -> None:
    from labrig.pipeline.depthnet import DepthModel

    card = train(campaign, TrainConfig(steps=24, val_every=12, checkpoint_every=12, **TINY), tmp_path / "m",
                 command="test", show_progress=False)
    losses = [v for _, v in card["training"]["loss_history"]]
    assert np.mean(losses[-4:]) < 0.8 * np.mean(losses[:4])
    assert card["training"]["steps"] == 24 and card["training"]["samples"] == 96
    assert card["training_data"]["split_counts"] == {"train": 1, "val": 1, "test": 0}
    assert card["val"]["total_mm"] is not None and card["val"]["contact_mm"] is not None
    assert card["reproduce"].startswith(f"labrig train {campaign} --width 4 --window-ms 10 --loss contact --steps 24")
    model = DepthModel(tmp_path / "m.onnx", threads=1)
    assert model.card.raw["parameters"] == card["parameters"] and model.card.raw["val"] == card["val"]
    assert model.depth_mm(np.zeros((2, 90, 112), np.float32)).shape == (90, 112)
    assert card["inference_ms_ort_1thread"] > 0
    with pytest.raises(LabrigError, match="--resume"):
        train(campaign, TrainConfig(steps=2, **TINY), tmp_path / "m", show_progress=False)


def test_resume_continues_where_the_checkpoint_stopped(campaign: Path, tmp_path: Path) -> None:
    cfg = {"val_every": 0, "checkpoint_every": 2, **TINY}
    whole = train(campaign, TrainConfig(steps=6, **cfg), tmp_path / "whole", show_progress=False)
    train(campaign, TrainConfig(steps=3, **cfg), tmp_path / "part", show_progress=False)  # "interrupted" at 3
    resumed = train(campaign, TrainConfig(steps=6, **cfg), tmp_path / "part", resume=True, show_progress=False)
    ckpt = torch.load(output_paths(tmp_path / "part")["checkpoint"], weights_only=False)
    assert ckpt["step"] == 6 and [s for s, _ in ckpt["history"]] == [1, 2, 3, 4, 5, 6]
    a, b = whole["training"]["loss_history"], resumed["training"]["loss_history"]
    np.testing.assert_allclose([v for _, v in b], [v for _, v in a], rtol=1e-5)
    with pytest.raises(LabrigError, match="width was 4"):
        train(campaign, TrainConfig(steps=8, **{**cfg, "width": 8}), tmp_path / "part", resume=True, show_progress=False)
    with pytest.raises(LabrigError, match="no checkpoint"):
        train(campaign, TrainConfig(steps=8, **cfg), tmp_path / "none", resume=True, show_progress=False)


def test_cli_train_json_and_errors(campaign: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from labrig.cli import app

    runner = CliRunner()
    result = runner.invoke(app, ["train", str(campaign), "--width", "4", "--steps", "2", "--batch-size", "2",
                                 "--val-windows", "4", "--loss", "uniform", "--window-ms", "5", "--out",
                                 str(tmp_path / "u"), "--shift-cells", "3", "--json"])
    assert result.exit_code == 0, result.output
    card = json.loads(result.output)
    assert card["loss"] == {"name": "uniform", "lambda_c": None} and card["window_ms"] == 5.0
    assert card["augmentation"]["translation"]["max_cells"] == 3
    assert (tmp_path / "u.onnx").exists() and (tmp_path / "u.json").exists()
    bad = runner.invoke(app, ["train", str(campaign), "--loss", "huber"])
    assert isinstance(bad.exception, LabrigError) and "--loss must be one of" in str(bad.exception)
    cosine = runner.invoke(app, ["train", str(campaign), "--lr-schedule", "cosine", "--time-budget-min", "1"])
    assert isinstance(cosine.exception, LabrigError) and "give --steps" in str(cosine.exception)
    empty = runner.invoke(app, ["train", str(tmp_path)])
    assert isinstance(empty.exception, LabrigError) and "manifest.csv" in str(empty.exception)


def test_windows_are_drawn_only_where_the_camera_has_events(campaign: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A camera that stalled leaves a dented gel without events: those windows would teach a dimple from nothing."""
    from labrig.recording import Recording
    from labrig.recording.quality import camera_shortfall_s

    with Recording(campaign / "a.h5") as rec:
        end_us = rec.events_end_us()
        assert end_us is not None and end_us == int(rec.events_between(0, rec.end_us() + 1)["t"].max())
        assert camera_shortfall_s(rec) < 0.05
        phases = {p.name: p for p in rec.phases()}
        cut = (phases["normal_down"].t_end_us + phases["normal_up"].t_start_us) // 2
        before = phases["normal_down"].t_start_us - PHASE_MARGIN_S * 1e6 - 1
    monkeypatch.setattr(Recording, "events_end_us", lambda self: cut)
    data = open_campaign(campaign)
    try:
        assert data.sources["train"][0].span_us[1] == cut
        with Recording(campaign / "a.h5") as rec:
            assert camera_shortfall_s(rec) == pytest.approx((rec.phases()[-1].t_end_us - cut) / 1e6)
    finally:
        data.close()
    monkeypatch.setattr(Recording, "events_end_us", lambda self: before)  # stalled before the probing
    with pytest.raises(LabrigError, match="no usable recording in the train split"):
        open_campaign(campaign)


# ----------------------------------------------------------------------------------------- noise augmentation


def test_background_noise_is_uniform_poisson_over_the_roi() -> None:
    from labrig.config import Roi
    from labrig.training.data import background_noise

    roi = Roi(100, 50, 300, 250)  # 200 x 200 px
    rng = np.random.default_rng(0)
    ev = background_noise(roi, 1_000.0, 11_000.0, 2.0, rng)  # 2 Hz x 40,000 px x 10 ms = 800 expected
    assert abs(len(ev) - 800) < 4 * np.sqrt(800)
    assert ev["x"].min() >= 100 and ev["x"].max() < 300 and ev["y"].min() >= 50 and ev["y"].max() < 250
    assert ev["t"].min() >= 1_000 and ev["t"].max() < 11_000 and np.all(np.diff(ev["t"].astype(np.int64)) >= 0)
    assert 0.4 < ev["p"].mean() < 0.6
    assert len(background_noise(roi, 0.0, 10_000.0, 0.0, rng)) == 0


def test_noise_augment_draws_log_uniform_rates_for_a_share_of_windows() -> None:
    from labrig.training.data import NoiseAugment

    aug = NoiseAugment(max_hz=2.0, min_hz=0.02, fraction=0.5)
    rng = np.random.default_rng(1)
    rates = np.array([aug.draw_hz(rng) for _ in range(4000)])
    noisy = rates[rates > 0]
    assert 0.45 < len(noisy) / len(rates) < 0.55
    assert noisy.min() >= 0.02 and noisy.max() <= 2.0
    assert abs(np.median(np.log10(noisy)) - np.log10(0.2)) < 0.1  # log-uniform: the median is the geometric mean
    with pytest.raises(LabrigError, match="noise rates"):
        NoiseAugment(max_hz=0.01)
    with pytest.raises(LabrigError, match="--noise-hz"):
        TrainConfig(noise_hz=-1.0).check()


def test_noise_fills_the_sae_but_leaves_the_target(campaign: Path) -> None:
    from labrig.training.data import background_noise

    data = open_campaign(campaign)
    try:
        src = data.sources["train"][0]
        start = src.span_us[0] + 0.3 * (src.span_us[1] - src.span_us[0])
        clean = src.window(start, 10_000)
        noise = background_noise(src.roi, start, start + 10_000, 1.0, np.random.default_rng(2))
        noisy = src.window(start, 10_000, noise=noise)
        assert np.array_equal(noisy.target, clean.target) and noisy.t_last_us == clean.t_last_us
        assert np.count_nonzero(noisy.sae) > np.count_nonzero(clean.sae) + 1000
        assert np.all(noisy.sae >= clean.sae)  # the latest event per cell: extra events only make it later
        sampler = WindowSampler(data.sources["train"], 10_000, seed=3, noise=TrainConfig(noise_hz=2.0).noise)
        counts = [np.count_nonzero(sampler.sample().sae) for _ in range(12)]
        assert max(counts) > 3 * min(counts)  # some windows clean, some noisy
    finally:
        data.close()


def test_the_card_and_the_reproduce_line_name_the_augmentation(campaign: Path, tmp_path: Path) -> None:
    cfg = {"val_every": 0, "checkpoint_every": 2, **TINY}
    card = train(campaign, TrainConfig(steps=2, noise_hz=1.5, **cfg), tmp_path / "n", show_progress=False)
    assert card["augmentation"] == {"background_noise": {"min_hz": 0.02, "max_hz": 1.5, "fraction": 0.5},
                                    "translation": ShiftAugment(DEFAULT_SHIFT_CELLS).describe()}
    assert "--noise-hz 1.5" in card["reproduce"] and f"--shift-cells {DEFAULT_SHIFT_CELLS}" in card["reproduce"]
    with pytest.raises(LabrigError, match=r"noise_hz was 1\.5"):
        train(campaign, TrainConfig(steps=4, **cfg), tmp_path / "n", resume=True, show_progress=False)
    ckpt_path = output_paths(tmp_path / "old")["checkpoint"]
    train(campaign, TrainConfig(steps=2, shift_cells=0, **cfg), tmp_path / "old", show_progress=False)
    ckpt = torch.load(ckpt_path, weights_only=False)
    for key in ("noise_hz", "shift_cells", "lr_schedule"):  # a checkpoint from before these augmentations existed
        del ckpt["config"][key]
    torch.save(ckpt, ckpt_path)
    with pytest.raises(LabrigError, match="shift_cells was 0"):
        train(campaign, TrainConfig(steps=3, **cfg), tmp_path / "old", resume=True, show_progress=False)
    resumed = train(campaign, TrainConfig(steps=3, shift_cells=0, **cfg), tmp_path / "old", resume=True,
                    show_progress=False)
    assert resumed["training"]["steps"] == 3 and resumed["augmentation"] is None


def test_shifted_moves_the_last_two_axes_and_fills_zeros() -> None:
    a = np.arange(1.0, 13.0).reshape(3, 4)
    np.testing.assert_array_equal(shifted(a, 1, -1), [[0, 0, 0, 0], [2, 3, 4, 0], [6, 7, 8, 0]])
    np.testing.assert_array_equal(shifted(a, 0, 0), a)
    assert not shifted(a, 3, 0).any() and not shifted(a, 0, -4).any()
    stack = np.stack([a, 10 * a])
    np.testing.assert_array_equal(shifted(stack, -1, 2)[1], shifted(10 * a, -1, 2))


def test_a_shifted_window_keeps_its_input_and_its_depth_in_register(campaign: Path) -> None:
    """The translation augmentation moves the SAE, the state channels, the depth and the contact mask together,
    within the 90 x 112 grid, and leaves the U-Net's padding rows empty."""
    from labrig.pipeline.sae import crop_from_unet

    data = open_campaign(campaign)
    try:
        src = data.sources["train"][0]
        window = pressed_window(src)
        moved = ShiftAugment(12).apply(window, 7, -9)
        np.testing.assert_array_equal(crop_from_unet(moved.sae)[:, 7:, :-9], crop_from_unet(window.sae)[:, :-7, 9:])
        np.testing.assert_array_equal(moved.target[7:, :-9], window.target[:-7, 9:])
        np.testing.assert_array_equal(moved.contact[7:, :-9], window.contact[:-7, 9:])
        assert not moved.sae[:, :3].any() and not moved.sae[:, 93:].any() and not moved.target[:7].any()
        assert moved.t_last_us == window.t_last_us and moved.sae.dtype == np.float32

        plain = WindowSampler(data.sources["train"], 10_000, seed=5)
        a, b = (WindowSampler(data.sources["train"], 10_000, seed=5, shift=ShiftAugment(12)) for _ in range(2))
        draws = [(a.sample(), b.sample()) for _ in range(6)]
        assert all(np.array_equal(x.sae, y.sae) and np.array_equal(x.target, y.target) for x, y in draws)
        centres = {tuple(np.round(np.argwhere(x.contact).mean(0))) for x, _ in draws if x.contact.any()}
        assert len(centres) > 1  # the same press seen at several places
        assert any(not np.array_equal(x.target, plain.sample().target) for x, _ in draws)
    finally:
        data.close()


def test_the_cosine_schedule_decays_the_rate_and_is_named_in_the_card(campaign: Path, tmp_path: Path) -> None:
    config = TrainConfig(steps=10, lr=1e-3, lr_schedule="cosine")
    rates = [config.lr_at(k) for k in range(11)]
    assert rates[0] == pytest.approx(1e-3) and rates[10] == pytest.approx(1e-3 * COSINE_FLOOR)
    assert all(x > y for x, y in itertools.pairwise(rates))
    assert TrainConfig(steps=10).lr_at(9) == 1e-3  # constant
    with pytest.raises(LabrigError, match="--lr-schedule cosine decays over --steps"):
        TrainConfig(time_budget_min=1.0, lr_schedule="cosine").check()
    with pytest.raises(LabrigError, match="--lr-schedule must be one of"):
        TrainConfig(steps=2, lr_schedule="step").check()
    with pytest.raises(LabrigError, match="--shift-cells must be"):
        TrainConfig(steps=2, shift_cells=-1).check()
    cfg = {"val_every": 0, "checkpoint_every": 4, **TINY}
    card = train(campaign, TrainConfig(steps=4, lr_schedule="cosine", **cfg), tmp_path / "c", show_progress=False)
    assert card["training"]["lr_schedule"] == "cosine" and "--lr-schedule cosine" in card["reproduce"]
    ckpt = torch.load(output_paths(tmp_path / "c")["checkpoint"], weights_only=False)
    used = ckpt["optimizer"]["param_groups"][0]["lr"]
    assert used == pytest.approx(TrainConfig(steps=4, lr_schedule="cosine", **cfg).lr_at(3)) == card["training"]["lr_final"]


# ----------------------------------------------------------------------------------------- inputs with state


def test_state_inputs_train_export_and_run_in_the_pipeline(campaign: Path, tmp_path: Path, rig: RigConfig,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """sae+disp+prev: the tracker's tracks are cached, windows carry 5 channels, the card names them, and the
    exported network runs through the depth-source builder (and refuses to run without the setup)."""
    from labrig.pipeline import depth_sources, run_setup, runtime
    from labrig.pipeline.depth_inputs import InputSpec
    from labrig.pipeline.depthnet import DepthModel
    from labrig.recording import Recording

    monkeypatch.setenv("LABRIG_CACHE", str(tmp_path / "cache"))
    data = open_campaign(campaign)
    try:
        spec = InputSpec.named("sae+disp+prev")
        sampler = WindowSampler(data.sources["train"], 10_000.0, seed=1, inputs=spec)
        x, target, _ = sampler.batch(8)
        assert x.shape == (8, 5, 96, 112) and target.shape == (8, 90, 112)
        assert len(list((tmp_path / "cache" / "tracks").glob("*.npz"))) == 1  # the tracker ran once, cached
        previous = x[:, 4, 3:93]
        assert previous.min() >= 0.0 and previous.max() <= 1.0
        assert np.abs(x[:, 2:4]).max() > 0.0  # the probe moved the markers somewhere in these windows
    finally:
        data.close()
    card = train(campaign, TrainConfig(steps=4, val_every=0, checkpoint_every=4, inputs="sae+disp+prev", **TINY),
                 tmp_path / "s", command="test", show_progress=False)
    assert card["inputs"]["kinds"] == ["sae", "displacement", "previous"] and card["architecture"]["in_channels"] == 5
    assert "--inputs sae+disp+prev" in card["reproduce"] and card["augmentation"]["previous_map"]["p_zero"] > 0
    assert DepthModel(tmp_path / "s.onnx").inputs == spec
    with pytest.raises(LabrigError, match="setup"):
        depth_sources.model_depth(tmp_path / "s.onnx")
    with pytest.raises(LabrigError, match="--resume: inputs was 'sae\\+disp\\+prev'"):
        train(campaign, TrainConfig(steps=5, val_every=0, **TINY), tmp_path / "s", resume=True, show_progress=False)
    with Recording(campaign / "a.h5") as rec:
        setup = run_setup.setup_for_recording(rec)
        source = depth_sources.depth_source("model", setup, rec, tmp_path / "s.onnx")
        results = list(runtime.Pipeline(setup, source).run(rec, window_us=10_000, concurrent=False))
    assert results and all(np.isfinite(r.net_force_n).all() and r.depth_mm.shape == (90, 112) for r in results)
    from labrig.evaluation.depth import DepthTask, evaluate_depth

    depth = evaluate_depth(DepthTask(str(campaign / "a.h5"), str(tmp_path / "s.onnx"), window_events=None,
                                     window_us=10_000))  # through the pipeline, window after window
    assert len(depth.t_us) == len(results) and np.isfinite(depth.total_mm).all()


def test_the_held_brightness_input_trains_and_its_card_carries_the_gated_leak(campaign: Path, tmp_path: Path,
                                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """sae+bright-hold: the card's brightness section names the gated leak, and the exported network's depth
    source integrates with it (a press held as long as it lasts)."""
    from labrig.pipeline import depth_sources, run_setup, runtime
    from labrig.pipeline.depth_inputs import HOLD_BRIGHTNESS, InputSpec
    from labrig.recording import Recording
    from labrig.training.state_data import prepare_states

    monkeypatch.setenv("LABRIG_CACHE", str(tmp_path / "cache"))
    prepare_states([campaign / "a.h5"], InputSpec.named("sae+bright-hold"), None, workers=2)  # worker processes
    assert len(list((tmp_path / "cache" / "brightness").glob("*.counts.npy"))) == 1
    card = train(campaign, TrainConfig(steps=3, val_every=0, checkpoint_every=3, inputs="sae+bright-hold", workers=2,
                                       **TINY), tmp_path / "h", command="test", show_progress=False)
    assert card["inputs"]["brightness"]["rest_tau_s"] == HOLD_BRIGHTNESS.rest_tau_s
    assert "--inputs sae+bright-hold" in card["reproduce"]
    with Recording(campaign / "a.h5") as rec:
        setup = run_setup.setup_for_recording(rec)
        source = depth_sources.depth_source("model", setup, rec, tmp_path / "h.onnx")
        assert source.integrator is not None and source.integrator.params == HOLD_BRIGHTNESS  # type: ignore[attr-defined]
        results = list(runtime.Pipeline(setup, source).run(rec, window_us=10_000, concurrent=False))
    assert results and all(np.isfinite(r.net_force_n).all() for r in results)


def test_fine_tuning_starts_from_the_network_and_says_what_it_gained(campaign: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from labrig.cli import app

    base = train(campaign, TrainConfig(steps=24, val_every=0, checkpoint_every=24, **TINY), tmp_path / "base",
                 show_progress=False)
    config = TrainConfig.from_init(str(tmp_path / "base.onnx"), steps=4, val_every=0, checkpoint_every=4,
                                   **{k: v for k, v in TINY.items() if k != "width"})
    assert (config.width, config.window_ms, config.inputs) == (4, 10.0, "sae")
    tuned = train(campaign, config, tmp_path / "tuned", show_progress=False)
    fresh = train(campaign, TrainConfig(steps=4, val_every=0, checkpoint_every=4, **TINY), tmp_path / "fresh",
                  show_progress=False)
    init = tuned["init"]
    assert init["model"] == "base" and init["val_before"] == base["val"]  # the same val windows, the same weights
    first = {name: card["training"]["loss_history"][0][1] for name, card in (("tuned", tuned), ("fresh", fresh))}
    assert first["tuned"] < 0.5 * first["fresh"]
    assert f"--init {tmp_path / 'base.onnx'}" in tuned["reproduce"] and "--width" not in tuned["reproduce"]
    runner = CliRunner()
    both = runner.invoke(app, ["train", str(campaign), "--init", str(tmp_path / "base.onnx"), "--width", "8"])
    assert isinstance(both.exception, LabrigError) and "leave out --width" in str(both.exception)
    output_paths(tmp_path / "fresh")["checkpoint"].unlink()
    bare = runner.invoke(app, ["train", str(campaign), "--init", str(tmp_path / "fresh.onnx")])
    assert isinstance(bare.exception, LabrigError) and "no torch weights" in str(bare.exception)
    nothing = runner.invoke(app, ["train", str(campaign), "--init", str(tmp_path / "nothing.onnx")])
    assert isinstance(nothing.exception, LabrigError) and "no network" in str(nothing.exception)
    other = runner.invoke(app, ["train", str(campaign), "--init", str(tmp_path / "base.onnx"), "--inputs", "sae+disp"])
    assert isinstance(other.exception, LabrigError) and "not which" in str(other.exception)


def test_a_fine_tune_may_learn_its_channels_made_another_way(campaign: Path, tmp_path: Path) -> None:
    """``--init`` with ``--inputs`` of the same kinds: the brightness counted with the dead band undone."""
    base = train(campaign, TrainConfig(steps=4, val_every=0, checkpoint_every=4, inputs="sae+bright-hold", **TINY),
                 tmp_path / "hold", show_progress=False)
    assert not base["inputs"]["brightness"].get("dead_band")
    config = TrainConfig.from_init(str(tmp_path / "hold.onnx"), "sae+bright-band", steps=2, val_every=0,
                                   checkpoint_every=2, **{k: v for k, v in TINY.items() if k != "width"})
    tuned = train(campaign, config, tmp_path / "band", show_progress=False)
    assert tuned["inputs"]["brightness"]["dead_band"] is True and tuned["init"]["model"] == "hold"
    assert "--inputs sae+bright-band" in tuned["reproduce"] and f"--init {tmp_path / 'hold.onnx'}" in tuned["reproduce"]


def test_a_patch_holds_the_contact_and_stays_in_register(campaign: Path) -> None:
    """Patch training cuts the input (without the U-Net's padding), the depth and the contact mask at one place,
    one that holds the contact's centre; a window without contact gets a patch anywhere in the grid."""
    from labrig.pipeline.sae import crop_from_unet

    data = open_campaign(campaign)
    try:
        src = data.sources["train"][0]
        window = pressed_window(src)
        patch = CropAugment(32)
        cut = patch.apply(window, 20, 40)
        assert cut.sae.shape == (window.sae.shape[0], 32, 32) and cut.target.shape == cut.contact.shape == (32, 32)
        np.testing.assert_array_equal(cut.sae, crop_from_unet(window.sae)[:, 20:52, 40:72])
        np.testing.assert_array_equal(cut.target, window.target[20:52, 40:72])
        np.testing.assert_array_equal(cut.contact, window.contact[20:52, 40:72])
        centre = np.argwhere(window.contact).mean(0)
        rng = np.random.default_rng(3)
        for _ in range(50):
            r0, c0 = patch.draw(rng, window.contact)
            assert r0 <= centre[0] < r0 + 32 and c0 <= centre[1] < c0 + 32
            assert 0 <= r0 <= 90 - 32 and 0 <= c0 <= 112 - 32
        corners = {patch.draw(rng, np.zeros((90, 112), bool)) for _ in range(200)}
        assert max(r for r, _ in corners) > 45 and min(c for _, c in corners) < 20
    finally:
        data.close()
    with pytest.raises(LabrigError, match=r"--crop-cells must be 0 \(the whole grid\) or a multiple of 16"):
        TrainConfig(steps=2, crop_cells=40).check()


def test_preloaded_windows_are_the_files_windows(campaign: Path) -> None:
    """A source whose sampled span is held in memory serves each window with the events the file gives, in
    its order, so a seeded sampler draws the same batches either way."""
    data = open_campaign(campaign)
    try:
        sources = data.sources["train"]
        from_file = WindowSampler(sources, 10_000, seed=2).batch(6)
        held = WindowSampler(sources, 10_000, seed=2, preload=True)
        from_memory = held.batch(6)
        assert sources[0].preloaded and sources[0].preload(10_000) > 0  # held, and not empty
        for a, b in zip(from_file, from_memory):
            np.testing.assert_array_equal(a, b)
        t0, t1 = sources[0].span_us
        for start in np.linspace(t0, t1 - 10_000, 7):
            np.testing.assert_array_equal(sources[0].events_between(start + 0.5, start + 10_000.5),
                                          sources[0].rec.events_between(start + 0.5, start + 10_000.5))
    finally:
        data.close()


def test_a_patch_trained_network_runs_on_the_whole_grid(campaign: Path, tmp_path: Path) -> None:
    card = train(campaign, TrainConfig(steps=2, crop_cells=32, val_every=0, **TINY), tmp_path / "p", show_progress=False)
    assert card["augmentation"]["crop"]["cells"] == 32 and "--crop-cells 32" in card["reproduce"]
    assert card["architecture"]["input_shape"][1:] == [96, 112] and card["val"]["maps"] > 0
