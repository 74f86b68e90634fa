"""torch -> ONNX export of the NBG denoiser with splat/slice/warp as ai.quietframe custom ops
(and the affinity kernels, for models that call quietframe.model.affinity_kernels).

The graph follows docs/model-interface.md: named buffer inputs, a reset flag, state in/out,
dynamic H and W, and metadata_props that make the file self-describing for the runtime.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import onnx
import onnxscript
import torch
from onnx.defs import OpSchema
from onnxscript import opset18 as _op
from torch import Tensor, nn

from quietframe.model import affinity_kernels, resample  # noqa: F401 (registers the op)
from quietframe.model.grid import range_cells
from quietframe.model.nbg import AccumulationDenoiser, NBGDenoiser
from quietframe.model.nbg_fused import LDR_EXPONENT, fusable, fused_forward
from quietframe.model.oidn_temporal import OIDNOnlyConfig, OIDNTemporal
from quietframe.model.temporal import (
    ALIGNED_TOLERANCE,
    DEPTH_REL_TOLERANCE,
    MIN_CURRENT_WEIGHT,
    NORMAL_MIN_DOT,
    WARP_MODES,
)
from quietframe.runtime.buffers import BUFFER_NAMES
from quietframe.runtime.card import (
    OUTPUT,
    RESET,
    SAMPLES_INPUT,
    STATE_IN,
    STATE_OUT,
    ModelCard,
    StateSpec,
    prepass_stage,
    split_metrics,
    stages_from_prepass,
)
from quietframe.runtime.oidn_prepass import PREPASS_BUFFERS
from quietframe.runtime.ops_library import OPS_DOMAIN
from quietframe.runtime.receptive import tiling_for
from quietframe.runtime.scalar_inputs import InputSpec

OPSET = 18
REQUIRED_BUFFERS = ("color", "albedo", "normal", "depth")
OPTIONAL_BUFFERS = ("motion",)  # missing: zeros, i.e. a static camera
STATE_NAME = "accumulation"


def buffer_roles(training: Mapping | None) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(required, optional) buffers of a model from its training config: a buffer the run
    dropped (TrainConfig.dropout, model/train.py) was seen absent in training, so the model
    lists it as optional; with all four dropped only colour is required (the colour-only
    path)."""
    training = training or {}
    dropped: set[str] = set()
    if float(training.get("dropout", 0) or 0) > 0:
        dropped = {b.strip() for b in str(training.get("dropout_buffers", "")).split(",")}
    required = tuple(b for b in REQUIRED_BUFFERS if b not in dropped)
    optional = (*(b for b in REQUIRED_BUFFERS if b in dropped), *OPTIONAL_BUFFERS)
    return required, optional


def _register_schemas() -> None:
    """Declare our op schemas to onnx so onnxscript can emit them with typed outputs."""
    float_t = [("T", ["tensor(float)"], "float32 tensors, NCHW / NCDHW")]
    attrs = [
        OpSchema.Attribute("sigma_s", OpSchema.AttrType.INT, "spatial sampling rate"),
        OpSchema.Attribute("sigma_r", OpSchema.AttrType.FLOAT, "range sampling rate"),
        OpSchema.Attribute("grid_depth", OpSchema.AttrType.INT, "range cells D"),
    ]
    param = OpSchema.FormalParameter
    schemas = [
        OpSchema(
            "BilateralSplat", OPS_DOMAIN, 1,
            inputs=[param("image", "T"), param("guide", "T")],
            outputs=[param("grid", "T"), param("weight", "T")],
            type_constraints=float_t, attributes=attrs,
        ),
        OpSchema(
            "BilateralSlice", OPS_DOMAIN, 1,
            inputs=[param("grid", "T"), param("weight", "T"), param("guide", "T")],
            outputs=[param("image", "T")],
            type_constraints=float_t, attributes=attrs,
        ),
        OpSchema(
            "BackwardWarp", OPS_DOMAIN, 1,
            doc="warped = image sampled at p + motion(p) (border padding), inside = 1 where "
                "that position lies in the image; quietframe.model.temporal.backward_warp",
            inputs=[param("image", "T"), param("motion", "T")],
            outputs=[param("warped", "T"), param("inside", "T")],
            type_constraints=float_t,
            attributes=[OpSchema.Attribute("mode", OpSchema.AttrType.INT,
                                           "0 = bilinear, 1 = nearest")],
        ),
    ]
    int_t = ("I", ["tensor(int64)"], "a kernel size: one int64, shape [] or [1]")
    affinity_attrs = [
        OpSchema.Attribute("dilation", OpSchema.AttrType.INT, "spatial tap spacing, >= 1"),
        OpSchema.Attribute("epsilon", onnx.helper.make_attribute("epsilon",
                                                                 affinity_kernels.EPSILON),
                           "ε of the normalisation (eq. 6, 8)"),
    ]
    spatial_inputs = [param("radiance", "T"), param("features", "T"), param("bandwidth", "T"),
                      param("center", "T")]
    schemas += [
        OpSchema(
            "AffinityFilter", OPS_DOMAIN, 1,
            doc="one dilated affinity kernel (Işık et al. 2021 eq. 4 + 6); "
                "quietframe.model.affinity_kernels.spatial_affinity_filter",
            inputs=[*spatial_inputs, param("kernel_size", "I")],
            outputs=[param("output", "T")],
            type_constraints=[*float_t, int_t], attributes=affinity_attrs,
        ),
        OpSchema(
            "AffinityTemporalFilter", OPS_DOMAIN, 1,
            doc="the last spatial kernel jointly normalised with the temporal kernel (eq. 7 + 8); "
                "quietframe.model.affinity_kernels.temporal_affinity_filter",
            inputs=[*spatial_inputs, param("prev_output", "T"), param("prev_features", "T"),
                    param("temporal_bandwidth", "T"), param("temporal_on", "T"),
                    param("kernel_size", "I"), param("temporal_kernel_size", "I")],
            outputs=[param("output", "T")],
            type_constraints=[*float_t, int_t], attributes=affinity_attrs,
        ),
    ]
    schemas.append(OpSchema(
        "PixelAligned", OPS_DOMAIN, 1,
        doc="1 where the pixel and its 3x3 neighbours move by the same whole number of pixels; "
            "quietframe.model.temporal.aligned_mask",
        inputs=[param("motion", "T")], outputs=[param("aligned", "T")],
        type_constraints=float_t,
        attributes=[OpSchema.Attribute("tolerance", OpSchema.AttrType.FLOAT, "pixels")],
    ))
    schemas.append(OpSchema(
        "ResampledTrust", OPS_DOMAIN, 1,
        doc="the share of a reprojected history kept so that the current frame weighs at least "
            "`floor` where the motion is not pixel-aligned; "
            "quietframe.model.temporal.resampled_trust",
        inputs=[param("motion", "T"), param("previous_count", "T"), param("floor", "T")],
        outputs=[param("trust", "T")],
        type_constraints=float_t,
        attributes=[OpSchema.Attribute("tolerance", OpSchema.AttrType.FLOAT, "pixels"),
                    OpSchema.Attribute("min_weight", OpSchema.AttrType.FLOAT,
                                       "a floor at or below it keeps every history"),
                    OpSchema.Attribute("max_count", OpSchema.AttrType.FLOAT,
                                       "the longest history length read")],
    ))
    schemas.append(OpSchema(
        "AlbedoPrefilter", OPS_DOMAIN, 1,
        doc="the albedo blurred by a Gaussian of sigma_at_one_spp * spp^-exponent px per image "
            "(separable, edges replicated); quietframe.model.albedo_prefilter.albedo_blur",
        inputs=[param("albedo", "T"), param("spp", "T")], outputs=[param("albedo_out", "T")],
        type_constraints=float_t,
        attributes=[OpSchema.Attribute("sigma_at_one_spp", OpSchema.AttrType.FLOAT, "pixels"),
                    OpSchema.Attribute("exponent", OpSchema.AttrType.FLOAT,
                                       "how fast the width falls with spp"),
                    OpSchema.Attribute("radius", OpSchema.AttrType.INT, "taps each way")],
    ))
    schemas.append(OpSchema(
        "UpsampleBilinear", OPS_DOMAIN, 1,
        doc="image resampled to the height and width of `like` (only its shape is read) as "
            "F.interpolate(mode='bilinear', align_corners=False); "
            "quietframe.model.resample.upsample_bilinear",
        inputs=[param("image", "T"), param("like", "T")], outputs=[param("output", "T")],
        type_constraints=float_t,
    ))
    float_attr = OpSchema.Attribute
    blend_inputs = [param("logits", "T"), param("safe_albedo", "T"), param("sliced0", "T"),
                    param("sliced1", "T"), param("sliced2", "T")]
    schemas += [
        OpSchema(
            "NBGAccumulate", OPS_DOMAIN, 1,
            doc="temporal accumulation after the history's reprojection; "
                "quietframe.model.nbg_fused.accumulate_warped",
            inputs=[param("radiance", "T"), param("warped", "T"), param("inside", "T"),
                    param("depth", "T"), param("normal", "T"), param("reset", "T")],
            outputs=[param("accumulated", "T"), param("state", "T")],
            type_constraints=float_t,
            attributes=[float_attr("depth_tolerance", OpSchema.AttrType.FLOAT, "relative"),
                        float_attr("normal_min_dot", OpSchema.AttrType.FLOAT, "cosine"),
                        float_attr("min_current_weight", OpSchema.AttrType.FLOAT, "α floor")],
        ),
        OpSchema(
            "NBGFeatures", OPS_DOMAIN, 1,
            doc="GuideNet's input; quietframe.model.nbg_fused.features_scaled",
            inputs=[param("radiance", "T"), param("safe_albedo", "T"), param("albedo", "T"),
                    param("normal", "T"), param("depth", "T"), param("depth_scale", "T")],
            outputs=[param("features", "T")],
            type_constraints=float_t,
            attributes=[float_attr("exponent", OpSchema.AttrType.FLOAT, "LDR gamma")],
        ),
        OpSchema(
            "NBGBlend", OPS_DOMAIN, 1,
            doc="softmax-weighted sum of three sliced grids, remodulated; "
                "quietframe.model.nbg_fused.blend_sliced",
            inputs=blend_inputs, outputs=[param("denoised", "T")], type_constraints=float_t,
        ),
        OpSchema(
            "NBGBlendPass", OPS_DOMAIN, 1,
            doc="softmax-weighted sum of three sliced grids, the accumulated irradiance and "
                "the frame's (NBGConfig.passthrough), remodulated; "
                "quietframe.model.nbg_fused.blend_sliced",
            inputs=[*blend_inputs, param("accumulated", "T"), param("frame", "T")],
            outputs=[param("denoised", "T")],
            type_constraints=float_t,
        ),
        OpSchema(
            "NBGBlendNoise", OPS_DOMAIN, 1,
            doc="NBGBlendPass with the blend logits moved by the pixel's noise level, from the "
                "frame's spp and the state's history length (NBGConfig.noise_blend); "
                "quietframe.model.nbg_fused.blend_noise",
            inputs=[*blend_inputs, param("accumulated", "T"), param("frame", "T"),
                    param("state", "T"), param("spp", "T"), param("noise_scale", "T"),
                    param("noise_shift", "T")],
            outputs=[param("denoised", "T")],
            type_constraints=float_t,
        ),
    ]
    for schema in schemas:
        try:
            onnx.defs.get_schema(schema.name, 1, OPS_DOMAIN)
        except onnx.defs.SchemaError:
            onnx.defs.register_schema(schema)


_register_schemas()
_QF = onnxscript.values.Opset(OPS_DOMAIN, 1)


def _splat_to_onnx(image, guide, sigma_s: int, sigma_r: float):
    return _QF.BilateralSplat(
        image, guide, sigma_s=sigma_s, sigma_r=sigma_r, grid_depth=range_cells(sigma_r)
    )


def _slice_to_onnx(grid, weight, guide, sigma_s: int, sigma_r: float):
    return _QF.BilateralSlice(
        grid, weight, guide, sigma_s=sigma_s, sigma_r=sigma_r, grid_depth=range_cells(sigma_r)
    )


def _warp_to_onnx(image, motion, mode: str = "bilinear"):
    return _QF.BackwardWarp(image, motion, mode=WARP_MODES.index(mode))


def _kernel_size(size: int):
    """A kernel size as the int64 [1] input the affinity ops take (so that a graph can also feed
    it from a graph input and change it per run)."""
    return _op.Constant(value_ints=[size])


def _affinity_to_onnx(radiance, features, bandwidth, center, kernel_size: int, dilation: int,
                      eps: float = affinity_kernels.EPSILON):
    return _QF.AffinityFilter(radiance, features, bandwidth, center, _kernel_size(kernel_size),
                              dilation=dilation, epsilon=eps)


def _affinity_temporal_to_onnx(radiance, features, bandwidth, center, prev_output,
                               prev_features, temporal_bandwidth, temporal_on, kernel_size: int,
                               dilation: int, temporal_kernel_size: int,
                               eps: float = affinity_kernels.EPSILON):
    return _QF.AffinityTemporalFilter(
        radiance, features, bandwidth, center, prev_output, prev_features, temporal_bandwidth,
        temporal_on, _kernel_size(kernel_size), _kernel_size(temporal_kernel_size),
        dilation=dilation, epsilon=eps)


def _upsample_to_onnx(image, like):
    return _QF.UpsampleBilinear(image, like)


def _accumulate_to_onnx(radiance, warped, inside, depth, normal, reset):
    return _QF.NBGAccumulate(radiance, warped, inside, depth, normal, reset,
                             depth_tolerance=DEPTH_REL_TOLERANCE, normal_min_dot=NORMAL_MIN_DOT,
                             min_current_weight=MIN_CURRENT_WEIGHT)


def _features_to_onnx(radiance, safe_albedo, albedo, normal, depth, depth_scale):
    return _QF.NBGFeatures(radiance, safe_albedo, albedo, normal, depth, depth_scale,
                           exponent=LDR_EXPONENT)


def _blend_to_onnx(logits, safe_albedo, sliced0, sliced1, sliced2):
    return _QF.NBGBlend(logits, safe_albedo, sliced0, sliced1, sliced2)


def _blend_pass_to_onnx(logits, safe_albedo, sliced0, sliced1, sliced2, accumulated, frame):
    return _QF.NBGBlendPass(logits, safe_albedo, sliced0, sliced1, sliced2, accumulated, frame)


def _blend_noise_to_onnx(logits, safe_albedo, sliced0, sliced1, sliced2, accumulated, frame,
                         state, spp, noise_scale, noise_shift):
    return _QF.NBGBlendNoise(logits, safe_albedo, sliced0, sliced1, sliced2, accumulated, frame,
                             state, spp, noise_scale, noise_shift)


def _aligned_to_onnx(motion):
    return _QF.PixelAligned(motion, tolerance=ALIGNED_TOLERANCE)


def _trust_to_onnx(motion, previous_count, floor):
    return _QF.ResampledTrust(motion, previous_count, floor, tolerance=ALIGNED_TOLERANCE,
                              min_weight=MIN_CURRENT_WEIGHT, max_count=1.0 / MIN_CURRENT_WEIGHT)


def _albedo_prefilter_to_onnx(albedo, spp, at_one_spp: float, exponent: float, radius: int):
    return _QF.AlbedoPrefilter(albedo, spp, sigma_at_one_spp=at_one_spp, exponent=exponent,
                               radius=radius)


def custom_translation_table() -> dict:
    """torch custom op -> its ai.quietframe op, for torch.onnx.export(custom_translation_table=)."""
    return {
        torch.ops.quietframe.bilateral_splat.default: _splat_to_onnx,
        torch.ops.quietframe.bilateral_slice.default: _slice_to_onnx,
        torch.ops.quietframe.backward_warp.default: _warp_to_onnx,
        torch.ops.quietframe.affinity_filter.default: _affinity_to_onnx,
        torch.ops.quietframe.affinity_temporal_filter.default: _affinity_temporal_to_onnx,
        torch.ops.quietframe.upsample_bilinear.default: _upsample_to_onnx,
        torch.ops.quietframe.nbg_accumulate.default: _accumulate_to_onnx,
        torch.ops.quietframe.nbg_features.default: _features_to_onnx,
        torch.ops.quietframe.nbg_blend.default: _blend_to_onnx,
        torch.ops.quietframe.nbg_blend_pass.default: _blend_pass_to_onnx,
        torch.ops.quietframe.nbg_blend_noise.default: _blend_noise_to_onnx,
        torch.ops.quietframe.aligned_mask.default: _aligned_to_onnx,
        torch.ops.quietframe.resampled_trust.default: _trust_to_onnx,
        torch.ops.quietframe.albedo_prefilter.default: _albedo_prefilter_to_onnx,
    }


class _ExportWrapper(nn.Module):
    """Positional signature in the order of the graph inputs."""

    def __init__(self, model: NBGDenoiser | AccumulationDenoiser | OIDNTemporal) -> None:
        super().__init__()
        self.model = model

    def forward(self, color: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
                motion: Tensor, reset: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        return self.model(color, albedo, normal, depth, motion, reset, state)


class _FusedExportWrapper(_ExportWrapper):
    """The same through model/nbg_fused.fused_forward: the glue as fused ops."""

    def forward(self, color: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
                motion: Tensor, reset: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        return fused_forward(self.model, color, albedo, normal, depth, motion, reset, state)


class _ExportWrapperWithSamples(_ExportWrapper):
    """The same, with the frame's samples per pixel (SAMPLES_INPUT, shape [1]) last."""

    def forward(self, color: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
                motion: Tensor, reset: Tensor, state: Tensor,
                spp: Tensor) -> tuple[Tensor, Tensor]:
        return self.model(color, albedo, normal, depth, motion, reset, state, spp)


class _FusedExportWrapperWithSamples(_ExportWrapper):
    """The fused graph with the frame's samples per pixel last (a noise-aware NBG blend)."""

    def forward(self, color: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
                motion: Tensor, reset: Tensor, state: Tensor,
                spp: Tensor) -> tuple[Tensor, Tensor]:
        return fused_forward(self.model, color, albedo, normal, depth, motion, reset, state,
                             spp)


def example_inputs(height: int = 48, width: int = 64, seed: int = 0,
                   state_channels: int = NBGDenoiser.state_channels) -> tuple[Tensor, ...]:
    """Plausible inputs (used for tracing and tests): (color, albedo, normal, depth, motion,
    reset, state); for the oidn-temporal stage the first is OIDN's output instead of color."""
    gen = torch.Generator().manual_seed(seed)
    normal = torch.randn(1, 3, height, width, generator=gen)
    return (
        torch.rand(1, 3, height, width, generator=gen) * 2,
        torch.rand(1, 3, height, width, generator=gen),
        normal / normal.norm(dim=1, keepdim=True).clamp_min(1e-6),
        1 + torch.rand(1, 1, height, width, generator=gen) * 4,
        torch.randn(1, 2, height, width, generator=gen),
        torch.ones(1),
        torch.zeros(1, state_channels, height, width),
    )


def export_nbg(
    model: NBGDenoiser | AccumulationDenoiser | OIDNTemporal,
    path: Path,
    *,
    version: str = "0",
    training: Mapping | None = None,
    metrics: Mapping | None = None,
    fuse: bool = True,
) -> Path:
    """Write `model` (an NBG variant, the accumulation-only pre-stage or an oidn-temporal
    stage) as a self-describing ONNX file at `path` and return the path.

    `fuse`: a model model/nbg_fused.py can fuse goes through its fused ops (the same frame,
    without ~60 element-wise nodes); False exports the unfused graph.

    A model with `inputs` names its own first graph inputs (oidn-temporal: the prepass result
    "oidn" instead of "color"); a config with `prepass()` becomes quietframe.prepass, which the
    runtime carries out before the graph (runtime/oidn_prepass.py)."""
    model = model.eval()
    height = torch.export.Dim("height", min=1, max=8192)
    width = torch.export.Dim("width", min=1, max=8192)
    image_dims = {2: height, 3: width}
    # In the order of the forward arguments: the exporter matches them by position.
    dynamic = {name: image_dims for name in BUFFER_NAMES} | {"reset": None, "state": image_dims}
    table = custom_translation_table()
    graph_inputs = tuple(getattr(model, "inputs", BUFFER_NAMES))
    # Run-time inputs after the state: the only one a graph of this kind takes is the frame's
    # spp (model/output_history.py), fed by the runtime from its default or an option.
    extra = model.run_time_inputs() if hasattr(model, "run_time_inputs") else []
    if [i["name"] for i in extra] not in ([], [SAMPLES_INPUT]):
        raise ValueError(f"export_nbg exports no run-time input but {SAMPLES_INPUT!r}")
    fused = fuse and fusable(model)
    if extra:
        wrapper_type = _FusedExportWrapperWithSamples if fused else _ExportWrapperWithSamples
    else:
        wrapper_type = _FusedExportWrapper if fused else _ExportWrapper
    wrapper = wrapper_type(model).eval()
    example = example_inputs(state_channels=model.state_channels)
    if extra:
        example = (*example, torch.full((1,), float(extra[0]["default"])))
        dynamic |= {SAMPLES_INPUT: None}
    with torch.no_grad():
        program = torch.onnx.export(
            wrapper, example, dynamo=True,
            opset_version=OPSET, custom_translation_table=table, dynamic_shapes=dynamic,
            input_names=[*graph_inputs, RESET, STATE_IN + STATE_NAME,
                         *(i["name"] for i in extra)],
            output_names=[OUTPUT, STATE_OUT + STATE_NAME],
            verbose=False,
        )
    config = model.config
    prepass = config.prepass() if hasattr(config, "prepass") else None
    state = [{"name": STATE_NAME, "channels": model.state_channels}]
    metadata = model_metadata(config, version, state, training, metrics, inputs=extra or None,
                              prepass=prepass)
    return save_described(program.model_proto, metadata, path)


def export_oidn_only(config: OIDNOnlyConfig, path: Path, *, version: str = "0") -> Path:
    """Write a prepass-only composition (model/oidn_temporal.OIDNOnlyConfig): a graph that
    passes the prepass result `oidn` through as `denoised`, with no state of its own (the
    color_from model keeps its own); the runtime does the rest from the metadata."""
    dims = [1, 3, "height", "width"]
    graph = onnx.helper.make_graph(
        [onnx.helper.make_node("Identity", ["oidn"], [OUTPUT])], config.name,
        [onnx.helper.make_tensor_value_info("oidn", onnx.TensorProto.FLOAT, dims)],
        [onnx.helper.make_tensor_value_info(OUTPUT, onnx.TensorProto.FLOAT, dims)])
    proto = onnx.helper.make_model(graph, opset_imports=[onnx.helper.make_opsetid("", OPSET)])
    # OIDN runs with the colour alone when albedo/normal are absent (runtime/oidn_prepass.py);
    # a color_from graph stage adds its own requirements (runtime/denoiser.model_info).
    roles = (PREPASS_BUFFERS[:1], PREPASS_BUFFERS[1:])
    metadata = model_metadata(config, version, [], {"trained": False, "learned_stage": False},
                              {}, roles=roles, prepass=config.prepass())
    return save_described(proto, metadata, path)


def model_card(
    config, version: str, state: list[dict], training: Mapping | None, metrics: Mapping | None,
    roles: tuple[tuple[str, ...], tuple[str, ...]] | None = None,
    inputs: list[dict] | None = None, prepass: Mapping | None = None,
) -> ModelCard:
    """The card of an exported model (runtime/card.py): `roles` = (required, optional) buffers,
    by default from the training config (buffer_roles); `inputs` = run-time inputs
    (`quietframe.inputs` dicts); `prepass` = the config's prepass spec (an OIDN stage, after a
    `color_from` graph); the tiling from the family's rule (runtime/receptive.py)."""
    required, optional = roles or buffer_roles(training)
    architecture = json.loads(json.dumps(config.to_dict()))  # as a reader sees it (lists)
    specs = tuple(InputSpec.from_dict(i) for i in inputs or [])
    stages = stages_from_prepass(prepass_stage(prepass) if prepass else None)
    notes, tables = split_metrics(metrics or {})
    return ModelCard(
        name=config.name, version=version, architecture=architecture, required=tuple(required),
        optional=tuple(optional),
        state=tuple(StateSpec(s["name"], int(s["channels"]), int(s.get("scale", 1)))
                    for s in state),
        inputs=specs, stages=stages,
        tiling=tiling_for(architecture, specs, prepass is not None),
        training=dict(training or {}), measurements=tables, notes=notes,
    )


def model_metadata(
    config, version: str, state: list[dict], training: Mapping | None, metrics: Mapping | None,
    roles: tuple[tuple[str, ...], tuple[str, ...]] | None = None,
    inputs: list[dict] | None = None, prepass: Mapping | None = None,
) -> dict[str, str]:
    """The metadata_props that make an exported model self-describing: its card as props
    (docs/model-interface.md)."""
    return model_card(config, version, state, training, metrics, roles, inputs,
                      prepass).to_props()


def save_described(proto: onnx.ModelProto, metadata: Mapping[str, str], path: Path) -> Path:
    """Attach the metadata, check the graph and write it to `path`."""
    onnx.helper.set_model_props(proto, dict(metadata))
    onnx.checker.check_model(proto)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save_model(proto, str(path))
    return path
