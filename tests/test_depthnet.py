"""The depth U-Net: shapes, parameter counts, ONNX export against torch, the onnxruntime wrapper."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from labrig.errors import LabrigError
from labrig.physics.grid import GRID_SHAPE
from labrig.pipeline.depthnet import (
    DepthModel,
    UNetConfig,
    benchmark_ms,
    build_unet,
    export_onnx,
    parameter_count,
)
from labrig.pipeline.model_card import ModelCard, find_models
from labrig.pipeline.sae import UNET_SHAPE


@pytest.mark.parametrize(("width", "pools"), [(4, 4), (8, 4), (4, 3), (4, 1)])
def test_unet_keeps_the_padded_grid_shape(width: int, pools: int) -> None:
    net = build_unet(width=width, pools=pools).eval()
    with torch.no_grad():
        y = net(torch.rand(3, 2, *UNET_SHAPE))
    assert y.shape == (3, 1, *UNET_SHAPE)


def test_parameter_counts_scale_with_width_and_width_32_is_the_papers_size() -> None:
    counts = {w: parameter_count(build_unet(width=w)) for w in (4, 8, 16, 32)}
    assert 7.7e6 < counts[32] < 7.9e6  # paper: 7.9 M
    for w in (4, 8, 16):  # convolutions dominate: about 4x per doubling
        assert 3.8 < counts[2 * w] / counts[w] < 4.1
    assert parameter_count(build_unet(width=8, pools=3)) < counts[8]


def test_bad_configs_are_refused() -> None:
    with pytest.raises(ValueError, match="divisible"):
        UNetConfig(width=8, pools=5)  # 96 x 112 is not divisible by 32
    with pytest.raises(ValueError):
        UNetConfig(width=0)


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[torch.nn.Module, Path]:
    torch.manual_seed(0)
    net = build_unet(width=8)
    net.train()
    with torch.no_grad():  # non-trivial batch-norm statistics
        for _ in range(3):
            net(torch.rand(4, 2, *UNET_SHAPE))
    path = tmp_path_factory.mktemp("onnx") / "w8.onnx"
    export_onnx(net, path, {"name": "w8", "scale_mm": 2.5, "window_ms": 10.0, "loss": {"name": "contact"}})
    return net.eval(), path


def test_onnx_export_matches_torch(exported: tuple[torch.nn.Module, Path]) -> None:
    net, path = exported
    x = np.random.default_rng(1).random((2, 2, *UNET_SHAPE), dtype=np.float32)
    with torch.no_grad():
        ref = net(torch.from_numpy(x)).numpy()[:, 0]
    model = DepthModel(path, threads=1)
    assert np.abs(model.normalised(x) - ref).max() < 1e-4
    assert np.abs(model.normalised(x[0]) - ref[0]).max() < 1e-4  # single window


def test_depth_model_returns_mm_on_the_grid(exported: tuple[torch.nn.Module, Path]) -> None:
    net, path = exported
    model = DepthModel(path.with_suffix(".json"), threads=2)  # the card's path works too
    sae = np.random.default_rng(2).random((2, *GRID_SHAPE), dtype=np.float32)
    depth = model.depth_mm(sae)  # unpadded input is padded
    assert depth.shape == GRID_SHAPE and depth.dtype == np.float32
    assert depth.min() >= 0.0 and depth.max() <= 2.5
    with torch.no_grad():
        raw = net(torch.from_numpy(np.pad(sae, ((0, 0), (3, 3), (0, 0))))[None]).numpy()[0, 0, 3:93]
    np.testing.assert_allclose(depth, np.clip(raw, 0, 1) * 2.5, atol=1e-3)
    assert model.depth_mm(np.stack([sae, sae])).shape == (2, *GRID_SHAPE)
    assert model.scale_mm == 2.5 and model.window_ms == 10.0 and model.threads == 2
    with pytest.raises(LabrigError, match="takes"):
        model.depth_mm(np.zeros((2, 50, 50), np.float32))


def test_find_models_reads_cards_and_bad_files_are_clear(exported: tuple[torch.nn.Module, Path], tmp_path: Path) -> None:
    _, path = exported
    cards = find_models(path.parent)
    assert [c.name for c in cards] == ["w8"] and cards[0].onnx == path
    assert ModelCard.load(path.with_suffix(".json")).raw["format"] == "labrig.depthnet"
    with pytest.raises(LabrigError, match="no such depth network"):
        DepthModel(tmp_path / "missing.onnx")
    (tmp_path / "x.onnx").write_bytes(b"not a model")
    with pytest.raises(LabrigError, match="no model card"):
        DepthModel(tmp_path / "x.onnx")
    (tmp_path / "x.json").write_text(json.dumps({"format": "labrig.depthnet", "scale_mm": 2.5}))
    with pytest.raises(LabrigError, match="onnxruntime"):
        DepthModel(tmp_path / "x.onnx")
    (tmp_path / "x.json").write_text("{}")
    with pytest.raises(LabrigError, match="not a labrig depth-network model card"):
        find_models(tmp_path)


def test_benchmark_gives_a_latency(exported: tuple[torch.nn.Module, Path]) -> None:
    ms = benchmark_ms(exported[1], threads=1, repeats=5, warmup=1)
    assert 0.0 < ms < 1000.0
