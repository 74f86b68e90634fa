"""Frame-wide statistics of a graph, computed on the whole frame and fed to each of its tiles.

A graph that reduces over the image axes (ReduceMean over H and W: NBG's and the affinity
guide's mean depth, NBG's mean luminance under the firefly floor) sees, in a tile, the tile's
statistic instead of the frame's. So a tiled run splits the graph once (`split_statistics`):
- the statistics graph: the part of the graph those reductions depend on, run on the whole
  frame (pointwise work plus the reductions, a few channels per pixel);
- the tile graph: the graph with each reduction's output turned into a graph input, run per
  tile with the frame's values fed.
Each tile then computes from the frame's statistics exactly as the untiled graph does (the
same onnxruntime kernel computes the same reduction of the same values).

Needs the `onnx` package to rewrite the graph (only when a frame of such a model is tiled).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

IMAGE_AXES = {2, 3}  # H and W of an NCHW tensor
STATISTIC_INPUT = "statistic."  # prefix of the tile graph's inputs that carry a statistic


@dataclass(frozen=True)
class SplitGraph:
    statistics: bytes  # ONNX model: the frame's buffers -> the statistics (graph outputs)
    tiles: bytes  # ONNX model: the original graph with the statistics as inputs
    names: tuple[str, ...]  # the statistics' tensor names in the original graph
    inputs: tuple[str, ...]  # the tile graph's input for each statistic


def _axes(node, constants: dict) -> set[int] | None:
    for attribute in node.attribute:
        if attribute.name == "axes":
            return set(attribute.ints)
    if len(node.input) > 1 and node.input[1] in constants:
        return {int(a) for a in constants[node.input[1]].reshape(-1)}
    return None  # all axes (noop_with_empty_axes aside): a frame-wide reduction too


def image_reductions(model) -> list[str]:
    """Outputs of the nodes that reduce over both image axes."""
    from onnx import numpy_helper

    constants = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    constants |= {n.output[0]: numpy_helper.to_array(n.attribute[0].t)
                  for n in model.graph.node if n.op_type == "Constant" and n.attribute
                  and n.attribute[0].name == "value"}
    found = []
    for node in model.graph.node:
        if not node.op_type.startswith("Reduce"):
            continue
        axes = _axes(node, constants)
        if axes is None or IMAGE_AXES <= {a % 4 for a in axes}:
            found.append(node.output[0])
    return found


def _drop_unused(graph, keep_inputs: bool = False) -> None:
    """Remove initializers (and, unless kept, graph inputs) that no node reads."""
    used = {name for node in graph.node for name in node.input}
    for init in [i for i in graph.initializer if i.name not in used]:
        graph.initializer.remove(init)
    if not keep_inputs:
        for value in [i for i in graph.input if i.name not in used]:
            graph.input.remove(value)


def split_statistics(path: Path) -> SplitGraph | None:
    """The statistics and tile graphs of the model at `path`; None when nothing in it reduces
    over the image axes (its tiles need nothing from the frame)."""
    try:
        import onnx
        from onnx.utils import Extractor
    except ImportError as exc:
        raise RuntimeError("running a frame in tiles needs the onnx package (pip install "
                           "'quietframe[serve]') to feed the tiles the frame's statistics") from exc

    model = onnx.load(str(path))
    names = image_reductions(model)
    if not names:
        return None
    inputs = [i.name for i in model.graph.input]
    statistics = Extractor(model).extract_model(inputs, names)
    _drop_unused(statistics.graph)
    tiles = onnx.ModelProto()
    tiles.CopyFrom(model)
    graph = tiles.graph
    for node in [n for n in graph.node if n.output[0] in names]:
        graph.node.remove(node)
    _drop_unused(graph, keep_inputs=True)
    fed = tuple(STATISTIC_INPUT + name for name in names)
    for name, feed in zip(names, fed, strict=True):  # first: nodes stay in topological order
        graph.input.append(onnx.helper.make_tensor_value_info(feed, onnx.TensorProto.FLOAT,
                                                              None))
        graph.node.insert(0, onnx.helper.make_node("Identity", [feed], [name]))
    return SplitGraph(statistics.SerializeToString(), tiles.SerializeToString(), tuple(names),
                      fed)
