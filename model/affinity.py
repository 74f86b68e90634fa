"""Affinity-kernel denoiser (Işık et al. 2021, §3): the quality tier.

Frame flow (one call of AffinityDenoiser.forward, state in / state out like NBG):
  demodulate albedo (NBG's divisor) -> per-pixel embedding e (eq. 1) -> warp the state
  (nearest, NBG's disocclusion test) -> U-Net on (e, W ē) predicts f^k, a^k, c^k, b, λ (eq. 2)
  -> accumulate ē and L̄ with λ (eq. 3, 5) -> K = 3 dilated affinity kernels in sequence
  (eq. 4, 6), the last jointly normalised with the temporal kernel over W O_{t-1} (eq. 7, 8)
  -> remodulate.

The network may run at half resolution (`unet_scale` s = 2): the pixel-mean buffers are averaged
over s×s blocks before the FC layers (the paper's "average before FC", over a block instead of a
pixel), the embedding is accumulated (eq. 3) and fed to the U-Net at that resolution, and the
kernel parameters are upsampled bilinearly; radiance accumulation and the kernels stay at full
resolution. The accumulated embedding is then a state tensor of ⌈H/s⌉×⌈W/s⌉ (metadata `scale`),
which saves warping, pooling and concatenating 64 full-resolution channels per frame.

Kernel math lives in model/affinity_kernels.py (torch custom ops exported as the C++ ops
ai.quietframe::AffinityFilter / AffinityTemporalFilter). The spatial kernel size is a forward
argument so the exported graph can take it as an input and a session can change it.

Deviation from the paper, on purpose: the state is detached between frames (truncated
back-propagation through time, one frame), because the warp op has no gradient; the temporal
loss still trains λ, b and the features through the current frame.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from quietframe.model.affinity_kernels import (
    EPSILON,
    spatial_affinity_filter,
    temporal_affinity_filter,
)
from quietframe.model.albedo_prefilter import check_albedo_prefilter, prefilter_albedo
from quietframe.model.losses import bandwidth_regulariser
from quietframe.model.nbg import demodulation_divisor, noise_level, suppress_outliers
from quietframe.model.resample import upsample_bilinear
from quietframe.model.temporal import (
    DEFAULT_SPP,
    MIN_CURRENT_WEIGHT,
    aligned_mask,
    backward_warp,
    fading_floor,
    frame_samples,
    history_valid,
    samples_input,
)

EMBEDDING_INPUT_CHANNELS = 10  # log radiance (3) + albedo (3) + normal (3) + relative depth (1)
EMBEDDING_CHANNELS = 32  # paper §3.2: 3 FC layers × 32
FEATURE_CHANNELS = 8  # d of f^k (paper §3.7: d = 8)
KERNELS = 3  # K, the paper's (§3.5); a config may use more (à-trous dilations up to 2^(K-1))
PARAMS_PER_KERNEL = FEATURE_CHANNELS + 2  # f^k, a^k, c^k
GUIDE_CHANNELS = 7  # albedo (3) + normal (3) + relative depth (1), at full resolution
LEAK = 0.01  # leaky ReLU slope (the paper does not give one: PyTorch's default)
DEFAULT_KERNEL_SIZE = 13  # paper §3.5: 13×13 windows
KERNEL_SIZES = (5, 7, 9, 11, 13)  # the session-time choices (paper §5.5.3)

# The state is two tensors: this full-resolution one (one warp serves all its channels) and the
# accumulated embedding ē_{t-1} (eq. 3, 32 channels) at the U-Net's resolution.
_STATE_LAYOUT = (
    ("radiance", 3),  # L̄_{t-1}, demodulated (eq. 5)
    ("output", 3),  # O_{t-1}, demodulated (eq. 8)
    ("features", FEATURE_CHANNELS),  # f^K_{t-1} (eq. 7)
    ("depth", 1),  # surface of t-1 for the disocclusion test
    ("normal", 3),
)
STATE_SLICES: dict[str, slice] = {}
_offset = 0
for _name, _channels in _STATE_LAYOUT:
    STATE_SLICES[_name] = slice(_offset, _offset + _channels)
    _offset += _channels
STATE_CHANNELS = _offset
# Added to each warped feature of a pixel whose previous output eq. 8 must not gather: its
# distance to any current feature vector is then ~8·offset² and ω underflows to 0 (as
# model/oidn_temporal's disoccluded pixels).
STALE_FEATURE_OFFSET = 1000.0
State = tuple[Tensor, Tensor]  # (N, STATE_CHANNELS, H, W), (N, 32, ⌈H/s⌉, ⌈W/s⌉)


@dataclass(frozen=True)
class AffinityConfig:
    """Everything needed to rebuild a model; stored in checkpoints and ONNX metadata."""

    name: str = "affinity-h16"
    family: str = "affinity"  # tells checkpoints of this model from NBG's (model/families.py)
    widths: tuple[int, ...] = (16, 24, 32)  # U-Net channels per level, multiples of 8
    unet_scale: int = 2  # 1: U-Net at full resolution; 2: at half resolution
    temporal: bool = True  # False: the single-frame variant (no eq. 3, 5, 7-8 history)
    temporal_kernel_size: int = 5  # u', v' window of eq. 8 (dilation 1)
    kernel_size: int = DEFAULT_KERNEL_SIZE  # default of the `kernel_size` input
    # K: kernels in sequence, dilation 2^(k-1). More than the paper's 3 widens the support at a
    # small kernel size (K = 5 at 5×5: 125 px, 125 taps per pixel; K = 3 at 13×13: 85 px, 507).
    kernels: int = KERNELS
    # Full-resolution guide: f^k += P_k g with g the pixel's albedo, normal and relative depth
    # and P_k a learned 8×7 matrix, so that the half-resolution features keep per-pixel edges.
    guide: bool = False
    # Dilation order: False is the paper's 1, 2, ..., 2^(K-1); True runs the coarsest kernel
    # first and ends at dilation 1, so that the last (temporal) kernel smooths out the grid
    # pattern a sparse dilated kernel leaves instead of printing it.
    coarse_first: bool = False
    # NBG's firefly clamp (model/nbg.suppress_outliers) on the demodulated radiance before
    # anything reads it; 0 = off (every model before version 3). Without it one 1-spp firefly
    # (66 951 where the reference is 1.3) left 17 523 in the output (docs/training.md).
    outlier_sigmas: float = 0.0
    outlier_floor: float = 0.0  # × the frame's mean luminance: the bound's floor (NBGConfig)
    # The frame's noise level, log2(spp) on [0, 1] (model/nbg.noise_level), as one more U-Net
    # input channel (not in the paper): the U-Net sees embeddings, not how many samples are
    # behind them, and one set of kernels served 1 and 64 spp alike, below its own input at 64
    # (docs/training.md). The frame's spp is then a run-time input of the exported graph.
    noise_input: bool = False
    # The resampled history fades with the frame's spp, as NBG's (NBGConfig; not in the paper):
    # where the motion is not a whole number of pixels (temporal.pixel_aligned) eq. 5's λ is at
    # most 1 - w(spp), w = clamp(0.2 + this · log2 spp, 0.2, 1) (temporal.fading_floor), and
    # from 2 spp (w > 0.2) eq. 8's temporal kernel gathers nothing from a resampled previous
    # output (its features offset as a disoccluded pixel's). A nearest fetch under sub-pixel
    # motion is up to half a pixel off every frame; on thin geometry at 16-64 spp that outgrows
    # the noise the history removes (docs/training.md, "The resampled history"). 0: off.
    resampled_weight_per_doubling: float = 0.0
    # The albedo anti-aliased before demodulation, as NBG's (NBGConfig.albedo_prefilter; not
    # in the paper): σ px at 1 spp, narrowing with the frame's spp. 0: off (before version 7).
    albedo_prefilter: float = 0.0

    def __post_init__(self) -> None:
        check_albedo_prefilter(self.albedo_prefilter)
        object.__setattr__(self, "widths", tuple(self.widths))  # JSON round trip gives a list
        if self.unet_scale not in (1, 2):
            raise ValueError(f"unet_scale must be 1 or 2, got {self.unet_scale}")
        if not 2 <= self.kernels <= 6:
            raise ValueError(f"kernels must be 2..6, got {self.kernels}")

    def to_dict(self) -> dict:
        return asdict(self)


def ldr_log(x: Tensor) -> Tensor:
    """The paper's x -> log(1 + x) compression, for network inputs only (§3.2)."""
    return torch.log1p(x.clamp_min(0))


def guide_inputs(albedo: Tensor, normal: Tensor, depth: Tensor) -> Tensor:
    """The noise-free auxiliary buffers, bounded: (N, 7, H, W)."""
    depth_scale = depth.mean(dim=(2, 3), keepdim=True).clamp_min(1e-6)
    relative_depth = depth / depth_scale  # scene-unit free, as NBG's GuideNet input
    return torch.cat((albedo.clamp(0, 1), normal.clamp(-1, 1),
                      relative_depth / (1 + relative_depth)), dim=1)


def embedding_inputs(color: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor) -> Tensor:
    """Pixel-mean buffers as the FC layers see them: (N, 10, H, W)."""
    return torch.cat((ldr_log(color), guide_inputs(albedo, normal, depth)), dim=1)


class Embedding(nn.Module):
    """eq. 1, 'average before FC' variant: FC over pixel means, as 1×1 convolutions."""

    def __init__(self) -> None:
        super().__init__()
        self.layers = nn.ModuleList([
            nn.Conv2d(EMBEDDING_INPUT_CHANNELS, EMBEDDING_CHANNELS, 1),
            nn.Conv2d(EMBEDDING_CHANNELS, EMBEDDING_CHANNELS, 1),
            nn.Conv2d(EMBEDDING_CHANNELS, EMBEDDING_CHANNELS, 1),
        ])

    def forward(self, inputs: Tensor) -> Tensor:
        x = inputs  # (N, 10, H, W)
        for layer in self.layers:
            x = F.leaky_relu(layer(x), LEAK)  # eq. 1: e = FC(r̄)
        return x  # (N, 32, H, W)


def unet_outputs(kernels: int) -> int:
    return kernels * PARAMS_PER_KERNEL + 2  # + b, λ


def _conv(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, padding=1)


class UNet(nn.Module):
    """eq. 2: a len(widths)-level U-Net, two 3×3 convolutions per level, 2×2 max-pool down,
    bilinear up, concatenated skips (the paper's structure, shallower and narrower for a CPU);
    a 1×1 convolution makes the raw kernel parameters."""

    def __init__(self, widths: tuple[int, ...], kernels: int = KERNELS,
                 noise_input: bool = False) -> None:
        super().__init__()
        cin = 2 * EMBEDDING_CHANNELS + noise_input  # e and W ē (and the noise level)
        self.down = nn.ModuleList()
        for w in widths:
            self.down.append(nn.ModuleList([_conv(cin, w), _conv(w, w)]))
            cin = w
        self.up = nn.ModuleList()
        for w in reversed(widths[:-1]):
            self.up.append(nn.ModuleList([_conv(cin + w, w), _conv(w, w)]))
            cin = w
        self.out = nn.Conv2d(cin, unet_outputs(kernels), 1)
        with torch.no_grad():
            # a = raw² has zero slope at raw = 0, where the kernels are box filters that ignore
            # the features: start at a = b = 1 so that the features get a gradient.
            for k in range(kernels):
                self.out.bias[k * PARAMS_PER_KERNEL + FEATURE_CHANNELS] = 1.0
            self.out.bias[kernels * PARAMS_PER_KERNEL] = 1.0

    def forward(self, x: Tensor, noise: Tensor | None = None) -> Tensor:
        """`noise` (N, 1, h, w): the noise-level plane, the first convolution's last input
        channel (noise_input), or None."""
        skips = []
        for depth, (a, b) in enumerate(self.down):
            if depth:
                # ceil_mode: odd sizes keep their last row/column, a 1×1 frame stays 1×1
                x = a(F.max_pool2d(x, 2, ceil_mode=True))
            else:
                x = self._first(a, x, noise)
            x = F.leaky_relu(b(F.leaky_relu(x, LEAK)), LEAK)
            skips.append(x)
        for i, (a, b) in enumerate(self.up):
            skip = skips[-2 - i]
            x = upsample_bilinear(x, skip)
            x = torch.cat((x, skip), dim=1)
            x = F.leaky_relu(b(F.leaky_relu(a(x), LEAK)), LEAK)
        return self.out(x)  # (N, 10 K + 2, h, w), raw

    @staticmethod
    def _first(conv: nn.Conv2d, x: Tensor, noise: Tensor | None) -> Tensor:
        """The first convolution, over [x, noise] where there is a noise plane, as two: the
        same sum, but the 64 embedding channels stay a multiple of onnxruntime's channel
        block, whose fast convolution a 65th channel pushed the whole layer off (+24 ms of
        ~500 at 720p)."""
        if noise is None:
            return conv(x)
        return (F.conv2d(x, conv.weight[:, :-1], conv.bias, padding=conv.padding)
                + F.conv2d(noise, conv.weight[:, -1:], padding=conv.padding))


@dataclass
class KernelParams:
    """The U-Net's output after its activations (eq. 2, 4, 7, 3), all at full resolution."""

    features: list[Tensor]  # K × (N, 8, H, W): f^k
    bandwidth: list[Tensor]  # K × (N, 1, H, W): a^k = raw² >= 0
    center: list[Tensor]  # K × (N, 1, H, W): c^k = sigmoid(raw) in [0, 1]
    temporal_bandwidth: Tensor  # (N, 1, H, W): b = raw² >= 0
    blend: Tensor  # (N, 1, H, W): λ = sigmoid(raw) in [0, 1]


def kernel_params(raw: Tensor) -> KernelParams:
    """eq. 2 outputs with the paper's activations: squares for bandwidths, sigmoids for c, λ."""
    features, bandwidth, center = [], [], []
    kernels = (raw.shape[1] - 2) // PARAMS_PER_KERNEL
    for k in range(kernels):
        p = raw[:, k * PARAMS_PER_KERNEL : (k + 1) * PARAMS_PER_KERNEL]
        features.append(p[:, :FEATURE_CHANNELS])
        bandwidth.append(p[:, FEATURE_CHANNELS : FEATURE_CHANNELS + 1].square())  # eq. 4: a >= 0
        center.append(torch.sigmoid(p[:, FEATURE_CHANNELS + 1 : FEATURE_CHANNELS + 2]))
    tail = raw[:, kernels * PARAMS_PER_KERNEL :]
    return KernelParams(features, bandwidth, center, tail[:, 0:1].square(),  # eq. 7: b >= 0
                        torch.sigmoid(tail[:, 1:2]))  # eq. 3: λ in [0, 1]


def upsample_params(params: KernelParams, like: Tensor, scale: int) -> KernelParams:
    """Bilinear upsampling of every parameter to the size of `like` (scale 1: as they are)."""
    def up(x: Tensor) -> Tensor:
        return x if scale == 1 else upsample_bilinear(x, like)

    return KernelParams([up(f) for f in params.features], [up(a) for a in params.bandwidth],
                        [up(c) for c in params.center], up(params.temporal_bandwidth),
                        up(params.blend))


def accumulate_embedding(embedding: Tensor, warped: Tensor, blend: Tensor) -> Tensor:
    # eq. 3: ē_t = (1 - λ) e_t + λ W ē_{t-1}   (λ = 0 at t = 0, after a cut, where disoccluded)
    return (1 - blend) * embedding + blend * warped


def accumulate_radiance(radiance: Tensor, warped: Tensor, blend: Tensor) -> Tensor:
    # eq. 5: L̄_t = (1 - λ) L_t + λ W L̄_{t-1}   (the same λ as eq. 3)
    return (1 - blend) * radiance + blend * warped


def guided_features(params: KernelParams, guide: Tensor, projection: nn.Conv2d) -> KernelParams:
    """f^k + P_k g at full resolution (AffinityConfig.guide): P is one 1×1 convolution."""
    extra = projection(guide).split(FEATURE_CHANNELS, dim=1)  # K × (N, 8, H, W)
    return KernelParams([f + e for f, e in zip(params.features, extra, strict=True)],
                        params.bandwidth, params.center, params.temporal_bandwidth,
                        params.blend)


def kernel_dilation(k: int, kernels: int, coarse_first: bool) -> int:
    """Dilation of the (k+1)-th kernel: 2^k (eq. 6), or 2^(K-1-k) with coarse_first."""
    return 2 ** (kernels - 1 - k) if coarse_first else 2**k


def spatial_kernels(radiance: Tensor, params: KernelParams, kernel_size: int,
                    coarse_first: bool = False, count: int | None = None) -> Tensor:
    # eq. 4 + 6: L^(k) = Σ w^k L^(k-1) / (ε + Σ w^k), k = 1..count, dilation 2^(k-1);
    # count = K - 1 (the K-th is final_kernel's), or K for the single-frame variant
    x = radiance  # (N, 3, H, W) = L^(0) = L̄
    kernels = len(params.features)
    for k in range(kernels - 1 if count is None else count):
        x = spatial_affinity_filter(x, params.features[k], params.bandwidth[k], params.center[k],
                                    kernel_size, kernel_dilation(k, kernels, coarse_first),
                                    EPSILON)
    return x  # L^(count)


def final_kernel(radiance: Tensor, params: KernelParams, prev_output: Tensor,
                 prev_features: Tensor, temporal_on: Tensor, kernel_size: int,
                 temporal_kernel_size: int, coarse_first: bool = False) -> Tensor:
    # eq. 7 + 8: the K-th spatial kernel (dilation 2^(K-1); 1 coarse-first) jointly normalised
    # with the temporal kernel ω = exp(-b ||f^K - W f^K_{t-1}||²) over W O_{t-1};
    # ω = 0 where temporal_on = 0
    kernels = len(params.features)
    k = kernels - 1
    return temporal_affinity_filter(
        radiance, params.features[k], params.bandwidth[k], params.center[k], prev_output,
        prev_features, params.temporal_bandwidth, temporal_on, kernel_size,
        kernel_dilation(k, kernels, coarse_first), temporal_kernel_size, EPSILON)


class AffinityDenoiser(nn.Module):
    """State-in / state-out affinity denoiser on (N, C, H, W) float tensors.

    forward(color, albedo, normal, depth, motion, reset, state, kernel_size) ->
    (denoised, new_state), state = (frame state, accumulated embedding) (see State). After each
    forward, `bandwidth_penalty` holds eq. 13 of that frame for the training loss.
    """

    state_channels = STATE_CHANNELS

    def __init__(self, config: AffinityConfig | None = None) -> None:
        super().__init__()
        self.config = config or AffinityConfig()
        self.embedding = Embedding()
        self.unet = UNet(self.config.widths, self.config.kernels, self.config.noise_input)
        self.guide = (nn.Conv2d(GUIDE_CHANNELS, self.config.kernels * FEATURE_CHANNELS, 1,
                                bias=False) if self.config.guide else None)
        self._init_hidden_layers()
        self.bandwidth_penalty: Tensor | None = None

    def initial_state(self, batch: int, height: int, width: int) -> State:
        s = self.config.unet_scale
        return (torch.zeros(batch, STATE_CHANNELS, height, width),
                torch.zeros(batch, EMBEDDING_CHANNELS, -(-height // s), -(-width // s)))

    def state_specs(self) -> list[dict]:
        """`quietframe.state` metadata: name, channels and resolution divisor of each tensor."""
        return [{"name": "affinity", "channels": STATE_CHANNELS, "scale": 1},
                {"name": "embedding", "channels": EMBEDDING_CHANNELS,
                 "scale": self.config.unet_scale}]

    def _init_hidden_layers(self) -> None:
        # He init for the leaky-ReLU layers: PyTorch's default shrinks the signal about 3× per
        # layer, and after the 3 FC + U-Net layers the features were near-constant over the
        # image (neighbour ||Δf||² ~ 1e-5), so every kernel was a box filter with no gradient.
        for module in (*self.embedding.layers, *self.unet.modules()):
            if isinstance(module, nn.Conv2d) and module is not self.unet.out:
                nn.init.kaiming_normal_(module.weight, a=LEAK, nonlinearity="leaky_relu")
                nn.init.zeros_(module.bias)
        nn.init.kaiming_normal_(self.unet.out.weight, nonlinearity="linear")
        if self.guide is not None:
            nn.init.kaiming_normal_(self.guide.weight, nonlinearity="linear")

    def _low(self, x: Tensor) -> Tensor:
        """s×s block means (ceil mode: a partial block averages the pixels it has)."""
        s = self.config.unet_scale
        return F.avg_pool2d(x, s, ceil_mode=True) if s > 1 else x

    @property
    def reads_spp(self) -> bool:
        """Whether forward reads the frame's spp (training feeds each item's)."""
        config = self.config
        return (config.noise_input or config.resampled_weight_per_doubling > 0
                or config.albedo_prefilter > 0)

    def adapt_state_dict(self, state: dict[str, Tensor]) -> dict[str, Tensor]:
        """A checkpoint's weights for this model: as they are, or, where this model takes the
        noise level and the checkpoint (trained without it) does not, its first convolution
        extended by a zero-weight input channel, so that the model starts as the checkpoint's."""
        key = "unet.down.0.0.weight"
        weight = state[key]
        if self.config.noise_input and weight.shape[1] == 2 * EMBEDDING_CHANNELS:
            zero = weight.new_zeros((weight.shape[0], 1, *weight.shape[2:]))
            state = {**state, key: torch.cat((weight, zero), dim=1)}
        return state

    def run_time_inputs(self) -> list[dict]:
        """`quietframe.inputs` the model itself reads beside the kernel size (which the export
        adds): the frame's spp, with noise_input (or a history that fades with it)."""
        if not self.reads_spp:
            return []
        return [samples_input(DEFAULT_SPP, "the frame's samples per pixel (the service fills "
                              "it from the EXR header, or auto's estimate): its log, the noise "
                              "level the U-Net reads beside the embeddings")]

    def forward(self, color: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
                motion: Tensor, reset: Tensor, state: State,
                kernel_size: int | None = None,
                spp: Tensor | None = None) -> tuple[Tensor, State]:
        """`spp` (N,) or (1,): the frame's samples per pixel, read with noise_input only
        (DEFAULT_SPP where not given)."""
        size = self.config.kernel_size if kernel_size is None else kernel_size
        frame_state, embedding_state = state
        albedo = prefilter_albedo(albedo, spp, self.config.albedo_prefilter)
        safe_albedo = demodulation_divisor(albedo)  # NBG's: remodulation undoes it exactly
        radiance = color / safe_albedo  # (N, 3, H, W) demodulated: the kernels filter this
        if self.config.outlier_sigmas > 0:  # the embedding then sees the clamped colour too
            radiance = suppress_outliers(radiance, sigmas=self.config.outlier_sigmas,
                                         floor=self.config.outlier_floor)
            color = radiance * safe_albedo
        # block means of the raw buffers (cheaper than mapping all pixels, then pooling)
        inputs = embedding_inputs(*(self._low(b) for b in (color, albedo, normal, depth)))
        embedding = self.embedding(inputs)  # eq. 1, (N, 32, h, w)
        s = STATE_SLICES
        if self.config.temporal:
            # Nearest reprojection (paper §3.3); the state carries no gradient (module doc).
            warped, inside = backward_warp(frame_state.detach(), motion, mode="nearest")
            keep = inside * history_valid(warped[:, s["depth"]], warped[:, s["normal"]],
                                          depth, normal)
            keep = keep * (1 - reset.view(-1, 1, 1, 1))  # (N, 1, H, W)
            # motion in low-resolution pixels: block centres map onto block centres
            low_motion = self._low(motion) / self.config.unet_scale
            warped_embedding, low_inside = backward_warp(embedding_state.detach(), low_motion,
                                                         mode="nearest")
            low_keep = low_inside * self._low(keep)  # (N, 1, h, w)
            warped_embedding = low_keep * warped_embedding
            temporal_on = 1 - reset  # (N,) eq. 8: ω = 0 on a first frame or a cut
        else:
            keep = low_keep = torch.zeros_like(inputs[:, :1])
            warped, warped_embedding = None, torch.zeros_like(embedding)
        noise = None
        if self.config.noise_input:
            noise = noise_level(frame_samples(spp), torch.ones_like(embedding[:, :1]))  # (N,1,h,w)
        raw = self.unet(torch.cat((embedding, warped_embedding), dim=1), noise)  # eq. 2
        low_params = kernel_params(raw)
        low_blend = low_params.blend * low_keep  # λ: no history where there is none
        new_embedding = accumulate_embedding(embedding, warped_embedding, low_blend)  # eq. 3
        # Activations before upsampling: cheaper, and bilinear weights are convex, so a, b >= 0
        # and c, λ in [0, 1] still hold.
        params = upsample_params(low_params, color, self.config.unet_scale)
        if self.guide is not None:
            params = guided_features(params, guide_inputs(albedo, normal, depth), self.guide)
        if warped is not None:
            blend, previous_features = params.blend * keep, warped[:, s["features"]]
            floor = fading_floor(self.config.resampled_weight_per_doubling, spp)
            if floor is not None:
                blend, previous_features = fade_resampled(blend, previous_features, motion,
                                                          floor)
            acc = accumulate_radiance(radiance, warped[:, s["radiance"]], blend)  # eq. 5
            filtered = spatial_kernels(acc, params, size, self.config.coarse_first)  # eq. 4, 6
            output = final_kernel(filtered, params, warped[:, s["output"]],
                                  previous_features, temporal_on, size,
                                  self.config.temporal_kernel_size,
                                  self.config.coarse_first)  # eq. 7, 8
        else:  # single-frame variant: all K kernels spatial, no temporal term (eq. 4, 6)
            acc = radiance
            output = spatial_kernels(acc, params, size, self.config.coarse_first,
                                     count=self.config.kernels)
        self.bandwidth_penalty = bandwidth_penalty_of(low_params)
        new_state = torch.cat((acc, output, params.features[-1], depth, normal),
                              dim=1)  # (N, STATE_CHANNELS, H, W)
        return output * safe_albedo, (new_state, new_embedding)


def fade_resampled(blend: Tensor, previous_features: Tensor, motion: Tensor,
                   floor: Tensor) -> tuple[Tensor, Tensor]:
    """AffinityConfig.resampled_weight_per_doubling: eq. 5's λ capped at 1 - floor where the
    history was resampled (the motion not pixel-aligned), and there, once the floor is above
    MIN_CURRENT_WEIGHT, the warped features of eq. 7 offset by STALE_FEATURE_OFFSET so that
    ω = exp(-b·d²) is 0 for them."""
    resampled = 1 - aligned_mask(motion)
    blend = torch.minimum(blend, 1 - resampled * floor)
    stale = resampled * (floor > MIN_CURRENT_WEIGHT).to(blend.dtype)
    return blend, previous_features + STALE_FEATURE_OFFSET * stale


def bandwidth_penalty_of(params: KernelParams) -> Tensor:
    return bandwidth_regulariser(params.bandwidth, params.temporal_bandwidth)  # eq. 13


def _variant(name: str, widths: tuple[int, ...], scale: int, temporal: bool = True,
             kernels: int = KERNELS, guide: bool = False, coarse_first: bool = False
             ) -> AffinityConfig:
    return AffinityConfig(name=name, widths=widths, unet_scale=scale, temporal=temporal,
                          kernels=kernels, guide=guide, coarse_first=coarse_first)


# The width sweep (docs/affinity.md): h = U-Net at half resolution, f = full resolution.
VARIANTS: dict[str, AffinityConfig] = {
    c.name: c for c in (
        _variant("affinity-h8", (8, 16, 24), 2),
        _variant("affinity-h16", (16, 24, 32), 2),
        _variant("affinity-h24", (24, 32, 48), 2),
        _variant("affinity-h32", (32, 48, 64), 2),
        _variant("affinity-f16", (16, 24, 32), 1),
        _variant("affinity-h16-single", (16, 24, 32), 2, temporal=False),
        # K = 5 à-trous kernels (dilations 1..16) and the full-resolution guide
        _variant("affinity-h16-k5g", (16, 24, 32), 2, kernels=5, guide=True),
        _variant("affinity-h16-k5", (16, 24, 32), 2, kernels=5),
        _variant("affinity-h16-g", (16, 24, 32), 2, guide=True),
        _variant("affinity-h16-k5gc", (16, 24, 32), 2, kernels=5, guide=True, coarse_first=True),
        _variant("affinity-h16-k6gc", (16, 24, 32), 2, kernels=6, guide=True, coarse_first=True),
    )
}
