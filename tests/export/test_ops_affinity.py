"""ai.quietframe::AffinityFilter / AffinityTemporalFilter (export/ops/affinity_*.cc) against the
PyTorch reference quietframe.model.affinity_kernels (Işık et al. 2021, eq. 4, 6, 7, 8), a dense
numpy transcription, and the rules of docs/affinity-math.md; gradcheck of the reference; export.

Criterion as in test_ops_parity: assert_allclose(ours, reference, rtol=1e-5,
atol=1e-5 * max|reference|).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from onnx import TensorProto, helper
from ops_support import make_session

from quietframe.runtime.ops_library import OPS_DOMAIN, ops_library_path

torch = pytest.importorskip("torch")
kernels = pytest.importorskip("quietframe.model.affinity_kernels")

SPATIAL = ["radiance", "features", "bandwidth", "center", "kernel_size"]
TEMPORAL = ["radiance", "features", "bandwidth", "center", "prev_output", "prev_features",
            "temporal_bandwidth", "temporal_on", "kernel_size", "temporal_kernel_size"]
INT_INPUTS = {"kernel_size", "temporal_kernel_size"}


def affinity_model(op: str, **attributes) -> bytes:
    """One-node model of an affinity op; attributes given as None are left out."""
    names = SPATIAL if op == "AffinityFilter" else TEMPORAL
    inputs = [helper.make_tensor_value_info(
        n, TensorProto.INT64 if n in INT_INPUTS else TensorProto.FLOAT, None) for n in names]
    outputs = [helper.make_tensor_value_info("output", TensorProto.FLOAT, None)]
    attrs = {k: v for k, v in attributes.items() if v is not None}
    node = helper.make_node(op, names, ["output"], domain=OPS_DOMAIN, **attrs)
    graph = helper.make_graph([node], op, inputs, outputs)
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid(OPS_DOMAIN, 1)]
    return helper.make_model(graph, opset_imports=opsets, ir_version=9).SerializeToString()


@pytest.fixture(scope="module")
def ops():
    """ops.spatial(inputs, k, dilation, threads=2, eps=None), ops.temporal(inputs, k, dilation,
    kt, ...) through onnxruntime, with the sessions cached."""
    library = str(ops_library_path())
    sessions = {}

    def session(op, dilation, eps, threads):
        key = (op, dilation, eps, threads)
        if key not in sessions:
            model = affinity_model(op, dilation=dilation, epsilon=eps)
            sessions[key] = make_session(library, model, threads)
        return sessions[key]

    class Ops:
        @staticmethod
        def spatial(x, k, dilation, threads=2, eps=None):
            feeds = dict(zip(SPATIAL, x[:4], strict=False)) | {"kernel_size": np.array(k)}
            return session("AffinityFilter", dilation, eps, threads).run(None, feeds)[0]

        @staticmethod
        def temporal(x, k, dilation, kt, threads=2, eps=None):
            feeds = dict(zip(TEMPORAL, x, strict=False))
            feeds |= {"kernel_size": np.array([k]), "temporal_kernel_size": np.array(kt)}
            return session("AffinityTemporalFilter", dilation, eps, threads).run(None, feeds)[0]

    return Ops


def inputs(n, c, d, h, w, seed=0, bandwidth_scale=2.0):
    """(radiance, features, bandwidth, center, prev_output, prev_features, temporal_bandwidth,
    temporal_on) as float32 arrays; features spread so that the weights span (0, 1]."""
    rng = np.random.default_rng(seed)
    f32 = np.float32
    return [
        (rng.random((n, c, h, w)) * 4).astype(f32),
        (rng.standard_normal((n, d, h, w)) * 0.5).astype(f32),
        (rng.random((n, 1, h, w)) * bandwidth_scale).astype(f32),
        rng.random((n, 1, h, w)).astype(f32),
        (rng.random((n, c, h, w)) * 4).astype(f32),
        (rng.standard_normal((n, d, h, w)) * 0.5).astype(f32),
        (rng.random((n, 1, h, w)) * bandwidth_scale).astype(f32),
        np.ones(n, f32),
    ]


def ref_spatial(x, k, dilation, eps=kernels.EPSILON):
    t = [torch.from_numpy(a) for a in x[:4]]
    return kernels.spatial_affinity_filter(*t, k, dilation, eps).numpy()


def ref_temporal(x, k, dilation, kt, eps=kernels.EPSILON):
    t = [torch.from_numpy(a) for a in x]
    return kernels.temporal_affinity_filter(*t, k, dilation, kt, eps).numpy()


def assert_parity(ours, reference, what=""):
    assert ours.shape == reference.shape and ours.dtype == np.float32, what
    scale = float(np.abs(reference).max())
    np.testing.assert_allclose(ours, reference, rtol=1e-5, atol=1e-5 * scale, err_msg=what)


# ---- parity with the PyTorch reference ----------------------------------------------------------


@pytest.mark.parametrize("n,h,w", [(2, 40, 56), (1, 33, 70)])
def test_paper_setting(ops, n, h, w):
    """d = 8, 13×13 taps, dilation 4 (the paper's last kernel), RGB."""
    x = inputs(n, 3, 8, h, w, seed=h)
    assert_parity(ops.spatial(x, 13, 4), ref_spatial(x, 13, 4), "spatial")
    assert_parity(ops.temporal(x, 13, 4, 13), ref_temporal(x, 13, 4, 13), "temporal")


@pytest.mark.parametrize("k", [1, 3, 5, 7, 9, 11, 13])
@pytest.mark.parametrize("dilation", [1, 2, 4])
def test_kernel_sizes_and_dilations(ops, k, dilation):
    x = inputs(1, 3, 8, 19, 29, seed=k * 10 + dilation)
    assert_parity(ops.spatial(x, k, dilation), ref_spatial(x, k, dilation), f"k={k}")
    kt = max(1, k - 2)
    assert_parity(ops.temporal(x, k, dilation, kt), ref_temporal(x, k, dilation, kt), f"k={k}")


@pytest.mark.parametrize("h,w", [(1, 1), (1, 9), (5, 3), (7, 8), (9, 17), (12, 47)])
def test_images_smaller_than_the_footprint(ops, h, w):
    """A 13×13 kernel at dilation 4 reaches 24 pixels: every pixel here is near a border, and
    rows of 8+ pixels run the vector path with masked lanes at both ends."""
    x = inputs(1, 3, 8, h, w, seed=h * w)
    assert_parity(ops.spatial(x, 13, 4), ref_spatial(x, 13, 4), "spatial")
    assert_parity(ops.temporal(x, 13, 4, 5), ref_temporal(x, 13, 4, 5), "temporal")


@pytest.mark.parametrize("c,d", [(1, 1), (2, 3), (4, 8), (5, 2), (9, 16)])
def test_channel_and_feature_counts(ops, c, d):
    x = inputs(2, c, d, 11, 21, seed=c + d)
    assert_parity(ops.spatial(x, 5, 2), ref_spatial(x, 5, 2), "spatial")
    assert_parity(ops.temporal(x, 5, 2, 3), ref_temporal(x, 5, 2, 3), "temporal")


def test_constant_radiance_is_kept_up_to_the_borders(ops):
    """A weighted mean of a constant is that constant (den >> ε), at the borders too: skipped
    neighbours outside the image must contribute nothing, not zeros."""
    x = inputs(1, 3, 8, 23, 37, seed=4)
    x[0][:] = 2.5
    x[3][:] = 1.0  # centre weight 1: den >= 1
    x[4][:] = 2.5
    for out in (ops.spatial(x, 13, 4), ops.temporal(x, 13, 4, 5)):
        np.testing.assert_allclose(out, 2.5, rtol=1e-6)


def test_zero_weight_neighbourhoods_give_zero(ops):
    """c = 0 and a huge bandwidth with distinct features: every weight is 0, out = 0/ε = 0."""
    x = inputs(1, 3, 8, 16, 24, seed=5)
    x[1] = (np.arange(16 * 24, dtype=np.float32).reshape(1, 1, 16, 24) * 10).repeat(8, 1)
    x[2][:] = 1e30
    x[3][:] = 0
    x[5] = x[1] + 5  # temporal neighbours differ too
    x[6][:] = 1e30
    for ours, ref in [(ops.spatial(x, 13, 4), ref_spatial(x, 13, 4)),
                      (ops.temporal(x, 13, 4, 13), ref_temporal(x, 13, 4, 13))]:
        assert not ours.any() and not ref.any()
    # one pixel keeps its centre: it alone is its own output
    x[3][0, 0, 7, 9] = 0.5
    out = ops.spatial(x, 13, 4)
    np.testing.assert_allclose(out[0, :, 7, 9], x[0][0, :, 7, 9], rtol=1e-6)
    assert np.count_nonzero(out.any(axis=1)) == 1


def test_temporal_off_equals_the_spatial_op(ops):
    """temporal_on = 0 (first frame, cut): the temporal op is the spatial one, bit for bit;
    per image of the batch."""
    x = inputs(2, 3, 8, 21, 35, seed=6)
    x[7] = np.array([0.0, 1.0], np.float32)
    spatial = ops.spatial(x, 13, 4)
    temporal = ops.temporal(x, 13, 4, 13)
    np.testing.assert_array_equal(temporal[0], spatial[0])
    assert not np.allclose(temporal[1], spatial[1])
    assert_parity(temporal, ref_temporal(x, 13, 4, 13))


def test_kernel_size_changes_per_run(ops):
    """One session, several kernel sizes: the size is an input, read at every run."""
    x = inputs(1, 3, 8, 17, 26, seed=7)
    outs = {k: ops.spatial(x, k, 2) for k in (3, 13, 5)}
    for k, out in outs.items():
        assert_parity(out, ref_spatial(x, k, 2), f"k={k}")
    assert not np.allclose(outs[3], outs[13])


# ---- an independent dense transcription -------------------------------------------------------


def dense_numpy(x, k, dilation, kt=None, eps=1e-10):
    """Eq. 4, 6 (and 7, 8 when kt is given) pixel by pixel in float64, straight from the paper."""
    radiance, features, a, c, prev_out, prev_f, b, on = (v.astype(np.float64) for v in x)
    n, ch, h, w = radiance.shape
    r = (k - 1) // 2
    out = np.zeros_like(radiance)
    for i in range(n):
        for y in range(h):
            for xx in range(w):
                num, den = np.zeros(ch), 0.0
                for u in range(-r, r + 1):
                    for v in range(-r, r + 1):
                        qy, qx = y + u * dilation, xx + v * dilation
                        if not (0 <= qy < h and 0 <= qx < w):
                            continue
                        diff = features[i, :, y, xx] - features[i, :, qy, qx]
                        wq = (c[i, 0, y, xx] if u == v == 0
                              else np.exp(-a[i, 0, y, xx] * diff @ diff))
                        num += wq * radiance[i, :, qy, qx]
                        den += wq
                if kt is not None:
                    rt = (kt - 1) // 2
                    for u in range(-rt, rt + 1):
                        for v in range(-rt, rt + 1):
                            qy, qx = y + u, xx + v
                            if not (0 <= qy < h and 0 <= qx < w):
                                continue
                            diff = features[i, :, y, xx] - prev_f[i, :, qy, qx]
                            omega = on[i] * np.exp(-b[i, 0, y, xx] * diff @ diff)
                            num += omega * prev_out[i, :, qy, qx]
                            den += omega
                out[i, :, y, xx] = num / (eps + den)
    return out


@pytest.mark.parametrize("h,w,k,dilation", [(6, 11, 5, 2), (9, 10, 3, 1), (4, 13, 7, 3)])
def test_dense_numpy_transcription(ops, h, w, k, dilation):
    x = inputs(2, 3, 4, h, w, seed=h + w)
    x[7] = np.array([1.0, 0.0], np.float32)
    spatial = dense_numpy(x, k, dilation)
    temporal = dense_numpy(x, k, dilation, kt=3)
    assert_parity(ops.spatial(x, k, dilation), spatial.astype(np.float32), "op, spatial")
    assert_parity(ref_spatial(x, k, dilation), spatial.astype(np.float32), "torch, spatial")
    assert_parity(ops.temporal(x, k, dilation, 3), temporal.astype(np.float32), "op, temporal")
    assert_parity(ref_temporal(x, k, dilation, 3), temporal.astype(np.float32), "torch")


# ---- threads and the scalar path ----------------------------------------------------------------


def test_results_do_not_depend_on_session_threads(ops):
    x = inputs(2, 3, 8, 45, 61, seed=8)
    np.testing.assert_array_equal(ops.spatial(x, 13, 4, threads=1),
                                  ops.spatial(x, 13, 4, threads=2))
    np.testing.assert_array_equal(ops.temporal(x, 13, 4, 5, threads=1),
                                  ops.temporal(x, 13, 4, 5, threads=2))


_CHILD = '''
import sys
import numpy as np
from test_ops_affinity import affinity_model, inputs, TEMPORAL
from ops_support import make_session
from quietframe.runtime.ops_library import ops_library_path

x = inputs(2, 3, 8, 45, 61, seed=8)
feeds = dict(zip(TEMPORAL, x)) | {"kernel_size": np.array(13), "temporal_kernel_size": np.array(5)}
session = make_session(str(ops_library_path()), affinity_model("AffinityTemporalFilter",
                                                               dilation=4), threads=2)
np.save(sys.argv[1], session.run(None, feeds)[0])
'''


def _run_child(tmp_path, name, **env):
    script = tmp_path / "child.py"
    script.write_text(_CHILD)
    # this module's folder (the child imports it) and tests/ (ops_support)
    tests = os.pathsep.join(str(p) for p in (Path(__file__).parent, Path(__file__).parents[1]))
    path = os.pathsep.join(p for p in (tests, os.environ.get("PYTHONPATH")) if p)
    out = tmp_path / f"{name}.npy"
    subprocess.run([sys.executable, str(script), str(out)], check=True,
                   env={**os.environ, "PYTHONPATH": path, **env})
    return np.load(out)


def test_results_do_not_depend_on_the_band_cut(tmp_path):
    """QUIETFRAME_OPS_NUM_THREADS sets how many bands the rows are cut into (read once per
    process): 1 and 5 CPUs' cuts give the same bits."""
    one = _run_child(tmp_path, "one", QUIETFRAME_OPS_NUM_THREADS="1")
    five = _run_child(tmp_path, "five", QUIETFRAME_OPS_NUM_THREADS="5")
    np.testing.assert_array_equal(one, five)


def test_scalar_reference_path(tmp_path):
    """QUIETFRAME_OPS_SIMD=0 runs the scalar reference loop everywhere: same results to float
    rounding, and the same as torch."""
    vector = _run_child(tmp_path, "vector")
    scalar = _run_child(tmp_path, "scalar", QUIETFRAME_OPS_SIMD="0")
    assert_parity(scalar, vector)
    assert_parity(scalar, ref_temporal(inputs(2, 3, 8, 45, 61, seed=8), 13, 4, 5))


# ---- never Inf/NaN -------------------------------------------------------------------------------

EXTREMES = {
    "negative bandwidth": (2, -50.0),
    "NaN bandwidth": (2, np.nan),
    "Inf bandwidth": (2, np.inf),
    "negative centre": (3, -3.0),
    "NaN centre": (3, np.nan),
    "huge features": (1, 1e30),
    "negative temporal bandwidth": (6, -50.0),
    "NaN temporal bandwidth": (6, np.nan),
}


@pytest.mark.parametrize("name", list(EXTREMES))
def test_extreme_inputs_follow_the_rules_and_stay_finite(ops, name):
    index, value = EXTREMES[name]
    x = inputs(1, 3, 8, 19, 27, seed=9)
    x[index].reshape(-1)[::3] = value  # every third value
    for ours, ref in [(ops.spatial(x, 13, 4), ref_spatial(x, 13, 4)),
                      (ops.temporal(x, 13, 4, 5), ref_temporal(x, 13, 4, 5))]:
        assert np.isfinite(ours).all() and np.isfinite(ref).all()
        assert_parity(ours, ref, name)


def test_huge_finite_radiance_and_odd_temporal_on_stay_finite(ops):
    x = inputs(2, 3, 8, 14, 20, seed=10)
    x[0][:] = 3e38
    x[2][:] = 0  # box filter: sums of many 3e38 overflow float
    x[4][:] = -3e38
    x[7] = np.array([np.nan, -1.0], np.float32)  # both count as 0
    for out in (ops.spatial(x, 13, 1), ops.temporal(x, 13, 1, 13)):
        assert np.isfinite(out).all()
    np.testing.assert_array_equal(ops.temporal(x, 13, 1, 13), ops.spatial(x, 13, 1))


# ---- errors: an exception naming the op ---------------------------------------------------------


def _expect_error(call, op, *words):
    with pytest.raises(Exception) as error:
        call()
    text = str(error.value)
    assert op in text, text
    for word in words:
        assert word in text, text


@pytest.mark.parametrize("k", [0, 2, 14, 33, -1])
def test_bad_kernel_sizes(ops, k):
    x = inputs(1, 3, 8, 6, 7)
    _expect_error(lambda: ops.spatial(x, k, 1), "AffinityFilter", "kernel_size", str(k))
    _expect_error(lambda: ops.temporal(x, 3, 1, k), "AffinityTemporalFilter",
                  "temporal_kernel_size")
    _expect_error(lambda: ops.temporal(x, k, 1, 3), "AffinityTemporalFilter", "kernel_size")


def test_kernel_size_must_be_one_value(ops):
    x = inputs(1, 3, 8, 6, 7)
    session = make_session(str(ops_library_path()), affinity_model("AffinityFilter", dilation=1))
    feeds = dict(zip(SPATIAL, x[:4], strict=False)) | {"kernel_size": np.array([3, 5])}
    _expect_error(lambda: session.run(None, feeds), "AffinityFilter", "kernel_size", "(2)")


def _bad(x, index, shape):
    y = list(x)
    y[index] = np.zeros(shape, np.float32)
    return y


SHAPE_ERRORS = [
    (0, (3, 6, 7), "radiance"),
    (0, (1, 0, 6, 7), "radiance"),
    (1, (1, 8, 6, 8), "features"),
    (1, (2, 8, 6, 7), "features"),
    (1, (8, 6, 7), "features"),
    (2, (1, 2, 6, 7), "bandwidth"),
    (3, (1, 1, 7, 7), "center"),
    (4, (1, 2, 6, 7), "prev_output"),
    (5, (1, 7, 6, 7), "prev_features"),
    (6, (1, 1, 6, 6), "temporal_bandwidth"),
    (7, (2,), "temporal_on"),
    (7, (1, 1), "temporal_on"),
]


@pytest.mark.parametrize("index,shape,word", SHAPE_ERRORS)
def test_shape_errors(ops, index, shape, word):
    x = _bad(inputs(1, 3, 8, 6, 7), index, shape)
    if index < 4:
        _expect_error(lambda: ops.spatial(x, 3, 1), "AffinityFilter", word)
    _expect_error(lambda: ops.temporal(x, 3, 1, 3), "AffinityTemporalFilter", word)
    # the sessions survive errors
    assert ops.spatial(inputs(1, 3, 8, 6, 7), 3, 1).shape == (1, 3, 6, 7)


@pytest.mark.parametrize("op", ["AffinityFilter", "AffinityTemporalFilter"])
@pytest.mark.parametrize("attributes,word", [
    ({"dilation": 0}, "dilation"),
    ({"dilation": None}, "dilation"),
    ({"dilation": 1, "epsilon": -1.0}, "epsilon"),
    ({"dilation": 1, "epsilon": float("inf")}, "epsilon"),
])
def test_bad_attributes(op, attributes, word):
    _expect_error(lambda: make_session(str(ops_library_path()), affinity_model(op, **attributes)),
                  op, word)


def test_epsilon_attribute_is_used(ops):
    x = inputs(1, 3, 8, 9, 10, seed=11)
    x[3][:] = 0
    x[2][:] = 1e30  # den = 0 except where features coincide: out = num / ε
    assert_parity(ops.spatial(x, 3, 1, eps=0.5), ref_spatial(x, 3, 1, eps=0.5))


# ---- the PyTorch reference itself --------------------------------------------------------------


def _double(x, requires_grad=True):
    return [torch.from_numpy(a).double().requires_grad_(requires_grad) for a in x]


def test_gradcheck_spatial():
    x = _double(inputs(1, 2, 3, 5, 6, seed=12, bandwidth_scale=1.0)[:4])
    assert torch.autograd.gradcheck(lambda *t: kernels.spatial_affinity_filter(*t, 3, 2), x)
    assert torch.autograd.gradcheck(lambda *t: kernels.spatial_math(*t, 5, 1), x)


def test_gradcheck_temporal():
    x = _double(inputs(2, 2, 3, 4, 5, seed=13, bandwidth_scale=1.0))
    x[7] = torch.tensor([1.0, 0.0], dtype=torch.float64)
    assert torch.autograd.gradcheck(
        lambda *t: kernels.temporal_affinity_filter(*t, x[7], 3, 1, 3), x[:7])


def test_custom_ops_schema_and_fake_shapes():
    x = [torch.from_numpy(a) for a in inputs(1, 3, 4, 5, 6)]
    torch.library.opcheck(torch.ops.quietframe.affinity_filter.default, (*x[:4], 3, 2),
                          test_utils=("test_schema", "test_faketensor"))
    torch.library.opcheck(torch.ops.quietframe.affinity_temporal_filter.default,
                          (*x, 3, 2, 3), test_utils=("test_schema", "test_faketensor"))
    with pytest.raises(ValueError, match="kernel_size"):
        kernels.spatial_affinity_filter(*x[:4], 4, 1)


def _saved_numel(fn) -> int:
    """Elements that autograd keeps for backward while fn() runs its forward."""
    saved = []

    def pack(t):
        saved.append(t.numel())
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        fn()
    return sum(saved)


def test_reference_keeps_only_its_inputs_for_backward(monkeypatch):
    """Between forward and backward the custom op holds its inputs, not the k² per-offset
    temporaries that autograd through spatial_math would keep; its gradients are those of
    spatial_math all the same (the reference path; the native one: test_affinity_native)."""
    monkeypatch.setenv("QUIETFRAME_TRAIN_KERNELS", "reference")
    x = [torch.from_numpy(a).requires_grad_() for a in inputs(1, 3, 8, 32, 32)[:4]]
    held = _saved_numel(lambda: kernels.spatial_affinity_filter(*x, 13, 4))
    assert held <= sum(t.numel() for t in x)
    assert _saved_numel(lambda: kernels.spatial_math(*x, 13, 4)) > 20 * held
    out = kernels.spatial_affinity_filter(*x, 13, 4)
    grads = torch.autograd.grad(out.square().sum(), x)
    expected = torch.autograd.grad(kernels.spatial_math(*x, 13, 4).square().sum(), x)
    for g, e in zip(grads, expected, strict=True):
        torch.testing.assert_close(g, e)


# ---- export --------------------------------------------------------------------------------------


class _TwoKernels(torch.nn.Module):
    def forward(self, radiance, features, bandwidth, center, prev_output, prev_features,
                temporal_bandwidth, temporal_on):
        x = kernels.spatial_affinity_filter(radiance, features, bandwidth, center, 5, 1)
        return kernels.temporal_affinity_filter(x, features, bandwidth, center, prev_output,
                                                prev_features, temporal_bandwidth, temporal_on,
                                                7, 2, 3)


def test_export_maps_both_functions_to_the_custom_ops():
    from quietframe.export.onnx_export import custom_translation_table

    x = [torch.from_numpy(a) for a in inputs(1, 3, 8, 12, 17, seed=14)]
    with torch.no_grad():
        program = torch.onnx.export(_TwoKernels().eval(), tuple(x), dynamo=True, opset_version=18,
                                    custom_translation_table=custom_translation_table(),
                                    verbose=False)
        expected = _TwoKernels().eval()(*x).numpy()
    proto = program.model_proto
    ops_used = [(n.op_type, n.domain) for n in proto.graph.node if n.domain == OPS_DOMAIN]
    assert ops_used == [("AffinityFilter", OPS_DOMAIN), ("AffinityTemporalFilter", OPS_DOMAIN)]
    session = make_session(str(ops_library_path()), proto.SerializeToString())
    feeds = {i.name: t.numpy() for i, t in zip(proto.graph.input, x, strict=True)}
    assert_parity(session.run(None, feeds)[0], expected)
