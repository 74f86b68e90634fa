"""ai.quietframe::UpsampleBilinear (export/ops/upsample_bilinear.cc) against its PyTorch
reference quietframe.model.resample.upsample_bilinear = F.interpolate(bilinear,
align_corners=False): exact 2×, odd and 1-pixel sizes, non-integer ratios, downsampling, several
images and channels; the thread count and band cut change no bit; the reference's gradient; the
op in an exported graph."""

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
resample = pytest.importorskip("quietframe.model.resample")


def upsample_model() -> bytes:
    inputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in ("image", "like")]
    outputs = [helper.make_tensor_value_info("output", TensorProto.FLOAT, None)]
    node = helper.make_node("UpsampleBilinear", ["image", "like"], ["output"], domain=OPS_DOMAIN)
    graph = helper.make_graph([node], "upsample", inputs, outputs)
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid(OPS_DOMAIN, 1)]
    return helper.make_model(graph, opset_imports=opsets, ir_version=9).SerializeToString()


@pytest.fixture(scope="module")
def run():
    sessions = {}

    def run(image: np.ndarray, height: int, width: int, threads: int = 2) -> np.ndarray:
        if threads not in sessions:
            sessions[threads] = make_session(str(ops_library_path()), upsample_model(), threads)
        like = np.zeros((1, 1, height, width), np.float32)
        return sessions[threads].run(None, {"image": image, "like": like})[0]

    return run


def reference(image: np.ndarray, height: int, width: int) -> np.ndarray:
    like = torch.zeros(1, 1, height, width)
    return resample.upsample_bilinear(torch.from_numpy(image), like).numpy()


def image(*shape: int, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).random(shape) * 4 - 1).astype(np.float32)


@pytest.mark.parametrize("shape, size", [
    ((1, 8, 36, 64), (72, 128)),   # the affinity model at an even frame size: exactly 2×
    ((2, 3, 5, 7), (9, 13)),       # ⌈H/2⌉ × ⌈W/2⌉ of an odd frame back to the frame
    ((1, 1, 1, 1), (4, 6)),        # one pixel: a constant
    ((1, 2, 1, 9), (3, 17)),       # one row
    ((1, 4, 6, 10), (6, 10)),      # same size: a copy
    ((1, 2, 7, 11), (20, 31)),     # non-integer ratio
    ((1, 2, 9, 12), (4, 5)),       # downsampling (no antialiasing, like the reference)
])
def test_matches_the_pytorch_reference(run, shape, size):
    x = image(*shape, seed=sum(shape))
    ours, ref = run(x, *size), reference(x, *size)
    assert ours.shape == (*shape[:2], *size)
    np.testing.assert_allclose(ours, ref, rtol=1e-6, atol=1e-6)


def test_same_size_is_the_input_and_one_pixel_is_a_constant(run):
    x = image(1, 3, 6, 10, seed=3)
    np.testing.assert_array_equal(run(x, 6, 10), x)
    one = image(1, 2, 1, 1, seed=4)
    np.testing.assert_array_equal(run(one, 5, 3), np.broadcast_to(one, (1, 2, 5, 3)))


def test_non_finite_values_stay_where_the_reference_puts_them(run):
    x = image(1, 1, 8, 8, seed=5)
    x[0, 0, 2, 3], x[0, 0, 6, 6] = np.nan, np.inf
    ours, ref = run(x, 16, 16), reference(x, 16, 16)
    np.testing.assert_array_equal(np.isnan(ours), np.isnan(ref))
    np.testing.assert_array_equal(np.isinf(ours), np.isinf(ref))


def test_results_do_not_depend_on_session_threads(run):
    x = image(2, 5, 45, 61, seed=6)
    np.testing.assert_array_equal(run(x, 90, 122, threads=1), run(x, 90, 122, threads=2))


_CHILD = '''
import sys
import numpy as np
from test_ops_upsample import upsample_model
from ops_support import make_session
from quietframe.runtime.ops_library import ops_library_path

x = (np.random.default_rng(7).random((1, 1, 100, 33)) * 4).astype(np.float32)
session = make_session(str(ops_library_path()), upsample_model(), threads=2)
like = np.zeros((1, 1, 200, 66), np.float32)
np.save(sys.argv[1], session.run(None, {"image": x, "like": like})[0])
'''


def test_results_do_not_depend_on_the_band_cut(tmp_path):
    """QUIETFRAME_OPS_NUM_THREADS sets how many bands the rows are cut into: 1 plane of 200
    rows in 1 band or in 12 gives the same bits."""
    script = tmp_path / "child.py"
    script.write_text(_CHILD)
    # this module's folder (the child imports it) and tests/ (ops_support)
    tests = os.pathsep.join(str(p) for p in (Path(__file__).parent, Path(__file__).parents[1]))
    path = os.pathsep.join(p for p in (tests, os.environ.get("PYTHONPATH")) if p)
    results = []
    for cpus in ("1", "7"):
        out = tmp_path / f"{cpus}.npy"
        subprocess.run([sys.executable, str(script), str(out)], check=True,
                       env={**os.environ, "PYTHONPATH": path, "QUIETFRAME_OPS_NUM_THREADS": cpus})
        results.append(np.load(out))
    np.testing.assert_array_equal(*results)


def test_shape_errors_name_the_input(run):
    session = make_session(str(ops_library_path()), upsample_model(), 1)
    with pytest.raises(Exception, match="like must be"):
        session.run(None, {"image": image(1, 1, 4, 4), "like": np.zeros((4, 4), np.float32)})
    with pytest.raises(Exception, match="image must be"):
        session.run(None, {"image": np.zeros((1, 1, 0, 4), np.float32),
                           "like": np.zeros((1, 1, 4, 4), np.float32)})


def test_reference_gradient():
    x = torch.rand(1, 2, 3, 5, dtype=torch.float64, requires_grad=True)
    like = torch.zeros(1, 1, 7, 9, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda t: resample.upsample_bilinear(t, like), (x,))
