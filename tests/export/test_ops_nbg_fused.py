"""ai.quietframe::NBGAccumulate / NBGFeatures / NBGBlend / NBGBlendPass / NBGBlendNoise
(export/ops/nbg_fused.cc) against their PyTorch references (quietframe.model.nbg_fused): odd
sizes, several images, edge values (reset, out-of-frame history, zero-length and flipped
normals, negative radiance, saturated logits, histories and spp the noise level spans); the
thread count changes no bit; fused_forward computes NBGDenoiser.forward, with and without the
pass-through; the shipped nbg-2l-3g.onnx uses the fused ops."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper
from ops_support import make_session

from quietframe.runtime.ops_library import OPS_DOMAIN, ops_library_path

torch = pytest.importorskip("torch")
fused = pytest.importorskip("quietframe.model.nbg_fused")
temporal = pytest.importorskip("quietframe.model.temporal")

REPO = Path(__file__).resolve().parents[2]
OPS = {
    "NBGAccumulate": (["radiance", "warped", "inside", "depth", "normal", "reset"],
                      ["accumulated", "state"],
                      {"depth_tolerance": temporal.DEPTH_REL_TOLERANCE,
                       "normal_min_dot": temporal.NORMAL_MIN_DOT,
                       "min_current_weight": temporal.MIN_CURRENT_WEIGHT}),
    "NBGFeatures": (["radiance", "safe_albedo", "albedo", "normal", "depth", "depth_scale"],
                    ["features"], {"exponent": fused.LDR_EXPONENT}),
    "NBGBlend": (["logits", "safe_albedo", "sliced0", "sliced1", "sliced2"], ["denoised"], {}),
    "NBGBlendPass": (["logits", "safe_albedo", "sliced0", "sliced1", "sliced2", "accumulated",
                      "frame"], ["denoised"], {}),
    "NBGBlendNoise": (["logits", "safe_albedo", "sliced0", "sliced1", "sliced2", "accumulated",
                       "frame", "state", "spp", "noise_scale", "noise_shift"], ["denoised"], {}),
}


def op_model(op: str) -> bytes:
    inputs, outputs, attributes = OPS[op]
    node = helper.make_node(op, inputs, outputs, domain=OPS_DOMAIN, **attributes)
    graph = helper.make_graph(
        [node], op, [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in inputs],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in outputs])
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid(OPS_DOMAIN, 1)]
    return helper.make_model(graph, opset_imports=opsets, ir_version=9).SerializeToString()


@pytest.fixture(scope="module")
def run():
    sessions = {}

    def run(op: str, feeds: dict[str, np.ndarray], threads: int = 2) -> list[np.ndarray]:
        if (op, threads) not in sessions:
            sessions[op, threads] = make_session(str(ops_library_path()), op_model(op), threads)
        return sessions[op, threads].run(None, feeds)

    return run


def unit_normals(rng: np.random.Generator, n: int, h: int, w: int) -> np.ndarray:
    normal = rng.standard_normal((n, 3, h, w)).astype(np.float32)
    return normal / np.linalg.norm(normal, axis=1, keepdims=True)


def accumulate_inputs(n: int, h: int, w: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    normal = unit_normals(rng, n, h, w)
    depth = (1 + rng.random((n, 1, h, w)) * 4).astype(np.float32)
    # A history that is the same surface on about half the pixels, another elsewhere.
    same = rng.random((n, 1, h, w)) < 0.5
    warped_depth = np.where(same, depth * 1.02, depth * 1.5).astype(np.float32)
    warped_normal = np.where(same, normal * 0.8, unit_normals(rng, n, h, w))
    warped_normal[:, :, 0, 0] = 0  # zero-length: never the same surface
    count = rng.integers(-1, 12, (n, 1, h, w)).astype(np.float32)  # beyond the clamp both ways
    warped = np.concatenate((rng.random((n, 3, h, w)) * 3, warped_depth, warped_normal, count),
                            axis=1).astype(np.float32)
    reset = np.zeros(n, np.float32)
    reset[-1] = 1.0 if n > 1 else 0.0
    return {"radiance": (rng.random((n, 3, h, w)) * 4 - 0.5).astype(np.float32),
            "warped": warped,
            "inside": (rng.random((n, 1, h, w)) < 0.9).astype(np.float32),
            "depth": depth, "normal": normal, "reset": reset}


def features_inputs(n: int, h: int, w: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    albedo = (rng.random((n, 3, h, w)) * 1.4 - 0.2).astype(np.float32)
    depth = (rng.random((n, 1, h, w)) * 50).astype(np.float32)
    return {"radiance": (rng.standard_normal((n, 3, h, w)) * 5).astype(np.float32),
            "safe_albedo": (0.01 + rng.random((n, 3, h, w))).astype(np.float32),
            "albedo": albedo,
            "normal": (rng.standard_normal((n, 3, h, w)) * 1.5).astype(np.float32),
            "depth": depth,
            "depth_scale": np.maximum(depth.mean(axis=(2, 3), keepdims=True), 1e-6)}


def blend_inputs(n: int, h: int, w: int, seed: int = 0,
                 passthrough: bool = False) -> dict[str, np.ndarray]:
    """NBGBlend's inputs, or with `passthrough` NBGBlendPass's (two more logits, the
    accumulated and the frame's irradiance)."""
    rng = np.random.default_rng(seed)
    candidates = 3 + 2 * int(passthrough)
    logits = (rng.standard_normal((n, 3 + candidates, h, w)) * 4).astype(np.float32)
    logits[:, 3, 0, :] = 90.0  # exp overflows without the max subtracted
    logits[:, -1, -1, :] = 90.0  # the last candidate's too (a tie in a one-row image)
    feeds = {"logits": logits, "safe_albedo": (0.01 + rng.random((n, 3, h, w))).astype(np.float32)}
    for g in range(3):
        feeds[f"sliced{g}"] = (rng.random((n, 3, h, w)) * 3).astype(np.float32)
    if passthrough:  # irradiance: not clamped, may be negative
        for name in ("accumulated", "frame"):
            feeds[name] = (rng.random((n, 3, h, w)) * 4 - 0.5).astype(np.float32)
    return feeds


def blend_pass_inputs(n: int, h: int, w: int, seed: int = 0) -> dict[str, np.ndarray]:
    return blend_inputs(n, h, w, seed, passthrough=True)


def blend_noise_inputs(n: int, h: int, w: int, seed: int = 0,
                       spp: tuple[float, ...] | None = None) -> dict[str, np.ndarray]:
    """NBGBlendNoise's: NBGBlendPass's, a state with histories of 1..6 frames, `spp` (default:
    1, 4, 64, ... one per image), and a modulation of both signs. The saturated logits of
    candidates 0 and 4 get a positive scale, so they still overflow exp unless the max is
    subtracted; the others' turn negative at the larger levels."""
    rng = np.random.default_rng(seed + 100)
    feeds = blend_pass_inputs(n, h, w, seed)
    state = (rng.random((n, 8, h, w)) * 3).astype(np.float32)
    state[:, 7] = rng.integers(1, 7, (n, h, w))
    spp = tuple((1.0, 4.0, 64.0)[i % 3] for i in range(n)) if spp is None else spp
    signs = np.array([1, -1, 1, -1, 1], np.float32)
    return feeds | {
        "state": state, "spp": np.array(spp, np.float32),
        "noise_scale": (signs * rng.uniform(0.3, 1.5, 5)).astype(np.float32),
        "noise_shift": (-signs * rng.uniform(0.5, 3.0, 5)).astype(np.float32)}


def blend_noise(logits, safe_albedo, sliced0, sliced1, sliced2, accumulated, frame, state, spp,
                noise_scale, noise_shift):
    """fused.blend_noise with NBGBlendNoise's inputs in its order."""
    return fused.blend_noise(logits, safe_albedo, (sliced0, sliced1, sliced2),
                             (accumulated, frame), state, spp, noise_scale, noise_shift)


REFERENCES = {
    "NBGAccumulate": (fused.accumulate_warped, accumulate_inputs),
    "NBGFeatures": (fused.features_scaled, features_inputs),
    "NBGBlend": (fused.blend_sliced, blend_inputs),
    "NBGBlendPass": (fused.nbg_blend_pass, blend_pass_inputs),  # blend_sliced(passthrough=)
    "NBGBlendNoise": (blend_noise, blend_noise_inputs),
}


@pytest.mark.parametrize("op", sorted(OPS))
@pytest.mark.parametrize("shape", [(1, 48, 64), (2, 7, 13), (1, 1, 1), (3, 33, 5)])
def test_matches_reference(run, op: str, shape: tuple[int, int, int]) -> None:
    reference, make_inputs = REFERENCES[op]
    feeds = make_inputs(*shape)
    want = reference(*(torch.from_numpy(feeds[name]) for name in OPS[op][0]))
    want = want if isinstance(want, tuple) else (want,)
    got = run(op, feeds)
    for g, w in zip(got, want, strict=True):
        assert g.shape == tuple(w.shape)
        np.testing.assert_allclose(g, w.numpy(), rtol=2e-6, atol=1e-6)


def noise_reference(feeds: dict[str, np.ndarray]) -> np.ndarray:
    return blend_noise(*(torch.from_numpy(feeds[name]) for name in OPS["NBGBlendNoise"][0]))


@pytest.mark.parametrize("spp", [(1.0,), (4.0,), (64.0,), (1.0, 64.0), (64.0, 4.0)])
def test_blend_noise_matches_reference_at_every_spp(run, spp: tuple[float, ...]) -> None:
    """One spp for both images (shape [1]) or one each ([N]); with histories of 1..6 frames
    the level spans log2(1..384) / 10. Larger than a block of the op, and in blocks of one
    history length too (the op takes one log2 for those)."""
    feeds = blend_noise_inputs(2, 37, 301, seed=5, spp=spp)
    feeds["state"][0, 7, :20] = 3.0
    (got,) = run("NBGBlendNoise", feeds)
    np.testing.assert_allclose(got, noise_reference(feeds).numpy(), rtol=2e-6, atol=1e-6)


def test_blend_noise_without_modulation_is_the_pass_through_blend(run) -> None:
    feeds = blend_noise_inputs(2, 9, 11)
    feeds["noise_scale"][:] = 0.0
    feeds["noise_shift"][:] = 0.0
    (noise,) = run("NBGBlendNoise", feeds)
    (plain,) = run("NBGBlendPass", {name: feeds[name] for name in OPS["NBGBlendPass"][0]})
    np.testing.assert_array_equal(noise, plain)


def test_blend_noise_level_saturates_and_keeps_nan(run) -> None:
    """Below one sample the level is 0, from 1024 on 1 (the clamps); a NaN history is NaN."""
    feeds = blend_noise_inputs(1, 4, 8, spp=(512.0,))
    state = feeds["state"]
    state[0, 7, 0] = 0.0  # no samples: level 0
    state[0, 7, 1] = 2.0  # 1024 samples: level 1
    state[0, 7, 2] = 1e30  # far beyond: level 1
    state[0, 7, 3, :4] = np.nan
    (got,) = run("NBGBlendNoise", feeds)
    want = noise_reference(feeds).numpy()
    np.testing.assert_allclose(got, want, rtol=2e-6, atol=1e-6)  # NaN where the reference's
    assert np.isnan(got[0, :, 3, :4]).all() and np.isfinite(got[0, :, :3]).all()


def test_reset_and_out_of_frame_drop_history(run) -> None:
    feeds = accumulate_inputs(2, 9, 11)
    feeds["inside"][0, 0, :3] = 0.0
    accumulated, state = run("NBGAccumulate", feeds)
    # No history kept: the frame alone, a history of length 1.
    np.testing.assert_array_equal(accumulated[1], feeds["radiance"][1])
    np.testing.assert_array_equal(state[1, 7], 1.0)
    np.testing.assert_array_equal(accumulated[0, :, :3], feeds["radiance"][0, :, :3])
    np.testing.assert_array_equal(state[:, 3:7], np.concatenate((feeds["depth"],
                                                                 feeds["normal"]), axis=1))


@pytest.mark.parametrize("op", sorted(OPS))
def test_threads_change_no_bit(run, op: str) -> None:
    feeds = REFERENCES[op][1](2, 67, 45, seed=3)
    for a, b in zip(run(op, feeds, threads=1), run(op, feeds, threads=3), strict=True):
        np.testing.assert_array_equal(a, b)


def test_wrong_shape_is_an_error(run) -> None:
    feeds = blend_inputs(1, 8, 8)
    feeds["sliced1"] = feeds["sliced1"][:, :, :4]
    with pytest.raises(Exception, match="NBGBlend: sliced1 must be"):
        run("NBGBlend", feeds)


def test_blend_logits_must_match_the_candidates(run) -> None:
    """A pass-through model's 8 logits given to NBGBlend, or a plain model's 6 to NBGBlendPass,
    is an error that says which count the op wants, not a read past the logits."""
    feeds = blend_pass_inputs(1, 8, 8)
    without = {k: v for k, v in feeds.items() if k not in ("accumulated", "frame")}
    with pytest.raises(Exception, match=r"NBGBlend: logits must be \(N, 6, H, W\)"):
        run("NBGBlend", without)
    feeds["logits"] = feeds["logits"][:, :6]
    with pytest.raises(Exception, match=r"NBGBlendPass: logits must be \(N, 8, H, W\) = "
                                        r"\(1, 8, 8, 8\) like the image, got \(1, 6, 8, 8\)"):
        run("NBGBlendPass", feeds)


@pytest.mark.parametrize(("name", "value", "message"), [
    ("logits", np.zeros((2, 6, 5, 7), np.float32),
     r"logits must be \(N, 8, H, W\) = \(2, 8, 5, 7\) like the image, got \(2, 6, 5, 7\)"),
    ("state", np.zeros((2, 7, 5, 7), np.float32),
     r"state must be \(N, 8, H, W\) = \(2, 8, 5, 7\) like the image, got \(2, 7, 5, 7\)"),
    ("state", np.zeros((2, 8, 5, 6), np.float32), r"state must be \(N, 8, H, W\)"),
    ("frame", np.zeros((1, 3, 5, 7), np.float32),
     r"frame must be \(N, 3, H, W\) = \(2, 3, 5, 7\) like the image, got \(1, 3, 5, 7\)"),
    ("safe_albedo", np.zeros((2, 3, 4, 7), np.float32), r"safe_albedo must be \(N, 3, H, W\)"),
    ("spp", np.ones(3, np.float32), r"spp must be \(1,\) or \(N,\) = \(2,\), got \(3\)"),
    ("spp", np.ones((2, 1), np.float32),
     r"spp must be \(1,\) or \(N,\) = \(2,\), got \(2, 1\)"),
    ("noise_scale", np.ones(4, np.float32),
     r"noise_scale must be \(5,\), one per blend candidate, got \(4\)"),
    ("noise_shift", np.ones((1, 5), np.float32),
     r"noise_shift must be \(5,\), one per blend candidate, got \(1, 5\)"),
])
def test_blend_noise_wrong_inputs_are_errors(run, name: str, value: np.ndarray,
                                              message: str) -> None:
    feeds = blend_noise_inputs(2, 5, 7) | {name: value}
    with pytest.raises(Exception, match="NBGBlendNoise: " + message):
        run("NBGBlendNoise", feeds)


def _frames(model, count: int = 3, seed: int = 0):
    """(inputs, reference outputs) of `count` frames of a sequence through the PyTorch model,
    the state carried."""
    from quietframe.export.onnx_export import example_inputs

    state, frames = None, []
    for t in range(count):
        inputs = example_inputs(40, 56, seed=seed + t)
        inputs = (*inputs[:5], torch.tensor([float(t == 0)]), inputs[6] if state is None
                  else state)
        with torch.no_grad():
            output, state = model(*inputs)
        frames.append((inputs, output, state))
    return frames


@pytest.mark.parametrize("passthrough", [False, True])
def test_fused_forward_is_the_model(passthrough: bool) -> None:
    from dataclasses import replace

    from quietframe.model.nbg import VARIANTS, NBGDenoiser

    torch.manual_seed(0)
    model = NBGDenoiser(replace(VARIANTS["nbg-2l-3g"], passthrough=passthrough)).eval()
    assert fused.fusable(model)
    for inputs, output, state in _frames(model):
        with torch.no_grad():
            got, got_state = fused.fused_forward(model, *inputs)
        torch.testing.assert_close(got, output, rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(got_state, state, rtol=1e-6, atol=1e-6)


def test_shipped_nbg_2l_3g_uses_the_fused_ops() -> None:
    """(tests/export/test_export.py holds the shipped file to its checkpoint's PyTorch model.)"""
    path = REPO / "models" / "nbg-2l-3g.onnx"
    if not path.is_file():
        pytest.skip("nbg-2l-3g is not in this checkout")
    model = onnx.load(str(path))
    ops = {n.op_type for n in model.graph.node}
    props = {p.key: p.value for p in model.metadata_props}
    architecture = json.loads(props["quietframe.architecture"])
    blend = ("NBGBlendNoise" if architecture.get("noise_blend")
             else "NBGBlendPass" if architecture.get("passthrough") else "NBGBlend")
    assert {"NBGAccumulate", "NBGFeatures", blend} <= ops


def test_only_three_grids_fuse() -> None:
    from dataclasses import replace

    from quietframe.model.nbg import VARIANTS, NBGDenoiser

    for passthrough in (False, True):
        one_grid = replace(VARIANTS["nbg-2l-1g"], passthrough=passthrough)
        assert not fused.fusable(NBGDenoiser(one_grid))
