"""Temporal pre-stage of the NBG denoiser (Meng et al. 2020 §4.6): reprojection + accumulation.

State-in / state-out (docs/architecture.md): the caller passes the previous state tensor and
gets the new one back, so the same code runs in training (unrolled sub-sequences) and in the
exported graph.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from quietframe.runtime.card import SAMPLES_INPUT
from quietframe.runtime.receptive import STILL_BLOCK

# History is kept where the reprojected surface matches the current one (disocclusion test).
DEPTH_REL_TOLERANCE = 0.1  # |d_prev - d| / d
NORMAL_MIN_DOT = 0.9  # n_prev · n
# Current-frame weight: the paper's fixed 0.2 (previous 0.8) once the history holds >= 5 frames;
# before that (after a reset or disocclusion) 1/n, i.e. a plain mean of the frames seen so far,
# so that fresh history is not dominated by its first noisy frame.
MIN_CURRENT_WEIGHT = 0.2
# A motion this close to a whole number of pixels counts as pixel-aligned: nearest reprojection
# is exact there (a locked-off shot, a pan by whole pixels), so a history kept only there never
# blurs (docs/evaluation/cycles-locked-off).
ALIGNED_TOLERANCE = 1 / 64  # px
# Depth (relative) and normal (absolute) this close to last frame's are the same sample: far
# below the change of an average of 4 or more samples, far above float32's rounding of a copy.
REPEAT_TOLERANCE = 1e-6
# The frame's spp a graph assumes where it is not given one (its `spp` input's default): the
# count the oidn-history tiers shipped with before they read it.
DEFAULT_SPP = 4.0
# Channels of the accumulation state: radiance (3), depth (1), normal (3), history length (1),
# named here once so every reader slices the same channels (`state[:, HISTORY_LENGTH]`).
STATE_CHANNELS = 8
RADIANCE = slice(0, 3)
DEPTH = slice(3, 4)
NORMAL = slice(4, 7)
HISTORY_LENGTH = slice(7, 8)


def frame_samples(spp: Tensor | None) -> Tensor:
    """The frame's spp as a model reads it: the one given, else DEFAULT_SPP (shape (1,))."""
    return torch.full((1,), DEFAULT_SPP) if spp is None else spp


def samples_input(default: float, doc: str) -> dict:
    """The `quietframe.inputs` entry of a graph that reads the frame's samples per pixel
    (SAMPLES_INPUT, shape [1]): the service fills it from the EXR header, a session option or
    auto's estimate, else `default`."""
    return {"name": SAMPLES_INPUT, "dtype": "float32", "shape": [1], "default": default,
            "allowed": None, "minimum": 1.0, "doc": doc}


# ai.quietframe::BackwardWarp attribute mode = index. Bicubic is PyTorch's (a = -0.75, each of
# the 4×4 taps clamped to the image): it resamples without bilinear's blur, for clean images
# (a denoised output); on noisy radiance it rings (docs/evaluation/cycles-locked-off).
WARP_MODES = ("bilinear", "nearest", "bicubic")


def _grid_fetch(image: Tensor, motion: Tensor, mode: str) -> tuple[Tensor, Tensor]:
    """backward_warp's computation (its docstring), differentiable in `image`."""
    if mode not in WARP_MODES:
        raise ValueError(f"backward_warp: mode must be one of {WARP_MODES}, got {mode!r}")
    n, _, h, w = image.shape
    ys = torch.arange(h, dtype=image.dtype, device=image.device).view(1, h, 1)
    xs = torch.arange(w, dtype=image.dtype, device=image.device).view(1, 1, w)
    src_x = xs + motion[:, 0]  # (N, H, W) pixel index in the previous frame
    src_y = ys + motion[:, 1]
    # grid_sample with align_corners=False maps pixel centre i to (2i + 1) / size - 1.
    grid = torch.stack(((2 * src_x + 1) / w - 1, (2 * src_y + 1) / h - 1), dim=-1)
    warped = F.grid_sample(image, grid, mode=mode, padding_mode="border", align_corners=False)
    inside = (src_x > -0.5) & (src_x < w - 0.5) & (src_y > -0.5) & (src_y < h - 0.5)
    return warped, inside.unsqueeze(1).to(image.dtype)


@torch.library.custom_op("quietframe::backward_warp", mutates_args=())
def backward_warp(image: Tensor, motion: Tensor, mode: str = "bilinear") -> tuple[Tensor, Tensor]:
    """Fetch image(t-1) at p + motion(p) (`mode`: WARP_MODES); also the in-frame mask.

    image (N, C, H, W), motion (N, 2, H, W) in pixels -> ((N, C, H, W), (N, 1, H, W))

    A custom op so that the ONNX export maps it to ai.quietframe::BackwardWarp (export/ops),
    which computes exactly this with the same float32 coordinate arithmetic; this grid_sample
    code is its reference. Differentiable in `image` only (see _warp_backward).
    """
    return _grid_fetch(image, motion, mode)


@backward_warp.register_fake
def _warp_fake(image: Tensor, motion: Tensor, mode: str = "bilinear") -> tuple[Tensor, Tensor]:
    n, _, h, w = image.shape  # h, w may be symbolic
    return torch.empty_like(image), image.new_empty((n, 1, h, w))


def _warp_setup_context(ctx, inputs, output) -> None:
    image, motion, mode = inputs
    ctx.save_for_backward(motion)
    ctx.mode, ctx.image_shape, ctx.image_dtype = mode, image.shape, image.dtype


def _warp_backward(ctx, grad_warped: Tensor | None, grad_inside: Tensor | None):
    # Gradient to the image: a history of a learned output (model/learned_blend.py) is trained
    # through its unrolled frames. The fetch is linear in the image, so its gradient is the
    # same at any image: differentiate grid_sample at zeros. Not to the motion: nothing
    # learns motion, and grid_sample's coordinate gradient is not the native op's.
    if ctx.needs_input_grad[1]:
        raise RuntimeError("backward_warp has no gradient for the motion vectors: detach them")
    (motion,) = ctx.saved_tensors
    if grad_warped is None:
        return None, None, None
    with torch.enable_grad():
        probe = torch.zeros(ctx.image_shape, dtype=ctx.image_dtype, device=motion.device,
                            requires_grad=True)
        warped, _ = _grid_fetch(probe, motion.detach(), ctx.mode)
        (grad_image,) = torch.autograd.grad(warped, probe, grad_warped)
    return grad_image, None, None


backward_warp.register_autograd(_warp_backward, setup_context=_warp_setup_context)


def history_valid(
    warped_depth: Tensor, warped_normal: Tensor, depth: Tensor, normal: Tensor,
    depth_tolerance: Tensor | float = DEPTH_REL_TOLERANCE,
    normal_min_dot: Tensor | float = NORMAL_MIN_DOT,
) -> Tensor:
    """Disocclusion test: 1 where the reprojected surface is the current one, else 0 (the
    tolerances may be per pixel, (N, 1, H, W))."""
    depth_ok = (warped_depth - depth).abs() <= depth_tolerance * depth.clamp_min(1e-6)
    # Cosine, not the raw dot: AOV normals averaged over a pixel's samples are shorter than 1 at
    # edges, and their length changes with sub-pixel motion while their direction does not.
    dot = (warped_normal * normal).sum(dim=1, keepdim=True)
    lengths = warped_normal.norm(dim=1, keepdim=True) * normal.norm(dim=1, keepdim=True)
    normal_ok = dot > normal_min_dot * lengths
    return (depth_ok & normal_ok).to(depth.dtype)


def whole_pixels(motion: Tensor) -> Tensor:
    """(N, 1, H, W) bool: both motion components are whole pixels at this pixel alone (NaN:
    not whole)."""
    return (motion - motion.round()).abs().amax(dim=1, keepdim=True) <= ALIGNED_TOLERANCE


def pixel_aligned(motion: Tensor) -> Tensor:
    """(N, 1, H, W) bool: the pixel and its 3×3 neighbours all move by the same whole number
    of pixels (NaN: not aligned; the frame's border counts only pixels inside it). A whole
    value at one pixel alone is an accident of sub-pixel motion (a camera orbit crosses whole
    values along thin curves), not an alignment: the nearest fetch there is off by up to
    ALIGNED_TOLERANCE at a pixel whose neighbours are resampled, and on studio-spin (zoo round
    2) such isolated pixels carried an accumulation of caustic fireflies that OIDN, seeing
    noise unlike the frame's around them, kept (-0.13 dB against the stage at 64 spp).
    Radius 2: the accumulation's tiling radius (runtime/receptive.nbg_tiling) covers it."""
    whole = whole_pixels(motion).to(motion.dtype)
    spread = (F.max_pool2d(motion, 3, 1, 1) + F.max_pool2d(-motion, 3, 1, 1)).amax(
        dim=1, keepdim=True)
    alike = whole * (spread <= ALIGNED_TOLERANCE).to(motion.dtype)  # NaN spread: not alike
    return -F.max_pool2d(-alike, 3, 1, 1) > 0.5  # every 3×3 neighbour alike and whole


@torch.library.custom_op("quietframe::aligned_mask", mutates_args=())
def aligned_mask(motion: Tensor) -> Tensor:
    """pixel_aligned as a float mask (N, 1, H, W) of 0 and 1, as a torch custom op: the ONNX
    export maps it onto ai.quietframe::PixelAligned (export/ops/pixel_aligned.cc), one pass
    where the max pools and reductions were ~15 nodes (tests/export/test_ops_pixel_aligned.py
    holds the C++ op to this). No gradient: the mask is a test on the motion."""
    return pixel_aligned(motion).to(motion.dtype)


@aligned_mask.register_fake
def _aligned_mask_fake(motion: Tensor) -> Tensor:
    return motion.new_empty((motion.shape[0], 1, *motion.shape[2:]))


def still_pixels(motion: Tensor, radius: int) -> Tensor:
    """(N, 1, H, W) 1 where every pixel within at least `radius` moves by the same whole
    number of pixels: a locked-off camera's pixels away from anything that moves (NaN: not
    still). The motion's range is taken per STILL_BLOCK² block (the frame's border: the pixels
    inside it) and over ⌈radius / STILL_BLOCK⌉ blocks each way, so a pixel's window reaches
    `radius` to `radius` + STILL_BLOCK - 1 px: a 33-wide max pool at every pixel was a third of
    the history graph's time at 720p. Blocks lie on the frame's grid (tiles align to them)."""
    height, width = motion.shape[-2:]
    reach = -(-radius // STILL_BLOCK)
    high = F.max_pool2d(motion, STILL_BLOCK, STILL_BLOCK, ceil_mode=True)
    low = F.max_pool2d(-motion, STILL_BLOCK, STILL_BLOCK, ceil_mode=True)
    window = 2 * reach + 1
    spread = (F.max_pool2d(high, window, 1, reach) + F.max_pool2d(low, window, 1, reach)).amax(
        dim=1, keepdim=True)
    spread = F.interpolate(spread, scale_factor=STILL_BLOCK, mode="nearest")[
        ..., :height, :width]
    return (whole_pixels(motion) & (spread <= ALIGNED_TOLERANCE)).to(motion.dtype)


def history_weights(keep: Tensor, previous_count: Tensor) -> tuple[Tensor, Tensor]:
    """(weight of the current frame, new history length) where `keep` (0/1) says whether the
    reprojected history is kept: 1/n over the first frames of a history, then the fixed
    MIN_CURRENT_WEIGHT (an exponential history). One rule for every history quietframe keeps."""
    count = keep * previous_count.clamp(0.0, 1.0 / MIN_CURRENT_WEIGHT) + 1
    return (1 / count).clamp_min(MIN_CURRENT_WEIGHT), count


def weight_floor(spp: Tensor, weight: float, per_doubling: float, maximum: float) -> Tensor:
    """A least weight of the current frame that rises with its spp, (1,) -> (1, 1, 1, 1):
    clamp(weight + per_doubling · log2 spp, MIN_CURRENT_WEIGHT, maximum), spp below 1 counting
    as 1. Where a history is resampled (fetched under sub-pixel motion) each frame resamples it
    again, so a long one compounds the fetch's error, which outweighs the noise it removes the
    sooner the cleaner the frame (the learned tiers' fading_floor, the output history's w(spp));
    the output history's untrusted pixels follow one too (u(spp))."""
    floor = weight + per_doubling * torch.log2(spp.clamp_min(1.0))
    return floor.clamp(MIN_CURRENT_WEIGHT, maximum).view(-1, 1, 1, 1)


def fading_floor(per_doubling: float, spp: Tensor | None) -> Tensor | None:
    """The floor of a learned tier whose resampled history fades with the frame's spp
    (NBGConfig / AffinityConfig.resampled_weight_per_doubling): weight_floor from
    MIN_CURRENT_WEIGHT at 1 spp to 1; None where per_doubling is 0 (every valid history kept)."""
    if per_doubling <= 0:
        return None
    return weight_floor(frame_samples(spp), MIN_CURRENT_WEIGHT, per_doubling, 1.0)


def resampled_trust(motion: Tensor, previous_count: Tensor, floor: Tensor) -> Tensor:
    """(N, 1, H, W) in [0, 1]: the share of a reprojected history to keep so that the current
    frame's weight (history_weights) is at least `floor` ((N or 1, 1, 1, 1), fading_floor)
    where the motion is not pixel-aligned; 1 where it is (the nearest fetch is exact there)
    and wherever the floor asks for no more than MIN_CURRENT_WEIGHT. A kept share k of a
    history of n frames gives n' = k·n + 1, so k = (1/floor - 1) / n caps n' at 1/floor:
    1/floor frames of history, α = floor. As a factor on `keep` it passes through
    NBGAccumulate's `inside` input unchanged (model/nbg_fused.py). No gradient (a test on the
    motion and the history's length): the custom op `trust_of_resampled`, which the ONNX
    export maps onto ai.quietframe::ResampledTrust (export/ops/pixel_aligned.cc), one pass
    where the aligned test's op and ~8 nodes over full-resolution planes were."""
    return trust_of_resampled(motion.detach(), previous_count.detach(), floor.detach())


@torch.library.custom_op("quietframe::resampled_trust", mutates_args=())
def trust_of_resampled(motion: Tensor, previous_count: Tensor, floor: Tensor) -> Tensor:
    """resampled_trust's arithmetic (tests/export/test_ops_resampled_trust.py holds the C++ op
    to this, bit for bit)."""
    aligned = pixel_aligned(motion).to(motion.dtype)
    count = previous_count.clamp(0.0, 1.0 / MIN_CURRENT_WEIGHT)
    share = ((1.0 / floor - 1.0) / count.clamp_min(1e-6)).clamp(max=1.0)
    share = torch.where(floor > MIN_CURRENT_WEIGHT, share, torch.ones_like(share))
    return aligned + (1 - aligned) * share


@trust_of_resampled.register_fake
def _trust_fake(motion: Tensor, previous_count: Tensor, floor: Tensor) -> Tensor:
    return motion.new_empty((motion.shape[0], 1, *motion.shape[2:]))


def reproject_history(state: Tensor, motion: Tensor, depth: Tensor, normal: Tensor,
                      reset: Tensor, depth_tolerance: Tensor | float = DEPTH_REL_TOLERANCE,
                      normal_min_dot: Tensor | float = NORMAL_MIN_DOT
                      ) -> tuple[Tensor, Tensor]:
    """A history state laid out as the accumulation's (colour 3, depth, normal 3, length)
    reprojected to the nearest pixel, and `keep` (N, 1, H, W): 1 where it is used (in the
    frame, the same surface, no reset).

    Nearest, for the whole state: the surface test then checks exactly the pixel whose colour
    is reused. Bilinear radiance mixed a tap from across a silhouette into the history (a light
    source next to a dark wall left a trail for frames) and blurred it a little more every
    frame; on the validation set nearest halved relMSE and lowered TRMAE by 7% at equal PSNR
    (docs/training.md)."""
    warped, inside = backward_warp(state, motion, mode="nearest")
    keep = inside * history_valid(warped[:, DEPTH], warped[:, NORMAL], depth, normal,
                                  depth_tolerance, normal_min_dot)
    return warped, keep * (1 - reset.view(-1, 1, 1, 1))


def repeated_sample(warped_depth: Tensor, warped_normal: Tensor, depth: Tensor,
                    normal: Tensor) -> Tensor:
    """(N, 1, H, W) 1 where this frame's depth and normal at a surface equal the fetched
    history's to float precision (REPEAT_TOLERANCE): at one sample a pixel, the renderer
    sampled the same point of the pixel as last frame. Cycles 4.5 does so at 1 spp (every
    frame's one sample of a still pixel hits the same point though the seed is animated: all
    of fence-locked's pixels); from 2 spp its aux differ between frames, and from 4 spp at all
    but ~0.5% of a still shot's pixels (zoo round 2, fence-locked and studio-locked)."""
    depth_same = (warped_depth - depth).abs() <= REPEAT_TOLERANCE * depth.abs()
    normal_same = (warped_normal - normal).abs().amax(dim=1, keepdim=True) <= REPEAT_TOLERANCE
    return (depth_same & normal_same).to(depth.dtype)


def accumulate(
    radiance: Tensor,
    depth: Tensor,
    normal: Tensor,
    motion: Tensor,
    reset: Tensor,
    state: Tensor,
    aligned_only: bool = False,
    restart_repeated: bool = False,
    spp: Tensor | None = None,
    floor: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """One step of temporal accumulation of demodulated radiance (NBG §4.6).

    radiance (N, 3, H, W), depth (N, 1, H, W), normal (N, 3, H, W), motion (N, 2, H, W),
    reset (N,) 1 = drop history, state (N, 8, H, W) -> (accumulated radiance, new state).
    `aligned_only`: keep history only where the motion is pixel-aligned (`pixel_aligned`), so
    the accumulation never resamples: under sub-pixel motion even the nearest fetch is half a
    pixel off, and OIDN on such a history lost up to 1 dB to OIDN on the frame alone on moving
    Cycles shots (docs/evaluation/cycles-locked-off).
    `restart_repeated`: on a frame of one sample a pixel (`spp` < 2), no history where the
    frame repeats last frame's sample (`repeated_sample`): a mean of samples of one point
    converges to that point, not to the pixel's mean, so thin branches and fine texture stay
    aliased however long the history; on a locked-off exterior of thin geometry at 1 spp OIDN
    on that accumulation lost 0.59 dB to OIDN on the frame alone (zoo round 2, fence-locked;
    docs/zoo.md "Repeated samples"). Only there do equal aux say the colour's sample is the
    same: a 1-spp frame's aux are its one sample's, while a pixel-centre G-buffer repeats at
    any spp though the colour's samples move. `spp` (1,), None: the test is off.
    `floor` ((N or 1, 1, 1, 1), fading_floor): where the motion is not pixel-aligned the
    current frame weighs at least this much (resampled_trust); None: every valid history kept.
    """
    warped, keep = reproject_history(state, motion, depth, normal, reset)
    prev_radiance, prev_count = warped[:, RADIANCE], warped[:, HISTORY_LENGTH]
    if aligned_only:
        keep = keep * aligned_mask(motion)
    if restart_repeated and spp is not None:
        single = (spp < 2).to(keep.dtype).view(-1, 1, 1, 1)  # one sample a pixel
        repeated = repeated_sample(warped[:, DEPTH], warped[:, NORMAL], depth, normal)
        keep = keep * (1 - single * repeated)
    if floor is not None:
        keep = keep * resampled_trust(motion, prev_count, floor)
    alpha, count = history_weights(keep, prev_count)  # (N, 1, H, W) weight of the current frame
    accumulated = alpha * radiance + (1 - alpha) * prev_radiance
    new_state = torch.cat((accumulated, depth, normal, count), dim=1)
    return accumulated, new_state
