"""The temporal stage of the `oidn-temporal` tier: Open Image Denoise per frame, then this graph.

OIDN (run by the runtime before the graph, see runtime/oidn_prepass.py) denoises each frame on
its own and flickers; this stage makes the sequence stable with Işık et al. 2021's temporal
mechanisms on top of OIDN's output D_t instead of on noisy radiance:

  warp the state (previous output O, accumulated history L̄, features f, depth, normal)
  -> small CNN on (D_t, aux, warped O and L̄, validity) -> f, a, c, b, λ per pixel (eq. 2),
     at full resolution or (net_scale 2) on a 2×2-averaged input, upsampled bilinearly
  -> L̄_t = (1 - λ) D_t + λ W L̄_{t-1}                                  (eq. 5)
  -> O_t = one spatial affinity kernel on L̄_t jointly normalised with the temporal kernel
     over W O_{t-1} (eq. 7 + 8), through temporal_affinity_filter (AffinityTemporalFilter).

State-in / state-out like every quietframe model (docs/architecture.md): one state tensor, zeros and
reset = 1 on a first frame or a cut.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from quietframe.model.affinity_kernels import temporal_affinity_filter
from quietframe.model.losses import bandwidth_regulariser
from quietframe.model.temporal import backward_warp, history_valid
from quietframe.runtime.oidn_prepass import PREPASS_KEY, OIDNSettings, read_prepass

FEATURES = 8  # f ∈ R^8 (the paper's d)
# State planes: previous output O (3), history L̄ (3), features f (8), depth (1), normal (3).
STATE_SLICES = {"output": (0, 3), "history": (3, 6), "features": (6, 6 + FEATURES),
                "depth": (6 + FEATURES, 7 + FEATURES), "normal": (7 + FEATURES, 10 + FEATURES)}
STATE_CHANNELS = 10 + FEATURES
# Net input: tonemap(D) 3, albedo 3, normal 3, tonemap(W L̄)·g 3, g 1. Lean on purpose: at 720p
# every full-frame plane of elementwise work costs ~1 ms and the stage's budget is 15% of OIDN's
# time (experiments/oidn_temporal_speed.py); depth enters through the surface test g, not the net.
NET_INPUT_CHANNELS = 13
# Net output: f (8), bandwidth a, centre c, temporal bandwidth b, λ.
NET_OUTPUT_CHANNELS = FEATURES + 4
# A warped neighbour whose surface test failed has this added to each of its features: its
# distance to any current feature vector is then ~8·OFFSET² and ω = exp(-b·d²) underflows to 0
# for any b >= MIN_BANDWIDTH, so the temporal kernel never gathers a sample from another surface
# (the ghosting case) whatever the learned features say. A broadcast add, not an extra channel:
# two 9-channel concatenations of a 720p frame cost more than the kernel's taps.
INVALID_FEATURE_OFFSET = 1000.0
MIN_BANDWIDTH = 1e-2


@dataclass(frozen=True)
class OIDNTemporalConfig:
    """Everything needed to rebuild a model; stored in checkpoints and ONNX metadata."""

    name: str = "oidn-temporal-high"
    quality: str = "high"  # the OIDN prepass: high or fast
    prefilter_aux: bool = False  # Blender's "accurate": albedo/normal denoised first
    width: int = 16  # hidden channels of the parameter CNN
    layers: int = 3  # convolutions (>= 2): 3×3 ones, then a 1×1 output layer
    kernel_size: int = 3  # spatial affinity kernel (eq. 4), dilation 1
    temporal_kernel_size: int = 3  # temporal window over W O_{t-1} (eq. 7)
    # 1: the parameter CNN runs at full resolution. 2: on the 2×2 average of its input, its
    # outputs upsampled bilinearly (the kernels still filter at full resolution): the CNN was
    # the largest cost of the stage at 720p and the per-pixel parameters are smooth
    # (docs/oidn-temporal.md, speed).
    net_scale: int = 1
    # "" : OIDN denoises each frame's colour. A model file (shipped in models/, e.g.
    # "accumulation.onnx"): OIDN denoises that model's output, the reprojected accumulation of
    # the noisy colour, so it sees several frames' samples (runtime/oidn_prepass.py color_from).
    color_from: str = ""

    def to_dict(self) -> dict:
        return asdict(self)

    def prepass(self) -> dict:
        """The model metadata's quietframe.prepass: what the runtime runs before the graph."""
        return prepass_spec(self.quality, self.prefilter_aux, self.color_from)

    def prepass_settings(self) -> OIDNSettings:
        """The prepass as the runtime reads it back from the metadata (training feeds the same)."""
        return read_prepass({PREPASS_KEY: json.dumps(self.prepass())})


def prepass_spec(quality: str, prefilter_aux: bool, color_from: str,
                 aux_quality: str = "") -> dict:
    """`quietframe.prepass` of a composition; `aux_quality` only when it differs ("": the
    main filter's)."""
    oidn = {"quality": quality, "prefilter_aux": prefilter_aux}
    spec = {"oidn": oidn | ({"aux_quality": aux_quality} if aux_quality else {}),
            "input": "oidn"}
    return {**spec, "color_from": color_from} if color_from else spec


@dataclass(frozen=True)
class OIDNOnlyConfig:
    """A composition without a learned stage: the prepass (OIDN on the frame, or on a
    color_from model's output) is the whole denoiser, and the graph passes OIDN's output
    through. On the reprojected accumulation the learned stage of oidn-temporal-acc converged
    to the identity (λ = 0, delta kernels; docs/training.md), so its cost bought nothing there:
    these variants drop it, and their temporal stability is the accumulation's."""

    name: str
    quality: str = "high"
    prefilter_aux: bool = False
    color_from: str = "accumulation.onnx"

    def to_dict(self) -> dict:
        return asdict(self)

    def prepass(self) -> dict:
        return prepass_spec(self.quality, self.prefilter_aux, self.color_from)


OIDN_ONLY_VARIANTS: dict[str, OIDNOnlyConfig] = {
    "oidn-acc": OIDNOnlyConfig(name="oidn-acc"),
    "oidn-fast-acc": OIDNOnlyConfig(name="oidn-fast-acc", quality="fast"),
    # OIDN on each frame alone: for frames without the depth/normal the accumulation's surface
    # test needs (colour only, no albedo, ...), where it is well ahead of NBG in PSNR and in
    # flicker (docs/benchmarks.md, buffer absence); it runs with whatever aux the frame has.
    "oidn-frame": OIDNOnlyConfig(name="oidn-frame", color_from=""),
}


VARIANTS: dict[str, OIDNTemporalConfig] = {
    "oidn-temporal-high": OIDNTemporalConfig(),
    "oidn-temporal-fast": OIDNTemporalConfig(name="oidn-temporal-fast", quality="fast",
                                             width=12, layers=2),
    "oidn-temporal-acc": OIDNTemporalConfig(name="oidn-temporal-acc",
                                            color_from="accumulation.onnx"),
    # OIDN-fast on the accumulation: within ~0.1 dB of OIDN-high on it (validation, experiments/
    # oidn_accumulated.py --quality fast) at about half of OIDN-high's time. Shipped as v1
    # until oidn-fast-acc (no learned stage) measured better and faster on the full validation
    # split (docs/oidn-temporal.md); kept for that comparison. Full-
    # resolution CNN: with net_scale 2 the stage trained (800 steps) to 0.45-0.65 dB below
    # oidn-temporal-acc on validation, below OIDN-fast alone at 4 spp (docs/oidn-temporal.md).
    "oidn-temporal-fast-acc": OIDNTemporalConfig(name="oidn-temporal-fast-acc", quality="fast",
                                                 color_from="accumulation.onnx"),
}


class ParameterNet(nn.Module):
    """3×3 CNN + 1×1 head: (N, 13, H, W) -> f (N, 8, H, W), a, c, b, λ (N, 1, H, W) (eq. 2).
    With net_scale 2 the CNN sees the 2×2 average of its input (odd sizes: the last row or
    column averages what it has) and its raw outputs are upsampled bilinearly to (H, W)."""

    def __init__(self, config: OIDNTemporalConfig) -> None:
        super().__init__()
        if config.layers < 2:
            raise ValueError(f"ParameterNet needs >= 2 layers, got {config.layers}")
        if config.net_scale not in (1, 2):
            raise ValueError(f"ParameterNet runs at scale 1 or 2, not {config.net_scale}")
        self.scale = config.net_scale
        widths = [NET_INPUT_CHANNELS] + [config.width] * (config.layers - 1)
        self.hidden = nn.ModuleList(
            nn.Conv2d(i, o, 3, padding=1) for i, o in zip(widths[:-1], widths[1:], strict=True))
        self.last = nn.Conv2d(config.width, NET_OUTPUT_CHANNELS, 1)
        with torch.no_grad():  # start near "keep half the history, modest bandwidths"
            self.last.bias.zero_()

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        size = x.shape[-2:]
        if self.scale > 1:
            x = F.avg_pool2d(x, self.scale, ceil_mode=True, count_include_pad=False)
        for conv in self.hidden:
            x = F.leaky_relu(conv(x), 0.2)
        out = self.last(x)  # (N, 12, H / scale, W / scale)
        if self.scale > 1:  # before the nonlinearities below, so a, b, c, λ keep their ranges
            out = F.interpolate(out, size=size, mode="bilinear", align_corners=False)
        features = out[:, :FEATURES]
        bandwidth = out[:, FEATURES:FEATURES + 1].square()  # a >= 0 (the paper squares it)
        center = torch.sigmoid(out[:, FEATURES + 1:FEATURES + 2])  # c ∈ (0, 1)
        temporal_bandwidth = out[:, FEATURES + 2:FEATURES + 3].square() + MIN_BANDWIDTH
        blend = torch.sigmoid(out[:, FEATURES + 3:FEATURES + 4])  # λ ∈ (0, 1), eq. 3/5
        return features, bandwidth, center, temporal_bandwidth, blend


def _state_part(state: Tensor, name: str) -> Tensor:
    start, stop = STATE_SLICES[name]
    return state[:, start:stop]


def accumulate_history(current: Tensor, warped_history: Tensor, blend: Tensor) -> Tensor:
    # eq. 5: L̄_t = (1 - λ) L_t + λ W L̄_{t-1}  (λ = 0 where the history is invalid)
    return (1 - blend) * current + blend * warped_history


def tonemap(x: Tensor) -> Tensor:
    """HDR radiance -> [0, 1) for the net: sqrt(x / (1 + x)). A square root instead of NBG's
    x^(1/2.2): a Pow over a 720p frame costs several times a Sqrt."""
    x = F.relu(x)
    return torch.sqrt(x / (1 + x))


def net_input(oidn: Tensor, albedo: Tensor, normal: Tensor, warped_history: Tensor,
              valid: Tensor) -> Tensor:
    """(N, 13, H, W); albedo and normal as the buffers give them ([0, 1] and [-1, 1] by the
    interface contract), history planes zero where invalid."""
    return torch.cat((tonemap(oidn), albedo, normal, tonemap(warped_history) * valid, valid),
                     dim=1)


class OIDNTemporal(nn.Module):
    """State-in / state-out temporal stage on (N, C, H, W) float tensors.

    forward(oidn, albedo, normal, depth, motion, reset, state) -> (denoised, new_state);
    `oidn` is OIDN's output for this frame, the rest as docs/model-interface.md. After each
    forward, `bandwidth_penalty` holds eq. 13 of that frame for the training loss (eq. 9).
    """

    state_channels = STATE_CHANNELS
    # Graph inputs in forward order before reset/state: the prepass result, then the buffers.
    inputs = ("oidn", "albedo", "normal", "depth", "motion")

    def __init__(self, config: OIDNTemporalConfig | None = None) -> None:
        super().__init__()
        self.config = config or OIDNTemporalConfig()
        self.net = ParameterNet(self.config)

    def forward(self, oidn: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
                motion: Tensor, reset: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        # Nearest reprojection (as model/temporal): the surface test checks the very pixel that
        # is reused, and repeated warps never blur the history.
        warped, inside = backward_warp(state.detach(), motion, mode="nearest")  # (N, 18, H, W)
        on = 1 - reset.view(-1, 1, 1, 1)  # (N, 1, 1, 1)
        valid = on * inside * history_valid(_state_part(warped, "depth"),
                                            _state_part(warped, "normal"), depth, normal)
        warped_output = _state_part(warped, "output")  # W O_{t-1}
        warped_history = _state_part(warped, "history")  # W L̄_{t-1}
        features, bandwidth, center, temporal_bandwidth, blend = self.net(net_input(
            oidn, albedo, normal, warped_history, valid))
        self.bandwidth_penalty = bandwidth_regulariser([bandwidth], temporal_bandwidth)  # eq. 13
        history = accumulate_history(oidn, warped_history, blend * valid)  # eq. 5
        # W f_{t-1}, pushed far away where the warped sample failed the surface test
        previous_features = (_state_part(warped, "features")
                             + (1 - valid) * INVALID_FEATURE_OFFSET)  # (N, 8, H, W)
        # eq. 7 + 8: spatial kernel on L̄_t, temporal kernel on W O_{t-1}, joint normalisation
        output = temporal_affinity_filter(
            history, features, bandwidth, center, warped_output, previous_features,
            temporal_bandwidth, on.view(-1), self.config.kernel_size, 1,
            self.config.temporal_kernel_size)
        new_state = torch.cat((output, history, features, depth, normal), dim=1)
        return output, new_state

    def initial_state(self, batch: int, height: int, width: int) -> Tensor:
        return torch.zeros(batch, STATE_CHANNELS, height, width)
