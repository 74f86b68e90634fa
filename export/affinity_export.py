"""torch -> ONNX export of the affinity denoiser (model/affinity.py), kernel size as an input.

Same graph interface as NBG (docs/model-interface.md: buffers, reset, state in/out, dynamic H
and W, self-describing metadata) plus one int64 graph input `kernel_size` (shape [1]) that the
AffinityFilter / AffinityTemporalFilter nodes read: a session picks 5×5 … 13×13 at run time
without re-export. Metadata `quietframe.inputs` describes it (default, allowed values) so the
runtime feeds it without knowing what it means.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import onnx
import torch
from torch import Tensor, nn

from quietframe.export import onnx_export
from quietframe.export.onnx_export import OPSET
from quietframe.model.affinity import KERNEL_SIZES, AffinityDenoiser
from quietframe.runtime.buffers import BUFFER_NAMES
from quietframe.runtime.card import OUTPUT, RESET, SAMPLES_INPUT, STATE_IN, STATE_OUT
from quietframe.runtime.ops_library import OPS_DOMAIN

KERNEL_SIZE_INPUT = "kernel_size"
# Input index of the spatial kernel size in each op (docs/affinity-math.md).
KERNEL_SIZE_SLOT = {"AffinityFilter": 4, "AffinityTemporalFilter": 8}


class _ExportWrapper(nn.Module):
    """Positional signature in the order of the graph inputs."""

    def __init__(self, model: AffinityDenoiser) -> None:
        super().__init__()
        self.model = model

    def forward(self, color: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
                motion: Tensor, reset: Tensor, state: Tensor,
                embedding: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        denoised, (state, embedding) = self.model(color, albedo, normal, depth, motion, reset,
                                                  (state, embedding))
        return denoised, state, embedding


class _ExportWrapperWithSamples(_ExportWrapper):
    """The same, with the frame's samples per pixel (SAMPLES_INPUT, shape [1]) last (a model
    with AffinityConfig.noise_input)."""

    def forward(self, color: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
                motion: Tensor, reset: Tensor, state: Tensor, embedding: Tensor,
                spp: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        denoised, (state, embedding) = self.model(color, albedo, normal, depth, motion, reset,
                                                  (state, embedding), spp=spp)
        return denoised, state, embedding


def example_inputs(model: AffinityDenoiser, height: int = 48, width: int = 64,
                   seed: int = 0) -> tuple[Tensor, ...]:
    """NBG's example frame with this model's state: (color, albedo, normal, depth, motion,
    reset, state, embedding state)."""
    *buffers, reset, _ = onnx_export.example_inputs(height, width, seed)
    return (*buffers, reset, *model.initial_state(1, height, width))


def translation_table() -> dict:
    """torch custom op -> ai.quietframe op, from the exporter (kernels engineer's mapping)."""
    return onnx_export.custom_translation_table()


def kernel_size_as_input(proto: onnx.ModelProto, default: int) -> onnx.ModelProto:
    """Rewire the spatial kernel size of every affinity node to one int64 [1] graph input.

    The traced graph holds the size the model was traced with as a constant; the constants
    left without a consumer are dropped."""
    graph = proto.graph
    nodes = [n for n in graph.node if n.domain == OPS_DOMAIN and n.op_type in KERNEL_SIZE_SLOT]
    if not nodes:
        raise ValueError("no affinity node in the graph: nothing reads a kernel size")
    for node in nodes:
        node.input[KERNEL_SIZE_SLOT[node.op_type]] = KERNEL_SIZE_INPUT
    graph.input.append(onnx.helper.make_tensor_value_info(
        KERNEL_SIZE_INPUT, onnx.TensorProto.INT64, [1]))
    used = {name for n in graph.node for name in n.input} | {o.name for o in graph.output}
    dead = [n for n in graph.node if n.op_type == "Constant" and not set(n.output) & used]
    for node in dead:
        graph.node.remove(node)
    for init in [i for i in graph.initializer if i.name not in used]:
        graph.initializer.remove(init)
    return proto


def input_metadata(default: int) -> list[dict]:
    """`quietframe.inputs`: extra graph inputs the runtime feeds from defaults or options."""
    return [{"name": KERNEL_SIZE_INPUT, "dtype": "int64", "shape": [1], "default": default,
             "allowed": list(KERNEL_SIZES),
             "doc": "spatial affinity kernel size k (k×k taps per kernel, Işık et al. §5.5.3)"}]


def export_affinity(
    model: AffinityDenoiser,
    path: Path,
    *,
    version: str = "0",
    training: Mapping | None = None,
    metrics: Mapping | None = None,
) -> Path:
    """Write `model` as a self-describing ONNX file at `path` (its card: onnx_export.model_card,
    with the kernel size as a run-time input, whose value sets the tiling's reach) and return
    the path."""
    model = model.eval()
    height = torch.export.Dim("height", min=1, max=8192)
    width = torch.export.Dim("width", min=1, max=8192)
    image_dims = {2: height, 3: width}
    # The embedding state is ⌈H/s⌉×⌈W/s⌉: AUTO lets the exporter derive its size from H and W.
    low_dims = {2: torch.export.Dim.AUTO, 3: torch.export.Dim.AUTO}
    dynamic = {name: image_dims for name in BUFFER_NAMES} | {
        "reset": None, "state": image_dims, "embedding": low_dims}
    names = [spec["name"] for spec in model.state_specs()]
    extra = model.run_time_inputs()  # the frame's spp, where the model reads it
    example = example_inputs(model)
    if extra:
        example = (*example, torch.full((1,), float(extra[0]["default"])))
        dynamic |= {SAMPLES_INPUT: None}
    wrapper = _ExportWrapperWithSamples(model) if extra else _ExportWrapper(model)
    with torch.no_grad():
        program = torch.onnx.export(
            wrapper.eval(), example, dynamo=True,
            opset_version=OPSET, custom_translation_table=translation_table(),
            dynamic_shapes=dynamic,
            input_names=[*BUFFER_NAMES, RESET, *(STATE_IN + n for n in names),
                         *(i["name"] for i in extra)],
            output_names=[OUTPUT, *(STATE_OUT + n for n in names)],
            verbose=False,
        )
    config = model.config
    proto = kernel_size_as_input(program.model_proto, config.kernel_size)
    metadata = onnx_export.model_metadata(
        config, version, model.state_specs(), training, metrics,
        inputs=[*input_metadata(config.kernel_size), *extra],
    )
    return onnx_export.save_described(proto, metadata, path)
