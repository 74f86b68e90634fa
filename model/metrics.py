"""Image and sequence error metrics (numpy), as defined by Işık et al. 2021 §4.2 and §5.1.1.

Shared by the evaluation and the benchmarks; no torch here so that evaluating an exported model
needs only the serving stack. The torch counterparts used for training are in `losses.py`.

Images are (H, W, 3) float32 linear HDR radiance; sequences are (T, H, W, 3). All arithmetic is
done in float64 so that a metric does not depend on the dtype it was handed. Relative metrics
(SMAPE, relMSE, TRMAE) are taken per element (pixel and channel), which is what the papers'
"1/3 E_xyt ||·||_1" with "the factor 3 accounts for color channels" amounts to.
"""

from __future__ import annotations

import numpy as np

# ε of Işık eq. 16 (stated there as 0.01); eq. 11 gives no value, we use the same.
EPS_RELATIVE = 1e-2
# SSIM constants of Wang et al. 2004 for a peak of 1 (τ maps into [0, 1]).
SSIM_K1, SSIM_K2 = 0.01, 0.03
SSIM_SIGMA, SSIM_RADIUS = 1.5, 5  # 11×11 Gaussian window
# Beyond this, x / (1 + x) is 1 in float64; clipping keeps +inf from becoming inf/inf = NaN.
_TAU_MAX_INPUT = 1e30


def _f64(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def _check_same_shape(pred: np.ndarray, ref: np.ndarray, name: str) -> None:
    if pred.shape != ref.shape:
        raise ValueError(f"{name}: pred {pred.shape} and ref {ref.shape} differ in shape")


def tonemap_tau(x: np.ndarray) -> np.ndarray:
    # Işık eq. 15: τ(x) = (x / (1 + x))^(1/2.4), negatives clamped to 0
    x = np.clip(_f64(x), 0.0, _TAU_MAX_INPUT)
    return np.power(x / (1.0 + x), 1.0 / 2.4)


def psnr(pred: np.ndarray, ref: np.ndarray) -> float:
    # Işık eq. 14: -10 log10(mean squared error of τ), peak 1; any shape (images or sequences)
    _check_same_shape(pred, ref, "psnr")
    mse = float(np.mean((tonemap_tau(pred) - tonemap_tau(ref)) ** 2))
    return float("inf") if mse == 0.0 else -10.0 * float(np.log10(mse))


def _gaussian_window_1d() -> np.ndarray:
    offsets = np.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=np.float64)
    w = np.exp(-0.5 * (offsets / SSIM_SIGMA) ** 2)
    return w / w.sum()


def _filter_valid(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Separable 'valid' filtering over the two leading axes: (H, W, C) → (H-2r, W-2r, C).

    'valid' (no padding) is Wang et al.'s reference choice: border pixels are simply not scored.
    """
    n = len(w)
    rows = sum(w[k] * x[k : x.shape[0] - n + 1 + k] for k in range(n))
    return sum(w[k] * rows[:, k : x.shape[1] - n + 1 + k] for k in range(n))


def ssim(pred: np.ndarray, ref: np.ndarray) -> float:
    """Mean SSIM (Wang et al. 2004) of τ-mapped images, Gaussian 11×11 window σ=1.5.

    Per channel, averaged over the valid (unpadded) pixels and the channels. (H, W) or (H, W, C).
    """
    _check_same_shape(pred, ref, "ssim")
    if pred.ndim not in (2, 3) or min(pred.shape[:2]) < 2 * SSIM_RADIUS + 1:
        raise ValueError(f"ssim: need (H, W[, C]) with H, W >= 11, got {pred.shape}")
    x, y = tonemap_tau(pred), tonemap_tau(ref)
    if x.ndim == 2:
        x, y = x[..., None], y[..., None]
    w = _gaussian_window_1d()
    mu_x, mu_y = _filter_valid(x, w), _filter_valid(y, w)
    var_x = _filter_valid(x * x, w) - mu_x**2
    var_y = _filter_valid(y * y, w) - mu_y**2
    cov = _filter_valid(x * y, w) - mu_x * mu_y
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    num = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    return float(np.mean(num / den))


def smape(pred: np.ndarray, ref: np.ndarray, eps: float = EPS_RELATIVE) -> float:
    # Işık eq. 11: mean |p - r| / (|p| + |r| + ε), per element, ε = 0.01
    _check_same_shape(pred, ref, "smape")
    p, r = _f64(pred), _f64(ref)
    return float(np.mean(np.abs(p - r) / (np.abs(p) + np.abs(r) + eps)))


def relmse(pred: np.ndarray, ref: np.ndarray, eps: float = EPS_RELATIVE) -> float:
    """Relative MSE: mean (p - r)² / (r² + ε), per element, ε = 0.01 (Rousselle et al. 2011)."""
    _check_same_shape(pred, ref, "relmse")
    p, r = _f64(pred), _f64(ref)
    return float(np.mean((p - r) ** 2 / (r * r + eps)))


def temporal_difference(seq: np.ndarray) -> np.ndarray:
    # ∂_t of Işık eq. 12/16: plain finite difference along time, no motion compensation
    return seq[1:] - seq[:-1]


def trmae(preds: np.ndarray, refs: np.ndarray, eps: float = EPS_RELATIVE) -> float:
    # Işık eq. 16: mean |∂t p - ∂t r| / (|∂t r| + ε), per element, ε = 0.01
    p, r = _f64(np.stack(preds)), _f64(np.stack(refs))
    _check_same_shape(p, r, "trmae")
    if p.shape[0] < 2:
        raise ValueError(f"trmae: need at least 2 frames, got {p.shape[0]}")
    dp, dr = temporal_difference(p), temporal_difference(r)
    return float(np.mean(np.abs(dp - dr) / (np.abs(dr) + eps)))


def flicker(preds: np.ndarray) -> float:
    """Flicker of a locked-off shot (static camera and scene, new noise every frame, so the
    true image is constant): the mean over pixels and channels of the temporal standard
    deviation of τ(output). Needs no reference, so no reference noise limits it."""
    p = tonemap_tau(_f64(np.stack(preds)))
    if p.shape[0] < 2:
        raise ValueError(f"flicker: need at least 2 frames, got {p.shape[0]}")
    return float(np.mean(np.std(p, axis=0)))
