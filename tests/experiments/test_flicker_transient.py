"""experiments/flicker_transient: the one-history floor and the settled flicker ratio."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
from quietframe.experiments.flicker_transient import BASE, flicker_ratio, one_history_ratio  # noqa: E402
from quietframe.model.temporal import MIN_CURRENT_WEIGHT  # noqa: E402


def simulated_history(frames: np.ndarray) -> np.ndarray:
    """The shipped weights written out by hand: 1/n, floored at MIN_CURRENT_WEIGHT."""
    out, history = [], None
    for t, x in enumerate(frames):
        alpha = max(1.0 / (t + 1), MIN_CURRENT_WEIGHT)
        history = x if history is None else alpha * x + (1 - alpha) * history
        out.append(history)
    return np.stack(out)


def test_two_frames_halve_the_deviation():
    # o0 = x0, o1 = (x0 + x1) / 2: the deviations about the mean are half those of x0, x1
    assert one_history_ratio(2) == pytest.approx(0.5)


@pytest.mark.parametrize("frames", [3, 8, 20])
def test_the_floor_matches_a_simulated_history_of_independent_frames(frames):
    x = np.random.default_rng(frames).standard_normal((frames, 200_000))
    ratio = np.sqrt(np.var(simulated_history(x), axis=0).mean() / np.var(x, axis=0).mean())
    assert one_history_ratio(frames) == pytest.approx(ratio, rel=0.01)


def test_settled_ratio_leaves_out_the_start_up():
    rng = np.random.default_rng(0)
    shots = rng.uniform(0.2, 0.8, (2, 8, 4, 4, 3))
    steady = shots.copy()
    steady[:, 3:] = steady[:, 3:4]  # constant from frame 3: only its start moves
    outputs = {BASE: list(shots), "tier": list(steady)}
    assert flicker_ratio(outputs, "tier", 3) == pytest.approx(0.0, abs=1e-12)
    assert 0.0 < flicker_ratio(outputs, "tier", 0) < 1.0
    assert flicker_ratio(outputs, BASE, 0) == 1.0
