"""The NBG denoiser's per-pixel glue as three fused ops, for the exported graph only.

NBGDenoiser.forward (model/nbg.py) is what trains; `fused_forward` computes the same frame with
the glue between its stages as torch custom ops, which the ONNX export maps onto
ai.quietframe::NBGAccumulate / NBGFeatures / NBGBlend, or NBGBlendPass for a model with the
pass-through candidates, NBGBlendNoise for one whose blend also reads the noise level
(export/ops/nbg_fused.cc). In onnxruntime that glue was ~60 element-wise
nodes, a pass over full-frame tensors each, about a third of nbg-2l-3g's time at 720p; each
fused op is one pass.

Each op's implementation below is its reference, built from the functions NBGDenoiser calls, so
the fused graph computes what the model computes (tests/export/test_ops_nbg_fused.py holds the
C++ ops to these). No autograd: nothing trains through them.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from quietframe.model.albedo_prefilter import prefilter_albedo
from quietframe.model.grid import bilateral_slice, bilateral_splat
from quietframe.model.nbg import (
    NBGDenoiser,
    channel_softmax,
    frame_irradiance,
    ldr,
    modulate_logits,
    noise_level,
)
from quietframe.model.temporal import (
    DEPTH,
    HISTORY_LENGTH,
    NORMAL,
    RADIANCE,
    backward_warp,
    fading_floor,
    frame_samples,
    history_valid,
    history_weights,
    resampled_trust,
)

LDR_EXPONENT = 1 / 2.2  # model/nbg.ldr's gamma
FUSED_GRIDS = 3  # NBGBlend, NBGBlendPass and NBGBlendNoise weigh three sliced grids


def accumulate_warped(radiance: Tensor, warped: Tensor, inside: Tensor, depth: Tensor,
                      normal: Tensor, reset: Tensor) -> tuple[Tensor, Tensor]:
    """model/temporal.accumulate after its reprojection (`warped`, `inside` =
    backward_warp(state, motion, "nearest")): (accumulated radiance, new state)."""
    keep = inside * history_valid(warped[:, DEPTH], warped[:, NORMAL], depth, normal)
    keep = keep * (1 - reset.view(-1, 1, 1, 1))
    alpha, count = history_weights(keep, warped[:, HISTORY_LENGTH])
    accumulated = alpha * radiance + (1 - alpha) * warped[:, RADIANCE]
    return accumulated, torch.cat((accumulated, depth, normal, count), dim=1)


def features_scaled(radiance: Tensor, safe_albedo: Tensor, albedo: Tensor, normal: Tensor,
                    depth: Tensor, depth_scale: Tensor) -> Tensor:
    """model/nbg.guide_features of the remodulated radiance, with the frame's depth scale
    (mean depth, clamped to 1e-6) given: (N, 10, H, W)."""
    relative_depth = depth / depth_scale
    return torch.cat(
        (
            ldr(radiance * safe_albedo),
            albedo.clamp(0, 1),
            (normal.clamp(-1, 1) + 1) * 0.5,
            relative_depth / (1 + relative_depth),
        ),
        dim=1,
    )


def blend_sliced(logits: Tensor, safe_albedo: Tensor, *sliced: Tensor,
                 passthrough: tuple[Tensor, ...] = ()) -> Tensor:
    """The softmax of GuideNet's blend logits (the channels after its G guides, G = the number
    of sliced grids) weighing the sliced grids and, with NBGConfig.passthrough, then the
    `passthrough` candidates (the accumulated irradiance, the frame's), remodulated:
    NBGDenoiser.forward's last lines."""
    candidates = (*sliced, *passthrough)
    weights = channel_softmax(logits[:, len(sliced) :])
    result = torch.zeros_like(sliced[0])
    for s, image in enumerate(candidates):
        result = result + weights[:, s : s + 1] * image
    return result * safe_albedo


@torch.library.custom_op("quietframe::nbg_accumulate", mutates_args=())
def nbg_accumulate(radiance: Tensor, warped: Tensor, inside: Tensor, depth: Tensor,
                   normal: Tensor, reset: Tensor) -> tuple[Tensor, Tensor]:
    """ai.quietframe::NBGAccumulate: accumulate_warped."""
    return accumulate_warped(radiance, warped, inside, depth, normal, reset)


@nbg_accumulate.register_fake
def _accumulate_fake(radiance, warped, inside, depth, normal, reset):
    return torch.empty_like(radiance), torch.empty_like(warped)


@torch.library.custom_op("quietframe::nbg_features", mutates_args=())
def nbg_features(radiance: Tensor, safe_albedo: Tensor, albedo: Tensor, normal: Tensor,
                 depth: Tensor, depth_scale: Tensor) -> Tensor:
    """ai.quietframe::NBGFeatures: features_scaled."""
    return features_scaled(radiance, safe_albedo, albedo, normal, depth, depth_scale)


@nbg_features.register_fake
def _features_fake(radiance, safe_albedo, albedo, normal, depth, depth_scale):
    n, _, h, w = radiance.shape
    return radiance.new_empty((n, 10, h, w))


@torch.library.custom_op("quietframe::nbg_blend", mutates_args=())
def nbg_blend(logits: Tensor, safe_albedo: Tensor, sliced0: Tensor, sliced1: Tensor,
              sliced2: Tensor) -> Tensor:
    """ai.quietframe::NBGBlend: blend_sliced of three grids."""
    return blend_sliced(logits, safe_albedo, sliced0, sliced1, sliced2)


@torch.library.custom_op("quietframe::nbg_blend_pass", mutates_args=())
def nbg_blend_pass(logits: Tensor, safe_albedo: Tensor, sliced0: Tensor, sliced1: Tensor,
                   sliced2: Tensor, accumulated: Tensor, frame: Tensor) -> Tensor:
    """ai.quietframe::NBGBlendPass: blend_sliced of three grids and the two pass-through
    candidates."""
    return blend_sliced(logits, safe_albedo, sliced0, sliced1, sliced2,
                        passthrough=(accumulated, frame))


def blend_noise(logits: Tensor, safe_albedo: Tensor, sliced: tuple[Tensor, ...],
                passthrough: tuple[Tensor, Tensor], state: Tensor, spp: Tensor,
                noise_scale: Tensor, noise_shift: Tensor) -> Tensor:
    """blend_sliced with the blend logits first moved by the noise level (model/nbg
    .modulate_logits of noise_level(spp, the state's history length)): NBGConfig.noise_blend."""
    grids = len(sliced)
    level = noise_level(spp, state[:, HISTORY_LENGTH])
    moved = modulate_logits(logits[:, grids:], level, noise_scale, noise_shift)
    return blend_sliced(torch.cat((logits[:, :grids], moved), dim=1), safe_albedo, *sliced,
                        passthrough=passthrough)


@torch.library.custom_op("quietframe::nbg_blend_noise", mutates_args=())
def nbg_blend_noise(logits: Tensor, safe_albedo: Tensor, sliced0: Tensor, sliced1: Tensor,
                    sliced2: Tensor, accumulated: Tensor, frame: Tensor, state: Tensor,
                    spp: Tensor, noise_scale: Tensor, noise_shift: Tensor) -> Tensor:
    """ai.quietframe::NBGBlendNoise: blend_noise of three grids and the two pass-through
    candidates, `state` the accumulation's new state (its history length)."""
    return blend_noise(logits, safe_albedo, (sliced0, sliced1, sliced2), (accumulated, frame),
                       state, spp, noise_scale, noise_shift)


@nbg_blend.register_fake
@nbg_blend_pass.register_fake
def _blend_fake(logits, safe_albedo, *candidates):
    return torch.empty_like(safe_albedo)


@nbg_blend_noise.register_fake
def _blend_noise_fake(logits, safe_albedo, *rest):
    return torch.empty_like(safe_albedo)


def fusable(model: NBGDenoiser) -> bool:
    """Whether fused_forward computes this model: a temporal 3-grid NBG, with or without the
    pass-through (and the noise-aware blend, which needs it), without the pixel-aligned history
    (NBGAccumulate keeps every valid history)."""
    config = model.config
    return (isinstance(model, NBGDenoiser) and config.temporal and config.grids == FUSED_GRIDS
            and not config.aligned_history and (config.passthrough or not config.noise_blend))


def fused_forward(model: NBGDenoiser, color: Tensor, albedo: Tensor, normal: Tensor,
                  depth: Tensor, motion: Tensor, reset: Tensor, state: Tensor,
                  spp: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """NBGDenoiser.forward with its glue as the fused ops (`fusable` models only); `spp` as
    there (a noise-aware blend's)."""
    config, net = model.config, model.guide_net
    albedo = prefilter_albedo(albedo, spp, config.albedo_prefilter)
    frame, safe_albedo = frame_irradiance(color, albedo, config.outlier_sigmas,
                                          config.outlier_floor)  # the pass-through's second
    warped, inside = backward_warp(state, motion, mode="nearest")
    floor = fading_floor(config.resampled_weight_per_doubling, spp)
    if floor is not None:  # the resampled history's share rides on NBGAccumulate's `inside`
        inside = inside * resampled_trust(motion, warped[:, HISTORY_LENGTH], floor)
    irradiance, new_state = nbg_accumulate(frame, warped, inside, depth, normal, reset)
    # The frame-wide reduction stays an onnx ReduceMean: a tiled run feeds the frame's value
    # to every tile (runtime/statistics.py).
    depth_scale = depth.mean(dim=(2, 3), keepdim=True).clamp_min(1e-6)
    features = nbg_features(irradiance, safe_albedo, albedo, normal, depth, depth_scale)
    x = F.leaky_relu(net.first(features), 0.2)  # GuideNet.forward up to its logits
    for conv in net.dense:
        x = torch.cat((x, F.leaky_relu(conv(x), 0.2)), dim=1)
    logits = net.last(x)
    guides = torch.sigmoid(logits[:, :FUSED_GRIDS])
    sliced = []
    for s, (sigma_s, sigma_r) in enumerate(model.scales):
        guide = guides[:, s : s + 1]
        grid, weight = bilateral_splat(irradiance, guide, sigma_s, sigma_r)
        sliced.append(bilateral_slice(grid, weight, guide, sigma_s, sigma_r))
    if config.noise_blend:
        spp = frame_samples(spp)
        return nbg_blend_noise(logits, safe_albedo, *sliced, irradiance, frame, new_state, spp,
                               *net.noise_modulation()), new_state
    if config.passthrough:
        return nbg_blend_pass(logits, safe_albedo, *sliced, irradiance, frame), new_state
    return nbg_blend(logits, safe_albedo, *sliced), new_state
