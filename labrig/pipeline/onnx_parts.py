"""An ONNX graph cut into consecutive parts of about equal cost, to be run one after another.

A depth network's run is longer than a 1 ms window's budget on one core. Cut into parts, it can run
one part per window in the windows' own thread (:class:`labrig.pipeline.depth_lane.SteppedLane`), so
no window carries all of it. Each part is a graph of its own: its inputs are the graph's inputs and
the tensors earlier parts made that its nodes read; its outputs are the tensors later parts read and
the graph's outputs it makes. Run in order, each fed what the parts before it gave, the parts compute
the whole graph's outputs, the same operations on the same values.

The cuts follow the stored node order (ONNX keeps nodes topologically sorted) and balance an
estimate of each node's cost (:func:`node_costs`): the multiply-adds of a convolution, the output
elements of anything else, from the shapes ONNX's shape inference gives.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

#: Operators whose cost is counted in multiply-adds (output elements x kernel elements x input channels / group).
CONVOLUTIONS = ("Conv", "ConvTranspose")
#: Channel counts under this cost as much as this many: CPU convolution kernels work on channel blocks of a SIMD
#: register's width (onnxruntime's NCHWc layout: 16 floats with AVX-512, 8 with AVX2).
CHANNEL_BLOCK = 16


def _shapes(inferred: Any) -> dict[str, list[int]]:
    """Tensor name -> shape (symbolic dims as 1) of every tensor of ``inferred`` (a model through ONNX's shape
    inference) that it types."""
    shapes: dict[str, list[int]] = {}
    graph = inferred.graph
    for info in [*graph.input, *graph.value_info, *graph.output]:
        dims = info.type.tensor_type.shape.dim
        shapes[info.name] = [d.dim_value if d.dim_value > 0 else 1 for d in dims]
    for init in graph.initializer:
        shapes[init.name] = list(init.dims)
    return shapes


def node_costs(model: Any, inferred: Any | None = None) -> list[float]:
    """Per node (stored order): the estimated cost, multiply-adds for a convolution, output elements otherwise
    (a node whose output shape is unknown counts 1); channel counts under :data:`CHANNEL_BLOCK` count as it.
    ``inferred``: ``model`` through ONNX's shape inference, if already made."""
    import onnx

    shapes = _shapes(inferred if inferred is not None else onnx.shape_inference.infer_shapes(model))
    costs = []
    for node in model.graph.node:
        out = shapes.get(node.output[0]) if node.output else None
        elements = float(np.prod(out)) if out else 1.0
        if out and len(out) > 1:
            elements *= max(CHANNEL_BLOCK, out[1]) / out[1]
        if node.op_type in CONVOLUTIONS and len(node.input) > 1 and node.input[1] in shapes:
            weight = shapes[node.input[1]]  # Conv: (out, in / group, k...); ConvTranspose: (in, out / group, k...)
            group = next((a.i for a in node.attribute if a.name == "group"), 1)
            per_output = float(np.prod(weight[2:])) * (weight[1] if node.op_type == "Conv" else weight[0] / group)
            elements *= max(CHANNEL_BLOCK, per_output / float(np.prod(weight[2:]))) * float(np.prod(weight[2:]))
        costs.append(elements)
    return costs


def cut_points(costs: Sequence[float], parts: int) -> list[int]:
    """Node indices where parts 2.. start: the first node at which the running cost reaches k / ``parts`` of the
    total, k = 1 .. parts - 1 (fewer cuts when the graph has fewer nodes than ``parts``)."""
    if parts < 1:
        raise ValueError(f"parts must be at least 1, not {parts}")
    running = np.cumsum(np.asarray(costs, np.float64))
    total = float(running[-1]) if running.size else 0.0
    cuts: list[int] = []
    for k in range(1, parts):
        at = int(np.searchsorted(running, total * k / parts, side="left")) + 1
        if (not cuts or at > cuts[-1]) and at < len(costs):
            cuts.append(at)
    return cuts


def split(model: Any, parts: int) -> list[Any]:
    """``model`` (an ``onnx.ModelProto``) as up to ``parts`` models run in order (see the module docstring)."""
    import onnx
    from onnx import helper

    graph = model.graph
    nodes = list(graph.node)
    inferred = onnx.shape_inference.infer_shapes(model)
    bounds = [0, *cut_points(node_costs(model, inferred), parts), len(nodes)]
    typed = inferred.graph
    infos = {i.name: i for i in [*typed.input, *typed.value_info, *typed.output]}
    initializers = {i.name: i for i in graph.initializer}
    graph_outputs = [o.name for o in graph.output]
    out: list[Any] = []
    for a, b in itertools.pairwise(bounds):
        made_before = {t for n in nodes[:a] for t in n.output} | {i.name for i in graph.input}
        made_here = [t for n in nodes[a:b] for t in n.output]
        read_here = [t for n in nodes[a:b] for t in n.input if t]
        read_after = {t for n in nodes[b:] for t in n.input} | set(graph_outputs)
        inputs = list(dict.fromkeys(t for t in read_here if t in made_before and t not in initializers))
        outputs = [t for t in made_here if t in read_after]
        used = [initializers[t] for t in dict.fromkeys(read_here) if t in initializers]
        part = helper.make_graph(nodes[a:b], f"{graph.name}-part{len(out) + 1}", [infos[t] for t in inputs],
                                 [infos[t] for t in outputs], used)
        sub = helper.make_model(part, opset_imports=model.opset_import, ir_version=model.ir_version)
        out.append(sub)
    return out


class PartedSession:
    """onnxruntime sessions of :func:`split`'s parts; :meth:`steps` runs them one at a time.

    ``options``: an ``onnxruntime.SessionOptions`` for every part."""

    def __init__(self, model: Any, parts: int, options: Any) -> None:
        import onnxruntime as ort

        self.requested = parts
        self.models = split(model, parts)
        self.sessions = [ort.InferenceSession(m.SerializeToString(), options, providers=["CPUExecutionProvider"])
                         for m in self.models]
        self.output_names = [[o.name for o in s.get_outputs()] for s in self.sessions]

    def __len__(self) -> int:
        return len(self.sessions)

    def steps(self, feeds: dict[str, npt.NDArray[Any]]) -> Iterator[None]:
        """Run the parts in order, yielding after every part but the last; the tensors the parts made (name ->
        array) are ``feeds`` updated in place, the graph's outputs among them when it ends."""
        for k, (session, names) in enumerate(zip(self.sessions, self.output_names, strict=True)):
            if k:
                yield
            wanted = {i.name: feeds[i.name] for i in session.get_inputs()}
            feeds.update(zip(names, session.run(names, wanted), strict=True))
