"""The onnxruntime custom-op library (export/ops): loading, registration, shapes, errors.

The library is found by quietframe.export.ops_library_path(): next to the installed package, or
QUIETFRAME_OPS_LIBRARY (in the dev venv: build/ops/libquietframe_ops.so).
"""

from __future__ import annotations

import functools
import shutil
import subprocess

import numpy as np
import onnxruntime as ort
import pytest
from ops_support import SCALES, attrs_for, make_session, op_model, range_cells, spatial_cells

from quietframe.runtime.ops_library import ops_library_path


@pytest.fixture(scope="session")
def ops_library() -> str:
    """The built library: next to the installed package, or QUIETFRAME_OPS_LIBRARY."""
    return str(ops_library_path())


@pytest.fixture(scope="session")
def session_for(ops_library):
    """session_for(model_bytes, threads=2) -> InferenceSession with our ops registered."""
    return functools.partial(make_session, ops_library)


def test_library_exports_only_its_entry_point_and_registers(ops_library):
    import ctypes

    import onnxruntime as ort

    library = ctypes.CDLL(ops_library)
    assert hasattr(library, "RegisterCustomOps")  # the entry point (exports.map)
    assert not hasattr(library, "cpu_count")  # internals stay hidden
    ort.SessionOptions().register_custom_ops_library(ops_library)


@pytest.mark.parametrize("sigma_s,sigma_r", SCALES)
@pytest.mark.parametrize(
    "n,c,h,w", [(1, 3, 1, 1), (1, 3, 3, 5), (2, 3, 37, 53), (1, 1, 20, 9), (2, 5, 8, 11)]
)
def test_output_shapes(session_for, sigma_s, sigma_r, n, c, h, w):
    rng = np.random.default_rng(0)
    image = rng.random((n, c, h, w), dtype=np.float32)
    guide = rng.random((n, 1, h, w), dtype=np.float32)
    attrs = attrs_for(sigma_s, sigma_r)
    grid, weight = session_for(op_model("BilateralSplat", **attrs)).run(
        None, {"image": image, "guide": guide}
    )
    cells = (range_cells(sigma_r), spatial_cells(h, sigma_s), spatial_cells(w, sigma_s))
    assert grid.shape == (n, c, *cells) and grid.dtype == np.float32
    assert weight.shape == (n, 1, *cells)
    (out,) = session_for(op_model("BilateralSlice", **attrs)).run(
        None, {"grid": grid, "weight": weight, "guide": guide}
    )
    assert out.shape == (n, c, h, w) and out.dtype == np.float32
    assert np.isfinite(out).all()
    # Every pixel splatted something, so slicing along the same guide reads non-empty cells.
    assert (weight > 0).any() and np.abs(out).max() > 0


def test_spec_cell_counts(session_for):
    """The examples of docs/grid-math.md."""
    image = np.zeros((1, 3, 720, 1280), np.float32)
    guide = np.zeros((1, 1, 720, 1280), np.float32)
    for (sigma_s, sigma_r), depth in zip(SCALES, (66, 34, 18), strict=True):
        _, weight = session_for(op_model("BilateralSplat", **attrs_for(sigma_s, sigma_r))).run(
            None, {"image": image, "guide": guide}
        )
        assert weight.shape[2] == depth
        if sigma_s == 4:
            assert weight.shape[3:] == (182, 322)
    _, weight = session_for(op_model("BilateralSplat", **attrs_for(4, 4.0))).run(
        None, {"image": image[..., :1], "guide": guide[..., :1]}
    )
    assert weight.shape[4] == 2  # W = 1 -> 2 cells


def test_results_do_not_depend_on_thread_count(session_for):
    rng = np.random.default_rng(1)
    image = rng.standard_normal((2, 3, 97, 131)).astype(np.float32)
    guide = rng.random((2, 1, 97, 131), dtype=np.float32)
    model = op_model("BilateralSplat", **attrs_for(4, 4.0))
    one = session_for(model, threads=1).run(None, {"image": image, "guide": guide})
    two = session_for(model, threads=2).run(None, {"image": image, "guide": guide})
    for a, b in zip(one, two, strict=True):
        np.testing.assert_array_equal(a, b)
    slice_model = op_model("BilateralSlice", **attrs_for(4, 4.0))
    feeds = {"grid": one[0], "weight": one[1], "guide": guide}
    np.testing.assert_array_equal(
        session_for(slice_model, threads=1).run(None, feeds)[0],
        session_for(slice_model, threads=2).run(None, feeds)[0],
    )


# ---- errors: an exception whose message names the op, never a crash ---------------------------

BAD_ATTRIBUTES = [
    ({"sigma_s": 4, "sigma_r": 4.0, "grid_depth": 65}, "grid_depth"),
    ({"sigma_s": 0, "sigma_r": 4.0, "grid_depth": 66}, "sigma_s"),
    ({"sigma_s": 4, "sigma_r": -4.0, "grid_depth": 66}, "sigma_r"),
    ({"sigma_s": 4, "sigma_r": float("nan"), "grid_depth": 66}, "sigma_r"),
    ({"sigma_s": None, "sigma_r": 4.0, "grid_depth": 66}, "sigma_s"),
    ({"sigma_s": 4, "sigma_r": None, "grid_depth": 66}, "sigma_r"),
    ({"sigma_s": 4, "sigma_r": 4.0, "grid_depth": None}, "grid_depth"),
    ({"sigma_s": 4, "sigma_r": 4, "grid_depth": 66}, "sigma_r"),  # an int where a float belongs
]


@pytest.mark.parametrize("op", ["BilateralSplat", "BilateralSlice"])
@pytest.mark.parametrize("attributes,word", BAD_ATTRIBUTES)
def test_bad_attributes_raise(session_for, op, attributes, word):
    with pytest.raises(Exception) as error:
        session_for(op_model(op, **attributes))
    assert op in str(error.value) and word in str(error.value)


def run_splat(session_for, image, guide, sigma_s=4, sigma_r=4.0):
    model = op_model("BilateralSplat", **attrs_for(sigma_s, sigma_r))
    return session_for(model).run(None, {"image": image, "guide": guide})


def run_slice(session_for, grid, weight, guide, sigma_s=4, sigma_r=4.0):
    model = op_model("BilateralSlice", **attrs_for(sigma_s, sigma_r))
    return session_for(model).run(None, {"grid": grid, "weight": weight, "guide": guide})[0]


def f32(*shape):
    return np.zeros(shape, np.float32)


@pytest.mark.parametrize(
    "image,guide,word",
    [
        (f32(1, 3, 10, 12), f32(1, 1, 10, 11), "guide"),
        (f32(1, 3, 10, 12), f32(2, 1, 10, 12), "guide"),
        (f32(1, 3, 10, 12), f32(1, 2, 10, 12), "guide"),
        (f32(3, 10, 12), f32(1, 10, 12), "image"),
        (f32(1, 3, 0, 12), f32(1, 1, 0, 12), "image"),
        (f32(0, 3, 10, 12), f32(0, 1, 10, 12), "image"),
    ],
)
def test_splat_shape_errors(session_for, image, guide, word):
    with pytest.raises(Exception) as error:
        run_splat(session_for, image, guide)
    assert "BilateralSplat" in str(error.value) and word in str(error.value)


def test_slice_shape_errors(session_for):
    guide = f32(1, 1, 37, 53)
    good = (1, 3, 66, 11, 15)
    cases = [
        (f32(1, 3, 66, 11, 14), f32(1, 1, 66, 11, 14), "grid"),  # GW of another width
        (f32(1, 3, 66, 10, 15), f32(1, 1, 66, 10, 15), "grid"),  # GH of another height
        (f32(1, 3, 34, 11, 15), f32(1, 1, 34, 11, 15), "grid"),  # D of another sigma_r
        (f32(2, 3, 66, 11, 15), f32(2, 1, 66, 11, 15), "grid"),  # N differs from the guide's
        (f32(*good), f32(1, 3, 66, 11, 15), "weight"),
        (f32(*good), f32(1, 1, 66, 11, 16), "weight"),
        (f32(3, 66, 11, 15), f32(1, 66, 11, 15), "grid"),
    ]
    for grid, weight, word in cases:
        with pytest.raises(Exception) as error:
            run_slice(session_for, grid, weight, guide)
        assert "BilateralSlice" in str(error.value) and word in str(error.value), grid.shape
    with pytest.raises(Exception, match="BilateralSlice.*guide"):
        run_slice(session_for, f32(*good), f32(1, 1, 66, 11, 15), f32(1, 2, 37, 53))
    # The session survives errors: a good call afterwards works.
    out = run_slice(session_for, f32(*good), f32(1, 1, 66, 11, 15), guide)
    assert out.shape == (1, 3, 37, 53) and not out.any()


# ---- loading ----------------------------------------------------------------------------------


def test_wrong_library_path_fails_loudly(tmp_path):
    options = ort.SessionOptions()
    with pytest.raises(Exception, match="libnothing.so"):
        options.register_custom_ops_library(str(tmp_path / "libnothing.so"))


def test_not_a_library_fails_loudly(tmp_path):
    fake = tmp_path / "libquietframe_ops.so"
    fake.write_bytes(b"not an ELF file")
    with pytest.raises(Exception, match="Failed to load"):
        ort.SessionOptions().register_custom_ops_library(str(fake))


def test_override_pointing_nowhere_raises(runtime_env, tmp_path):
    runtime_env("QUIETFRAME_OPS_LIBRARY", str(tmp_path / "missing.so"))
    with pytest.raises(FileNotFoundError, match="QUIETFRAME_OPS_LIBRARY"):
        ops_library_path()


def test_model_without_registration_fails():
    with pytest.raises(Exception, match="BilateralSplat|ai.quietframe"):
        ort.InferenceSession(
            op_model("BilateralSplat", **attrs_for(4, 4.0)), providers=["CPUExecutionProvider"]
        )


@pytest.mark.skipif(shutil.which("nm") is None, reason="needs binutils' nm")
def test_exports_only_register_custom_ops_and_the_training_abi(ops_library):
    if not ops_library.endswith(".so"):
        pytest.skip("ELF only")
    listing = subprocess.run(
        ["nm", "-D", "--defined-only", ops_library], check=True, capture_output=True, text=True
    ).stdout
    symbols = {line.split()[-1] for line in listing.splitlines() if line.strip()}
    training = {"qf_affinity_train_abi_version", "qf_affinity_train_supported",
                "qf_affinity_forward", "qf_affinity_backward"}  # affinity_train_abi.cc
    assert symbols == {"RegisterCustomOps"} | training
