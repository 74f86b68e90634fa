"""Neural Bilateral Grid denoiser (Meng et al. 2020): GuideNet + multi-scale bilateral grids.

Frame flow (one call of NBGDenoiser.forward):
  demodulate albedo -> suppress outliers -> temporal accumulation (state in/out) ->
  GuideNet on LDR features -> per scale: splat + slice along its guide -> blend -> remodulate.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from quietframe.model.albedo_prefilter import check_albedo_prefilter, prefilter_albedo
from quietframe.model.grid import bilateral_slice, bilateral_splat
from quietframe.model.temporal import (
    DEFAULT_SPP,
    HISTORY_LENGTH,
    STATE_CHANNELS,
    accumulate,
    fading_floor,
    frame_samples,
    samples_input,
)

ALBEDO_EPSILON = 1e-2  # demodulation divides by (albedo + eps): invertible, gain bounded by 100
# Below this max-channel albedo (sky, emitters, black paint) demodulation fades out linearly to a
# divisor of 1: dividing a bright sky by 0.01 made it 100× brighter than the surfaces next to it
# and the grid blur bled it across silhouettes.
ALBEDO_DEMODULATION_FLOOR = 5e-2
OUTLIER_SIGMAS = 3.0  # luminance above neighbourhood mean + k·std is pulled back to that bound
GUIDE_INPUT_CHANNELS = 10  # LDR radiance·albedo (3) + albedo (3) + normal (3) + depth (1)


@dataclass(frozen=True)
class NBGConfig:
    """Everything needed to rebuild a model; stored in checkpoints and ONNX metadata."""

    name: str = "nbg-2l-3g"
    layers: int = 2  # GuideNet depth: 2 (low spp, real time) or 7 (five-layer dense block)
    width: int = 20  # channels of the first hidden layer (authors' code: 20)
    growth: int = 5  # channels added per dense-block layer (7-layer net)
    grids: int = 3  # 1 or 3 bilateral grids
    sigma_s: int = 4  # finest grid; grid s uses sigma * 2**s (paper §4.5)
    sigma_r: float = 4.0
    temporal: bool = True
    # Firefly clamp before accumulation (k of suppress_outliers); 0 = off. On sparse low-spp
    # frames (a sunlit room at 1 spp: ~90% of pixels black) every lit pixel is an "outlier" of
    # its black neighbours, and the clamp removed about half of the frame's energy (validation
    # split, docs/training.md); the g1 models were trained with 3.
    outlier_sigmas: float = OUTLIER_SIGMAS
    # The clamp's bound never goes below this multiple of the frame's mean luminance (0: no
    # floor). With a floor only pixels that are outliers of their neighbours AND far above the
    # frame's level are pulled back: a 1-spp frame's sparse lit pixels (~10× the mean) pass,
    # LED fireflies (100–1000×) do not. experiments/clamp_energy.py on 22 validation frames: the 3σ
    # clamp kept 61% of the 1-spp energy, with a floor of 128 means 87%, none 100%.
    outlier_floor: float = 0.0
    # Keep the accumulated history only where the motion is pixel-aligned
    # (model/temporal.accumulate aligned_only): the input of the oidn-history tiers' OIDN pass.
    aligned_history: bool = False
    # No history where the frame repeats last frame's sample (model/temporal.accumulate
    # restart_repeated): set with aligned_history for the oidn-history tiers' OIDN pass.
    restart_repeated: bool = False
    # Pass-through candidates beside the grids (not in the paper): the blend's softmax also
    # weighs the accumulated irradiance and the frame's own (demodulated, clamped), grids of no
    # spatial extent. A sliced grid averages over sigma_s-pixel cells and keeps only the
    # detail its 1-D guide separates, so on thin geometry at 16-64 spp the paper's model was
    # 4-10 dB below its own noisy input (docs/zoo.md); the frame's own is there because the
    # accumulation itself loses to the input where reflections move unlike the surface (a
    # glossy studio: -3.4 dB at 64 spp by frame 4, docs/training.md).
    passthrough: bool = False
    # Blend logits modulated by the pixel's noise level (not in the paper; noise_level,
    # modulate_logits): the guide sees an LDR image, not how many samples are behind it, so one
    # blend served 1 and 64 spp alike and stayed below its own input at 64 (docs/training.md).
    # The frame's spp is then a run-time input of the exported graph.
    noise_blend: bool = False
    # The accumulation's resampled history fades with the frame's spp (not in the paper;
    # model/temporal.fading_floor, resampled_trust): where the motion is not a whole number
    # of pixels the current frame weighs at least clamp(0.2 + this · log2 spp, 0.2, 1). A
    # nearest fetch under sub-pixel motion is up to half a pixel off, every frame again, and on
    # thin geometry that error outgrows the noise the history removes once the frame is clean:
    # on turning wireframes at 64 spp version 7 gave 25.8 dB on the first frame and 18.7 by the
    # sixth (zoo round 2, studio-spin; docs/training.md "The resampled history"). 0: every
    # valid history is kept (the paper's, and versions before 8). The frame's spp is a run-time
    # input of the graph.
    resampled_weight_per_doubling: float = 0.0
    # The albedo anti-aliased before demodulation (not in the paper; model/albedo_prefilter): a
    # Gaussian of this many pixels at 1 spp, narrowing with the frame's spp. Remodulation
    # multiplies the output by the albedo, so a few point samples of the texture under a pixel
    # put their sampling noise back at full strength, however well the irradiance is filtered:
    # on the corpus's validation shots the reference's albedo gained ~2.9 dB at 1 spp
    # (docs/training.md, "The albedo's own noise"). 0: off (versions before 10). The frame's
    # spp is a run-time input of the graph.
    albedo_prefilter: float = 0.0

    def __post_init__(self) -> None:
        check_albedo_prefilter(self.albedo_prefilter)

    def to_dict(self) -> dict:
        return asdict(self)


def ldr(x: Tensor) -> Tensor:
    """Map linear HDR radiance to [0, 1) for the network (Reinhard, then gamma 1/2.2)."""
    x = x.clamp_min(0)
    return (x / (1 + x)).pow(1 / 2.2)


def luminance(rgb: Tensor) -> Tensor:
    r, g, b = rgb[:, 0:1], rgb[:, 1:2], rgb[:, 2:3]
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def suppress_outliers(radiance: Tensor, kernel: int = 5, sigmas: float = OUTLIER_SIGMAS,
                      floor: float = 0.0) -> Tensor:
    """Clamp firefly pixels to mean + k·std of their neighbours' luminance (KBS15-style), but
    never below `floor` × the frame's mean luminance (0: no floor).

    The pixel itself is left out of its neighbourhood statistics: a single 1e6 sample would
    otherwise inflate the std enough to pass its own test.
    """
    lum = luminance(radiance).clamp_min(0)
    area = kernel * kernel
    pad = kernel // 2
    sum1 = F.avg_pool2d(lum, kernel, 1, pad, count_include_pad=False) * area
    sum2 = F.avg_pool2d(lum * lum, kernel, 1, pad, count_include_pad=False) * area
    count = F.avg_pool2d(torch.ones_like(lum), kernel, 1, pad, count_include_pad=False) * area
    others = (count - 1).clamp_min(1)
    mean = (sum1 - lum) / others
    var = ((sum2 - lum * lum) / others - mean * mean).clamp_min(0)
    bound = mean + sigmas * var.sqrt()
    if floor > 0:
        bound = torch.maximum(bound, floor * lum.mean(dim=(2, 3), keepdim=True))
    scale = torch.where(lum > bound, bound / lum.clamp_min(1e-12), torch.ones_like(lum))
    return radiance * scale


def demodulation_divisor(albedo: Tensor) -> Tensor:
    """Per-pixel divisor for demodulation (and factor for remodulation), (N, 3, H, W)."""
    albedo = albedo.clamp_min(0)
    ramp = (albedo.amax(dim=1, keepdim=True) / ALBEDO_DEMODULATION_FLOOR).clamp(max=1)
    return 1 + ramp * (albedo + ALBEDO_EPSILON - 1)


def frame_irradiance(color: Tensor, albedo: Tensor, outlier_sigmas: float = OUTLIER_SIGMAS,
                     outlier_floor: float = 0.0) -> tuple[Tensor, Tensor]:
    """The frame demodulated, outliers suppressed (unless outlier_sigmas is 0) ->
    (irradiance, safe albedo)."""
    safe_albedo = demodulation_divisor(albedo)
    irradiance = color / safe_albedo
    if outlier_sigmas > 0:
        irradiance = suppress_outliers(irradiance, sigmas=outlier_sigmas, floor=outlier_floor)
    return irradiance, safe_albedo


def prestage(
    color: Tensor,
    albedo: Tensor,
    normal: Tensor,
    depth: Tensor,
    motion: Tensor,
    reset: Tensor,
    state: Tensor,
    temporal: bool = True,
    outlier_sigmas: float = OUTLIER_SIGMAS,
    outlier_floor: float = 0.0,
    aligned_history: bool = False,
    restart_repeated: bool = False,
    spp: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """frame_irradiance, then accumulated over time -> (irradiance, safe albedo, state)."""
    irradiance, safe_albedo = frame_irradiance(color, albedo, outlier_sigmas, outlier_floor)
    if not temporal:
        return irradiance, safe_albedo, state
    irradiance, new_state = accumulate(irradiance, depth, normal, motion, reset, state,
                                       aligned_history, restart_repeated, spp)
    return irradiance, safe_albedo, new_state


# log2 of a pixel's samples that maps to noise level 1: 1..1024 samples span the level's [0, 1]
NOISE_LOG2_RANGE = 10.0
# The modulation's parameters are stored divided by this: Adam moves a parameter by about the
# learning rate a step whatever its gradient, and a fine-tune's (2e-4..5e-4) would take
# thousands of steps to move a logit by the few units a blend needs.
NOISE_PARAMETER_GAIN = 20.0


def noise_level(spp: Tensor, count: Tensor) -> Tensor:
    """A pixel's noise level in [0, 1]: log2(spp · history length) / NOISE_LOG2_RANGE, the
    samples behind its accumulated irradiance on a log scale. spp (N,) or (1,), count (N,1,H,W):
    the accumulation state's history length after this frame (1 without a history)."""
    samples = spp.view(-1, 1, 1, 1) * count
    return (torch.log2(samples.clamp_min(1.0)) / NOISE_LOG2_RANGE).clamp(0.0, 1.0)


def modulate_logits(logits: Tensor, level: Tensor, scale: Tensor, shift: Tensor) -> Tensor:
    """Blend logits (N, C, H, W) moved by the noise level (N, 1, H, W), per candidate c:
    l_c (1 + scale_c · level) + shift_c · level. Zero scale and shift leave them as they are;
    a shift moves the blend towards a candidate as the samples grow, a scale sharpens (or
    flattens) the content's own preference. ai.quietframe::NBGBlendNoise evaluates it in this
    order."""
    scale, shift = scale.view(1, -1, 1, 1), shift.view(1, -1, 1, 1)
    return logits * (1 + scale * level) + shift * level


def channel_softmax(logits: Tensor) -> Tensor:
    """Softmax over dim 1 with element-wise ops: onnxruntime's Softmax on a non-last axis of
    an NCHW tensor transposes the whole frame (45 ms at 720p); this form stays element-wise."""
    exp = torch.exp(logits - logits.amax(dim=1, keepdim=True))
    return exp / exp.sum(dim=1, keepdim=True)


class GuideNet(nn.Module):
    """2-layer CNN, or 7 layers with a five-layer dense block (paper Fig. 2), 5×5 convolutions.

    Outputs `grids` guides in (0, 1) and, for several grids, per-pixel blend logits.
    """

    def __init__(self, config: NBGConfig) -> None:
        super().__init__()
        self.grids = config.grids
        out_channels = config.grids + blend_candidates(config)
        self.first = nn.Conv2d(GUIDE_INPUT_CHANNELS, config.width, 5, padding=2)
        self.dense = nn.ModuleList()
        channels = config.width
        if config.layers == 7:
            for _ in range(5):
                self.dense.append(nn.Conv2d(channels, config.growth, 5, padding=2))
                channels += config.growth
        elif config.layers != 2:
            raise ValueError(f"GuideNet has 2 or 7 layers, not {config.layers}")
        self.last = nn.Conv2d(channels, out_channels, 5, padding=2)
        if config.noise_blend:  # zero: the blend the logits alone give (modulate_logits)
            blend = blend_candidates(config)
            self.noise_scale = nn.Parameter(torch.zeros(blend))
            self.noise_shift = nn.Parameter(torch.zeros(blend))

    def noise_modulation(self) -> tuple[Tensor, Tensor]:
        """modulate_logits' (scale, shift): the parameters times NOISE_PARAMETER_GAIN."""
        return self.noise_scale * NOISE_PARAMETER_GAIN, self.noise_shift * NOISE_PARAMETER_GAIN

    def forward(self, features: Tensor,
                level: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """(guides, blend weights); `level` (noise_level) where the config has noise_blend."""
        x = F.leaky_relu(self.first(features), 0.2)  # (N, width, H, W)
        for conv in self.dense:
            x = torch.cat((x, F.leaky_relu(conv(x), 0.2)), dim=1)
        out = self.last(x)
        guides = torch.sigmoid(out[:, : self.grids])  # (N, grids, H, W)
        # The paper's w2 = 1 - w0 - w1 can go negative; a softmax keeps a convex combination.
        # Channel g weighs grid g; with a pass-through the last two weigh the accumulated
        # irradiance and the frame's own.
        if out.shape[1] <= self.grids + 1:
            return guides, None
        logits = out[:, self.grids :]
        if hasattr(self, "noise_scale"):
            if level is None:
                raise ValueError("a noise-aware blend (noise_blend) needs the noise level")
            logits = modulate_logits(logits, level, *self.noise_modulation())
        return guides, channel_softmax(logits)


PASSTHROUGH_CANDIDATES = 2  # the accumulated irradiance, then the frame's own


def blend_candidates(config: NBGConfig) -> int:
    """How many blend logits GuideNet outputs after its guides: one per candidate (each grid,
    then with a pass-through the accumulated and the frame's irradiance), none for a single
    grid alone."""
    candidates = config.grids + PASSTHROUGH_CANDIDATES * config.passthrough
    return candidates if candidates > 1 else 0


# The pass-through logits where a fine-tune adds them to a model trained without them
# (add_passthrough): the model's output moves towards its input by a few percent at first, a
# few Adam steps on the conv's 5x5xwidth weights from wherever training needs it.
PASSTHROUGH_INITIAL_LOGIT = -4.0


def guide_features(radiance: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor) -> Tensor:
    """GuideNet input, every channel in [0, 1] (paper §5): (N, 10, H, W)."""
    depth_scale = depth.mean(dim=(2, 3), keepdim=True).clamp_min(1e-6)
    relative_depth = depth / depth_scale  # scene-unit free
    return torch.cat(
        (
            ldr(radiance),
            albedo.clamp(0, 1),
            (normal.clamp(-1, 1) + 1) * 0.5,
            relative_depth / (1 + relative_depth),
        ),
        dim=1,
    )


class NBGDenoiser(nn.Module):
    """State-in / state-out NBG denoiser on (N, C, H, W) float tensors.

    forward(color, albedo, normal, depth, motion, reset, state) -> (denoised, new_state)
    """

    def __init__(self, config: NBGConfig | None = None) -> None:
        super().__init__()
        self.config = config or NBGConfig()
        self.guide_net = GuideNet(self.config)
        self.scales = [
            (self.config.sigma_s * 2**s, self.config.sigma_r * 2**s)
            for s in range(self.config.grids)
        ]

    state_channels = STATE_CHANNELS

    @property
    def reads_spp(self) -> bool:
        """Whether forward reads the frame's spp (training feeds each item's)."""
        config = self.config
        return (config.noise_blend or config.resampled_weight_per_doubling > 0
                or config.albedo_prefilter > 0)

    def forward(
        self,
        color: Tensor,
        albedo: Tensor,
        normal: Tensor,
        depth: Tensor,
        motion: Tensor,
        reset: Tensor,
        state: Tensor,
        spp: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """`spp` (N,) or (1,): the frame's samples per pixel, read by a noise-aware blend only
        (DEFAULT_SPP where not given)."""
        config = self.config
        albedo = prefilter_albedo(albedo, spp, config.albedo_prefilter)
        frame, safe_albedo = frame_irradiance(color, albedo, config.outlier_sigmas,
                                              config.outlier_floor)
        floor = fading_floor(config.resampled_weight_per_doubling, spp)
        irradiance, new_state = (accumulate(frame, depth, normal, motion, reset, state,
                                            config.aligned_history, floor=floor)
                                 if config.temporal else (frame, state))
        level = None
        if config.noise_blend:
            spp = frame_samples(spp)
            count = new_state[:, HISTORY_LENGTH] if config.temporal else torch.ones_like(depth)
            level = noise_level(spp, count)
        guides, weights = self.guide_net(
            guide_features(irradiance * safe_albedo, albedo, normal, depth), level
        )
        result = torch.zeros_like(irradiance)
        for s, (sigma_s, sigma_r) in enumerate(self.scales):
            guide = guides[:, s : s + 1]
            grid, weight = bilateral_splat(irradiance, guide, sigma_s, sigma_r)
            sliced = bilateral_slice(grid, weight, guide, sigma_s, sigma_r)
            result = result + (sliced if weights is None else weights[:, s : s + 1] * sliced)
        if config.passthrough:
            result = result + weights[:, -2:-1] * irradiance + weights[:, -1:] * frame
        return result * safe_albedo, new_state

    def adapt_state_dict(self, state: dict[str, Tensor]) -> dict[str, Tensor]:
        """A checkpoint's weights for this model: as they are, or, where this model has the
        pass-through or the noise-aware blend and the checkpoint (trained without) lacks it,
        extended so that the model starts as the checkpoint's (add_passthrough, zero
        modulation)."""
        state = add_passthrough(state, self.config) if self.config.passthrough else state
        if self.config.noise_blend and "guide_net.noise_scale" not in state:
            blend = blend_candidates(self.config)
            state = {**state, "guide_net.noise_scale": torch.zeros(blend),
                     "guide_net.noise_shift": torch.zeros(blend)}
        return state

    def run_time_inputs(self) -> list[dict]:
        """`quietframe.inputs` of the exported graph: the frame's spp, where the blend reads
        the noise level (or the history's floor follows it)."""
        if not self.reads_spp:
            return []
        return [samples_input(DEFAULT_SPP, "the frame's samples per pixel (the service fills "
                              "it from the EXR header, or auto's estimate): with the history's "
                              "length, the noise level that moves the blend between the grids "
                              "and the pass-through")]

    def initial_state(self, batch: int, height: int, width: int) -> Tensor:
        return torch.zeros(batch, STATE_CHANNELS, height, width)


class AccumulationDenoiser(nn.Module):
    """The NBG pre-stage alone (reprojection + accumulation, no network): a baseline, a cheap
    preview model, and the input of oidn-temporal-acc's OIDN pass. Same call signature and state
    as NBGDenoiser. No firefly clamp by default: alone, nothing after it can give back the
    energy the clamp takes from a sparse low-spp frame (NBGConfig.outlier_sigmas).
    `aligned_history`: the pixel-aligned accumulation (`aligned-accumulation`, NBGConfig), which
    also restarts where a frame repeats last frame's sample (`restart_repeated`, version 3;
    False gives version 2)."""

    state_channels = STATE_CHANNELS

    def __init__(self, outlier_sigmas: float = 0.0, aligned_history: bool = False,
                 restart_repeated: bool | None = None) -> None:
        super().__init__()
        name = "aligned-accumulation" if aligned_history else "accumulation"
        repeated = aligned_history if restart_repeated is None else restart_repeated
        self.config = NBGConfig(name=name, layers=0, width=0, grids=0,
                                outlier_sigmas=outlier_sigmas, aligned_history=aligned_history,
                                restart_repeated=repeated)

    def forward(self, color: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
                motion: Tensor, reset: Tensor, state: Tensor,
                spp: Tensor | None = None) -> tuple[Tensor, Tensor]:
        if self.config.restart_repeated:
            spp = frame_samples(spp)
        irradiance, safe_albedo, new_state = prestage(
            color, albedo, normal, depth, motion, reset, state,
            outlier_sigmas=self.config.outlier_sigmas,
            aligned_history=self.config.aligned_history,
            restart_repeated=self.config.restart_repeated, spp=spp,
        )
        return irradiance * safe_albedo, new_state

    def run_time_inputs(self) -> list[dict]:
        """`quietframe.inputs` of the exported graph: the frame's samples per pixel, where
        the repeated-sample test reads it (version 3 of the aligned accumulation)."""
        if not self.config.restart_repeated:
            return []
        return [samples_input(DEFAULT_SPP, "the frame's samples per pixel (the service fills "
                              "it from the EXR header, or auto's estimate): at 1, a still pixel "
                              "whose aux repeat last frame's to the last bit restarts its "
                              "accumulation")]

    def initial_state(self, batch: int, height: int, width: int) -> Tensor:
        return torch.zeros(batch, STATE_CHANNELS, height, width)


def add_passthrough(state: dict[str, Tensor], config: NBGConfig) -> dict[str, Tensor]:
    """Weights of a model without the pass-through, extended to `config`'s (which has it): the
    GuideNet's last conv gains the pass-through logits (zero weights, PASSTHROUGH_INITIAL_LOGIT),
    so the model starts as the one it was, each of its two inputs weighed by about
    exp(-4)/(1 + ...)."""
    weight, bias = state["guide_net.last.weight"], state["guide_net.last.bias"]
    want = config.grids + blend_candidates(config)
    if weight.shape[0] == want:
        return state
    if weight.shape[0] != want - PASSTHROUGH_CANDIDATES - int(config.grids == 1):
        raise ValueError(f"a last conv of {weight.shape[0]} channels is not a {config.grids}-grid "
                         "GuideNet without a pass-through")
    new_weight = weight.new_zeros((want, *weight.shape[1:]))
    new_bias = bias.new_full((want,), PASSTHROUGH_INITIAL_LOGIT)
    new_weight[: weight.shape[0]], new_bias[: weight.shape[0]] = weight, bias
    if config.grids == 1:  # a lone grid had no logit: give it 0, as the softmax's reference
        new_bias[1] = 0.0
    return {**state, "guide_net.last.weight": new_weight, "guide_net.last.bias": new_bias}


VARIANTS: dict[str, NBGConfig] = {
    "nbg-2l-1g": NBGConfig(name="nbg-2l-1g", layers=2, grids=1),
    "nbg-2l-3g": NBGConfig(name="nbg-2l-3g", layers=2, grids=3),
    "nbg-7l-3g": NBGConfig(name="nbg-7l-3g", layers=7, grids=3),
}
