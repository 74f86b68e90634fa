"""Training losses (torch). Same definitions as the numpy metrics in `metrics.py` where they share
a name, so a training curve and an evaluation table measure the same thing."""

from __future__ import annotations

import torch

from .metrics import EPS_RELATIVE

# NBG §5: for the BMFR data, S is gamma correction with exponent 1/2.2 onto the displayable range.
NBG_GAMMA = 2.2
# x^(1/2.2) has an infinite slope at 0; flooring the clamp keeps gradients finite (0 below it).
# The mapped floor, 1e-8^(1/2.2) ≈ 2e-4, is far below one 8-bit LDR step.
_GAMMA_FLOOR = 1e-8


def smape_loss(pred: torch.Tensor, ref: torch.Tensor, eps: float = EPS_RELATIVE) -> torch.Tensor:
    # Işık eq. 11 (as metrics.smape): mean |p - r| / (|p| + |r| + ε), per element
    return ((pred - ref).abs() / (pred.abs() + ref.abs() + eps)).mean()


def _check_frames(preds: torch.Tensor, dim: int) -> None:
    """The temporal terms need a frame difference: at least 2 frames along `dim`."""
    if preds.shape[dim] < 2:
        raise ValueError(f"temporal_loss: need >= 2 frames along dim {dim}, got {preds.shape}")


def temporal_loss(
    preds: torch.Tensor, refs: torch.Tensor, dim: int = 1, eps: float = EPS_RELATIVE
) -> torch.Tensor:
    # Işık eq. 12: SMAPE(∂t O, ∂t O*), ∂t plain finite difference along `dim` of (N, T, C, H, W)
    _check_frames(preds, dim)
    return smape_loss(torch.diff(preds, dim=dim), torch.diff(refs, dim=dim), eps)


def relmse_unbiased_loss(
    pred: torch.Tensor, ref: torch.Tensor, scale: torch.Tensor | None = None,
    eps: float = EPS_RELATIVE,
) -> torch.Tensor:
    # Noise2Noise (Lehtinen et al. 2018, §3.3 "L_HDR"): (p - r)² / (sg(s) + ε)², s = p unless
    # given. The weight does not depend on the target, and the loss is quadratic in it, so for a
    # target r = r* + n with E[n] = 0 the expected gradient is the one against r*: a noisy
    # Monte Carlo reference trains the same model as a clean one would, only with noisier steps.
    # SMAPE and L1 have no such property (their minimiser is a median-like, biased statistic).
    weight = (pred if scale is None else scale).detach().abs() + eps
    return ((pred - ref) / weight).square().mean()


def temporal_relmse_unbiased_loss(
    preds: torch.Tensor, refs: torch.Tensor, dim: int = 1, eps: float = EPS_RELATIVE
) -> torch.Tensor:
    # Işık eq. 12's temporal term with the unbiased loss above: ∂t of output and reference,
    # weighted by the later output frame (a difference's own magnitude can be ~0)
    _check_frames(preds, dim)
    later = preds.narrow(dim, 1, preds.shape[dim] - 1)
    return relmse_unbiased_loss(torch.diff(preds, dim=dim), torch.diff(refs, dim=dim), later, eps)


def ldr_gamma(x: torch.Tensor, gamma: float = NBG_GAMMA) -> torch.Tensor:
    """NBG's S (§4.4 eq. 14, §5): clamp to [0, 1], then gamma correction x^(1/γ)."""
    return x.clamp(_GAMMA_FLOOR, 1.0).pow(1.0 / gamma)


def l1_tonemapped_loss(
    pred: torch.Tensor, ref: torch.Tensor, gamma: float = NBG_GAMMA
) -> torch.Tensor:
    # NBG eq. 14: mean |S(R) - S(I)| on the LDR-mapped output and ground truth
    return (ldr_gamma(pred, gamma) - ldr_gamma(ref, gamma)).abs().mean()


def tonemap_tau(x: torch.Tensor) -> torch.Tensor:
    # Işık eq. 15, metrics.tonemap_tau in torch; the floor keeps the slope of ^(1/2.4) finite
    x = x.clamp_min(_GAMMA_FLOOR)
    return (x / (1 + x)).pow(1.0 / 2.4)


def tau_mse_loss(pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    # Işık eq. 14's own error: the mean squared difference of τ-mapped images, the quantity the
    # evaluation's PSNR is -10 log10 of; its minimiser is the conditional mean in τ space
    return (tonemap_tau(pred) - tonemap_tau(ref)).square().mean()


def temporal_tau_mse_loss(preds: torch.Tensor, refs: torch.Tensor, dim: int = 1) -> torch.Tensor:
    # eq. 12's temporal term in the same space: frame differences of τ-mapped outputs
    _check_frames(preds, dim)
    diff_pred = torch.diff(tonemap_tau(preds), dim=dim)
    return (diff_pred - torch.diff(tonemap_tau(refs), dim=dim)).square().mean()


def bandwidth_regulariser(
    bandwidths: list[torch.Tensor], temporal_bandwidth: torch.Tensor
) -> torch.Tensor:
    # Işık eq. 13: Σ_k E ||a^k||² + E ||b||², bandwidths (N, 1, H, W) each; without it the scale
    # ambiguity between a, b and the feature magnitudes made training unstable (paper §4.2)
    return sum(a.square().mean() for a in bandwidths) + temporal_bandwidth.square().mean()
