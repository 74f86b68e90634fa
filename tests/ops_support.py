"""Helpers shared by the tests of the custom-op library (test_ops_library, test_ops_parity,
test_ops_pixel_aligned, test_ops_resampled_trust, test_ops_albedo_prefilter)."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
from onnx import TensorProto, helper

from quietframe.runtime.ops_library import OPS_DOMAIN

SCALES = [(4, 4.0), (8, 8.0), (16, 16.0)]


def range_cells(sigma_r: float) -> int:
    return int(np.floor(255.0 / sigma_r - 0.5)) + 3


def spatial_cells(n: int, sigma_s: int) -> int:
    return (2 * n - 1 - sigma_s) // (2 * sigma_s) + 3


def op_model(op: str, **attributes) -> bytes:
    """One-node model of our op; attributes given as None are left out."""
    names = {
        "BilateralSplat": (["image", "guide"], ["grid", "weight"]),
        "BilateralSlice": (["grid", "weight", "guide"], ["image"]),
        "PixelAligned": (["motion"], ["aligned"]),
        "ResampledTrust": (["motion", "previous_count", "floor"], ["trust"]),
        "AlbedoPrefilter": (["albedo", "spp"], ["albedo_out"]),
    }[op]
    inputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in names[0]]
    outputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in names[1]]
    attrs = {k: v for k, v in attributes.items() if v is not None}
    node = helper.make_node(op, names[0], names[1], domain=OPS_DOMAIN, **attrs)
    graph = helper.make_graph([node], op, inputs, outputs)
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid(OPS_DOMAIN, 1)]
    # IR 9: readable by every supported onnxruntime (>= 1.16).
    return helper.make_model(graph, opset_imports=opsets, ir_version=9).SerializeToString()


def attrs_for(sigma_s: int, sigma_r: float) -> dict:
    return {"sigma_s": sigma_s, "sigma_r": sigma_r, "grid_depth": range_cells(sigma_r)}


def make_session(library: str, model: bytes, threads: int = 2) -> ort.InferenceSession:
    """An onnxruntime session of `model` with the custom-op library at `library` registered."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.register_custom_ops_library(library)
    return ort.InferenceSession(model, options, providers=["CPUExecutionProvider"])


def patchy_motion(n: int, h: int, w: int, seed: int, tolerance: float) -> np.ndarray:
    """(n, 2, h, w) motion: whole pixels in random rectangles (some nudged by up to twice the
    alignment `tolerance`), sub-pixel elsewhere."""
    rng = np.random.default_rng(seed)
    motion = rng.uniform(-3, 3, (n, 2, h, w)).astype(np.float32)
    for i in range(n):
        for _ in range(6):
            y, x = rng.integers(0, h), rng.integers(0, w)
            dy, dx = rng.integers(1, 17), rng.integers(1, 17)
            motion[i, :, y:y + dy, x:x + dx] = rng.integers(-4, 5, (2, 1, 1))
            if rng.random() < 0.3:  # a nudge inside or just outside the tolerance
                nudge = rng.uniform(-2 * tolerance, 2 * tolerance, (2, 1, 1))
                motion[i, :, y:y + dy, x:x + dx] += nudge.astype(np.float32)
    return motion
