"""bench/lookahead_method: `<tier>/lookahead-<k>` scores the shipped look-ahead like any method:
k = 0 is the tier itself, each output is scored against its own frame's reference, a flagged
cut is not looked across, and zoo_eval builds it by name."""

from __future__ import annotations

import numpy as np
import pytest

from quietframe.bench.evaluate import Scores, run_sequence
from quietframe.bench.harness import RuntimeMethod, score_sequence
from quietframe.bench.lookahead_method import LookaheadMethod, lookahead_methods
from quietframe.bench.synthetic import frame_buffers
from quietframe.runtime import find_model

H, W = 24, 32


def static_shot(n: int, cut_at: int | None = None):
    """`n` frames of one still picture (zero motion), fresh colour noise each, the clean
    picture as the reference; a cut at `cut_at` flagged."""
    base = frame_buffers(H, W, seed=0)
    base["motion"][:] = 0
    rng = np.random.default_rng(1)
    clean = (0.2 + 0.6 * base["albedo"]).astype(np.float32)
    frames = []
    for t in range(n):
        planes = {**base, "color": (clean + rng.normal(0, 0.1, clean.shape)).clip(0).astype(
            np.float32)}
        frames.append((planes, clean.transpose(1, 2, 0), t == 0 or t == cut_at))
    return frames


def outputs(method, frames) -> list[np.ndarray]:
    if hasattr(method, "look_ahead"):
        frames = method.look_ahead(frames)
    return score_sequence(method, frames).outputs


@pytest.fixture(scope="module")
def tier():
    return find_model("oidn-fast-history")


def test_k0_is_the_tier_and_k2_is_scored_frame_by_frame(tier) -> None:
    frames = static_shot(5)
    causal = outputs(RuntimeMethod(tier, threads=1), frames)
    same = outputs(LookaheadMethod(RuntimeMethod(tier, threads=1), 0), frames)
    assert all(np.array_equal(a, b) for a, b in zip(causal, same, strict=True))
    ahead = LookaheadMethod(RuntimeMethod(tier, threads=1), 2)
    blended = outputs(ahead, frames)
    assert np.array_equal(blended[-1], causal[-1])  # nothing after the last frame
    clean = frames[0][1]
    for t in range(4):  # closer to frame t's reference than its causal output
        assert np.abs(blended[t] - clean).mean() < np.abs(causal[t] - clean).mean()
    assert ahead.blended == 4 and min(ahead.trusted) > 0.5
    scores = Scores()
    run_sequence(LookaheadMethod(RuntimeMethod(tier, threads=1), 2), frames, scores)
    assert len(scores.per_frame["psnr"]) == 5


def test_a_flagged_cut_is_not_looked_across(tier) -> None:
    frames = static_shot(4, cut_at=2)
    causal = outputs(RuntimeMethod(tier, threads=1), frames)
    blended = outputs(LookaheadMethod(RuntimeMethod(tier, threads=1), 2), frames)
    assert np.array_equal(blended[1], causal[1])  # the run of frames 0-1 ends at the cut
    assert not np.array_equal(blended[0], causal[0])
    assert np.array_equal(blended[3], causal[3])


def test_zoo_eval_builds_lookahead_methods_by_name(tier) -> None:
    base = {"oidn-fast-history": lambda: RuntimeMethod(tier, threads=1)}
    made = lookahead_methods(base, ["oidn-fast-history/lookahead-2", "nbg/lookahead-1",
                                    "oidn-fast-history/lookahead-x", "oidn-fast-history"])
    assert list(made) == ["oidn-fast-history/lookahead-2"]
    assert made["oidn-fast-history/lookahead-2"]().k == 2
    with pytest.raises(ValueError, match="0..4"):
        LookaheadMethod(RuntimeMethod(tier, threads=1), 5)
