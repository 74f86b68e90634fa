"""ai.quietframe::ResampledTrust (export/ops/pixel_aligned.cc) against its PyTorch reference
quietframe.model.temporal.resampled_trust, bit for bit: patchy whole/sub-pixel motion with
history lengths from 0 to past the cap, floors at, below and above MIN_CURRENT_WEIGHT, one
floor or one per image, NaN counts, odd and 1-pixel sizes; the thread count changes no bit;
bad shapes and attributes are errors; nbg-2l-3g's exported graph uses it."""

from __future__ import annotations

import numpy as np
import pytest
from ops_support import make_session, op_model, patchy_motion

from quietframe.runtime.ops_library import ops_library_path

torch = pytest.importorskip("torch")
temporal = pytest.importorskip("quietframe.model.temporal")

def trust_model(min_weight: float = temporal.MIN_CURRENT_WEIGHT,
                max_count: float = 1 / temporal.MIN_CURRENT_WEIGHT) -> bytes:
    return op_model("ResampledTrust", tolerance=temporal.ALIGNED_TOLERANCE,
                    min_weight=min_weight, max_count=max_count)


@pytest.fixture(scope="module")
def run():
    sessions = {}

    def run(motion: np.ndarray, count: np.ndarray, floor: np.ndarray,
            threads: int = 2) -> np.ndarray:
        if threads not in sessions:
            sessions[threads] = make_session(str(ops_library_path()), trust_model(), threads)
        return sessions[threads].run(None, {"motion": motion, "previous_count": count,
                                            "floor": floor})[0]

    return run


def inputs(n: int, h: int, w: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed + 100)
    motion = patchy_motion(n, h, w, seed, temporal.ALIGNED_TOLERANCE)
    count = rng.choice(np.array([0, 0.5, 1, 2, 3, 4.5, 5, 7, 30], np.float32), (n, 1, h, w))
    return motion, count


def reference(motion: np.ndarray, count: np.ndarray, floor: np.ndarray) -> np.ndarray:
    return temporal.resampled_trust(torch.from_numpy(motion), torch.from_numpy(count),
                                    torch.from_numpy(floor)).numpy()


def floors(values: list[float]) -> np.ndarray:
    return np.array(values, np.float32).reshape(-1, 1, 1, 1)


@pytest.mark.parametrize(("n", "h", "w", "seed"), [
    (1, 1, 1, 0), (1, 2, 3, 1), (2, 7, 13, 2), (1, 48, 64, 3), (3, 33, 5, 4)])
@pytest.mark.parametrize("spp", [1.0, 2.0, 4.0, 11.0, 64.0, 512.0])
def test_matches_reference(run, n: int, h: int, w: int, seed: int, spp: float) -> None:
    motion, count = inputs(n, h, w, seed)
    floor = temporal.fading_floor(0.134, torch.tensor([spp])).numpy()  # what the graph feeds
    expected = reference(motion, count, floor)
    np.testing.assert_array_equal(run(motion, count, floor), expected)
    if h * w > 100 and spp > 1:
        assert expected.min() < 1 and expected.max() == 1  # shares and whole histories


def test_one_floor_per_image_and_a_nan_count(run) -> None:
    motion, count = inputs(3, 20, 17, seed=9)
    count[1, 0, 4, :6] = np.nan
    per_image = floors([0.2, 0.5, 0.9])  # the first keeps every history
    got = run(motion, count, per_image)
    np.testing.assert_array_equal(got, reference(motion, count, per_image))
    assert np.all(got[0] == 1) and np.isnan(got[1, 0, 4, :6]).all()


def test_threads_change_no_bit(run) -> None:
    motion, count = inputs(2, 70, 37, seed=7)
    floor = floors([0.6])
    np.testing.assert_array_equal(run(motion, count, floor, threads=1),
                                  run(motion, count, floor, threads=3))


def test_bad_inputs_are_errors() -> None:
    session = make_session(str(ops_library_path()), trust_model(), 1)
    motion, count = inputs(2, 4, 4, seed=1)
    with pytest.raises(Exception, match="ResampledTrust: floor must hold 1 or N = 2 values"):
        session.run(None, {"motion": motion, "previous_count": count, "floor": floors([.5] * 3)})
    with pytest.raises(Exception, match="ResampledTrust"):
        session.run(None, {"motion": motion, "previous_count": count[:, :, :3],
                           "floor": floors([0.5])})
    for bad in ({"min_weight": 0.0}, {"max_count": -1.0}):
        with pytest.raises(Exception, match="ResampledTrust: (min_weight|max_count) must be"):
            make_session(str(ops_library_path()), trust_model(**bad), 1).run(
                None, {"motion": motion, "previous_count": count, "floor": floors([0.5])})


def test_shipped_nbg_uses_the_op() -> None:
    import onnx

    from quietframe.runtime.registry import find_model

    ops = {node.op_type for node in onnx.load(str(find_model("nbg-2l-3g"))).graph.node}
    assert "ResampledTrust" in ops and "PixelAligned" not in ops
