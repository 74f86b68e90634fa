"""ai.quietframe::PixelAligned (export/ops/pixel_aligned.cc) against its PyTorch reference
quietframe.model.temporal.aligned_mask (pixel_aligned as 0/1): motion that is whole in patches,
sub-pixel elsewhere, within and just beyond the tolerance, NaN, the frame's border, 1-pixel and
odd sizes, several images; the thread count changes no bit; a bad shape or tolerance is an
error; the affinity tier's, the aligned accumulation's and the output history's exported
graphs use the op (nbg-2l-3g uses ResampledTrust, which holds the same test)."""

from __future__ import annotations

import numpy as np
import pytest
from ops_support import make_session, op_model, patchy_motion

from quietframe.runtime.ops_library import ops_library_path

torch = pytest.importorskip("torch")
temporal = pytest.importorskip("quietframe.model.temporal")


def aligned_model(tolerance: float = temporal.ALIGNED_TOLERANCE) -> bytes:
    return op_model("PixelAligned", tolerance=tolerance)


@pytest.fixture(scope="module")
def run():
    sessions = {}

    def run(motion: np.ndarray, threads: int = 2) -> np.ndarray:
        if threads not in sessions:
            sessions[threads] = make_session(str(ops_library_path()), aligned_model(), threads)
        return sessions[threads].run(None, {"motion": motion})[0]

    return run


def reference(motion: np.ndarray) -> np.ndarray:
    return temporal.aligned_mask(torch.from_numpy(motion)).numpy()


@pytest.mark.parametrize(("n", "h", "w", "seed"), [
    (1, 1, 1, 0), (1, 2, 3, 1), (2, 7, 13, 2), (1, 48, 64, 3), (3, 33, 5, 4), (1, 64, 40, 5)])
def test_matches_reference(run, n: int, h: int, w: int, seed: int) -> None:
    motion = patchy_motion(n, h, w, seed, temporal.ALIGNED_TOLERANCE)
    expected = reference(motion)
    np.testing.assert_array_equal(run(motion), expected)
    if h * w > 100:
        assert 0 < expected.mean() < 1  # both answers occur


def test_still_frame_is_aligned_everywhere_and_nan_is_not(run) -> None:
    motion = np.zeros((1, 2, 9, 11), np.float32)
    assert np.all(run(motion) == 1)
    motion[0, 1, 4, 5] = np.nan
    got = run(motion)
    np.testing.assert_array_equal(got, reference(motion))
    assert np.all(got[0, 0, 2:7, 3:8] == 0) and got[0, 0, 0, 0] == 1  # 2 px around the NaN


def test_threads_change_no_bit(run) -> None:
    motion = patchy_motion(2, 70, 37, 7, temporal.ALIGNED_TOLERANCE)
    np.testing.assert_array_equal(run(motion, threads=1), run(motion, threads=3))


def test_bad_inputs_are_errors() -> None:
    session = make_session(str(ops_library_path()), aligned_model(), 1)
    with pytest.raises(Exception, match=r"PixelAligned: motion must be \(N, 2, H, W\)"):
        session.run(None, {"motion": np.zeros((1, 3, 4, 4), np.float32)})
    with pytest.raises(Exception, match="PixelAligned: tolerance must be in"):
        make_session(str(ops_library_path()), aligned_model(0.0), 1).run(
            None, {"motion": np.zeros((1, 2, 4, 4), np.float32)})


@pytest.mark.parametrize("name", ["affinity-h16-k5gc", "aligned-accumulation", "oidn-history"])
def test_shipped_tiers_use_the_op(name: str) -> None:
    import onnx

    from quietframe.runtime.registry import find_model

    graph = onnx.load(str(find_model(name))).graph
    assert "PixelAligned" in {node.op_type for node in graph.node}
    # the test as onnxruntime nodes rounded the motion: no Round is left (the output history
    # still rounds it for its test of still pixels, temporal.still_pixels)
    assert sum(node.op_type == "Round" for node in graph.node) == (name == "oidn-history")
