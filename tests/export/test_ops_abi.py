"""Every onnxruntime C API slot the op library uses (export/ops/ort_abi.h), exercised.

docs/ort-abi.md records the slots, their signatures and how each was checked. Here: the slots of
the header and of that page agree; the ones callable without a kernel are called directly on the
installed libonnxruntime through ctypes with our signatures; every other one is driven through the
ops down the path that calls it, checking what it makes observable.
"""

from __future__ import annotations

import ctypes
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
from ops_support import attrs_for, make_session, op_model, spatial_cells

from quietframe.runtime.ops_library import ops_library_path

ROOT = Path(__file__).resolve().parents[2]
API_VERSION = 16


def header_slots() -> dict[str, int]:
    text = (ROOT / "export/ops/ort_abi.h").read_text()
    body = re.search(r"enum Slot : size_t \{(.*?)\};", text, re.S).group(1)
    return {name: int(index) for name, index in re.findall(r"k(\w+) = (\d+),", body)}


def documented_slots() -> dict[str, int]:
    text = (ROOT / "docs/ort-abi.md").read_text()
    return {name: int(index) for index, name in re.findall(r"^\| (\d+) \| (\w+) \|", text, re.M)}


def test_header_and_docs_list_the_same_slots():
    assert header_slots() == documented_slots()
    assert set(header_slots()) == set(SCENARIOS), "every slot needs a scenario below"


# ---- ctypes: the slots that need no kernel, called with our signatures ----------------------

class _ApiBase(ctypes.Structure):
    _fields_ = [("GetApi", ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_uint32)),
                ("GetVersionString", ctypes.CFUNCTYPE(ctypes.c_char_p))]


def _runtime_library() -> ctypes.CDLL:
    folder = Path(ort.__file__).parent / "capi"
    candidates = sorted(folder.glob("libonnxruntime.so*"))
    if not candidates:
        pytest.skip("no libonnxruntime.so in the onnxruntime wheel")
    return ctypes.CDLL(str(candidates[0]))


@pytest.fixture(scope="module")
def api():
    """slot(index, restype, *argtypes) -> the function of that slot of GetApi(16)."""
    lib = _runtime_library()
    lib.OrtGetApiBase.restype = ctypes.POINTER(_ApiBase)
    base = lib.OrtGetApiBase().contents
    assert base.GetVersionString().decode().startswith("1.")
    table = base.GetApi(API_VERSION)
    assert table, "GetApi(16) answered NULL"
    slots = ctypes.cast(table, ctypes.POINTER(ctypes.c_void_p))

    def slot(index, restype, *argtypes):
        return ctypes.CFUNCTYPE(restype, *argtypes)(slots[index])

    return slot


def status_slots(api):
    slots = header_slots()
    create = api(slots["CreateStatus"], ctypes.c_void_p, ctypes.c_int, ctypes.c_char_p)
    code = api(slots["GetErrorCode"], ctypes.c_int, ctypes.c_void_p)
    message = api(slots["GetErrorMessage"], ctypes.c_char_p, ctypes.c_void_p)
    release = api(slots["ReleaseStatus"], None, ctypes.c_void_p)
    return create, code, message, release


def check_status_round_trip(api):
    create, code, message, release = status_slots(api)
    for error_code, text in [(1, b"quietframe: fail"), (2, b"quietframe: invalid argument")]:
        status = create(error_code, text)
        assert status
        assert code(status) == error_code
        assert message(status) == text
        release(status)


def check_domain_create_release(api):
    slots = header_slots()
    create = api(slots["CreateCustomOpDomain"], ctypes.c_void_p, ctypes.c_char_p,
                 ctypes.POINTER(ctypes.c_void_p))
    release = api(slots["ReleaseCustomOpDomain"], None, ctypes.c_void_p)
    domain = ctypes.c_void_p()
    assert not create(b"ai.quietframe.abi_test", ctypes.byref(domain))  # NULL status: success
    assert domain.value
    release(domain)


# ---- ops: the slots that need a kernel --------------------------------------------------------

def _session(model: bytes, threads: int = 2):
    return make_session(str(ops_library_path()), model, threads)


def check_ops_resolve(_api):
    """Registration (CreateCustomOpDomain, CustomOpDomain_Add, AddCustomOpDomain) made every op
    of the library resolvable; without it the same model does not load."""
    model = op_model("BilateralSplat", **attrs_for(4, 4.0))
    _session(model)
    with pytest.raises(Exception, match="BilateralSplat|ai.quietframe"):
        ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    from test_ops_affinity import affinity_model
    from test_ops_upsample import upsample_model
    from test_ops_warp import warp_model

    _session(warp_model(0))
    _session(op_model("BilateralSlice", **attrs_for(4, 4.0)))
    _session(affinity_model("AffinityFilter", dilation=2))
    _session(affinity_model("AffinityTemporalFilter", dilation=2))
    _session(upsample_model())


def check_attributes(_api):
    """int64 and float attributes are read (they set the grid's shape), and a missing one is
    refused with onnxruntime's own message quoted (GetErrorMessage of its status)."""
    image = np.ones((1, 3, 9, 17), np.float32)
    guide = np.full((1, 1, 9, 17), 0.5, np.float32)
    for sigma_s, sigma_r, depth in [(4, 4.0, 66), (8, 16.0, 18)]:
        grid, _ = _session(op_model("BilateralSplat", **attrs_for(sigma_s, sigma_r))).run(
            None, {"image": image, "guide": guide})
        assert grid.shape[2] == depth and grid.shape[4] == spatial_cells(17, sigma_s)
    with pytest.raises(Exception) as error:
        _session(op_model("BilateralSplat", sigma_s=4, sigma_r=4.0))
    text = str(error.value)
    assert "BilateralSplat: attribute 'grid_depth'" in text
    assert re.search(r"is missing or not an int: \S", text), "onnxruntime's message is quoted"
    with pytest.raises(Exception, match="sigma_r"):
        _session(op_model("BilateralSplat", sigma_s=4, sigma_r=4, grid_depth=66))


def check_tensor_queries(_api):
    """Inputs are read through GetTensorTypeAndShape / GetTensorElementType / GetDimensionsCount
    / GetDimensions (the error quotes the exact shape), outputs allocated with GetOutput and
    written through GetTensorMutableData."""
    session = _session(op_model("BilateralSplat", **attrs_for(4, 4.0)))
    with pytest.raises(Exception, match=r"BilateralSplat: guide .* got \(1, 1, 10, 11\)"):
        session.run(None, {"image": np.zeros((1, 3, 10, 12), np.float32),
                           "guide": np.zeros((1, 1, 10, 11), np.float32)})
    with pytest.raises(Exception, match=r"BilateralSplat: image .* got \(3, 10, 12\)"):
        session.run(None, {"image": np.zeros((3, 10, 12), np.float32),
                           "guide": np.zeros((1, 10, 12), np.float32)})
    image = np.full((2, 3, 12, 20), 0.25, np.float32)
    guide = np.full((2, 1, 12, 20), 0.5, np.float32)
    grid, weight = session.run(None, {"image": image, "guide": guide})
    (out,) = _session(op_model("BilateralSlice", **attrs_for(4, 4.0))).run(
        None, {"grid": grid, "weight": weight, "guide": guide})
    assert out.shape == image.shape
    np.testing.assert_allclose(out, image, rtol=1e-6)  # a constant image slices back unchanged
    # an int64 input (the affinity kernel size) next to float32 ones, read as a value
    from test_ops_affinity import affinity_model

    session = _session(affinity_model("AffinityFilter", dilation=1))
    feeds = {"radiance": image, "features": np.zeros((2, 2, 12, 20), np.float32),
             "bandwidth": guide, "center": guide}
    for size, good in [(np.array(3), True), (np.array([5]), True), (np.array(4), False)]:
        if good:
            (out,) = session.run(None, feeds | {"kernel_size": size})
            np.testing.assert_allclose(out, image, rtol=1e-6)
        else:
            with pytest.raises(Exception, match="AffinityFilter: kernel_size .* got 4"):
                session.run(None, feeds | {"kernel_size": size})


def check_parallel_for(_api):
    """Several bands on 2 intra-op threads (KernelContext_ParallelFor on onnxruntime >= 1.17,
    else the library's own threads) give the same bits as one thread."""
    rng = np.random.default_rng(3)
    feeds = {"image": rng.random((1, 3, 96, 64), dtype=np.float32),
             "guide": rng.random((1, 1, 96, 64), dtype=np.float32)}
    model = op_model("BilateralSplat", **attrs_for(4, 4.0))
    one = _session(model, threads=1).run(None, feeds)
    two = _session(model, threads=2).run(None, feeds)
    for a, b in zip(one, two, strict=True):
        np.testing.assert_array_equal(a, b)


SCENARIOS = {
    "CreateStatus": check_status_round_trip,
    "GetErrorCode": check_status_round_trip,
    "GetErrorMessage": check_status_round_trip,
    "ReleaseStatus": check_status_round_trip,
    "CreateCustomOpDomain": check_domain_create_release,
    "ReleaseCustomOpDomain": check_domain_create_release,
    "CustomOpDomain_Add": check_ops_resolve,
    "AddCustomOpDomain": check_ops_resolve,
    "KernelInfoGetAttribute_float": check_attributes,
    "KernelInfoGetAttribute_int64": check_attributes,
    "GetTensorTypeAndShape": check_tensor_queries,
    "GetTensorElementType": check_tensor_queries,
    "GetDimensionsCount": check_tensor_queries,
    "GetDimensions": check_tensor_queries,
    "ReleaseTensorTypeAndShapeInfo": check_tensor_queries,
    "KernelContext_GetInput": check_tensor_queries,
    "KernelContext_GetOutput": check_tensor_queries,
    "GetTensorMutableData": check_tensor_queries,
    "KernelContext_ParallelFor": check_parallel_for,
}


@pytest.mark.parametrize("slot", sorted(header_slots()))
def test_slot_is_exercised(api, slot):
    SCENARIOS[slot](api)


def test_scalar_references_match_the_default_build(tmp_path):
    """QUIETFRAME_OPS_SIMD=0 runs the scalar reference of every SIMD loop; in a fresh process
    (the switch is read once) the three ops must agree with the default paths to float rounding."""
    script = tmp_path / "run.py"
    script.write_text(_SCALAR_SCRIPT)
    outputs = {}
    for simd in ("1", "0"):
        out = tmp_path / f"simd{simd}.npz"
        # this module's folder (test_ops_warp) and tests/ (ops_support)
        tests = os.pathsep.join(str(p) for p in (Path(__file__).parent, Path(__file__).parents[1]))
        path = os.pathsep.join(p for p in (tests, os.environ.get("PYTHONPATH")) if p)
        env = {**os.environ, "QUIETFRAME_OPS_SIMD": simd, "PYTHONPATH": path}
        subprocess.run([sys.executable, str(script), str(out)], check=True, env=env)
        outputs[simd] = np.load(out)
    for name in outputs["1"].files:
        a, b = outputs["1"][name], outputs["0"][name]
        scale = float(np.abs(a).max()) or 1.0
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6 * scale, err_msg=name)


_SCALAR_SCRIPT = '''
import sys
import numpy as np
from ops_support import attrs_for, make_session, op_model
from test_ops_warp import warp_model
from quietframe.runtime.ops_library import ops_library_path

lib = str(ops_library_path())
rng = np.random.default_rng(5)
image = rng.random((1, 3, 45, 77), dtype=np.float32)
guide = rng.random((1, 1, 45, 77), dtype=np.float32)
motion = (rng.standard_normal((1, 2, 45, 77)) * 3).astype(np.float32)
grid, weight = make_session(lib, op_model("BilateralSplat", **attrs_for(4, 4.0))).run(
    None, {"image": image, "guide": guide})
(sliced,) = make_session(lib, op_model("BilateralSlice", **attrs_for(4, 4.0))).run(
    None, {"grid": grid, "weight": weight, "guide": guide})
results = {"grid": grid, "weight": weight, "sliced": sliced}
for mode in (0, 1):
    warped, inside = make_session(lib, warp_model(mode)).run(
        None, {"image": image, "motion": motion})
    results[f"warped{mode}"], results[f"inside{mode}"] = warped, inside
np.savez(sys.argv[1], **results)
'''
