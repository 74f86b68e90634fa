"""The serving pipeline (quietframe.runtime): input rule, buffer checks, state handling."""

from __future__ import annotations

import numpy as np
import pytest

from quietframe.bench.synthetic import frame_buffers
from quietframe.runtime import BufferError, Denoiser, default_model_path, find_model
from quietframe.runtime.sanitize import sanitize_buffer

H, W = 24, 32


def frame(seed: int = 0) -> dict[str, np.ndarray]:
    buffers = frame_buffers(H, W, seed)  # (C, H, W) planes
    buffers["motion"][:] = 0  # a static camera: history lines up
    buffers["albedo"] = 0.1 + 0.8 * buffers["albedo"]
    return buffers


@pytest.fixture(scope="module")
def runtime() -> Denoiser:
    return Denoiser(default_model_path(), threads=1)


def test_colour_rule_counts_and_replaces():
    color = np.ones((2, 3, 3), np.float32)
    color[0, 0] = [np.nan, np.inf, -np.inf]
    color[0, 1, 0] = -2.0
    color[1, 2, 1] = 1e35
    original = color.copy()
    clean, count = sanitize_buffer("color", color)
    assert count == 5
    assert clean[0, 0].tolist() == [0, 0, 0] and clean[0, 1, 0] == 0
    assert clean[1, 2, 1] == np.float32(65504)  # the radiance ceiling (half max)
    np.testing.assert_array_equal(color, original)  # the caller's array is untouched


def test_depth_rule_uses_the_farthest_finite_depth():
    depth = np.array([[1.0, np.inf], [3.0, -1.0]], np.float32)
    clean, count = sanitize_buffer("depth", depth)
    assert count == 2 and clean.tolist() == [[1.0, 3.0], [3.0, 3.0]]
    clean, count = sanitize_buffer("normal", np.array([[[np.nan, -1.0, 0.5]]], np.float32))
    assert count == 1 and clean.tolist() == [[[0.0, -1.0, 0.5]]]


def test_missing_required_buffer_names_what_is_needed():
    runtime = Denoiser(find_model("accumulation"), threads=1)  # needs albedo (demodulation)
    buffers = frame()
    del buffers["albedo"]
    with pytest.raises(BufferError, match=r"missing required buffers \['albedo'\]"):
        runtime.denoise(buffers, None)


def test_wrong_size_buffer_is_rejected(runtime):
    buffers = frame()
    buffers["depth"] = buffers["depth"][:, :-1]
    with pytest.raises(BufferError, match="buffer 'depth' has shape"):
        runtime.denoise(buffers, None)


def test_state_is_returned_not_mutated_and_history_matters(runtime):
    first = runtime.denoise(frame(0), None)
    before = {k: v.copy() for k, v in first.state.items()}
    second = runtime.denoise(frame(1), first.state)
    for name, tensor in first.state.items():
        np.testing.assert_array_equal(tensor, before[name])
    fresh = runtime.denoise(frame(1), None)
    assert np.abs(second.color - fresh.color).max() > 1e-4  # the history was used
    # The graph's reset flag ignores whatever state comes with it (a cut with a stale history).
    feeds = {f"state_in.{k}": v for k, v in first.state.items()}
    feeds.update({k: v[None] for k, v in frame(1).items()}, reset=np.ones(1, np.float32))
    feeds.update(runtime.option_feeds)  # run-time inputs (the frame's spp) as the runtime feeds
    reset = runtime.session.run(["denoised"], feeds)[0][0]
    np.testing.assert_allclose(reset, fresh.color, rtol=1e-6, atol=1e-6)


def test_hostile_values_never_leave_non_finite(runtime):
    buffers = frame()
    buffers["color"][:, 0, 0] = np.nan
    buffers["color"][:, 1, 1] = np.inf
    buffers["color"][:, 2, 2] = 1e38
    buffers["depth"][:, 3, 3] = np.inf
    buffers["motion"][:, 4, 4] = np.nan
    result = runtime.denoise(buffers, None)
    assert np.isfinite(result.color).all()
    assert result.sanitized == {"color": 9, "depth": 1, "motion": 2}  # values, not pixels
    result = runtime.denoise({k: np.zeros_like(v) for k, v in frame().items()}, None)
    assert np.isfinite(result.color).all() and np.abs(result.color).max() == 0  # black frame


def test_missing_motion_is_a_static_camera(runtime):
    buffers = frame()
    with_zero_motion = runtime.denoise(buffers, None)
    del buffers["motion"]
    without = runtime.denoise(buffers, None)
    assert without.missing == ("motion",) and with_zero_motion.missing == ()
    np.testing.assert_array_equal(without.color, with_zero_motion.color)


def test_find_model_by_name_and_unknown():
    assert find_model("accumulation").name == "accumulation.onnx"
    with pytest.raises(LookupError, match="unknown model 'nope'; installed"):
        find_model("nope")
