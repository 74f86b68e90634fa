"""ai.quietframe::BackwardWarp (export/ops/backward_warp.cc) against its PyTorch reference
quietframe.model.temporal.backward_warp (F.grid_sample, border padding), and the torch custom op
that the exporter maps onto it.

Criterion as in test_ops_parity: assert_allclose(ours, reference, rtol=1e-5,
atol=1e-5 * max|reference|); the `inside` masks must agree exactly. (The op repeats the
reference's float32 coordinate arithmetic, so on an FMA machine bilinear and nearest are
bit-identical; bicubic agrees to float rounding.)
"""

from __future__ import annotations

import numpy as np
import pytest
from onnx import TensorProto, helper
from ops_support import make_session

from quietframe.runtime.ops_library import OPS_DOMAIN, ops_library_path

torch = pytest.importorskip("torch")
temporal = pytest.importorskip("quietframe.model.temporal")

MODES = {"bilinear": 0, "nearest": 1, "bicubic": 2}
SIZES = [(1, 1), (3, 5), (37, 53), (16, 64), (7, 528), (5, 515)]  # 528, 515: several segments


def warp_model(mode: int | None) -> bytes:
    """One-node model of BackwardWarp; mode=None leaves the attribute out."""
    inputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None)
              for n in ("image", "motion")]
    outputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None)
               for n in ("warped", "inside")]
    attrs = {} if mode is None else {"mode": mode}
    node = helper.make_node("BackwardWarp", ["image", "motion"], ["warped", "inside"],
                            domain=OPS_DOMAIN, **attrs)
    graph = helper.make_graph([node], "BackwardWarp", inputs, outputs)
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid(OPS_DOMAIN, 1)]
    return helper.make_model(graph, opset_imports=opsets, ir_version=9).SerializeToString()


@pytest.fixture(scope="session")
def ops_library() -> str:
    return str(ops_library_path())


@pytest.fixture(scope="module")
def warp(ops_library):
    """warp(image, motion, mode, threads=2) -> (warped, inside) through onnxruntime."""
    sessions = {}

    def run(image, motion, mode, threads=2):
        key = (mode, threads)
        if key not in sessions:
            sessions[key] = make_session(ops_library, warp_model(MODES[mode]), threads)
        return sessions[key].run(None, {"image": image, "motion": motion})

    return run


def reference(image, motion, mode):
    warped, inside = temporal.backward_warp(torch.from_numpy(image), torch.from_numpy(motion),
                                            mode)
    return warped.numpy(), inside.numpy()


def far_for_nonfinite(motion):
    """The motion that bicubic reads like `motion`: PyTorch's bicubic turns a non-finite position
    (±Inf, NaN, or 3e38, whose grid value overflows) into NaN, while the op clamps it to the
    border (NaN like -Inf), as it does a position far out of the frame."""
    return np.where(np.isnan(motion), -1e6, np.clip(motion, -1e6, 1e6)).astype(np.float32)


def assert_parity(ours, theirs, what):
    (warped, inside), (ref_warped, ref_inside) = ours, theirs
    assert warped.shape == ref_warped.shape and warped.dtype == np.float32, what
    assert inside.shape == ref_inside.shape, what
    np.testing.assert_array_equal(inside, ref_inside, err_msg=f"{what}: inside")
    scale = float(np.abs(ref_warped).max())
    np.testing.assert_allclose(warped, ref_warped, rtol=1e-5, atol=1e-5 * scale, err_msg=what)


def motions(n, h, w, seed):
    """Named motion fields (N, 2, H, W): subpixel, out of frame, large, integer and half-pixel
    (nearest's ties), smooth, and non-finite."""
    rng = np.random.default_rng(seed)
    shape = (n, 2, h, w)
    subpixel = rng.uniform(-1.5, 1.5, shape)
    special = rng.uniform(-2, 2, shape)
    flat = special.reshape(-1)
    flat[::7] = np.nan
    flat[3::11] = np.inf
    flat[5::13] = -np.inf
    flat[2::5] = 3e38
    yy, xx = np.mgrid[0:h, 0:w]
    smooth = np.stack((0.3 + 1.7 * np.sin(xx / 9.0), -0.6 + 0.04 * (yy - xx)))[None]
    return {
        "subpixel": subpixel,
        "outside": subpixel + rng.choice([-1, 1], shape) * np.array([w, h])[None, :, None, None]
        * rng.uniform(0.2, 1.2, shape),
        "large": rng.uniform(-1e6, 1e6, shape),
        "halves": np.round(rng.uniform(-3, 3, shape) * 2) / 2,
        "smooth": np.broadcast_to(smooth, shape),
        "nonfinite": special,
    }


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("h,w", SIZES)
def test_matches_grid_sample(warp, mode, h, w):
    n, c = (2, 3) if h * w < 5000 else (1, 8)
    rng = np.random.default_rng(h * 1000 + w)
    image = rng.standard_normal((n, c, h, w)).astype(np.float32)
    for name, motion in motions(n, h, w, seed=h + w).items():
        motion = np.ascontiguousarray(motion, dtype=np.float32)
        expected = reference(image, motion, mode)
        if mode == "bicubic" and name == "nonfinite":
            expected = (reference(image, far_for_nonfinite(motion), mode)[0], expected[1])
        assert_parity(warp(image, motion, mode), expected, f"{mode}, {h}x{w}, {name} motion")


@pytest.mark.parametrize("mode", MODES)
def test_channel_counts(warp, mode):
    rng = np.random.default_rng(3)
    for c in (1, 2, 4, 8, 13):
        image = rng.random((1, c, 19, 24), dtype=np.float32)
        motion = rng.uniform(-4, 4, (1, 2, 19, 24)).astype(np.float32)
        assert_parity(warp(image, motion, mode), reference(image, motion, mode), f"C={c}")


@pytest.mark.parametrize("mode", MODES)
def test_static_and_integer_motion_copy_pixels(warp, mode):
    # Up to rounding: like the reference, the op maps positions to [-1, 1] and back, which is
    # exact only for power-of-two sizes (W = 32 here, H = 12 not), so a bilinear or bicubic copy
    # may blend in 1e-7 of a neighbour.
    rng = np.random.default_rng(4)
    image = rng.random((1, 3, 12, 32), dtype=np.float32)
    motion = np.zeros((1, 2, 12, 32), np.float32)
    warped, inside = warp(image, motion, mode)
    np.testing.assert_allclose(warped, image, rtol=0, atol=1e-6)
    assert inside.all()
    motion[:, 0] = -2.0  # pixel x came from x - 2: columns 0, 1 read column 0 (border)
    warped, inside = warp(image, motion, mode)
    np.testing.assert_allclose(warped[..., 2:], image[..., :-2], rtol=0, atol=1e-6)
    np.testing.assert_allclose(warped[..., :2], image[..., :1].repeat(2, -1), rtol=0, atol=1e-6)
    assert not inside[..., :2].any() and inside[..., 2:].all()


@pytest.mark.parametrize("mode", MODES)
def test_nonfinite_motion_is_outside_and_reads_inside_the_image(warp, mode):
    # Bicubic too: at its clamped positions every tap but one has weight exactly 0.
    rng = np.random.default_rng(5)
    image = rng.random((1, 2, 6, 9), dtype=np.float32)
    motion = np.full((1, 2, 6, 9), np.nan, np.float32)
    warped, inside = warp(image, motion, mode)
    assert not inside.any()
    np.testing.assert_array_equal(warped, np.broadcast_to(image[:, :, :1, :1], warped.shape))
    for value, corner in [(np.inf, (-1, -1)), (-np.inf, (0, 0)), (3e38, (-1, -1))]:
        motion[:] = value
        warped, inside = warp(image, motion, mode)
        assert not inside.any()
        np.testing.assert_array_equal(
            warped, np.broadcast_to(image[:, :, corner[0], corner[1]][..., None, None],
                                    warped.shape))


def test_nearest_rounds_half_to_even(warp):
    image = np.arange(8, dtype=np.float32).reshape(1, 1, 1, 8)
    motion = np.zeros((1, 2, 1, 8), np.float32)
    motion[0, 0] = 0.5  # x + 0.5: ties go to the even column
    warped, _ = warp(image, motion, "nearest")
    np.testing.assert_array_equal(warped[0, 0, 0], [0, 2, 2, 4, 4, 6, 6, 7])
    np.testing.assert_array_equal(warped, reference(image, motion, "nearest")[0])


def test_bicubic_resamples_a_smooth_image_better_than_bilinear(warp):
    h, w, period = 24, 40, 8.0
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)

    def f(x, y):
        return np.sin(2 * np.pi / period * x + 0.3) * np.cos(1.4 * np.pi / period * y)

    image = f(xx, yy).astype(np.float32)[None, None]
    motion = np.zeros((1, 2, h, w), np.float32)
    motion[0, 0], motion[0, 1] = 0.37, -0.45
    core = (slice(3, -3), slice(3, -3))  # away from the border
    truth = f(xx + 0.37, yy - 0.45)[core]
    error = {mode: np.abs(warp(image, motion, mode)[0][0, 0][core] - truth).max()
             for mode in ("bilinear", "bicubic")}
    assert error["bicubic"] < 0.5 * error["bilinear"], error


def test_bicubic_overshoots_at_an_edge_like_the_reference(warp):
    image = np.zeros((1, 1, 4, 12), np.float32)
    image[..., 6:] = 1.0
    motion = np.full((1, 2, 4, 12), 0.5, np.float32)
    warped, inside = warp(image, motion, "bicubic")
    assert warped.min() < -0.01 and warped.max() > 1.01  # not clamped to the texels' range
    assert_parity((warped, inside), reference(image, motion, "bicubic"), "edge")


@pytest.mark.parametrize("mode", MODES)
def test_results_do_not_depend_on_thread_count(warp, mode):
    rng = np.random.default_rng(6)
    image = rng.standard_normal((2, 5, 97, 131)).astype(np.float32)
    motion = rng.uniform(-6, 6, (2, 2, 97, 131)).astype(np.float32)
    one = warp(image, motion, mode, threads=1)
    two = warp(image, motion, mode, threads=2)
    for a, b in zip(one, two, strict=True):
        np.testing.assert_array_equal(a, b)


# ---- errors: an exception whose message names the op, never a crash ---------------------------


@pytest.mark.parametrize("mode", [None, 3, -1])
def test_bad_mode_raises(ops_library, mode):
    with pytest.raises(Exception) as error:
        make_session(ops_library, warp_model(mode))
    assert "BackwardWarp" in str(error.value) and "mode" in str(error.value)


def f32(*shape):
    return np.zeros(shape, np.float32)


@pytest.mark.parametrize(
    "image,motion,word",
    [
        (f32(1, 3, 10, 12), f32(1, 2, 10, 11), "motion"),
        (f32(1, 3, 10, 12), f32(1, 1, 10, 12), "motion"),
        (f32(1, 3, 10, 12), f32(2, 2, 10, 12), "motion"),
        (f32(3, 10, 12), f32(2, 10, 12), "image"),
        (f32(1, 3, 0, 12), f32(1, 2, 0, 12), "image"),
    ],
)
def test_shape_errors(warp, image, motion, word):
    with pytest.raises(Exception) as error:
        warp(image, motion, "bilinear")
    assert "BackwardWarp" in str(error.value) and word in str(error.value)
    # The session survives errors.
    warped, _ = warp(f32(1, 3, 4, 4), f32(1, 2, 4, 4), "bilinear")
    assert warped.shape == (1, 3, 4, 4)


# ---- the torch custom op ----------------------------------------------------------------------


def test_custom_op_fake_shapes_and_schema():
    image, motion = torch.rand(2, 3, 5, 7), torch.zeros(2, 2, 5, 7)
    torch.library.opcheck(torch.ops.quietframe.backward_warp.default, (image, motion, "nearest"),
                          test_utils=("test_schema", "test_faketensor"))
    with pytest.raises(ValueError, match="mode"):
        temporal.backward_warp(image, motion, "lanczos")


def test_export_maps_the_warp_to_the_custom_op(tmp_path):
    import onnx

    from quietframe.export.onnx_export import export_nbg
    from quietframe.model.nbg import AccumulationDenoiser

    path = export_nbg(AccumulationDenoiser(), tmp_path / "accumulation.onnx")
    nodes = onnx.load(str(path)).graph.node
    warps = [n for n in nodes if n.op_type == "BackwardWarp" and n.domain == OPS_DOMAIN]
    # one warp of the whole state, nearest (mode 1): see model/temporal.accumulate
    assert [a.i for n in warps for a in n.attribute if a.name == "mode"] == [1]
    assert not [n for n in nodes if n.op_type == "GridSample"]


def test_training_backward_through_two_frames():
    """GuideNet gets gradients through an unrolled sequence: the warped state needs none."""
    from quietframe.export.onnx_export import example_inputs
    from quietframe.model.nbg import VARIANTS, NBGDenoiser

    torch.manual_seed(0)
    model = NBGDenoiser(VARIANTS["nbg-2l-3g"]).train()
    state = model.initial_state(1, 16, 24)
    outputs = []
    for index in range(2):
        color, albedo, normal, depth, motion, _, _ = example_inputs(16, 24, seed=index)
        out, state = model(color, albedo, normal, depth, motion,
                           torch.tensor([float(index == 0)]), state)
        outputs.append(out)
    assert not state.requires_grad
    torch.stack(outputs).abs().mean().backward()
    for name, parameter in model.named_parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all(), name
        assert parameter.grad.abs().sum() > 0, name


@pytest.mark.parametrize("mode", ["nearest", "bilinear", "bicubic"])
def test_backward_through_the_warp_is_grid_samples_gradient(mode):
    """The image gradient (a learned output's history, trained unrolled) is the reference
    computation's own, checked numerically; motion gets none and says so."""
    torch.manual_seed(0)
    image = torch.rand(1, 2, 5, 6, dtype=torch.float64, requires_grad=True)
    motion = (torch.rand(1, 2, 5, 6, dtype=torch.float64) - 0.5) * 3
    torch.autograd.gradcheck(lambda x: temporal.backward_warp(x, motion, mode)[0], (image,))
    moving = motion.clone().requires_grad_(True)
    warped, _ = temporal.backward_warp(image, moving, mode)
    with pytest.raises(RuntimeError, match="motion"):
        warped.sum().backward()
