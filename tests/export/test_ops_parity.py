"""Parity: the C++ onnxruntime ops (export/ops) against the PyTorch reference quietframe.model.grid,
and both against a small independent numpy transcription of docs/grid-math.md on tiny inputs.

Criterion (docs/grid-math.md: "parity tests hold them to 1e-5 relative"):
    assert_allclose(ours, reference, rtol=1e-5, atol=1e-5 * max|reference|)
Both sides compute the same tent weights in float32 but sum them in different orders, so each
output carries float32 rounding of order 1e-7 times the magnitude of the terms it sums. Where
terms of mixed sign (negative radiance) or of very different size (a firefly next to dim pixels)
cancel, that absolute error is large relative to the small result; a purely element-wise rtol
would then test the rounding, not the math. Hence the absolute floor tied to the tensor's scale,
and rtol for everything else. Masks must agree exactly: which cells are empty (weight == 0).
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from ops_support import SCALES, attrs_for, make_session, op_model

from quietframe.runtime.ops_library import ops_library_path

torch = pytest.importorskip("torch")
grid_ref = pytest.importorskip("quietframe.model.grid")

ALL_SCALES = [*SCALES, (3, 5.5)]  # and an odd rate pair: divisions that are not exact


@pytest.fixture(scope="session")
def ops_library() -> str:
    """The built library: next to the installed package, or QUIETFRAME_OPS_LIBRARY."""
    return str(ops_library_path())


@pytest.fixture(scope="session")
def session_for(ops_library):
    """session_for(model_bytes, threads=2) -> InferenceSession with our ops registered."""
    return functools.partial(make_session, ops_library)


def assert_parity(ours: np.ndarray, reference: np.ndarray, what: str) -> None:
    assert ours.shape == reference.shape, what
    assert np.isfinite(ours).all(), f"{what}: non-finite output"
    scale = float(np.abs(reference).max()) if reference.size else 0.0
    np.testing.assert_allclose(ours, reference, rtol=1e-5, atol=1e-5 * scale, err_msg=what)


class Ops:
    """Splat and slice through onnxruntime, sessions cached per (σs, σr)."""

    def __init__(self, session_for):
        self.session_for = session_for
        self.sessions = {}

    def session(self, op, sigma_s, sigma_r):
        key = (op, sigma_s, sigma_r)
        if key not in self.sessions:
            self.sessions[key] = self.session_for(op_model(op, **attrs_for(sigma_s, sigma_r)))
        return self.sessions[key]

    def splat(self, image, guide, sigma_s, sigma_r):
        return self.session("BilateralSplat", sigma_s, sigma_r).run(
            None, {"image": image, "guide": guide})

    def slice(self, grid, weight, guide, sigma_s, sigma_r):
        return self.session("BilateralSlice", sigma_s, sigma_r).run(
            None, {"grid": grid, "weight": weight, "guide": guide})[0]


@pytest.fixture(scope="module")
def ops(session_for):
    return Ops(session_for)


def torch_splat(image, guide, sigma_s, sigma_r):
    grid, weight = grid_ref.splat_forward(torch.from_numpy(image), torch.from_numpy(guide),
                                          sigma_s, sigma_r)
    return grid.numpy(), weight.numpy()


def torch_slice(grid, weight, guide, sigma_s, sigma_r):
    return grid_ref.slice_forward(torch.from_numpy(grid), torch.from_numpy(weight),
                                  torch.from_numpy(guide), sigma_s, sigma_r).numpy()


def check_against_torch(ops, image, guide, sigma_s, sigma_r, slice_guide=None):
    """Splat and slice parity; the slice of both sides reads the same (our) grid."""
    slice_guide = guide if slice_guide is None else slice_guide
    grid, weight = ops.splat(image, guide, sigma_s, sigma_r)
    ref_grid, ref_weight = torch_splat(image, guide, sigma_s, sigma_r)
    tag = f"sigma=({sigma_s}, {sigma_r}) image {image.shape}"
    np.testing.assert_array_equal(weight > 0, ref_weight > 0, err_msg=f"{tag}: empty cells")
    assert_parity(weight, ref_weight, f"{tag}: weight")
    assert_parity(grid, ref_grid, f"{tag}: grid")
    out = ops.slice(grid, weight, slice_guide, sigma_s, sigma_r)
    assert_parity(out, torch_slice(grid, weight, slice_guide, sigma_s, sigma_r), f"{tag}: slice")
    return grid, weight, out


# ---- random inputs ----------------------------------------------------------------------------


@pytest.mark.parametrize("sigma_s,sigma_r", ALL_SCALES)
@pytest.mark.parametrize("shape", [(1, 3, 1, 1), (1, 3, 3, 5), (2, 3, 37, 53), (1, 1, 37, 53),
                                   (2, 5, 23, 17), (1, 3, 72, 128)])
def test_random_inputs(ops, sigma_s, sigma_r, shape):
    rng = np.random.default_rng(sum(shape) + sigma_s)
    n, c, h, w = shape
    image = (rng.standard_normal(shape) * 2 + 1).astype(np.float32)  # mixed sign
    guide = rng.random((n, 1, h, w), dtype=np.float32)
    other = rng.random((n, 1, h, w), dtype=np.float32)  # slice along another guide: masks matter
    check_against_torch(ops, image, guide, sigma_s, sigma_r)
    check_against_torch(ops, image, guide, sigma_s, sigma_r, slice_guide=other)


@pytest.mark.parametrize("sigma_s,sigma_r", SCALES)
def test_smooth_guide_full_frame_width(ops, sigma_s, sigma_r):
    """A smooth guide on a wide frame: the slice copies only the grid blocks it reads."""
    h, w = 45, 1280
    yy, xx = np.mgrid[0:h, 0:w] / w
    rng = np.random.default_rng(5)
    guide = np.clip(0.5 + 0.4 * np.sin(7 * xx + 3 * yy) + 0.02 * rng.standard_normal((h, w)),
                    0, 1)[None, None].astype(np.float32)
    image = rng.lognormal(0, 1, (1, 3, h, w)).astype(np.float32)
    shifted = np.clip(guide + 0.05, 0, 1).astype(np.float32)
    check_against_torch(ops, image, guide, sigma_s, sigma_r)
    check_against_torch(ops, image, guide, sigma_s, sigma_r, slice_guide=shifted)


# ---- hard inputs (docs/grid-math.md, "Hard inputs") ---------------------------------------------


@pytest.mark.parametrize("sigma_s,sigma_r", SCALES)
@pytest.mark.parametrize("h,w", [(1, 1), (3, 5), (37, 53)])
def test_hard_inputs(ops, sigma_s, sigma_r, h, w):
    rng = np.random.default_rng(h * w)
    guide = rng.random((1, 1, h, w), dtype=np.float32)

    black = np.zeros((1, 3, h, w), np.float32)
    grid, weight, out = check_against_torch(ops, black, guide, sigma_s, sigma_r)
    assert not grid.any() and not out.any() and (weight > 0).any()

    firefly = rng.random((1, 3, h, w), dtype=np.float32)
    firefly[0, :, h // 2, w // 2] = 1e6
    check_against_torch(ops, firefly, guide, sigma_s, sigma_r)

    negative = -rng.random((1, 3, h, w), dtype=np.float32) * 5
    _, _, out = check_against_torch(ops, negative, guide, sigma_s, sigma_r)
    assert (out < 0).all()  # no clamping of radiance, empty cells decided by the weight

    huge = (rng.random((1, 3, h, w)) * 2e30 - 1e30).astype(np.float32)
    check_against_torch(ops, huge, guide, sigma_s, sigma_r)

    for value in (0.0, 1.0):  # guide exactly at the ends of its range
        flat = np.full((1, 1, h, w), value, np.float32)
        check_against_torch(ops, firefly, flat, sigma_s, sigma_r)
    ends = np.where(rng.random((1, 1, h, w)) < 0.5, 0.0, 1.0).astype(np.float32)
    check_against_torch(ops, negative, ends, sigma_s, sigma_r)


@pytest.mark.parametrize("sigma_s,sigma_r", SCALES)
def test_non_finite_inputs_are_sanitised(ops, sigma_s, sigma_r):
    rng = np.random.default_rng(7)
    h, w = 37, 53
    image = rng.random((1, 3, h, w), dtype=np.float32)
    bad = rng.random((1, 3, h, w)) < 0.05
    image[bad] = rng.choice(np.array([np.nan, np.inf, -np.inf], np.float32), bad.sum())
    guide = rng.random((1, 1, h, w), dtype=np.float32)
    guide[0, 0, ::7, ::5] = np.nan
    guide[0, 0, 3::11, ::3] = np.inf
    guide[0, 0, 5::13, 1::4] = -np.inf
    grid, weight, out = check_against_torch(ops, image, guide, sigma_s, sigma_r)
    assert np.isfinite(grid).all() and np.isfinite(weight).all() and np.isfinite(out).all()
    # Non-finite radiance counts as 0, a NaN guide as 0, ±Inf guides land on 1 and 0.
    clean = np.where(np.isfinite(image), image, 0).astype(np.float32)
    guide_clean = np.clip(np.nan_to_num(guide, nan=0.0), 0, 1).astype(np.float32)
    expected = ops.splat(clean, guide_clean, sigma_s, sigma_r)
    np.testing.assert_array_equal(grid, expected[0])
    np.testing.assert_array_equal(weight, expected[1])


def test_nothing_to_read_gives_zero(ops):
    """η = 0 (every cell a pixel reads is empty) -> 0, not NaN."""
    image = np.ones((1, 3, 16, 16), np.float32)
    grid, weight = ops.splat(image, np.zeros((1, 1, 16, 16), np.float32), 4, 4.0)
    out = ops.slice(grid, weight, np.ones((1, 1, 16, 16), np.float32), 4, 4.0)
    assert not out.any()
    assert not torch_slice(grid, weight, np.ones((1, 1, 16, 16), np.float32), 4, 4.0).any()


def test_slice_of_empty_or_broken_cells_is_finite(ops):
    """Cells with weight <= 0 or NaN are empty, whatever value they hold (even Inf/NaN)."""
    guide = np.full((1, 1, 8, 8), 0.5, np.float32)  # fills range cells 32 and 33 (cz = 31.875)
    grid, weight = ops.splat(np.ones((1, 3, 8, 8), np.float32), guide, 4, 4.0)
    reads = np.full((1, 1, 8, 8), 32.6 * 4 / 255, np.float32)  # reads 33 and the empty 34
    assert (weight[0, 0, 33] > 0).all() and not weight[0, 0, 34].any()
    clean = ops.slice(grid, weight, reads, 4, 4.0)
    np.testing.assert_allclose(clean, 1.0, rtol=1e-6)
    broken = grid.copy()
    empty = weight[:, 0] == 0
    broken[:, 0][empty] = np.inf
    broken[:, 1][empty] = np.nan
    np.testing.assert_array_equal(ops.slice(broken, weight, reads, 4, 4.0), clean)
    assert_parity(clean, torch_slice(broken, weight, reads, 4, 4.0), "empty cells holding Inf/NaN")
    for mark in (-1.0, np.nan):
        marked = np.where(weight == 0, np.float32(mark), weight).astype(np.float32)
        np.testing.assert_array_equal(ops.slice(broken, marked, reads, 4, 4.0), clean)


# ---- an independent transcription of docs/grid-math.md (numpy, tiny sizes) ----------------------


def tent(d):
    # float32 like both implementations, so the weights are the same floats
    return np.maximum(np.float32(1) - np.sqrt(d * d + np.float32(1e-7)), np.float32(0))


def axis_taps(n, sigma_s):
    """Index of the first of the 2 cells of each pixel and both weights (from float64)."""
    x = np.arange(n)
    u0 = (2 * x + 1 - sigma_s) // (2 * sigma_s)
    c = (x + 0.5) / sigma_s
    t0 = np.maximum(1 - np.sqrt((c - (u0 + 0.5)) ** 2 + 1e-7), 0)
    t1 = np.maximum(1 - np.sqrt((c - (u0 + 1.5)) ** 2 + 1e-7), 0)
    return u0 + 1, np.stack([t0, t1]).astype(np.float32)


def range_taps(guide, sigma_r, depth):
    g = np.clip(np.nan_to_num(guide, nan=0.0), 0, 1).astype(np.float32)
    cz = np.float32(255) * g / np.float32(sigma_r)
    w0 = np.clip(np.floor(cz - np.float32(0.5)), -1, depth - 3)
    t = np.stack([tent(cz - (w0 + np.float32(0.5))), tent(cz - (w0 + np.float32(1.5)))])
    return w0.astype(np.int64) + 1, t


def corners(guide, sigma_s, sigma_r):
    """For each pixel (y, x) of guide (H, W): 8 x (cell index (z, v, u), weight), float64."""
    h, w = guide.shape
    depth = int(np.floor(255 / sigma_r - 0.5)) + 3
    iy, ty = axis_taps(h, sigma_s)
    ix, tx = axis_taps(w, sigma_s)
    iz, tz = range_taps(guide, sigma_r, depth)
    for a in range(2):
        for b in range(2):
            for c in range(2):
                z = iz + a
                v = np.broadcast_to((iy + b)[:, None], (h, w))
                u = np.broadcast_to((ix + c)[None, :], (h, w))
                t = tz[a].astype(np.float64) * ty[b][:, None] * tx[c][None, :]
                yield (z, v, u), t


def numpy_splat(image, guide, sigma_s, sigma_r):
    _, c, h, w = image.shape
    shape = (int(np.floor(255 / sigma_r - 0.5)) + 3, (2 * h - 1 - sigma_s) // (2 * sigma_s) + 3,
             (2 * w - 1 - sigma_s) // (2 * sigma_s) + 3)
    values = np.where(np.isfinite(image[0]), image[0], 0).astype(np.float64)
    alpha = np.zeros((c, *shape))
    beta = np.zeros(shape)
    for index, t in corners(guide[0, 0], sigma_s, sigma_r):  # eq. 6, 7
        np.add.at(beta, index, t)
        for k in range(c):
            np.add.at(alpha[k], index, t * values[k])
    grid = np.divide(alpha, beta, out=np.zeros_like(alpha), where=beta > 0)  # eq. 8
    return grid[None], beta[None, None]


def numpy_slice(grid, weight, guide, sigma_s, sigma_r):
    c = grid.shape[1]
    h, w = guide.shape[2:]
    mu = np.zeros((c, h, w))
    eta = np.zeros((h, w))
    for index, t in corners(guide[0, 0], sigma_s, sigma_r):  # eq. 20–22, m = 1[weight > 0]
        tm = t * (weight[0, 0][index] > 0)
        eta += tm
        mu += tm * grid[0][(slice(None), *index)]
    return np.divide(mu, eta, out=np.zeros_like(mu), where=eta > 0)[None]  # eq. 23


@pytest.mark.parametrize("sigma_s,sigma_r", ALL_SCALES)
@pytest.mark.parametrize("h,w", [(1, 1), (3, 5), (37, 53)])
def test_numpy_transcription(ops, sigma_s, sigma_r, h, w):
    rng = np.random.default_rng(h + w)
    image = (rng.standard_normal((1, 3, h, w)) + 0.5).astype(np.float32)
    image[0, 1, 0, 0] = np.nan
    guide = rng.random((1, 1, h, w), dtype=np.float32)
    guide[0, 0, -1, -1] = 1.0
    guide[0, 0, 0, -1] = 0.0
    grid, weight = ops.splat(image, guide, sigma_s, sigma_r)
    ref_grid, ref_weight = numpy_splat(image, guide, sigma_s, sigma_r)
    np.testing.assert_array_equal(weight > 0, ref_weight > 0)
    assert_parity(weight, ref_weight, "numpy weight")
    assert_parity(grid, ref_grid, "numpy grid")
    other = rng.random((1, 1, h, w), dtype=np.float32)
    for g in (guide, other):
        assert_parity(ops.slice(grid, weight, g, sigma_s, sigma_r),
                      numpy_slice(grid.astype(np.float64), weight, g, sigma_s, sigma_r),
                      "numpy slice")
