"""Differentiable bilateral grid: splat and slice (Meng et al. 2020, supplement §5).

docs/grid-math.md is the spec; this module and the C++ onnxruntime ops in export/ops implement it
to the letter and are held to each other by parity tests. How the work is laid out:

- every pixel touches 8 cells, 2 per axis (eq. 10); `corners` builds their flat cell indices once
  per call, and a corner's tent weights from per-axis factors when a pass needs them;
- splat scatter-adds the pixels into a zeroed flat grid, slice gathers from it, one corner at a
  time: vectorised over all pixels, with temporaries of image size (not 8× image size);
- the backward passes are the closed forms of supplement §5 (eq. 9–32), not autograd through
  the forward, so the custom ops stay opaque to torch.export and map 1:1 onto the ONNX ops
  ai.quietframe::BilateralSplat / BilateralSlice.

Tensors: image (N, C, H, W), guide (N, 1, H, W), grid (N, C, D, GH, GW), weight (N, 1, D, GH, GW).
"""

import functools
import math
import operator
from typing import NamedTuple

import torch
from torch import Tensor

TENT_EPSILON = 1e-7  # eq. 5: |a|* = sqrt(a² + ε)
GUIDE_LEVELS = 255.0  # the guide in [0, 1] spans 256 levels: cz = 255 · g / σr


# ---------------------------------------------------------------------------------------------
# Grid geometry
# ---------------------------------------------------------------------------------------------


def grid_cells(n: int, rate: int | float) -> int:
    """Cells along an axis of n pixels sampled at `rate` (GW, GH): floor((n-0.5)/rate-0.5) + 3.

    Integer rates use the exact integer form, which also works on torch.export's symbolic sizes.
    """
    if isinstance(rate, int):
        return (2 * n - 1 - rate) // (2 * rate) + 3
    return math.floor((n - 0.5) / rate - 0.5) + 3


def range_cells(sigma_r: float) -> int:
    """Range cells D for a guide in [0, 1] mapped to 256 levels at range rate sigma_r."""
    return math.floor(GUIDE_LEVELS / sigma_r - 0.5) + 3


# ---------------------------------------------------------------------------------------------
# Tent weights and the 8 corners of each pixel
# ---------------------------------------------------------------------------------------------


def tent(d: Tensor) -> Tensor:
    # eq. 4–5: tent = max(1 - sqrt(d² + ε), 0)
    return (1 - torch.sqrt(d * d + TENT_EPSILON)).clamp_min_(0)


def tent_slope(d: Tensor) -> Tensor:
    # eq. 17, 19 (∂tent/∂γ): -d / sqrt(d² + ε) inside the tent's support, 0 outside
    root = torch.sqrt(d * d + TENT_EPSILON)
    return torch.where(root < 1, -d / root, 0)


class Corners(NamedTuple):
    """The 8 cells each pixel touches (eq. 10), factored into a range and a spatial part.

    Corner k = 4·a + 2·b + c is range cell a, row b, column c of the pixel's 2×2×2 block. The
    indices are built once per call (every pass reads them); the (N, 1, P) weights of a corner
    are formed on demand from the factors, which is one multiply.
    """

    cell: Tensor  # (8, N, 1, P) int64: flat cell index inside one (D, GH, GW) block
    z_weight: Tensor  # (N, 2, P) tent_z of both range cells
    z_slope: Tensor | None  # (N, 2, P) ∂tent_z/∂g, only when gradients are wanted
    xy_weight: Tensor  # (4, P) tent_y · tent_x

    def index(self, k: int) -> Tensor:
        return self.cell[k]

    def weight(self, k: int) -> Tensor:
        # t = tent_z · tent_y · tent_x
        a, b = divmod(k, 4)
        return self.z_weight[:, a : a + 1] * self.xy_weight[b]

    def slope(self, k: int) -> Tensor:
        # t' = ∂tent_z/∂g · tent_y · tent_x
        a, b = divmod(k, 4)
        return self.z_slope[:, a : a + 1] * self.xy_weight[b]


def sanitize_guide(guide: Tensor) -> Tensor:
    """NaN counts as 0, then clamp to [0, 1] (±Inf land on the bounds)."""
    return torch.nan_to_num(guide, nan=0.0).clamp_(0, 1)


def sanitize_image(image: Tensor) -> Tensor:
    """Non-finite radiance counts as 0: an overflowed or failed sample carries no estimate."""
    return torch.where(torch.isfinite(image), image, 0)


@functools.lru_cache(maxsize=64)
def _spatial_axis(
    n: int, sigma_s: int, dtype: torch.dtype, device: torch.device
) -> tuple[Tensor, Tensor]:
    """Storage indices (2, n) and tent weights (2, n) of the 2 cells of each pixel of an axis.

    Data-independent, so cached (a few KB per axis). u0 = floor(cx - 0.5) in exact integer
    form; weights computed in float64, the cast to `dtype` being their only rounding.
    """
    with torch.inference_mode(False), torch.no_grad():
        x = torch.arange(n, device=device, dtype=torch.int64)
        u0 = torch.div(2 * x + 1 - sigma_s, 2 * sigma_s, rounding_mode="floor")
        cx = (x.double() + 0.5) / sigma_s
        d = torch.stack((cx - (u0 + 0.5), cx - (u0 + 1.5)))
        return torch.stack((u0 + 1, u0 + 2)), tent(d).to(dtype)


def corners(
    guide: Tensor,
    shape: tuple[int, int, int],
    sigma_s: int,
    sigma_r: float,
    dtype: torch.dtype,
    slope: bool = False,
) -> Corners:
    """Cells and tent weights of every pixel of `guide` in a grid of `shape` = (D, GH, GW)."""
    n, _, h, w = guide.shape
    depth, gh, gw = shape
    iy, wy = _spatial_axis(h, sigma_s, dtype, guide.device)  # (2, H) each
    ix, wx = _spatial_axis(w, sigma_s, dtype, guide.device)  # (2, W) each
    # Spatial corner (b, c) = 2·b + c: row b, column c, (4, P).
    xy_index = (iy[:, None, :, None] * gw + ix[None, :, None, :]).view(4, h * w)
    xy_weight = (wy[:, None, :, None] * wx[None, :, None, :]).view(4, h * w)

    # Range part: cz = 255 · g / σr, no +0.5 bias on the guide (a value, not a pixel index).
    g = guide.reshape(n, 1, h * w).to(dtype)
    cz = GUIDE_LEVELS * sanitize_guide(g) / sigma_r
    # The clamp only guards float rounding: for g in [0, 1] the exact floor is in [-1, D-3].
    w0 = torch.floor(cz - 0.5).clamp_(-1, depth - 3)
    dz = torch.cat((cz - (w0 + 0.5), cz - (w0 + 1.5)), dim=1)  # (N, 2, P)
    z_index = (w0.to(torch.int64) + 1) * (gh * gw)  # (N, 1, P)
    cell = z_index.new_empty(2, 4, n, 1, h * w)
    torch.add(z_index, xy_index[:, None, None, :], out=cell[0])
    torch.add(cell[0], gh * gw, out=cell[1])  # the upper range cell, one plane further
    z_slope = None
    if slope:
        # ∂cz/∂g = 255/σr strictly inside (0, 1); 0 where the clamp is active (and for NaN).
        inside = (g > 0) & (g < 1)
        z_slope = tent_slope(dz) * torch.where(inside, GUIDE_LEVELS / sigma_r, 0)
    return Corners(cell.view(8, n, 1, h * w), tent(dz), z_slope, xy_weight)


def _gather(cells: Tensor, index: Tensor) -> Tensor:
    """Read cells (N, C, cells) at one corner's index (N, 1, P): (N, C, P)."""
    n, c = cells.shape[:2]
    # The index is expanded (stride 0) over C: one int64 index serves all channels.
    return torch.gather(cells, 2, index.expand(n, c, -1))


def _scatter_add(cells: Tensor, index: Tensor, values: Tensor) -> None:
    """Add one corner's values (N, C, P) into cells (N, C, cells) at index (N, 1, P)."""
    n, c = cells.shape[:2]
    cells.scatter_add_(2, index.expand(n, c, -1), values)


def _check(op: str, ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(f"{op}: {message}")


def _check_rates(op: str, sigma_s: int, sigma_r: float) -> None:
    _check(
        op,
        isinstance(sigma_s, int) and sigma_s >= 1,
        f"sigma_s must be an int >= 1, got {sigma_s!r}",
    )
    _check(op, math.isfinite(sigma_r) and sigma_r > 0, f"sigma_r must be > 0, got {sigma_r!r}")


def _check_guide(op: str, guide: Tensor, n: int) -> None:
    _check(
        op,
        guide.dim() == 4 and guide.shape[:2] == (n, 1),
        f"guide must be (N={n}, 1, H, W), got {tuple(guide.shape)}",
    )


# ---------------------------------------------------------------------------------------------
# Splat (eq. 2, 6–8)
# ---------------------------------------------------------------------------------------------


def splat_sums(image: Tensor, cs: Corners, cells: int) -> tuple[Tensor, Tensor]:
    # eq. 6–7: α[c, cell] = Σ_p t(p, cell) · image[c, p], (N, C, cells);
    #          β[cell] = Σ_p t(p, cell), (N, 1, cells)
    n, c = image.shape[:2]
    flat = image.flatten(2)
    alpha = image.new_zeros(n, c, cells)
    beta = image.new_zeros(n, 1, cells)
    for k in range(8):
        index, t = cs.index(k), cs.weight(k)
        _scatter_add(alpha, index, flat * t)
        _scatter_add(beta, index, t)
    return alpha, beta


def grid_values(alpha: Tensor, beta: Tensor) -> Tensor:
    # eq. 8 (and 2): grid = α / β where β > 0, else 0; in place on α, which is ours (one
    # reciprocal per cell serves all channels)
    return alpha.mul_(_reciprocal_where_positive(beta))


def _reciprocal_where_positive(x: Tensor) -> Tensor:
    """1/x where x > 0, else 0 (x is a sum of tent weights, never negative)."""
    return torch.where(x > 0, 1 / x, 0)


def splat_forward(
    image: Tensor, guide: Tensor, sigma_s: int = 4, sigma_r: float = 4.0
) -> tuple[Tensor, Tensor]:
    """Splat `image` into a bilateral grid along `guide`: (grid, weight). No autograd."""
    op = "bilateral_splat"
    _check(
        op,
        image.dim() == 4 and image.is_floating_point(),
        f"image must be a float (N, C, H, W) tensor, got {image.dtype} {tuple(image.shape)}",
    )
    n, c, h, w = image.shape
    _check_guide(op, guide, n)
    _check(
        op,
        guide.shape[2:] == image.shape[2:],
        f"guide {tuple(guide.shape)} and image {tuple(image.shape)} differ in H, W",
    )
    _check_rates(op, sigma_s, sigma_r)
    shape = (range_cells(sigma_r), grid_cells(h, sigma_s), grid_cells(w, sigma_s))
    cells = math.prod(shape)
    cs = corners(guide, shape, sigma_s, sigma_r, image.dtype)
    alpha, beta = splat_sums(sanitize_image(image), cs, cells)
    return grid_values(alpha, beta).view(n, c, *shape), beta.view(n, 1, *shape)


# ---------------------------------------------------------------------------------------------
# Slice (eq. 20–23)
# ---------------------------------------------------------------------------------------------


def occupied_cells(grid: Tensor, weight: Tensor) -> Tensor:
    # eq. 20 [qf]: [grid · m, m] side by side, (N, C+1, cells), m = 1[weight > 0]: empty is
    # decided by the splat weight (the supplement's 1[grid > 0] drops black and negative
    # radiance), and an empty cell is skipped whatever it holds
    n, c = grid.shape[:2]
    occupied = weight.flatten(2) > 0
    cells = grid.new_empty(n, c + 1, occupied.shape[-1])
    torch.where(occupied, grid.flatten(2), grid.new_zeros(()), out=cells[:, :c])
    cells[:, c:] = occupied
    return cells


def slice_sums(cells: Tensor, cs: Corners, slope: bool = False) -> tuple[Tensor, Tensor | None]:
    # eq. 21–22: [μ, η] = Σ_cells t · [grid · m, m], (N, C+1, P); with `slope` also
    # eq. 31–32: [∂μ/∂g, ∂η/∂g] = Σ_cells t' · [grid · m, m], from the same reads
    sums = cells.new_zeros(*cells.shape[:2], cs.cell.shape[-1])
    slopes = torch.zeros_like(sums) if slope else None
    for k in range(8):
        values = _gather(cells, cs.index(k))
        sums.addcmul_(values, cs.weight(k))
        if slopes is not None:
            slopes.addcmul_(values, cs.slope(k))
    return sums, slopes


def slice_values(sums: Tensor) -> Tensor:
    # eq. 23: out = μ / η where η > 0, else 0, (N, C, P)
    return sums[:, :-1] * _reciprocal_where_positive(sums[:, -1:])


def _check_slice(grid: Tensor, weight: Tensor, guide: Tensor, sigma_s: int, sigma_r: float):
    op = "bilateral_slice"
    _check(
        op,
        grid.dim() == 5 and grid.is_floating_point(),
        f"grid must be a float (N, C, D, GH, GW) tensor, got {grid.dtype} {tuple(grid.shape)}",
    )
    n, _, depth, gh, gw = grid.shape
    _check(
        op,
        weight.shape == (n, 1, depth, gh, gw),
        f"weight must be (N, 1, D, GH, GW) = {(n, 1, depth, gh, gw)}, got {tuple(weight.shape)}",
    )
    _check_guide(op, guide, n)
    _check_rates(op, sigma_s, sigma_r)
    h, w = guide.shape[2:]
    expected = (range_cells(sigma_r), grid_cells(h, sigma_s), grid_cells(w, sigma_s))
    _check(
        op,
        (depth, gh, gw) == expected,
        f"grid (D, GH, GW) = {(depth, gh, gw)} does not fit a {h}x{w} guide at sigma_s="
        f"{sigma_s}, sigma_r={sigma_r}: expected {expected}",
    )


def slice_forward(
    grid: Tensor, weight: Tensor, guide: Tensor, sigma_s: int = 4, sigma_r: float = 4.0
) -> Tensor:
    """Read `grid` back at every pixel along `guide`: (N, C, H, W). No autograd."""
    _check_slice(grid, weight, guide, sigma_s, sigma_r)
    n, c, *shape = grid.shape
    h, w = guide.shape[2:]
    cs = corners(guide, tuple(shape), sigma_s, sigma_r, grid.dtype)
    sums, _ = slice_sums(occupied_cells(grid, weight), cs)
    return slice_values(sums).view(n, c, h, w)


# ---------------------------------------------------------------------------------------------
# Backward (supplement §5): splat eq. 9–19, slice eq. 24–32
# ---------------------------------------------------------------------------------------------


def splat_image_grad(grad_per_weight: Tensor, cs: Corners, image: Tensor) -> Tensor:
    # eq. 9–14: ∂L/∂image[c,p] = Σ_cells t(p, cell) · ∂L/∂grid[c,cell] / β[cell]
    n, c, h, w = image.shape
    grad = image.new_zeros(n, c, h * w)
    for k in range(8):
        grad.addcmul_(_gather(grad_per_weight, cs.index(k)), cs.weight(k))
    # Non-finite inputs were replaced by a constant: no gradient flows to them.
    return grad.view(n, c, h, w).masked_fill_(~torch.isfinite(image), 0)


def splat_guide_grad(grad_cells: Tensor, cs: Corners, image: Tensor) -> Tensor:
    # eq. 15–19: ∂L/∂g(p) = Σ_cells t' · (Σ_c (image[c,p] - grid[c,cell]) · ∂L/∂grid / β
    #                                      + ∂L/∂β[cell])
    # grad_cells (N, C+1, cells) = [∂L/∂grid / β, ∂L/∂β - Σ_c grid · ∂L/∂grid / β]: the bracket
    # is then Σ over those C+1 channels of grad_cells · [image, 1], one gather per corner.
    n, c, h, w = image.shape
    pixel = image.new_ones(n, c + 1, h * w)
    pixel[:, :c] = sanitize_image(image).view(n, c, h * w)
    grad = image.new_zeros(n, 1, h * w)
    for k in range(8):
        bracket = (_gather(grad_cells, cs.index(k)) * pixel).sum(1, keepdim=True)
        grad.addcmul_(bracket, cs.slope(k))
    return grad.view(n, 1, h, w)


def splat_backward(
    grad_grid: Tensor | None,
    grad_weight: Tensor | None,
    image: Tensor,
    guide: Tensor,
    grid: Tensor,
    weight: Tensor,
    sigma_s: int = 4,
    sigma_r: float = 4.0,
    need_image: bool = True,
    need_guide: bool = True,
) -> tuple[Tensor | None, Tensor | None]:
    """Gradients of a loss w.r.t. splat's image and guide, given those w.r.t. grid and weight.

    weight = β depends on the guide too (eq. 19: ∂β/∂g = t'), so a loss that uses the weight
    output directly gets that path as well; a missing gradient (None) counts as zero.
    """
    n, c, *shape = grid.shape
    cs = corners(guide, tuple(shape), sigma_s, sigma_r, grid.dtype, slope=need_guide)
    inv_beta = _reciprocal_where_positive(weight.flatten(2))
    grad_cells = grid.new_zeros(n, c + 1, inv_beta.shape[-1])
    grad_per_weight = grad_cells[:, :c]  # ∂L/∂grid / β, 0 in empty cells
    if grad_grid is not None:
        torch.mul(grad_grid.flatten(2), inv_beta, out=grad_per_weight)
    grad_image = splat_image_grad(grad_per_weight, cs, image) if need_image else None
    grad_guide = None
    if need_guide:
        per_cell = grad_cells[:, c:]
        torch.sum(grid.flatten(2) * grad_per_weight, 1, keepdim=True, out=per_cell)
        per_cell.neg_()
        if grad_weight is not None:
            per_cell += grad_weight.flatten(2)
        grad_guide = splat_guide_grad(grad_cells, cs, image).to(guide.dtype)
    return grad_image, grad_guide


def slice_grid_grad(grad_scaled: Tensor, occupied: Tensor, cs: Corners) -> Tensor:
    # eq. 24–28: ∂L/∂grid[c,cell] = m(cell) · Σ_p t(p, cell) · ∂L/∂out[c,p] / η[p]
    n, c = grad_scaled.shape[:2]
    grad = grad_scaled.new_zeros(n, c, occupied.shape[-1])
    for k in range(8):
        _scatter_add(grad, cs.index(k), grad_scaled * cs.weight(k))
    return grad.mul_(occupied)  # m depends on the cell only: applied once, after the sum


def slice_guide_grad(grad_scaled: Tensor, slopes: Tensor, out: Tensor) -> Tensor:
    # eq. 29–30: ∂L/∂g(p) = Σ_c ∂L/∂out / η · (∂μ/∂g - out · ∂η/∂g), slopes from eq. 31–32
    return (grad_scaled * (slopes[:, :-1] - out * slopes[:, -1:])).sum(1, keepdim=True)


def slice_backward(
    grad_out: Tensor,
    grid: Tensor,
    weight: Tensor,
    guide: Tensor,
    sigma_s: int = 4,
    sigma_r: float = 4.0,
    need_grid: bool = True,
    need_guide: bool = True,
) -> tuple[Tensor | None, Tensor | None]:
    """Gradients of a loss w.r.t. slice's grid and guide, given those w.r.t. its output.

    The weight only decides the mask, which is piecewise constant: it gets no gradient.
    """
    n, c, *shape = grid.shape
    h, w = guide.shape[2:]
    cs = corners(guide, tuple(shape), sigma_s, sigma_r, grid.dtype, slope=need_guide)
    cells = occupied_cells(grid, weight)
    sums, slopes = slice_sums(cells, cs, slope=need_guide)
    # ∂L/∂out / η; 0 where nothing was read (the output there is the constant 0).
    grad_scaled = grad_out.reshape(n, c, h * w) * _reciprocal_where_positive(sums[:, c:])
    grad_grid = grad_guide = None
    if need_grid:
        grad_grid = slice_grid_grad(grad_scaled, cells[:, c:], cs).view(grid.shape)
    if need_guide:
        grad_guide = slice_guide_grad(grad_scaled, slopes, slice_values(sums))
        grad_guide = grad_guide.view(n, 1, h, w).to(guide.dtype)
    return grad_grid, grad_guide


# ---------------------------------------------------------------------------------------------
# Custom ops: what torch.export sees and the ONNX exporter maps to ai.quietframe ops
# ---------------------------------------------------------------------------------------------


@torch.library.custom_op("quietframe::bilateral_splat", mutates_args=())
def splat_op(image: Tensor, guide: Tensor, sigma_s: int, sigma_r: float) -> tuple[Tensor, Tensor]:
    return splat_forward(image, guide, sigma_s, sigma_r)


@splat_op.register_fake
def _splat_fake(image: Tensor, guide: Tensor, sigma_s: int, sigma_r: float):
    n, c, h, w = image.shape  # h, w may be symbolic: grid_cells stays in integer arithmetic
    shape = (range_cells(sigma_r), grid_cells(h, sigma_s), grid_cells(w, sigma_s))
    return image.new_empty((n, c, *shape)), image.new_empty((n, 1, *shape))


def _splat_setup_context(ctx, inputs, output) -> None:
    image, guide, sigma_s, sigma_r = inputs
    ctx.save_for_backward(image, guide, *output)
    ctx.rates = (sigma_s, sigma_r)


def _splat_autograd(ctx, grad_grid: Tensor | None, grad_weight: Tensor | None):
    image, guide, grid, weight = ctx.saved_tensors
    need_image, need_guide = ctx.needs_input_grad[:2]
    grads = splat_backward(
        grad_grid,
        grad_weight,
        image,
        guide,
        grid,
        weight,
        *ctx.rates,
        need_image=need_image,
        need_guide=need_guide,
    )
    return *grads, None, None


splat_op.register_autograd(_splat_autograd, setup_context=_splat_setup_context)


@torch.library.custom_op("quietframe::bilateral_slice", mutates_args=())
def slice_op(grid: Tensor, weight: Tensor, guide: Tensor, sigma_s: int, sigma_r: float) -> Tensor:
    return slice_forward(grid, weight, guide, sigma_s, sigma_r)


@slice_op.register_fake
def _slice_fake(grid: Tensor, weight: Tensor, guide: Tensor, sigma_s: int, sigma_r: float):
    n, c = grid.shape[:2]
    return grid.new_empty((n, c, *guide.shape[2:]))


def _slice_setup_context(ctx, inputs, output) -> None:
    grid, weight, guide, sigma_s, sigma_r = inputs
    ctx.save_for_backward(grid, weight, guide)
    ctx.rates = (sigma_s, sigma_r)


def _slice_autograd(ctx, grad_out: Tensor):
    grid, weight, guide = ctx.saved_tensors
    need_grid, need_guide = ctx.needs_input_grad[0], ctx.needs_input_grad[2]
    grad_grid, grad_guide = slice_backward(
        grad_out, grid, weight, guide, *ctx.rates, need_grid=need_grid, need_guide=need_guide
    )
    return grad_grid, None, grad_guide, None, None


slice_op.register_autograd(_slice_autograd, setup_context=_slice_setup_context)


# ---------------------------------------------------------------------------------------------
# Public entry points (differentiable, exportable)
# ---------------------------------------------------------------------------------------------


def bilateral_splat(
    image: Tensor, guide: Tensor, sigma_s: int = 4, sigma_r: float = 4.0
) -> tuple[Tensor, Tensor]:
    """(grid (N, C, D, GH, GW), weight (N, 1, D, GH, GW)) of `image` splatted along `guide`."""
    return splat_op(image, guide, operator.index(sigma_s), float(sigma_r))


def bilateral_slice(
    grid: Tensor, weight: Tensor, guide: Tensor, sigma_s: int = 4, sigma_r: float = 4.0
) -> Tensor:
    """(N, C, H, W) image read from `grid` along `guide`; empty cells (weight 0) are skipped."""
    return slice_op(grid, weight, guide, operator.index(sigma_s), float(sigma_r))


def bilateral_filter(
    image: Tensor, guide: Tensor, sigma_s: int = 4, sigma_r: float = 4.0
) -> Tensor:
    """Edge-aware smoothing of `image`: splat and slice along the same guide."""
    grid, weight = bilateral_splat(image, guide, sigma_s, sigma_r)
    return bilateral_slice(grid, weight, guide, sigma_s, sigma_r)
