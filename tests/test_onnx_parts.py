"""A depth network cut into parts: the parts run in order give the whole network's output, bit for bit."""

from __future__ import annotations

import numpy as np
import onnx
import pytest

from labrig.models import bundled_model_path
from labrig.pipeline import onnx_parts
from labrig.pipeline.depthnet import DepthModel


@pytest.mark.parametrize("parts", [1, 2, 3, 5])
def test_the_parts_of_the_bundled_network_give_its_output(parts: int) -> None:
    model = DepthModel(bundled_model_path())
    assert model.split(parts) == parts
    x = np.random.default_rng(parts).random((model.inputs.channels, 90, 112), dtype=np.float32)
    steps = model.depth_mm_steps(x)
    taken = 0
    while True:
        try:
            next(steps)
            taken += 1
        except StopIteration as done:
            depth = done.value
            break
    assert taken == parts - 1  # a yield between two parts
    assert np.array_equal(depth, model.depth_mm(x))


def test_cuts_balance_the_cost_and_every_part_reads_only_what_came_before() -> None:
    model = onnx.load(str(bundled_model_path()))
    costs = onnx_parts.node_costs(model)
    assert len(costs) == len(model.graph.node) and min(costs) > 0
    cuts = onnx_parts.cut_points(costs, 4)
    assert cuts == sorted(set(cuts)) and cuts[0] > 0 and cuts[-1] < len(costs)
    shares = np.diff([0, *np.cumsum(costs)[np.array(cuts) - 1], sum(costs)]) / sum(costs)
    assert shares.max() < 0.5  # no part far over a quarter
    made = {"inputs"}
    for part in onnx_parts.split(model, 4):
        onnx.checker.check_model(part)
        assert {i.name for i in part.graph.input} <= made
        made |= {o.name for o in part.graph.output}
    assert "depth" in made
    assert onnx_parts.cut_points([1.0, 1.0], 5) == [1]  # no more parts than nodes
    with pytest.raises(ValueError, match="at least 1"):
        onnx_parts.cut_points(costs, 0)
