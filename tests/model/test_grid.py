"""quietframe.model.grid against an independent dense reference of docs/grid-math.md.

The reference touches every cell of the grid with the tent formula (no 2-neighbour shortcut)
and is differentiated by torch autograd, so it checks the forward passes and the closed-form
backward passes (supplement eq. 9–32) independently of how the module indexes its corners.
"""

import math

import pytest
import torch

from quietframe.model.grid import (
    bilateral_filter,
    bilateral_slice,
    bilateral_splat,
    grid_cells,
    range_cells,
    slice_backward,
    slice_forward,
    splat_backward,
    splat_forward,
)

F64 = torch.float64


# ---------------------------------------------------------------------------------------------
# Dense reference, float64: all (D, GH, GW) cells for every pixel
# ---------------------------------------------------------------------------------------------


def ref_cells(n: int, rate: float) -> int:
    return math.floor((n - 0.5) / rate - 0.5) + 3


def ref_depth(sigma_r: float) -> int:
    return math.floor(255 / sigma_r - 0.5) + 3


def ref_tent(d: torch.Tensor) -> torch.Tensor:
    return torch.clamp(1 - torch.sqrt(d * d + 1e-7), min=0)


def ref_centres(count: int) -> torch.Tensor:
    """Centres of all cells of an axis: cell u (from -1) is stored at u + 1, centred at u + 0.5."""
    return torch.arange(count, dtype=F64) - 1 + 0.5


def ref_weights(guide: torch.Tensor, sigma_s: int, sigma_r: float) -> torch.Tensor:
    """t(p, cell) for all pixels and all cells: (N, H, W, D, GH, GW)."""
    n, _, h, w = guide.shape
    depth, gh, gw = ref_depth(sigma_r), ref_cells(h, sigma_s), ref_cells(w, sigma_s)
    # Pixel x sits at (x + 0.5)/σs; the guide value is not biased.
    tx = ref_tent((torch.arange(w, dtype=F64) + 0.5)[:, None] / sigma_s - ref_centres(gw))
    ty = ref_tent((torch.arange(h, dtype=F64) + 0.5)[:, None] / sigma_s - ref_centres(gh))
    cz = 255 * guide[:, 0].clamp(0, 1) / sigma_r  # (N, H, W)
    tz = ref_tent(cz[..., None] - ref_centres(depth))  # (N, H, W, D)
    return torch.einsum("nhwd,hv,wu->nhwdvu", tz, ty, tx)


def ref_splat(image, guide, sigma_s, sigma_r):
    t = ref_weights(guide, sigma_s, sigma_r)
    alpha = torch.einsum("nchw,nhwdvu->ncdvu", image, t)
    beta = t.sum((1, 2))[:, None]
    grid = torch.where(beta > 0, alpha / torch.where(beta > 0, beta, 1), 0)
    return grid, beta


def ref_slice(grid, weight, guide, sigma_s, sigma_r):
    tm = ref_weights(guide, sigma_s, sigma_r) * (weight[:, 0] > 0)[:, None, None]
    mu = torch.einsum("nhwdvu,ncdvu->nchw", tm, grid)
    eta = tm.sum((3, 4, 5))[:, None]
    return torch.where(eta > 0, mu / torch.where(eta > 0, eta, 1), 0)


# ---------------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------------


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def smooth_guide(shape, sigma_r: float, g: torch.Generator) -> torch.Tensor:
    """Guide in (0.05, 0.95) whose range coordinate stays >= 0.05 away from every tent kink.

    cz = k + 0.5 + f, f in [0.05, 0.95]: |d| is never near 0 (rounded tip) or 1 (support edge,
    where the pixel also switches cells), so finite differences see a smooth function.
    """
    lo = math.ceil(255 * 0.05 / sigma_r - 0.5)
    hi = math.floor(255 * 0.95 / sigma_r - 1.5)
    k = torch.randint(lo, hi + 1, shape, generator=g, dtype=F64)
    f = 0.05 + 0.9 * torch.rand(shape, generator=g, dtype=F64)
    return (k + 0.5 + f) * sigma_r / 255


def rand(*shape, g, lo=-1.0, hi=2.0, dtype=F64) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand(shape, generator=g, dtype=dtype)


def with_edges(guide: torch.Tensor) -> torch.Tensor:
    """Put exact 0 and 1 (clamp bounds) into a guide."""
    flat = guide.clone().view(-1)
    flat[0], flat[-1] = 0.0, 1.0
    return flat.view(guide.shape)


SIZES = [  # (H, W, sigma_s, sigma_r)
    (5, 7, 1, 4.0),
    (5, 7, 2, 8.0),
    (1, 1, 4, 4.0),
    (3, 5, 4, 16.0),
    (5, 7, 3, 32.0),
    (6, 4, 2, 2.5),
    (1, 6, 1, 100.0),
]
BACKWARD_SIZES = [(5, 7, 2, 8.0), (5, 7, 3, 32.0), (1, 1, 4, 4.0)]


# ---------------------------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------------------------


def test_cell_count_examples():
    assert grid_cells(1280, 4) == 322
    assert grid_cells(720, 4) == 182
    assert grid_cells(1, 4) == 2
    assert (range_cells(4.0), range_cells(8.0), range_cells(16.0)) == (66, 34, 18)


def test_integer_cell_form_equals_real_form():
    for rate in range(1, 18):
        for n in range(1, 300):
            assert grid_cells(n, rate) == ref_cells(n, rate), (n, rate)
    assert grid_cells(10, 2.5) == ref_cells(10, 2.5)


@pytest.mark.parametrize("h, w, sigma_s, sigma_r", SIZES)
def test_output_shapes(h, w, sigma_s, sigma_r):
    image = torch.zeros(2, 3, h, w)
    grid, weight = bilateral_splat(image, torch.zeros(2, 1, h, w), sigma_s, sigma_r)
    cells = (ref_depth(sigma_r), ref_cells(h, sigma_s), ref_cells(w, sigma_s))
    assert grid.shape == (2, 3, *cells) and weight.shape == (2, 1, *cells)
    assert grid.is_contiguous() and weight.is_contiguous()


# ---------------------------------------------------------------------------------------------
# Forward = dense reference
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("h, w, sigma_s, sigma_r", SIZES)
def test_splat_matches_dense_reference(h, w, sigma_s, sigma_r):
    g = gen(1)
    image = rand(2, 3, h, w, g=g)
    guide = with_edges(torch.rand(2, 1, h, w, generator=g, dtype=F64))
    grid, weight = splat_forward(image, guide, sigma_s, sigma_r)
    ref_grid, ref_weight = ref_splat(image, guide, sigma_s, sigma_r)
    torch.testing.assert_close(weight, ref_weight, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(grid, ref_grid, rtol=1e-12, atol=1e-12)
    assert (weight == 0).any()  # the test covers empty cells


@pytest.mark.parametrize("h, w, sigma_s, sigma_r", SIZES)
def test_slice_matches_dense_reference(h, w, sigma_s, sigma_r):
    g = gen(2)
    splat_guide = torch.rand(2, 1, h, w, generator=g, dtype=F64)
    grid, weight = splat_forward(rand(2, 3, h, w, g=g), splat_guide, sigma_s, sigma_r)
    guide = with_edges(torch.rand(2, 1, h, w, generator=g, dtype=F64))
    for gd in (splat_guide, guide):
        torch.testing.assert_close(
            slice_forward(grid, weight, gd, sigma_s, sigma_r),
            ref_slice(grid, weight, gd, sigma_s, sigma_r),
            rtol=1e-12,
            atol=1e-12,
        )
    # An arbitrary grid (negative values) with arbitrary empty cells.
    grid = rand(*grid.shape, g=g)
    weight = torch.rand(weight.shape, generator=g, dtype=F64) * (
        torch.rand(weight.shape, generator=g) > 0.4
    )
    torch.testing.assert_close(
        slice_forward(grid, weight, guide, sigma_s, sigma_r),
        ref_slice(grid, weight, guide, sigma_s, sigma_r),
        rtol=1e-12,
        atol=1e-12,
    )


def test_float32_matches_float64():
    g = gen(3)
    image = rand(2, 3, 19, 23, g=g)
    guide = torch.rand(2, 1, 19, 23, generator=g, dtype=F64)
    out64 = bilateral_filter(image, guide, 4, 4.0)
    out32 = bilateral_filter(image.float(), guide.float(), 4, 4.0)
    assert out32.dtype == torch.float32
    torch.testing.assert_close(out32.double(), out64, rtol=1e-5, atol=1e-5)


# ---------------------------------------------------------------------------------------------
# Backward: closed forms (eq. 9–32) = autograd of the dense reference; gradcheck of the ops
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("h, w, sigma_s, sigma_r", BACKWARD_SIZES)
def test_splat_backward_matches_dense_autograd(h, w, sigma_s, sigma_r):
    g = gen(4)
    image = rand(2, 3, h, w, g=g).requires_grad_()
    guide = smooth_guide((2, 1, h, w), sigma_r, g).requires_grad_()
    ref_grid, ref_weight = ref_splat(image, guide, sigma_s, sigma_r)
    grad_grid, grad_weight = rand(*ref_grid.shape, g=g), rand(*ref_weight.shape, g=g)
    grid, weight = splat_forward(image.detach(), guide.detach(), sigma_s, sigma_r)
    # With and without a loss on the weight output (β depends on the guide, eq. 19).
    for gw in (grad_weight, None):
        loss = (ref_grid * grad_grid).sum() + (0 if gw is None else (ref_weight * gw).sum())
        expected = torch.autograd.grad(loss, (image, guide), retain_graph=True)
        got = splat_backward(
            grad_grid, gw, image.detach(), guide.detach(), grid, weight, sigma_s, sigma_r
        )
        torch.testing.assert_close(got[0], expected[0], rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(got[1], expected[1], rtol=1e-10, atol=1e-10)
        if h * w > 1:  # a lone pixel's grid is its own value: no guide gradient via grid
            assert expected[1].abs().max() > 0.1


@pytest.mark.parametrize("h, w, sigma_s, sigma_r", BACKWARD_SIZES)
def test_slice_backward_matches_dense_autograd(h, w, sigma_s, sigma_r):
    g = gen(5)
    grid, weight = splat_forward(
        rand(2, 3, h, w, g=g), smooth_guide((2, 1, h, w), sigma_r, g), sigma_s, sigma_r
    )
    # Make some cells that the slice guide reads empty (masked) at random.
    weight = weight * (torch.rand(weight.shape, generator=g) > 0.3)
    grid = grid.requires_grad_()
    guide = smooth_guide((2, 1, h, w), sigma_r, g).requires_grad_()
    ref = ref_slice(grid, weight, guide, sigma_s, sigma_r)
    grad_out = rand(*ref.shape, g=g)
    expected = torch.autograd.grad((ref * grad_out).sum(), (grid, guide))
    got = slice_backward(grad_out, grid.detach(), weight, guide.detach(), sigma_s, sigma_r)
    torch.testing.assert_close(got[0], expected[0], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(got[1], expected[1], rtol=1e-10, atol=1e-10)


# Full Jacobians on tiny grids; a random projection (fast_mode) on a larger, odd-rate one.
GRADCHECKS = [((1, 2, 4, 5), 2, 64.0, False), ((2, 3, 7, 9), 3, 16.0, True)]


@pytest.mark.parametrize("shape, sigma_s, sigma_r, fast", GRADCHECKS)
def test_gradcheck_splat(shape, sigma_s, sigma_r, fast):
    g = gen(6)
    n, c, h, w = shape
    image = rand(*shape, g=g).requires_grad_()
    guide = smooth_guide((n, 1, h, w), sigma_r, g).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda i, q: bilateral_splat(i, q, sigma_s, sigma_r), (image, guide), fast_mode=fast
    )


@pytest.mark.parametrize("shape, sigma_s, sigma_r, fast", GRADCHECKS)
def test_gradcheck_slice(shape, sigma_s, sigma_r, fast):
    g = gen(7)
    n, c, h, w = shape
    grid, weight = splat_forward(
        rand(*shape, g=g), smooth_guide((n, 1, h, w), sigma_r, g), sigma_s, sigma_r
    )
    grid = rand(*grid.shape, g=g).requires_grad_()
    guide = smooth_guide((n, 1, h, w), sigma_r, g).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda a, q: bilateral_slice(a, weight, q, sigma_s, sigma_r), (grid, guide), fast_mode=fast
    )


def test_gradcheck_filter():
    g = gen(8)
    image = rand(2, 2, 6, 5, g=g).requires_grad_()
    guide = smooth_guide((2, 1, 6, 5), 16.0, g).requires_grad_()
    assert torch.autograd.gradcheck(lambda i, q: bilateral_filter(i, q, 2, 16.0), (image, guide))


def test_opcheck_registrations():
    """Schema, fake (meta) impl and autograd registration of both custom ops."""
    g = gen(9)
    image, guide = rand(1, 2, 6, 9, g=g), smooth_guide((1, 1, 6, 9), 32.0, g)
    image.requires_grad_(), guide.requires_grad_()
    utils = ("test_schema", "test_autograd_registration", "test_faketensor")
    torch.library.opcheck(
        torch.ops.quietframe.bilateral_splat, (image, guide, 2, 32.0), test_utils=utils
    )
    grid, weight = splat_forward(image.detach(), guide.detach(), 2, 32.0)
    grid.requires_grad_()
    torch.library.opcheck(
        torch.ops.quietframe.bilateral_slice, (grid, weight, guide, 2, 32.0), test_utils=utils
    )


# ---------------------------------------------------------------------------------------------
# Hard inputs
# ---------------------------------------------------------------------------------------------


def test_black_frame_gives_zeros():
    guide = torch.rand(2, 1, 16, 12, generator=gen(10))
    grid, weight = bilateral_splat(torch.zeros(2, 3, 16, 12), guide)
    out = bilateral_slice(grid, weight, guide)
    assert (grid == 0).all() and (out == 0).all() and (weight > 0).any()


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("value", [1.0, 0.0, -2.5, 3.7e4])
def test_constant_image_is_reproduced(dtype, value):
    g = gen(11)
    for sigma_s, sigma_r in [(4, 4.0), (2, 16.0), (8, 1.0)]:
        guide = with_edges(torch.rand(2, 1, 13, 17, generator=g, dtype=dtype))
        image = torch.full((2, 3, 13, 17), value, dtype=dtype)
        out = bilateral_filter(image, guide, sigma_s, sigma_r)
        tol = 4 * torch.finfo(dtype).eps * abs(value)
        torch.testing.assert_close(out, image, rtol=0, atol=tol)


def test_negative_radiance_stays_within_its_range():
    g = gen(12)
    image = rand(1, 3, 20, 20, g=g, lo=-5.0, hi=-1.0, dtype=torch.float32)
    out = bilateral_filter(image, torch.rand(1, 1, 20, 20, generator=g))
    assert (out <= -1.0 + 1e-6).all() and (out >= -5.0 - 1e-6).all()


def test_firefly_stays_finite_and_local():
    sigma_s, sigma_r = 4, 4.0
    g = gen(13)
    image = torch.zeros(1, 3, 48, 48)
    image[0, :, 20, 27] = 1e6
    guide = torch.rand(1, 1, 48, 48, generator=g)
    out = bilateral_filter(image, guide, sigma_s, sigma_r)
    assert torch.isfinite(out).all() and out.max() <= 1e6 and out.max() > 0
    # Support: < 2 cells between firefly and pixel on every axis (one to splat, one to slice).
    y, x = torch.meshgrid(torch.arange(48), torch.arange(48), indexing="ij")
    cz = 255 * guide[0, 0] / sigma_r
    near = ((y - 20).abs() < 2 * sigma_s) & ((x - 27).abs() < 2 * sigma_s)
    near &= (cz - cz[20, 27]).abs() < 2
    assert (out[0, :, ~near] == 0).all()
    assert (out[0, :, near] > 0).any()


def test_guide_exactly_on_the_clamp_bounds():
    image = rand(1, 3, 8, 8, g=gen(14))
    guide = torch.zeros(1, 1, 8, 8, dtype=F64)
    guide[..., 4:] = 1.0
    image.requires_grad_(), guide.requires_grad_()
    out = bilateral_filter(image, guide, 2, 4.0)
    assert torch.isfinite(out).all()
    # Pixels at g = 0 and g = 1 are 31.875 range cells apart: the two halves never mix.
    torch.testing.assert_close(
        out[..., :4],
        bilateral_filter(image[..., :4], guide[..., :4], 2, 4.0)[..., :4],
        rtol=0,
        atol=0,
    )
    (grad_guide,) = torch.autograd.grad(out.sum(), guide)
    assert (grad_guide == 0).all()  # the clamp is active at both bounds


def test_non_finite_image_counts_as_zero():
    g = gen(15)
    image = rand(1, 3, 12, 12, g=g, dtype=torch.float32)
    guide = torch.rand(1, 1, 12, 12, generator=g)
    bad = image.clone()
    bad[0, 0, 3, 4], bad[0, 1, 7, 7], bad[0, 2, 0, 11] = math.nan, math.inf, -math.inf
    clean = bad.nan_to_num(0.0, 0.0, 0.0)
    bad.requires_grad_(), guide.requires_grad_()
    out = bilateral_filter(bad, guide)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, bilateral_filter(clean, guide.detach()), rtol=0, atol=0)
    grad_image, grad_guide = torch.autograd.grad(out.square().sum(), (bad, guide))
    assert torch.isfinite(grad_image).all() and torch.isfinite(grad_guide).all()
    assert grad_image[0, 0, 3, 4] == 0 and grad_image[0, 1, 7, 7] == 0
    assert grad_image[0, 0, 3, 5] != 0


def test_non_finite_guide():
    g = gen(16)
    image = rand(1, 3, 9, 9, g=g)
    guide = torch.rand(1, 1, 9, 9, generator=g, dtype=F64)
    bad = guide.clone()
    bad[0, 0, 1, 1], bad[0, 0, 2, 2], bad[0, 0, 3, 3] = math.nan, math.inf, -math.inf
    fixed = guide.clone()
    fixed[0, 0, 1, 1], fixed[0, 0, 2, 2], fixed[0, 0, 3, 3] = 0.0, 1.0, 0.0
    out = bilateral_filter(image, bad, 2, 8.0)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, bilateral_filter(image, fixed, 2, 8.0), rtol=0, atol=0)
    bad.requires_grad_()
    (grad,) = torch.autograd.grad(bilateral_filter(image, bad, 2, 8.0).sum(), bad)
    assert torch.isfinite(grad).all() and grad[0, 0, 1, 1] == 0


def test_empty_cells_are_skipped_whatever_they_hold():
    g = gen(20)
    guide = torch.rand(1, 1, 10, 10, generator=g, dtype=F64)
    grid, weight = splat_forward(rand(1, 3, 10, 10, g=g), guide, 2, 8.0)
    empty = (weight == 0).expand_as(grid)
    assert empty.any()
    dirty = grid.masked_fill(empty, math.nan)
    dirty[:, 0].masked_fill_(empty[:, 0], math.inf)
    dirty.requires_grad_()
    read = torch.rand(1, 1, 10, 10, generator=g, dtype=F64).requires_grad_()
    out = bilateral_slice(dirty, weight, read, 2, 8.0)
    torch.testing.assert_close(out, bilateral_slice(grid, weight, read, 2, 8.0), rtol=0, atol=0)
    grad_grid, grad_read = torch.autograd.grad(out.sum(), (dirty, read))
    assert torch.isfinite(grad_grid).all() and torch.isfinite(grad_read).all()
    assert (grad_grid[empty] == 0).all()


def test_huge_values_stay_finite_in_float32():
    g = gen(17)
    image = rand(1, 3, 32, 32, g=g, lo=-1e30, hi=1e30, dtype=torch.float32)
    guide = torch.rand(1, 1, 32, 32, generator=g)
    for sigma_s in (4, 16):
        out = bilateral_filter(image, guide, sigma_s, 4.0)
        assert torch.isfinite(out).all()
        ref = bilateral_filter(image.double(), guide.double(), sigma_s, 4.0)
        torch.testing.assert_close(out.double(), ref, rtol=1e-4, atol=1e25)


def test_any_batch_and_channel_count():
    g = gen(18)
    for n, c in [(0, 3), (1, 1), (3, 5)]:
        image = rand(n, c, 4, 6, g=g)
        guide = torch.rand(n, 1, 4, 6, generator=g, dtype=F64)
        out = bilateral_filter(image, guide, 2, 8.0)
        assert out.shape == image.shape
        for i in range(n):  # images of a batch do not interact
            torch.testing.assert_close(
                out[i : i + 1],
                bilateral_filter(image[i : i + 1], guide[i : i + 1], 2, 8.0),
                rtol=0,
                atol=0,
            )


def test_rejects_mismatched_shapes():
    image, guide = torch.zeros(1, 3, 8, 8), torch.zeros(1, 1, 8, 8)
    with pytest.raises(ValueError, match="bilateral_splat"):
        bilateral_splat(image, torch.zeros(1, 1, 8, 9))
    with pytest.raises(ValueError, match="sigma_r"):
        bilateral_splat(image, guide, 4, 0.0)
    grid, weight = bilateral_splat(image, guide)
    with pytest.raises(ValueError, match="bilateral_slice"):
        bilateral_slice(grid, weight, torch.zeros(1, 1, 16, 8))


# ---------------------------------------------------------------------------------------------
# torch.export with dynamic H, W (the fake impls must work on symbolic sizes)
# ---------------------------------------------------------------------------------------------


class _SplatSlice(torch.nn.Module):
    def forward(self, image: torch.Tensor, guide: torch.Tensor):
        grid, weight = bilateral_splat(image, guide, 4, 8.0)
        return bilateral_slice(grid, weight, guide, 4, 8.0), grid


def test_export_with_dynamic_height_and_width():
    g = gen(19)
    height, width = (
        torch.export.Dim("height", min=1, max=4096),
        torch.export.Dim("width", min=1, max=4096),
    )
    dims = {2: height, 3: width}
    program = torch.export.export(
        _SplatSlice(),
        (torch.rand(1, 3, 9, 14, generator=g), torch.rand(1, 1, 9, 14, generator=g)),
        dynamic_shapes={"image": dims, "guide": dims},
    )
    targets = {node.target for node in program.graph.nodes if node.op == "call_function"}
    assert torch.ops.quietframe.bilateral_splat.default in targets
    assert torch.ops.quietframe.bilateral_slice.default in targets
    for h, w in [(9, 14), (37, 21), (1, 1)]:
        image, guide = torch.rand(1, 3, h, w, generator=g), torch.rand(1, 1, h, w, generator=g)
        out, grid = program.module()(image, guide)
        assert grid.shape == (1, 3, range_cells(8.0), grid_cells(h, 4), grid_cells(w, 4))
        torch.testing.assert_close(out, bilateral_filter(image, guide, 4, 8.0), rtol=0, atol=0)
