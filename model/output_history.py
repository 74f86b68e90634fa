"""The temporal stage of the `oidn-history` tiers: a history of OIDN's output, kept where it
stays sharp (the ablation behind it: docs/evaluation/cycles-locked-off).

The runtime first runs `aligned-accumulation.onnx` (the accumulation of the noisy colour, kept
only where the motion is a whole number of pixels, model/temporal.accumulate aligned_only),
then OIDN on its output (D_t), then this graph:

  P_t = O_{t-1}(p + m)      the nearest pixel, unclamped, where m is pixel-aligned (exact);
        clip(max(B O_{t-1}(p + m), 0), min₃ₓ₃ D_t, max₃ₓ₃ D_t)   elsewhere, B = bicubic fetch
  O_t = α D_t + (1 - α) P_t   where the reprojected surface is this one (history_valid),
        α = max(1/n, 0.2) over the history's n frames (model/temporal.history_weights), and at
        least w(spp) where the history was resampled (OutputHistoryConfig.resampled_floor);
        α = 1 (the stage, history restarted) where the evidence says the fetch cannot be
        right: a resampled fetch across a depth or motion edge, whose shading changed, or
        on detail a bicubic fetch blurs; an exact fetch beside pixels that move otherwise
        (`OutputHistory.history`, OutputHistoryConfig's trust tests)

Why each piece (measured on Cycles test shots, 1–64 spp): OIDN on a history fetched from the
nearest pixel under sub-pixel motion lost up to 1 dB to OIDN on the frame alone, and a bicubic
fetch of the noisy history rang (−4.6 dB at 1 spp); a bicubic fetch of OIDN's clean output,
clipped to this frame's neighbourhood, kept its detail. State-in / state-out like every
quietframe model (docs/architecture.md): zeros and reset = 1 on a first frame or a cut.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from quietframe.model.oidn_temporal import prepass_spec
from quietframe.model.temporal import (
    DEFAULT_SPP,
    DEPTH,
    DEPTH_REL_TOLERANCE,
    HISTORY_LENGTH,
    NORMAL_MIN_DOT,
    RADIANCE,
    aligned_mask,
    backward_warp,
    history_weights,
    reproject_history,
    samples_input,
    still_pixels,
    weight_floor,
)

FAMILY = "output-history"  # the architecture's family (runtime/receptive.py tiling rule)
# State planes: previous output O (3), depth (1), normal (3), history length n (1).
STATE_CHANNELS = 8


@dataclass(frozen=True)
class OutputHistoryConfig:
    """Everything needed to rebuild the stage (no learned parameters); in ONNX metadata."""

    name: str = "oidn-history"
    quality: str = "high"  # the OIDN pass: high or fast
    prefilter_aux: bool = False  # OIDN denoises the albedo and normal first (Blender's Accurate)
    aux_quality: str = ""  # those prefilters' quality ("": the main filter's)
    color_from: str = "aligned-accumulation.onnx"
    family: str = FAMILY
    # The current frame's weight where the history is fetched bicubically (sub-pixel motion) is
    # at least w(spp) = clamp(resampled_weight + resampled_weight_per_doubling · log2 spp,
    # MIN_CURRENT_WEIGHT, resampled_weight_max) (elsewhere MIN_CURRENT_WEIGHT): every frame the
    # history is resampled again, so a long history there compounds the resampling's error,
    # which outweighs the noise it removes once OIDN's output is clean, and the cleaner the
    # input the sooner. The frame's spp is the run-time input `spp` (SAMPLES_INPUT: the
    # renderer's count from the EXR header, auto's estimate, or a session option; default
    # default_spp). Chosen on the Cycles validation split (8 moving sequences), per spp the
    # floor with the largest gain over OIDN on the frame: 1-4 spp 0.35, 8 spp 0.5, 16 spp 0.6,
    # 64 spp 0.7-0.85 (a constant 0.5 lost 0.04 dB at 64 spp; the schedule's worst gain over
    # 1-64 spp is +0.07 dB; experiments/output_history.py --resampled-weights,
    # docs/evaluation/cycles-history/README.md).
    resampled_weight: float = 0.35
    resampled_weight_per_doubling: float = 0.075
    resampled_weight_max: float = 0.85
    default_spp: float = DEFAULT_SPP  # w = 0.5 there: the constant the tier shipped with before
    # Per-pixel trust of a resampled history (`trusted_resample`): the bicubic fetch is used
    # only where its footprint lies on one surface moving as one, now and in the previous
    # frame; elsewhere the pixel is its per-frame stage. 0 turns a test off (the tiers' version
    # 2: every pixel that passes the nearest pixel's surface test). Chosen on zoo round 2's
    # validation shots (experiments/history_trust, docs/zoo.md "Per-pixel trust"; with
    # exact_edge_motion below): against the stage, fence-truck's -0.22/-0.24/-0.21 dB at
    # 4/16/64 spp became +0.12/+0.12/+0.09 and studio-spin's -0.80/-1.68/-1.84 became
    # +0.01/-0.07/-0.16; looser bounds (0.1, 0.5) kept more of the history's loss on the
    # turning wireframe. The price: 1 spp gains less (fence-truck +0.13 where it was +0.45).
    edge_depth: float = 0.05  # max relative 3x3 depth range (current, and previous at p + m)
    edge_motion: float = 0.25  # max 3x3 range of either motion component, pixels
    # The motion test at pixels fetched exactly (whole-pixel motion: a locked-off camera, the
    # sky): one next to pixels that move otherwise (the sky beside a moving branch, a still wall
    # beside a turning object) holds, in its history, what passed over it (mixed pixels of the
    # thin object; the surface test reads only the nearest surface). 0: off. A locked-off shot
    # without moving objects has no motion anywhere and keeps every pixel's history.
    exact_edge_motion: float = 0.25  # max 3x3 range of either motion component, pixels
    # An untrusted pixel's current-frame weight is at least u(spp) = clamp(untrusted_weight +
    # untrusted_weight_per_doubling · log2 spp, MIN_CURRENT_WEIGHT, 1); 1 makes it its stage.
    # u = 0.5 + 0.25 log2 spp gained +0.3 dB at 1 spp on fence-truck and shelf-whip but cost
    # studio-spin's worst frame 0.24 dB: never below the stage comes first.
    untrusted_weight: float = 1.0
    untrusted_weight_per_doubling: float = 0.0
    # The resampled history's clip box: 0 is the 3×3 min/max of OIDN's output; γ > 0 the 3×3
    # mean ± γ·std (variance clipping, Salvi 2016), inside min/max: tighter where a caustic or
    # a reflection moves over a still surface (the motion vectors follow the surface, not what
    # it shows), so the history cannot carry last frame's shading there.
    clip_sigma: float = 0.0
    # The shading test of a resampled fetch: where the grey levels (`grey_level`: channel
    # mean, tone-mapped by Işık eq. 15) of the clipped history P_t and this frame's D_t differ
    # by more than θ(spp) = shading_change · (16 / spp)^shading_change_power, the pixel is its
    # stage. The motion vectors follow surfaces, not what they show: a caustic, a reflection
    # or a shadow moving over a still surface passes the surface and footprint tests, and its
    # history is last frame's shading. Only from ~16 spp is D_t clean enough for the
    # difference to be the shading's rather than noise (at 1–4 spp the history gained even
    # where it differed most), hence the bound falls with spp (1 spp 0.48, 16 spp 0.06, 64 spp
    # 0.021). Chosen on the zoo's validation shots (experiments/history_trust, docs/zoo.md
    # "History tiers version 4"): studio-spin -0.06/-0.06 dB against the stage at 16/64 spp
    # became -0.01/+0.00; 0.03 cost gallery-pan 0.16-0.19 dB at 4-16 spp, 0.12 left studio-spin
    # -0.03 at 16 spp. 0: off.
    shading_change: float = 0.06
    shading_change_power: float = 0.75
    # The detail test of a resampled fetch: a bicubic fetch blurs detail finer than a pixel by
    # an amount that depends on the sub-pixel offset and on the content, and every frame
    # resamples the history again. Its size at p is measured on this frame: D_t shifted by the
    # motion's fraction and back (two bicubic fetches of its grey level); above θ_r(spp) =
    # resampling_detail · (16 / spp)^resampling_detail_power the blur costs more than the
    # history's averaging gains and the pixel is its stage. The cleaner the frame, the less
    # noise the history can remove, so the bound falls fast with spp (16 spp 0.04, 64 spp
    # 0.005). Chosen on the zoo's validation shots: gallery-pan (10 px a frame past 22 cm
    # bricks and posters) -0.11 dB against the stage at 64 spp became +0.04 (its 16 spp
    # unchanged); 0.02 with power 1 cost it 0.04 at 16 spp. 0: off.
    resampling_detail: float = 0.04
    resampling_detail_power: float = 1.5
    # The surface test at a still pixel (`still_pixels`: every pixel within still_radius moves
    # by the same whole pixels, a locked-off camera away from anything that moves): the depth
    # within still_depth_tolerance and the normals within cos still_normal_min_dot, looser
    # than elsewhere (10%, 0.9). At 1–16 spp the aux of thin bars and rough or dark surfaces
    # are averages of a few samples and change from frame to frame though nothing moves: on
    # studio-locked at 4 spp the strict test failed at 17% of the pixels between consecutive
    # frames and restarted the history at a fifth of the frame on most frames (flicker 0.78x
    # Blender's denoise). What the test is for there, a surface uncovered by a moving object,
    # cannot happen at a still pixel: an object that moved up to still_radius pixels since the
    # last frame still has moving pixels within that radius. Chosen on studio-locked
    # (validation; docs/zoo.md "Locked-off flicker"): +0.73/+2.04 dB over the stage at 4/16
    # spp became +1.29/+2.52, flicker 0.78/0.57x Blender's became 0.60/0.47x; the moving
    # validation shots unchanged. 0: off.
    still_radius: int = 16
    still_depth_tolerance: float = 0.3
    still_normal_min_dot: float = 0.5

    def shading_threshold(self, spp: Tensor) -> Tensor:
        """θ(spp) of the comment above, (1,) -> (1, 1, 1, 1)."""
        return _bound_from_16_spp(spp, self.shading_change, self.shading_change_power)

    def resampling_threshold(self, spp: Tensor) -> Tensor:
        """θ_r(spp) of the comment above, (1,) -> (1, 1, 1, 1)."""
        return _bound_from_16_spp(spp, self.resampling_detail, self.resampling_detail_power)

    def resampled_floor(self, spp: Tensor) -> Tensor:
        """w(spp) of the comment above, (1,) -> (1, 1, 1, 1); spp below 1 counts as 1."""
        return weight_floor(spp, self.resampled_weight, self.resampled_weight_per_doubling,
                            self.resampled_weight_max)

    def untrusted_floor(self, spp: Tensor) -> Tensor:
        """u(spp) of the comment above, (1,) -> (1, 1, 1, 1)."""
        return weight_floor(spp, self.untrusted_weight, self.untrusted_weight_per_doubling, 1.0)

    def to_dict(self) -> dict:
        return asdict(self)

    def prepass(self) -> dict:
        return prepass_spec(self.quality, self.prefilter_aux, self.color_from, self.aux_quality)


def _bound_from_16_spp(spp: Tensor, at_16: float, power: float) -> Tensor:
    """at_16 · (16 / spp)^power, (1,) -> (1, 1, 1, 1): a test's bound that falls as the frame
    gets cleaner; spp below 1 counts as 1."""
    return (at_16 * (16.0 / spp.clamp_min(1.0)) ** power).view(-1, 1, 1, 1)


VARIANTS: dict[str, OutputHistoryConfig] = {
    "oidn-history": OutputHistoryConfig(),
    "oidn-fast-history": OutputHistoryConfig(name="oidn-fast-history", quality="fast"),
    # On Cycles frames plain-aux OIDN is 0.2-0.4 dB below Blender's denoise, which prefilters
    # the aux; prefiltered at fast quality it matches Blender's (the prefilters' quality made no
    # difference, docs/evaluation/cycles-aux-prefilter) at ~60% of Blender's Accurate cost.
    "oidn-history-cleanaux": OutputHistoryConfig(name="oidn-history-cleanaux",
                                                 prefilter_aux=True, aux_quality="fast"),
}


def _range3(x: Tensor) -> Tensor:
    """Per channel, max - min over each pixel's 3×3 neighbourhood (inside the frame)."""
    return F.max_pool2d(x, 3, 1, 1) + F.max_pool2d(-x, 3, 1, 1)


def motion_spread(motion: Tensor) -> Tensor:
    """(N, 1, H, W) the larger 3×3 range of the two motion components, pixels."""
    return _range3(motion).amax(dim=1, keepdim=True)


def trusted_resample(config: OutputHistoryConfig, motion: Tensor, depth: Tensor,
                     previous_depth: Tensor, spread: Tensor | None = None) -> Tensor:
    """(N, 1, H, W) 1 where a bicubic fetch of the history can be right, else 0. It cannot
    where its 4×4 footprint straddles surfaces: a depth edge around p now or around p + m in
    the previous frame (mixed pixels of thin geometry against a far background, silhouettes,
    disocclusions), or where neighbouring pixels move differently (parallax, a turning object:
    the footprint's pixels came from different places). Clipping to the 3×3 range of OIDN's
    output does not catch these: there the range spans both surfaces. `spread`:
    motion_spread(motion), where the caller has it already."""
    smooth = torch.ones_like(depth)
    if config.edge_depth > 0:
        scale = config.edge_depth * depth.clamp_min(1e-6)
        here = (_range3(depth) <= scale).to(depth.dtype)
        spans = torch.cat((F.max_pool2d(previous_depth, 3, 1, 1),
                           -F.max_pool2d(-previous_depth, 3, 1, 1)), dim=1)
        there, _ = backward_warp(spans, motion, mode="nearest")
        before = ((there[:, 0:1] - there[:, 1:2]) <= scale).to(depth.dtype)
        smooth = smooth * here * before
    if config.edge_motion > 0:
        spread = motion_spread(motion) if spread is None else spread
        smooth = smooth * (spread <= config.edge_motion).to(depth.dtype)
    return smooth


def grey_level(x: Tensor) -> Tensor:
    """(N, 1, H, W) the channel mean of `x` through Işık eq. 15's tone map, τ(y) = (y / (1 +
    y))^(1/2.4), negatives as 0: a difference of grey levels is about what it costs in the
    figures (model/metrics.tonemap_tau), where a difference of radiance is not."""
    y = x.mean(dim=1, keepdim=True).clamp_min(0.0)
    return (y / (1 + y)) ** (1 / 2.4)


def resampling_blur(mapped: Tensor, motion: Tensor) -> Tensor:
    """(N, 1, H, W) what one round of bicubic resampling at this frame's sub-pixel offsets does
    to `mapped` (N, 1, H, W), this frame's grey level (`grey_level`): shifted by the motion's
    fraction and back, the absolute difference (0 where the motion is whole pixels or the
    content is smooth)."""
    fraction = motion - motion.round()
    there, _ = backward_warp(mapped, fraction, mode="bicubic")
    back, _ = backward_warp(there, -fraction, mode="bicubic")
    return (back - mapped).abs()


def clamp_to_neighbourhood(previous: Tensor, current: Tensor, sigma: float = 0.0) -> Tensor:
    """`previous` clipped per channel to the 3×3 min/max of `current` (border: the pixels
    inside the frame); with `sigma` > 0 also to the 3×3 mean ± sigma·std (border: the
    neighbourhood's pixels outside the frame count as the edge's, replicate padding)."""
    low = -F.max_pool2d(-current, 3, 1, 1)
    high = F.max_pool2d(current, 3, 1, 1)
    if sigma > 0:
        padded = F.pad(current, (1, 1, 1, 1), mode="replicate")
        mean = F.avg_pool2d(padded, 3, 1)
        spread = (F.avg_pool2d(padded * padded, 3, 1) - mean * mean).clamp_min(0).sqrt()
        low = torch.maximum(low, mean - sigma * spread)
        high = torch.minimum(high, mean + sigma * spread)
    return torch.minimum(torch.maximum(previous, low), high)


class OutputHistory(nn.Module):
    """forward(oidn, albedo, normal, depth, motion, reset, state) -> (denoised, new_state);
    `oidn` is OIDN's output for this frame, the rest as docs/model-interface.md (albedo is
    not read: the blend is of final colours, whose texture OIDN has already restored)."""

    state_channels = STATE_CHANNELS
    inputs = ("oidn", "albedo", "normal", "depth", "motion")

    def __init__(self, config: OutputHistoryConfig | None = None) -> None:
        super().__init__()
        self.config = config or OutputHistoryConfig()

    def forward(self, oidn: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
                motion: Tensor, reset: Tensor, state: Tensor,
                spp: Tensor | None = None) -> tuple[Tensor, Tensor]:
        previous, alpha, count, _ = self.history(oidn, normal, depth, motion, reset, state, spp)
        output = oidn + (1 - alpha) * (previous - oidn)  # α D_t + (1 - α) P_t
        return output, torch.cat((output, depth, normal, count), dim=1)

    def history(self, oidn: Tensor, normal: Tensor, depth: Tensor, motion: Tensor,
                reset: Tensor, state: Tensor, spp: Tensor | None = None
                ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(P_t, α, the new history length, `exact`) of the module docstring: the history
        fetched to this frame, this frame's weight by the rule, and where the fetch is exact."""
        # The nearest pixel's depth and normal test the surface, as in the accumulation;
        # looser at still pixels (OutputHistoryConfig.still_radius).
        config = self.config
        depth_tolerance, normal_min_dot = DEPTH_REL_TOLERANCE, NORMAL_MIN_DOT
        if config.still_radius > 0:
            still = still_pixels(motion, config.still_radius)
            depth_tolerance = DEPTH_REL_TOLERANCE + still * (
                config.still_depth_tolerance - DEPTH_REL_TOLERANCE)
            normal_min_dot = NORMAL_MIN_DOT + still * (config.still_normal_min_dot
                                                       - NORMAL_MIN_DOT)
        warped, keep = reproject_history(state, motion, depth, normal, reset, depth_tolerance,
                                         normal_min_dot)
        fetched, _ = backward_warp(state[:, RADIANCE], motion, mode="bicubic")
        # bicubic overshoots below 0
        fetched = clamp_to_neighbourhood(F.relu(fetched), oidn, self.config.clip_sigma)
        # Arithmetic blends, not Where: onnxruntime broadcasts a 1-channel condition over 3
        # channels slowly (three Wheres were a quarter of this graph's time at 720p).
        exact = aligned_mask(motion)  # 1: the nearest pixel is exact
        previous = fetched + exact * (warped[:, RADIANCE] - fetched)
        alpha, count = history_weights(keep, warped[:, HISTORY_LENGTH])  # alpha = 1 where not kept
        if spp is None:
            spp = torch.full((1,), self.config.default_spp)
        alpha = torch.maximum(alpha, (1 - exact) * self.config.resampled_floor(spp))
        if (config.edge_depth > 0 or config.edge_motion > 0 or config.exact_edge_motion > 0
                or config.shading_change > 0 or config.resampling_detail > 0):
            # a pixel whose fetch cannot be right weighs at least u(spp); at 1 it is its
            # stage, and its history starts afresh (length 1)
            # one 3×3 motion range for both tests (it is on the service's per-frame path)
            spread = (motion_spread(motion)
                      if config.edge_motion > 0 or config.exact_edge_motion > 0 else None)
            trusted = trusted_resample(config, motion, depth, state[:, DEPTH], spread)
            # both tests read grey levels: a tone-mapped channel mean (Pow on three channels
            # was a quarter of this graph's time at 720p)
            mapped = (grey_level(oidn) if config.shading_change > 0
                      or config.resampling_detail > 0 else None)
            if config.shading_change > 0:
                changed = (grey_level(previous) - mapped).abs() > config.shading_threshold(spp)
                trusted = trusted * (1 - changed.to(oidn.dtype))
            if config.resampling_detail > 0:
                blur = resampling_blur(mapped, motion)
                trusted = trusted * (blur <= config.resampling_threshold(spp)).to(oidn.dtype)
            doubt = (1 - exact) * (1 - trusted)
            if config.exact_edge_motion > 0:
                doubt = doubt + exact * (spread > config.exact_edge_motion).to(oidn.dtype)
            floor = config.untrusted_floor(spp)
            alpha = torch.maximum(alpha, doubt * floor)
            count = count - doubt * floor * (count - 1)
        return previous, alpha, count, exact

    def run_time_inputs(self) -> list[dict]:
        """`quietframe.inputs` of the exported graph: the frame's samples per pixel."""
        return [samples_input(self.config.default_spp, "the frame's samples per pixel (the "
                              "service fills it from the EXR header, or auto's estimate): how "
                              "long a resampled history is kept")]

    def initial_state(self, batch: int, height: int, width: int) -> Tensor:
        return torch.zeros(batch, STATE_CHANNELS, height, width)
