"""How noisy a frame is, without a reference: a noise statistic of its colour and, through the
fit `bench/noise_calibration.py` writes to `noise_calibration.json`, the equivalent spp. The
same spp is a clean frame in a sunlit room and a speckled one in a room lit through a window,
so `auto` reads the statistic as well as the spp (service/choice_policy.py)."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

CALIBRATION_FILE = Path(__file__).with_name("noise_calibration.json")
ESTIMATE = "estimate"  # a NoiseLevel's source where the spp was estimated from the pixels


@dataclass(frozen=True)
class NoiseLevel:
    spp: float
    source: str  # the header attribute it came from, "estimate" or "unknown"
    # log2 of noise_statistic of the deciding frame (None: not measured), and whether it was
    # demodulated by the frame's albedo (by_noise points carry both kinds).
    log2_sigma: float | None = None
    demodulated: bool = True


def _box(x: np.ndarray, size: int) -> np.ndarray:
    """Mean over a size×size window (edge-padded), by summed-area table."""
    h, w = x.shape
    padded = np.pad(x, size // 2, mode="edge")
    table = np.pad(padded, ((1, 0), (1, 0))).cumsum(0).cumsum(1)
    return (
        table[size : size + h, size : size + w] - table[:h, size : size + w]
        - table[size : size + h, :w] + table[:h, :w]
    ) / (size * size)


def noise_statistic(color: np.ndarray, albedo: np.ndarray | None = None) -> float:
    """A reference-free noise statistic of one (3, H, W) frame: the relative variance of the
    demodulated luminance around its 5×5 box mean. Dividing by albedo removes texture, so what
    is left around the local mean is mostly Monte Carlo noise (variance ∝ 1/spp). Not a robust
    (median) spread: at 1–2 spp most pixels of a dim scene are exactly 0, which a median reads
    as no noise; instead the brightest 0.1 % (fireflies) are clipped."""
    lum = np.nan_to_num(np.asarray(color, np.float64).mean(0), nan=0.0, posinf=0.0)
    lum = np.maximum(lum, 0.0)
    if albedo is not None:
        lum = lum / np.maximum(np.asarray(albedo, np.float64).mean(0), 0.05)
    lum = np.minimum(lum, np.percentile(lum, 99.9))
    smooth = _box(lum, 5)
    scale = float(smooth.mean()) ** 2
    if not math.isfinite(scale) or scale <= 0:
        return 0.0
    return float(((lum - smooth) ** 2).mean() / scale)


def load_calibration(path: Path = CALIBRATION_FILE) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def spp_from_sigma(sigma: float, calibration: Mapping) -> float:
    """Equivalent spp of a noise statistic: log2(spp) = intercept + slope·log2(σ) (fitted by
    bench/noise_calibration.py; σ is a variance ∝ 1/spp, so the slope is near -1)."""
    if sigma <= 0:
        return float(calibration.get("max_spp", 1024))
    log_spp = calibration["intercept"] + calibration["slope"] * math.log2(sigma)
    lo, hi = calibration.get("min_spp", 0.25), calibration.get("max_spp", 1024)
    return float(min(max(2.0**log_spp, lo), hi))


def log2_statistic(sigma: float) -> float | None:
    return math.log2(sigma) if sigma > 0 and math.isfinite(sigma) else None


def estimate_spp(
    color: np.ndarray, albedo: np.ndarray | None, calibration: Mapping | None,
    header: NoiseLevel | None = None,
) -> NoiseLevel:
    """The frame's noise: the header's spp where given (`header`), else the calibrated estimate,
    and in both cases the statistic itself (the choice's by_noise lookup)."""
    sigma = noise_statistic(color, albedo)
    measured = {"log2_sigma": log2_statistic(sigma), "demodulated": albedo is not None}
    if header is not None:
        return NoiseLevel(header.spp, header.source, **measured)
    if calibration is None:  # no fit shipped: the choice then plans for the noisiest input
        return NoiseLevel(1.0, "unknown", **measured)
    return NoiseLevel(round(spp_from_sigma(sigma, calibration), 2), ESTIMATE, **measured)


def shot_samples(color: np.ndarray, albedo: np.ndarray | None,
                 calibration: Mapping | None) -> float | None:
    """The spp a model reading one is given for a shot whose spp nothing states: the estimate
    from its first frame, at least 1 as the model takes it (runtime/stream.chosen_samples).
    None (the model's default; the next frame estimates again) without a calibration or where
    the frame shows no noise to measure (black, or flat: a fade-in's first frame)."""
    noise = estimate_spp(color, albedo, calibration)
    if noise.source != ESTIMATE or noise.log2_sigma is None:
        return None
    return max(1.0, noise.spp)
