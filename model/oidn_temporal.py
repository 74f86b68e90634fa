"""The temporal stage of the `oidn-temporal` tier: Open Image Denoise per frame, then this graph.

OIDN (run by the runtime before the graph, see runtime/oidn_prepass.py) denoises each frame on
its own and flickers; this stage makes the sequence stable with Işık et al. 2021's temporal
mechanisms on top of OIDN's output D_t instead of on noisy radiance:

  warp the state (previous output O, accumulated history L̄, features f, depth, normal)
  -> small CNN on (D_t, aux, warped O and L̄, validity) -> f, a, c, b, λ per pixel (eq. 2)
  -> L̄_t = (1 - λ) D_t + λ W L̄_{t-1}                                  (eq. 5)
  -> O_t = one spatial affinity kernel on L̄_t jointly normalised with the temporal kernel
     over W O_{t-1} (eq. 7 + 8), through temporal_affinity_filter (AffinityTemporalFilter).

State-in / state-out like every quietframe model (DESIGN.md): one state tensor, zeros and
reset = 1 on a first frame or a cut.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from quietframe.model.affinity_kernels import temporal_affinity_filter
from quietframe.model.nbg import ldr
from quietframe.model.temporal import backward_warp, history_valid

FEATURES = 8  # f ∈ R^8 (the paper's d)
# State planes: previous output O (3), history L̄ (3), features f (8), depth (1), normal (3).
STATE_SLICES = {"output": (0, 3), "history": (3, 6), "features": (6, 6 + FEATURES),
                "depth": (6 + FEATURES, 7 + FEATURES), "normal": (7 + FEATURES, 10 + FEATURES)}
STATE_CHANNELS = 10 + FEATURES
# Net input: ldr(D) 3, albedo 3, normal 3, relative depth 1, ldr(W O)·g 3, ldr(W L̄)·g 3, g 1.
NET_INPUT_CHANNELS = 17
# Net output: f (8), bandwidth a, centre c, temporal bandwidth b, λ.
NET_OUTPUT_CHANNELS = FEATURES + 4
# A warped neighbour whose surface test failed gets this offset in an extra feature channel:
# ω = exp(-b·OFFSET²) underflows to 0 for any b >= MIN_BANDWIDTH, so the temporal kernel never
# gathers a sample from another surface (the ghosting case) whatever the learned features say.
INVALID_FEATURE_OFFSET = 100.0
MIN_BANDWIDTH = 1e-2


@dataclass(frozen=True)
class OIDNTemporalConfig:
    """Everything needed to rebuild a model; stored in checkpoints and ONNX metadata."""

    name: str = "oidn-temporal-high"
    quality: str = "high"  # the OIDN prepass: high or fast
    prefilter_aux: bool = False  # Blender's "accurate": albedo/normal denoised first
    width: int = 16  # hidden channels of the parameter CNN
    layers: int = 3  # 3×3 convolutions (>= 2)
    kernel_size: int = 3  # spatial affinity kernel (eq. 4), dilation 1
    temporal_kernel_size: int = 3  # temporal window over W O_{t-1} (eq. 7)

    def to_dict(self) -> dict:
        return asdict(self)

    def prepass(self) -> dict:
        """The model metadata's quietframe.prepass: what the runtime runs before the graph."""
        return {"oidn": {"quality": self.quality, "prefilter_aux": self.prefilter_aux},
                "input": "oidn"}


VARIANTS: dict[str, OIDNTemporalConfig] = {
    "oidn-temporal-high": OIDNTemporalConfig(),
    "oidn-temporal-fast": OIDNTemporalConfig(name="oidn-temporal-fast", quality="fast",
                                             width=12),
}


class ParameterNet(nn.Module):
    """3×3 CNN: (N, 17, H, W) -> f (N, 8, H, W) and a, c, b, λ (N, 1, H, W) each (eq. 2)."""

    def __init__(self, config: OIDNTemporalConfig) -> None:
        super().__init__()
        if config.layers < 2:
            raise ValueError(f"ParameterNet needs >= 2 layers, got {config.layers}")
        widths = [NET_INPUT_CHANNELS] + [config.width] * (config.layers - 1)
        self.hidden = nn.ModuleList(
            nn.Conv2d(i, o, 3, padding=1) for i, o in zip(widths[:-1], widths[1:], strict=True))
        self.last = nn.Conv2d(config.width, NET_OUTPUT_CHANNELS, 3, padding=1)
        with torch.no_grad():  # start near "keep half the history, modest bandwidths"
            self.last.bias.zero_()

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        for conv in self.hidden:
            x = F.leaky_relu(conv(x), 0.2)
        out = self.last(x)  # (N, 12, H, W)
        features = out[:, :FEATURES]
        bandwidth = out[:, FEATURES:FEATURES + 1].square()  # a >= 0 (the paper squares it)
        center = torch.sigmoid(out[:, FEATURES + 1:FEATURES + 2])  # c ∈ (0, 1)
        temporal_bandwidth = F.softplus(out[:, FEATURES + 2:FEATURES + 3]) + MIN_BANDWIDTH
        blend = torch.sigmoid(out[:, FEATURES + 3:FEATURES + 4])  # λ ∈ (0, 1), eq. 3/5
        return features, bandwidth, center, temporal_bandwidth, blend


def _state_part(state: Tensor, name: str) -> Tensor:
    start, stop = STATE_SLICES[name]
    return state[:, start:stop]


def accumulate_history(current: Tensor, warped_history: Tensor, blend: Tensor) -> Tensor:
    # eq. 5: L̄_t = (1 - λ) L_t + λ W L̄_{t-1}  (λ = 0 where the history is invalid)
    return (1 - blend) * current + blend * warped_history


def net_input(oidn: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
              warped_output: Tensor, warped_history: Tensor, valid: Tensor) -> Tensor:
    """(N, 17, H, W), every channel in about [0, 1]; history planes are zero where invalid."""
    relative_depth = depth / depth.mean(dim=(2, 3), keepdim=True).clamp_min(1e-6)
    return torch.cat((ldr(oidn), albedo.clamp(0, 1), (normal.clamp(-1, 1) + 1) * 0.5,
                      relative_depth / (1 + relative_depth), ldr(warped_output) * valid,
                      ldr(warped_history) * valid, valid), dim=1)


class OIDNTemporal(nn.Module):
    """State-in / state-out temporal stage on (N, C, H, W) float tensors.

    forward(oidn, albedo, normal, depth, motion, reset, state) -> (denoised, new_state);
    `oidn` is OIDN's output for this frame, the rest as docs/model-interface.md.
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
            oidn, albedo, normal, depth, warped_output, warped_history, valid))
        history = accumulate_history(oidn, warped_history, blend * valid)  # eq. 5
        # The extra feature channel: 0 for the current frame, INVALID_FEATURE_OFFSET where a
        # warped neighbour failed the surface test (see the constant).
        zero = torch.zeros_like(valid)
        current_features = torch.cat((features, zero), dim=1)  # (N, 9, H, W)
        previous_features = torch.cat((_state_part(warped, "features"),
                                       (1 - valid) * INVALID_FEATURE_OFFSET), dim=1)
        # eq. 7 + 8: spatial kernel on L̄_t, temporal kernel on W O_{t-1}, joint normalisation
        output = temporal_affinity_filter(
            history, current_features, bandwidth, center, warped_output, previous_features,
            temporal_bandwidth, on.view(-1), self.config.kernel_size, 1,
            self.config.temporal_kernel_size)
        new_state = torch.cat((output, history, features, depth, normal), dim=1)
        return output, new_state

    def initial_state(self, batch: int, height: int, width: int) -> Tensor:
        return torch.zeros(batch, STATE_CHANNELS, height, width)


def load_checkpoint(path: str) -> tuple[OIDNTemporal, dict]:
    """Rebuild a model from a training checkpoint: {"config", "model", "training", "metrics"}."""
    checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    model = OIDNTemporal(OIDNTemporalConfig(**checkpoint["config"]))
    model.load_state_dict(checkpoint["model"])
    return model, checkpoint
