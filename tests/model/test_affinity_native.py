"""Training's native affinity kernels (quietframe.model.affinity_native, export/ops/
affinity_train_abi.cc + affinity_backward.h): the forward is the served op's bit for bit and
within 1e-5 of the reference; the gradients equal autograd of the reference (spatial_math /
temporal_math in float64) for every input, at every kernel size, dilation, border and rule of
docs/affinity-math.md; they do not depend on the thread count; the custom ops route to them only
when QUIETFRAME_TRAIN_KERNELS=native; and a few training steps of a small affinity model give the
reference's losses.

The library is the one the other op tests use (QUIETFRAME_OPS_LIBRARY or the installed copy).
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
from onnx import TensorProto, helper
from ops_support import make_session

from quietframe.runtime.ops_library import OPS_DOMAIN, ops_library_path

torch = pytest.importorskip("torch")
kernels = pytest.importorskip("quietframe.model.affinity_kernels")
from quietframe.model import affinity_native as native  # noqa: E402

EPS = kernels.EPSILON
TEMPORAL = ["radiance", "features", "bandwidth", "center", "prev_output", "prev_features",
            "temporal_bandwidth", "temporal_on", "kernel_size", "temporal_kernel_size"]
GRAD_NAMES = TEMPORAL[:7]


@pytest.fixture(autouse=True, scope="module")
def library():
    reason = native.unavailable_reason()
    assert reason is None, reason  # built from this tree: the ABI must be there


def inputs(n=2, c=3, d=8, h=19, w=29, seed=0, on=(1.0, 0.0)):
    """(radiance, features, bandwidth, center, prev_output, prev_features, temporal_bandwidth,
    temporal_on) float32, features spread so that the weights span (0, 1]."""
    g = torch.Generator().manual_seed(seed)
    return [
        torch.rand(n, c, h, w, generator=g) * 4,
        torch.randn(n, d, h, w, generator=g) * 0.5,
        torch.rand(n, 1, h, w, generator=g) * 2,
        torch.rand(n, 1, h, w, generator=g),
        torch.rand(n, c, h, w, generator=g) * 4,
        torch.randn(n, d, h, w, generator=g) * 0.5,
        torch.rand(n, 1, h, w, generator=g) * 2,
        torch.tensor(on, dtype=torch.float32),
    ]


def reference_grads(x, grad, k, dilation, kt=None, dtype=torch.float64):
    """Output and gradients (all inputs but temporal_on) of the reference in `dtype`."""
    xs = [t.to(dtype).requires_grad_(i < 7) for i, t in enumerate(x)]
    if kt is None:
        out = kernels.spatial_math(*xs, k, dilation, EPS)
    else:
        out = kernels.temporal_math(*xs, k, dilation, kt, EPS)
    wanted = [t for t in xs if t.requires_grad]
    grads = torch.autograd.grad(out, wanted, grad.to(dtype), allow_unused=True)  # k = 1: no f, a
    return out.detach(), [torch.zeros_like(t) if g is None else g for t, g in
                          zip(wanted, grads, strict=True)]


def native_grads(x, grad, k, dilation, kt=None, threads=None):
    if kt is None:
        return native.spatial_backward(grad, *x, k, dilation, EPS, threads=threads)
    return native.temporal_backward(grad, *x, k, dilation, kt, EPS, threads=threads)


def check_against_reference(x, k, dilation, kt=None, seed=1):
    """Native forward within 1e-5 of the reference; native gradients against float64 autograd of
    the reference: within 2e-5 of the largest gradient, or, where float32 cancels (k = 1:
    ∂c = g·(L - out)/D ≈ 0), no further off than 8× the error of float32 autograd of the
    reference itself. Returns the native gradients."""
    x = x[:4] if kt is None else x
    g = torch.randn(x[0].shape, generator=torch.Generator().manual_seed(seed))
    exact_out, exact = reference_grads(x, g, k, dilation, kt)
    _, single = reference_grads(x, g, k, dilation, kt, torch.float32)
    out = (native.spatial_forward(*x, k, dilation, EPS) if kt is None
           else native.temporal_forward(*x, k, dilation, kt, EPS))
    np.testing.assert_allclose(out.double().numpy(), exact_out.numpy(), rtol=1e-5,
                               atol=1e-5 * float(exact_out.abs().max()))
    what = f"k={k} dilation={dilation} kt={kt} shape={tuple(x[0].shape)}"
    ours = native_grads(x, g, k, dilation, kt)
    assert len(ours) == len(exact) == (4 if kt is None else 7)
    for name, a, b, s in zip(GRAD_NAMES, ours, exact, single, strict=False):
        assert a.dtype == torch.float32 and a.shape == b.shape, name
        float32_error = float((s.double() - b).abs().max())
        atol = max(2e-5 * float(b.abs().max()), 8 * float32_error, 1e-30)
        np.testing.assert_allclose(a.double().numpy(), b.numpy(), rtol=1e-4, atol=atol,
                                   err_msg=f"{what} ∂{name}")
    return ours


# ---- forward: the served op, bit for bit ------------------------------------------------------


def temporal_session(dilation, threads=2):
    names = TEMPORAL
    ints = {"kernel_size", "temporal_kernel_size"}
    model_inputs = [helper.make_tensor_value_info(
        n, TensorProto.INT64 if n in ints else TensorProto.FLOAT, None) for n in names]
    outputs = [helper.make_tensor_value_info("output", TensorProto.FLOAT, None)]
    node = helper.make_node("AffinityTemporalFilter", names, ["output"], domain=OPS_DOMAIN,
                            dilation=dilation)
    graph = helper.make_graph([node], "t", model_inputs, outputs)
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid(OPS_DOMAIN, 1)]
    model = helper.make_model(graph, opset_imports=opsets, ir_version=9)
    return make_session(str(ops_library_path()), model.SerializeToString(), threads)


@pytest.mark.parametrize("k,dilation,kt", [(5, 1, 5), (13, 4, 13), (3, 2, 1)])
@pytest.mark.parametrize("d", [8, 3])
def test_forward_is_the_served_op_bit_for_bit(k, dilation, kt, d):
    """onnxruntime runs the same code on its pool; the library is then also registered in this
    process, and the ABI must still use its own threads (no kernel context)."""
    x = inputs(d=d, seed=k + d)
    feeds = {n: t.numpy() for n, t in zip(TEMPORAL, x, strict=False)}
    feeds |= {"kernel_size": np.array(k), "temporal_kernel_size": np.array(kt)}
    served = temporal_session(dilation).run(None, feeds)[0]
    ours = native.temporal_forward(*x, k, dilation, kt, EPS, threads=2).numpy()
    np.testing.assert_array_equal(ours, served)
    spatial = native.spatial_forward(*x[:4], k, dilation, EPS, threads=3)
    with torch.no_grad():
        reference = kernels.spatial_math(*x[:4], k, dilation, EPS)
    np.testing.assert_allclose(spatial.numpy(), reference.numpy(), rtol=1e-5,
                               atol=1e-5 * float(reference.abs().max()))


# ---- gradients against autograd of the reference ----------------------------------------------


@pytest.mark.parametrize("k", [1, 5, 13])
@pytest.mark.parametrize("dilation", [1, 2, 4])
def test_spatial_gradients(k, dilation):
    """C = 3, D = 8 (the AVX2 loop, W = 29 leaves a scalar tail of 5 columns), N = 2."""
    check_against_reference(inputs(seed=k * 10 + dilation), k, dilation)


@pytest.mark.parametrize("k", [1, 5, 13])
@pytest.mark.parametrize("dilation", [1, 2, 4])
@pytest.mark.parametrize("kt", [1, 5, 13])
def test_temporal_gradients(k, dilation, kt):
    """temporal_on = (1, 0): one image of the batch with the temporal term, one without."""
    check_against_reference(inputs(h=17, w=21, seed=k + dilation + kt), k, dilation, kt)


@pytest.mark.parametrize("c,d", [(1, 1), (2, 3), (4, 8), (3, 5)])
def test_gradients_for_other_channel_and_feature_counts(c, d):
    """The scalar loop (the AVX2 one takes C = 3, D = 8 only)."""
    x = inputs(c=c, d=d, h=12, w=18, seed=c * 7 + d, on=(0.5, 1.0))
    check_against_reference(x, 5, 2)
    check_against_reference(x, 5, 2, 3)


@pytest.mark.parametrize("h,w", [(1, 1), (2, 9), (6, 11)])
def test_images_smaller_than_the_window(h, w):
    """13×13 at dilation 4 spans 49 pixels: most taps fall outside; W = 9 runs one AVX2 group
    whose every neighbour group straddles an edge."""
    x = inputs(h=h, w=w, seed=h * w)
    check_against_reference(x, 13, 4)
    check_against_reference(x, 13, 4, 13)


@pytest.mark.parametrize("c,d,w", [(3, 8, 29), (2, 3, 13)])  # AVX2 + scalar tail, scalar
@pytest.mark.parametrize("on", [(-1.0, 0.5), (0.25, 1.0)])
def test_zero_negative_and_nan_parameters(c, d, w, on):
    """a, b, c below 0 or NaN count as 0 and get no gradient; on < 0 counts as 0, a fraction
    scales ω; large bandwidths push weights past the cutoff (weight and gradient 0)."""
    x = inputs(c=c, d=d, h=16, w=w, seed=3, on=on)
    for i, t in ((2, x[2]), (3, x[3]), (6, x[6])):
        t[:, :, ::3, ::2] = 0.0
        t[:, :, 1::3, ::2] = -0.5
        t[:, :, 2::5, 1::4] = float("nan")
        if i != 3:
            t[:, :, 2::3, 1::2] = 400.0  # a·d² past 87 for most neighbours
    for kt in (None, 5):
        xs = x[:4] if kt is None else x
        ours = check_against_reference(xs, 5, 2, kt, seed=4)
        for name, index in (("bandwidth", 2), ("center", 3), ("temporal_bandwidth", 6)):
            if index < len(ours):
                dead = ~(xs[index] > 0)
                assert (ours[index][dead] == 0).all(), name
        if kt is not None and on[0] < 0:  # no temporal term, no temporal gradients
            for index in (4, 5, 6):
                assert (ours[index][0] == 0).all()


def test_all_zero_weights():
    """c = 0 and every neighbour past the cutoff: out = 0/ε = 0; the gradients stay finite and
    equal the reference's."""
    x = inputs(n=1, h=9, w=10, seed=5, on=(0.0,))
    x[3].zero_()
    x[2].fill_(1e4)
    ours = check_against_reference(x[:4], 3, 1, seed=6)
    assert all(torch.isfinite(t).all() for t in ours)


# ---- threads ----------------------------------------------------------------------------------


def test_gradients_do_not_depend_on_the_thread_count():
    x = inputs(n=2, h=37, w=45, seed=9, on=(1.0, 1.0))
    g = torch.randn(x[0].shape, generator=torch.Generator().manual_seed(10))
    for kt in (None, 5):
        xs = x[:4] if kt is None else x
        runs = [native_grads(xs, g, 5, 2, kt, threads=t) for t in (1, 2, 3, 7)]
        forwards = [native.temporal_forward(*x, 5, 2, 5, EPS, threads=t) for t in (1, 2, 7)]
        for other in runs[1:]:
            assert all(torch.equal(a, b) for a, b in zip(runs[0], other, strict=True))
        assert all(torch.equal(forwards[0], f) for f in forwards[1:])


# ---- the custom ops' routing ------------------------------------------------------------------


def test_custom_ops_route_by_the_switch(monkeypatch):
    """Unset: 'auto', native where the library has it (here it has); 'reference' forces the
    PyTorch loop; an unknown value is refused."""
    monkeypatch.delenv(native.KERNELS_ENV, raising=False)
    assert native.DEFAULT_KERNELS == "auto" and native.available()
    x = inputs(seed=11)
    assert torch.equal(kernels.spatial_affinity_filter(*x[:4], 5, 2, EPS),
                       native.spatial_forward(*x[:4], 5, 2, EPS))
    monkeypatch.setenv(native.KERNELS_ENV, "reference")
    with torch.no_grad():
        expected = kernels.spatial_math(*x[:4], 5, 2, EPS)
    assert torch.equal(kernels.spatial_affinity_filter(*x[:4], 5, 2, EPS), expected)
    monkeypatch.setenv(native.KERNELS_ENV, "fast")
    with pytest.raises(ValueError, match="QUIETFRAME_TRAIN_KERNELS"):
        kernels.spatial_affinity_filter(*x[:4], 5, 2, EPS)


def test_auto_falls_back_to_the_reference_without_the_library(monkeypatch):
    monkeypatch.delenv(native.KERNELS_ENV, raising=False)
    monkeypatch.setattr(native, "unavailable_reason", lambda: "no library here")
    x = inputs(seed=15)
    with torch.no_grad():
        expected = kernels.spatial_math(*x[:4], 5, 2, EPS)
    assert torch.equal(kernels.spatial_affinity_filter(*x[:4], 5, 2, EPS), expected)
    monkeypatch.setenv(native.KERNELS_ENV, "native")
    with pytest.raises(RuntimeError, match="no library here"):
        kernels.spatial_affinity_filter(*x[:4], 5, 2, EPS)


def test_custom_ops_run_native_when_selected(monkeypatch):
    monkeypatch.setenv(native.KERNELS_ENV, "native")
    x = inputs(seed=12)
    g = torch.randn(x[0].shape, generator=torch.Generator().manual_seed(13))
    # spatial, with only some inputs wanting a gradient
    xs = [t.clone().requires_grad_(i in (1, 3)) for i, t in enumerate(x[:4])]
    out = kernels.spatial_affinity_filter(*xs, 5, 2, EPS)
    assert torch.equal(out.detach(), native.spatial_forward(*x[:4], 5, 2, EPS))
    out.backward(g)
    expected = native.spatial_backward(g, *x[:4], 5, 2, EPS)
    assert xs[0].grad is None and xs[2].grad is None
    assert torch.equal(xs[1].grad, expected[1]) and torch.equal(xs[3].grad, expected[3])
    # temporal, every input (temporal_on gets no gradient)
    xt = [t.clone().requires_grad_(i < 7) for i, t in enumerate(x)]
    out = kernels.temporal_affinity_filter(*xt, 5, 2, 3, EPS)
    assert torch.equal(out.detach(), native.temporal_forward(*x, 5, 2, 3, EPS))
    out.backward(g)
    expected = native.temporal_backward(g, *x, 5, 2, 3, EPS)
    for t, e in zip(xt, expected, strict=False):
        assert torch.equal(t.grad, e)


def test_float64_takes_the_reference_under_native(monkeypatch):
    """gradcheck's float64 falls back to the reference, which passes it."""
    monkeypatch.setenv(native.KERNELS_ENV, "native")
    x = [t.double().requires_grad_(i < 7) for i, t in enumerate(inputs(n=2, h=5, w=6, seed=14))]
    assert torch.autograd.gradcheck(
        lambda *t: kernels.temporal_affinity_filter(*t, x[7], 3, 2, 3, EPS), tuple(x[:7]))


def test_bad_shapes_are_refused():
    x = inputs(seed=15)
    with pytest.raises(ValueError, match="bandwidth must be"):
        native.spatial_forward(x[0], x[1], x[2][:, :, :-1], x[3], 5, 1, EPS)
    with pytest.raises(ValueError, match="temporal_on must be"):
        native.temporal_forward(*x[:7], x[7][:1], 5, 1, 5, EPS)
    with pytest.raises(ValueError, match="kernel_size must be an odd int"):
        native.spatial_forward(*x[:4], 4, 1, EPS)
    with pytest.raises(TypeError, match="float32"):
        native.spatial_forward(x[0].double(), *x[1:4], 5, 1, EPS)


@pytest.mark.skipif(sys.platform != "linux", reason="names glibc's libm")
def test_a_library_without_the_abi_is_reported():
    assert "no affinity training ABI" in native._load("libm.so.6")


# ---- a few training steps of a small model ----------------------------------------------------


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from dataset_support import write_sequence

    from quietframe.scenes.generator import GENERATOR_VERSION

    root = tmp_path_factory.mktemp("data")
    for seed in (11, 12):
        write_sequence(root / GENERATOR_VERSION / "train", seed, frames=3)
    return root


def training_run(data, kernel_size: int, steps: int = 4) -> tuple[list[float], torch.Tensor]:
    """Losses of `steps` Adam steps of a small model, and the first step's parameter gradient
    (flattened)."""
    from quietframe.model import train as qt

    cfg = qt.TrainConfig(variant="affinity-h8", data=str(data), crop=24, frames=3, batch=2,
                         steps=steps, threads=1, seed=5, kernel_size=kernel_size)
    torch.manual_seed(cfg.seed)
    model = qt.build_model(cfg)
    batches = qt.TrainingBatches(cfg)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses, first_grad = [], None
    for step in range(steps):
        batch = batches(step)
        loss = qt.batch_loss(cfg, model, batch)
        optimizer.zero_grad()
        loss.backward()
        if first_grad is None:
            first_grad = torch.cat([p.grad.flatten() for p in model.parameters()])
        optimizer.step()
        losses.append(loss.item())
    return losses, first_grad


@pytest.mark.parametrize("kernel_size", [5, pytest.param(13, marks=pytest.mark.slow)])  # 13: ~100 s
def test_training_steps_match_the_reference(data, monkeypatch, kernel_size):
    """The first step's loss and parameter gradient equal the reference's to float rounding;
    the next steps stay close (Adam amplifies rounding differences step by step, so the later
    losses get a looser bound)."""
    monkeypatch.setenv(native.KERNELS_ENV, "reference")
    reference, reference_grad = training_run(data, kernel_size)
    monkeypatch.setenv(native.KERNELS_ENV, "native")
    ours, our_grad = training_run(data, kernel_size)
    assert len(set(reference)) == len(reference)  # the model does move
    assert ours[0] == pytest.approx(reference[0], rel=1e-5)
    assert float((our_grad - reference_grad).norm()) < 1e-3 * float(reference_grad.norm())
    np.testing.assert_allclose(ours, reference, rtol=2e-3)
