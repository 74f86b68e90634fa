"""Kernel filtering of the affinity denoiser (Işık et al. 2021, §3.4–3.5): the PyTorch reference.

The C++ onnxruntime ops ai.quietframe::AffinityFilter / AffinityTemporalFilter (export/ops)
compute exactly this and are held to it by tests/export/test_ops_affinity.py;
docs/affinity-math.md is the contract of both. Tensors are NCHW: radiance (N, C, H, W), features
(N, D, H, W), bandwidth and centre (N, 1, H, W), temporal_on (N,).

Memory: the k×k window is a loop over offsets with shifted views of one padded copy, accumulating
numerator and denominator, never an unfold of D·k² channels. The public functions are torch
custom ops (so that torch.export keeps them whole and the ONNX exporter maps them onto the C++
ops); their backward recomputes the forward with autograd, so training keeps only the inputs
between the passes and builds the k×k graph one filter at a time.

Native kernels: with QUIETFRAME_TRAIN_KERNELS=native (the default is affinity_native.
DEFAULT_KERNELS) the custom ops' forward and backward on float32 CPU tensors run the C++ code of
the served ops and its analytic gradients instead (quietframe.model.affinity_native); the
functions below stay the reference they are tested against.

Rules beyond the paper's equations (the C++ ops follow them too):
- bandwidths, the centre weight and temporal_on below 0 or NaN count as 0;
- a weight exp(-a·d²) that is NaN (a = Inf with d² = 0, NaN features) counts as 0;
- neighbours outside the image contribute nothing;
- the result goes through nan_to_num (NaN -> 0, ±Inf -> ±float max), so the filter never returns
  a non-finite value (an all-zero neighbourhood already gives 0/(ε + 0) = 0).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from quietframe.model import affinity_native as native

EPSILON = 1e-10  # ε of eq. 6 and 8
MAX_KERNEL_SIZE = 31  # the C++ ops accept odd kernel sizes 1..31


def _check_kernel(name: str, size: int) -> int:
    """Radius r of an odd kernel size 2r + 1."""
    if not (isinstance(size, int) and 1 <= size <= MAX_KERNEL_SIZE and size % 2 == 1):
        raise ValueError(f"{name} must be an odd int in [1, {MAX_KERNEL_SIZE}], got {size!r}")
    return (size - 1) // 2


def _non_negative(x: Tensor) -> Tensor:
    """x where x > 0, else 0 (negative and NaN values count as 0)."""
    return torch.where(x > 0, x, torch.zeros_like(x))


class _Window:
    """Shifted views of one zero-padded copy of a tensor: view(dy, dx)[..., y, x] is
    x[..., y + dy, x + dx], and inside(dy, dx) is 1 where that pixel lies in the image."""

    def __init__(self, x: Tensor, reach: int) -> None:
        self.h, self.w = x.shape[-2:]
        self.reach = reach
        self.padded = F.pad(x, (reach, reach, reach, reach))

    def view(self, dy: int, dx: int) -> Tensor:
        top, left = self.reach + dy, self.reach + dx
        return self.padded[..., top:top + self.h, left:left + self.w]

    def inside(self, dy: int, dx: int, like: Tensor) -> Tensor:
        ys = torch.arange(self.h, device=like.device).view(-1, 1) + dy
        xs = torch.arange(self.w, device=like.device).view(1, -1) + dx
        mask = (ys >= 0) & (ys < self.h) & (xs >= 0) & (xs < self.w)
        return mask.to(like.dtype)


def affinity(bandwidth: Tensor, features: Tensor, neighbour_features: Tensor) -> Tensor:
    # eq. 4 / eq. 7: exp(-a_p ||f_p - f_q||²), NaN -> 0
    d2 = (features - neighbour_features).square().sum(1, keepdim=True)
    w = torch.exp(-(bandwidth * d2))
    return torch.where(torch.isnan(w), torch.zeros_like(w), w)


def _spatial_sums(radiance: Tensor, features: Tensor, bandwidth: Tensor, center: Tensor,
                  kernel_size: int, dilation: int) -> tuple[Tensor, Tensor]:
    # eq. 4 + 6: Σ_q w_pq L_q and Σ_q w_pq, w_pp = c_p, over a dilated k×k window
    r = _check_kernel("kernel_size", kernel_size)
    if not (isinstance(dilation, int) and dilation >= 1):
        raise ValueError(f"dilation must be an int >= 1, got {dilation!r}")
    a, c = _non_negative(bandwidth), _non_negative(center)
    num, den = c * radiance, c
    f_win, l_win = _Window(features, r * dilation), _Window(radiance, r * dilation)
    for i in range(-r, r + 1):
        for j in range(-r, r + 1):
            if i == 0 and j == 0:
                continue
            dy, dx = i * dilation, j * dilation
            w = affinity(a, features, f_win.view(dy, dx)) * f_win.inside(dy, dx, features)
            num = num + w * l_win.view(dy, dx)
            den = den + w
    return num, den


def _temporal_sums(num: Tensor, den: Tensor, features: Tensor, prev_output: Tensor,
                   prev_features: Tensor, temporal_bandwidth: Tensor, temporal_on: Tensor,
                   temporal_kernel_size: int) -> tuple[Tensor, Tensor]:
    # eq. 7 + 8: adds Σ_q' ω_pq' W O_q' and Σ_q' ω_pq' (dilation 1) to the spatial sums
    r = _check_kernel("temporal_kernel_size", temporal_kernel_size)
    b = _non_negative(temporal_bandwidth)
    on = _non_negative(temporal_on).view(-1, 1, 1, 1)  # ω = 0 at t = 0 and after a cut
    f_win, o_win = _Window(prev_features, r), _Window(prev_output, r)
    for i in range(-r, r + 1):
        for j in range(-r, r + 1):
            omega = on * affinity(b, features, f_win.view(i, j)) * f_win.inside(i, j, features)
            num = num + omega * o_win.view(i, j)
            den = den + omega
    return num, den


def _normalise(num: Tensor, den: Tensor, eps: float) -> Tensor:
    # eq. 6 / eq. 8: num / (ε + den), never non-finite
    return torch.nan_to_num(num / (eps + den))


def spatial_math(radiance: Tensor, features: Tensor, bandwidth: Tensor, center: Tensor,
                 kernel_size: int, dilation: int, eps: float = EPSILON) -> Tensor:
    """eq. 4 + 6 in plain autograd-able torch (what spatial_affinity_filter computes)."""
    num, den = _spatial_sums(radiance, features, bandwidth, center, kernel_size, dilation)
    return _normalise(num, den, eps)


def temporal_math(radiance: Tensor, features: Tensor, bandwidth: Tensor, center: Tensor,
                  prev_output: Tensor, prev_features: Tensor, temporal_bandwidth: Tensor,
                  temporal_on: Tensor, kernel_size: int, dilation: int,
                  temporal_kernel_size: int, eps: float = EPSILON) -> Tensor:
    """eq. 7 + 8 in plain autograd-able torch (what temporal_affinity_filter computes)."""
    num, den = _spatial_sums(radiance, features, bandwidth, center, kernel_size, dilation)
    num, den = _temporal_sums(num, den, features, prev_output, prev_features,
                              temporal_bandwidth, temporal_on, temporal_kernel_size)
    return _normalise(num, den, eps)


def _recompute_backward(math, ctx, grad: Tensor) -> tuple[Tensor | None, ...]:
    """Gradients of `math` at the saved inputs by recomputing it under autograd."""
    tensors = [t.detach().requires_grad_(need) for t, need in
               zip(ctx.saved_tensors, ctx.needs_input_grad[:len(ctx.saved_tensors)], strict=True)]
    wanted = [t for t in tensors if t.requires_grad]
    with torch.enable_grad():
        out = math(*tensors, *ctx.settings)
        grads = iter(torch.autograd.grad(out, wanted, grad, allow_unused=True) if wanted else [])
    return tuple(next(grads) if t.requires_grad else None for t in tensors) + (None,) * len(
        ctx.settings)


@torch.library.custom_op("quietframe::affinity_filter", mutates_args=())
def spatial_affinity_filter(radiance: Tensor, features: Tensor, bandwidth: Tensor, center: Tensor,
                            kernel_size: int, dilation: int, eps: float = EPSILON) -> Tensor:
    """One dilated affinity kernel (eq. 4 + 6): out = Σ_q w_pq L_q / (ε + Σ_q w_pq).

    Exported as ai.quietframe::AffinityFilter (kernel_size becomes an int64 input)."""
    if native.enabled(radiance, features, bandwidth, center):
        return native.spatial_forward(radiance, features, bandwidth, center, kernel_size,
                                      dilation, eps)
    with torch.no_grad():
        return spatial_math(radiance, features, bandwidth, center, kernel_size, dilation, eps)


@spatial_affinity_filter.register_fake
def _spatial_fake(radiance: Tensor, features: Tensor, bandwidth: Tensor, center: Tensor,
                  kernel_size: int, dilation: int, eps: float = EPSILON) -> Tensor:
    _check_kernel("kernel_size", kernel_size)
    return torch.empty_like(radiance)


def _spatial_setup(ctx, inputs, output) -> None:
    ctx.save_for_backward(*inputs[:4])
    ctx.settings = inputs[4:]


def _native_backward(backward, ctx, grad: Tensor) -> tuple[Tensor | None, ...]:
    """The native gradients, None where no input needs one (temporal_on never gets one)."""
    grads = backward(grad, *ctx.saved_tensors, *ctx.settings)
    needed = ctx.needs_input_grad
    return tuple(g if needed[i] else None for i, g in enumerate(grads)) + (None,) * (
        len(needed) - len(grads))


def _spatial_backward(ctx, grad: Tensor):
    if native.enabled(grad, *ctx.saved_tensors):
        return _native_backward(native.spatial_backward, ctx, grad)
    return _recompute_backward(spatial_math, ctx, grad)


spatial_affinity_filter.register_autograd(_spatial_backward, setup_context=_spatial_setup)


@torch.library.custom_op("quietframe::affinity_temporal_filter", mutates_args=())
def temporal_affinity_filter(radiance: Tensor, features: Tensor, bandwidth: Tensor,
                             center: Tensor, prev_output: Tensor, prev_features: Tensor,
                             temporal_bandwidth: Tensor, temporal_on: Tensor, kernel_size: int,
                             dilation: int, temporal_kernel_size: int,
                             eps: float = EPSILON) -> Tensor:
    """The K-th spatial kernel normalised jointly with the temporal kernel (eq. 7 + 8).

    prev_output and prev_features are already warped to this frame (W_t O_{t-1}, W_t f_{t-1});
    temporal_on (N,) is 0 on a first frame or after a cut (ω = 0), 1 otherwise.
    Exported as ai.quietframe::AffinityTemporalFilter."""
    if native.enabled(radiance, features, bandwidth, center, prev_output, prev_features,
                      temporal_bandwidth, temporal_on):
        return native.temporal_forward(radiance, features, bandwidth, center, prev_output,
                                       prev_features, temporal_bandwidth, temporal_on,
                                       kernel_size, dilation, temporal_kernel_size, eps)
    with torch.no_grad():
        return temporal_math(radiance, features, bandwidth, center, prev_output, prev_features,
                             temporal_bandwidth, temporal_on, kernel_size, dilation,
                             temporal_kernel_size, eps)


@temporal_affinity_filter.register_fake
def _temporal_fake(radiance: Tensor, features: Tensor, bandwidth: Tensor, center: Tensor,
                   prev_output: Tensor, prev_features: Tensor, temporal_bandwidth: Tensor,
                   temporal_on: Tensor, kernel_size: int, dilation: int,
                   temporal_kernel_size: int, eps: float = EPSILON) -> Tensor:
    _check_kernel("kernel_size", kernel_size)
    _check_kernel("temporal_kernel_size", temporal_kernel_size)
    return torch.empty_like(radiance)


def _temporal_setup(ctx, inputs, output) -> None:
    ctx.save_for_backward(*inputs[:8])
    ctx.settings = inputs[8:]


def _temporal_backward(ctx, grad: Tensor):
    if native.enabled(grad, *ctx.saved_tensors):
        return _native_backward(native.temporal_backward, ctx, grad)
    return _recompute_backward(temporal_math, ctx, grad)


temporal_affinity_filter.register_autograd(_temporal_backward, setup_context=_temporal_setup)
