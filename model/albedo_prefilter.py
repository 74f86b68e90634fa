"""The albedo anti-aliased before demodulation: a Gaussian whose width falls with the frame's spp.

Not in Meng et al. 2020 or Işık et al. 2021. Both learned tiers divide the frame by its albedo and
multiply their output by the same albedo (model/nbg.demodulation_divisor). At a few samples per
pixel the albedo a renderer writes is a few point samples of the texture and of the edges under
the pixel, where the reference holds their pixel-filtered mean: remodulation puts that sampling
noise back into the output at full strength (error = irradiance · (a - E[a])), however well the
irradiance is filtered. On the corpus's validation shots the reference's own albedo put in the
input's place gained both tiers ~2.9 dB at 1 spp and ~1.7 at 4 (normal and depth: under 0.1);
this blur gets most of it at no training (docs/training.md, "The albedo's own noise").

The blur's width σ(spp) = σ₁ · max(spp, 1)^(-SIGMA_EXPONENT) px: a sample mean's noise falls with
spp, and what a blur costs (texture detail under ~2σ) does not; from 64 spp on it is below a
third of a pixel and leaves the albedo nearly as it is. Separable, RADIUS taps each way, edges
replicated, taps normalised to sum 1 (so a flat albedo stays exactly flat).

The custom op `albedo_blur` is the reference of ai.quietframe::AlbedoPrefilter
(export/ops/albedo_prefilter.cc), which the ONNX export maps it onto. No gradient: the albedo
is an input, and nothing before it learns.
"""

from __future__ import annotations

import torch
from torch import Tensor

from quietframe.model.temporal import frame_samples
from quietframe.runtime.receptive import ALBEDO_PREFILTER_RADIUS

RADIUS = ALBEDO_PREFILTER_RADIUS  # taps each way: 2.5σ at the widest σ₁ the setting allows
MAX_SIGMA_AT_ONE_SPP = 1.2  # px; wider would be cut short by RADIUS
SIGMA_EXPONENT = 1 / 3  # σ(spp) = σ₁ · spp^(-1/3), chosen on validation (docs/training.md)


def check_albedo_prefilter(at_one_spp: float) -> None:
    """A config's setting: 0 (off) up to MAX_SIGMA_AT_ONE_SPP px."""
    if not 0 <= at_one_spp <= MAX_SIGMA_AT_ONE_SPP:
        raise ValueError(f"albedo_prefilter must be 0 (off) to {MAX_SIGMA_AT_ONE_SPP} px, "
                         f"got {at_one_spp}")


def prefilter_sigma(spp: Tensor, at_one_spp: float, exponent: float = SIGMA_EXPONENT) -> Tensor:
    """σ(spp) in pixels, per image: spp below 1 (or NaN) counts as 1."""
    spp = torch.where(spp >= 1.0, spp, torch.ones_like(spp))
    return at_one_spp * spp.pow(-exponent)


def gaussian_taps(sigma: Tensor, radius: int = RADIUS) -> Tensor:
    """(N,) -> (N, 2·radius + 1) normalised Gaussian taps; a σ under 1e-3 px is the identity."""
    offsets = torch.arange(-radius, radius + 1, dtype=sigma.dtype, device=sigma.device)
    safe = torch.where(sigma > 1e-3, sigma, torch.ones_like(sigma)).view(-1, 1)
    taps = torch.exp(-0.5 * (offsets / safe) ** 2)
    identity = (offsets == 0).to(sigma.dtype).expand_as(taps)
    taps = torch.where((sigma > 1e-3).view(-1, 1), taps, identity)
    return taps / taps.sum(dim=1, keepdim=True)


def prefilter_albedo(albedo: Tensor, spp: Tensor | None, at_one_spp: float) -> Tensor:
    """The albedo as the learned tiers demodulate by it: blurred by σ(spp) where `at_one_spp`
    (NBGConfig / AffinityConfig.albedo_prefilter) is above 0, else as it is."""
    if at_one_spp <= 0:
        return albedo
    return albedo_blur(albedo.detach(), frame_samples(spp).to(albedo.dtype), at_one_spp,
                       SIGMA_EXPONENT, RADIUS)


def _blur_axis(x: Tensor, taps: Tensor, radius: int, dim: int) -> Tensor:
    """One separable pass along `dim` (3 = rows, 2 = columns), edges replicated, the taps
    summed from -radius to +radius in order (the C++ op sums in the same order)."""
    size = x.shape[dim]
    index = torch.arange(size, device=x.device)
    out = torch.zeros_like(x)
    for i, offset in enumerate(range(-radius, radius + 1)):
        shifted = x.index_select(dim, (index + offset).clamp(0, size - 1))
        out = out + taps[:, i].view(-1, 1, 1, 1) * shifted
    return out


@torch.library.custom_op("quietframe::albedo_prefilter", mutates_args=())
def albedo_blur(albedo: Tensor, spp: Tensor, at_one_spp: float, exponent: float,
                radius: int) -> Tensor:
    """(N, C, H, W), spp (N,) or (1,) -> the albedo blurred by σ(spp) per image: rows first,
    then columns (tests/export/test_ops_albedo_prefilter.py holds the C++ op to this)."""
    sigma = prefilter_sigma(spp, at_one_spp, exponent)
    taps = gaussian_taps(sigma.expand(albedo.shape[0]) if sigma.numel() == 1 else sigma,
                         radius)
    return _blur_axis(_blur_axis(albedo, taps, radius, 3), taps, radius, 2)


@albedo_blur.register_fake
def _albedo_blur_fake(albedo: Tensor, spp: Tensor, at_one_spp: float, exponent: float,
                      radius: int) -> Tensor:
    return torch.empty_like(albedo)
