"""A learned per-pixel blend for the output history (an ablation row: a learned per-pixel
blend between OIDN on the frame and the temporal estimate, Işık et al. eq. 5's λ).

The `oidn-history` stage (model/output_history.py) blends OIDN's output D_t with the fetched
history P_t by a hand rule: O_t = α D_t + (1 - α) P_t, α from the history's length and, where
the history was resampled, a floor w(spp). Işık et al. eq. 5 learns that weight per pixel
(L̄_t = (1 - λ) D_t + λ W L̄_{t-1}). Here a small CNN corrects the rule's weight in logit space:

    α = σ(logit(α_rule) + f_θ(τD, τP, τD - τP, τA, exact, α_rule, log2 spp / 6))

with f_θ's last layer zero at initialisation, so an untrained blend is the shipped rule exactly
and training can only move away from it where the data says so. Where the rule takes no history
(α_rule = 1: a disocclusion, a cut, the first frame) α stays 1. τ is the metric's tone map
(model/losses.tonemap_tau): the blend sees what PSNR scores.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from quietframe.model.losses import tonemap_tau
from quietframe.model.output_history import OutputHistory, OutputHistoryConfig

FEATURES = 3 + 3 + 3 + 3 + 1 + 1 + 1  # τD, τP, τD - τP, τA, exact, α_rule, log2 spp / 6
LOGIT_EPS = 1e-3


class BlendNet(nn.Module):
    """f_θ: two 3×3 convolutions and a 1×1 to one logit correction per pixel."""

    def __init__(self, width: int = 24) -> None:
        super().__init__()
        self.layers = nn.Sequential(
            nn.Conv2d(FEATURES, width, 3, padding=1), nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=1), nn.ReLU(),
            nn.Conv2d(width, 1, 1))
        nn.init.zeros_(self.layers[-1].weight)  # untrained: the rule's weight exactly
        nn.init.zeros_(self.layers[-1].bias)

    def forward(self, features: Tensor) -> Tensor:
        return self.layers(features)


class LearnedBlendHistory(nn.Module):
    """OutputHistory with α corrected per pixel by BlendNet; the same interface and state."""

    state_channels = OutputHistory.state_channels

    def __init__(self, config: OutputHistoryConfig | None = None, width: int = 24) -> None:
        super().__init__()
        self.rule = OutputHistory(config)
        self.net = BlendNet(width)

    def forward(self, oidn: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor,
                motion: Tensor, reset: Tensor, state: Tensor,
                spp: Tensor | None = None) -> tuple[Tensor, Tensor]:
        previous, rule, count, exact = self.rule.history(oidn, normal, depth, motion, reset,
                                                         state, spp)
        if spp is None:
            spp = torch.full((1,), self.rule.config.default_spp)
        t_oidn, t_previous = tonemap_tau(oidn), tonemap_tau(previous)
        level = (torch.log2(spp.clamp_min(1.0)) / 6).view(-1, 1, 1, 1).expand_as(exact)
        features = torch.cat((t_oidn, t_previous, t_oidn - t_previous, tonemap_tau(albedo),
                              exact, rule, level), dim=1)
        logit = torch.logit(rule.clamp(LOGIT_EPS, 1 - LOGIT_EPS))
        learned = torch.sigmoid(logit + self.net(features))
        uses_history = (rule < 1).to(oidn.dtype)
        alpha = 1 - uses_history * (1 - learned)
        output = oidn + (1 - alpha) * (previous - oidn)
        return output, torch.cat((output, depth, normal, count), dim=1)

    def initial_state(self, batch: int, height: int, width: int) -> Tensor:
        return self.rule.initial_state(batch, height, width)
