"""experiments/history_keep: the surface test's verdict on a locked-off shot, synthetic frames."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
from quietframe.experiments.history_keep import measure_sequence  # noqa: E402


def locked_off(frames: int, normal_jitter: float, seed: int = 0) -> list[dict[str, np.ndarray]]:
    """A static plane at depth 3 with noisy colour; normals jittered per frame by `normal_jitter`
    (what averaging a few samples over a bumpy surface does), zero motion."""
    rng = np.random.default_rng(seed)
    h = w = 16
    out = []
    for _ in range(frames):
        normal = np.zeros((h, w, 3), np.float32)
        normal[..., 2] = 1
        normal[..., :2] = rng.normal(0, normal_jitter, (h, w, 2))
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        out.append({"color": rng.gamma(1.0, 0.5, (h, w, 3)).astype(np.float32),
                    "depth": np.full((h, w, 1), 3.0, np.float32), "normal": normal,
                    "motion": np.zeros((h, w, 2), np.float32)})
    return out


def test_clean_aux_keeps_every_pixel_and_halves_the_noise():
    r = measure_sequence(locked_off(8, 0.0), [True] + [False] * 7)
    assert r["kept"] == 1.0 and r["depth_fails"] == 0.0 and r["normal_fails"] == 0.0
    assert r["frames_held"] == pytest.approx(6.0)  # the count saturates at 1 / 0.2 + 1
    assert r["noise_left"] == pytest.approx(r["noise_left_all_kept"])
    assert r["noise_left"] < 0.6


def test_noisy_normals_reject_history_that_all_kept_would_use():
    r = measure_sequence(locked_off(8, 0.5), [True] + [False] * 7)
    assert r["normal_fails"] > 0.3 and r["depth_fails"] == 0.0
    assert r["kept"] < 0.7 and r["frames_held"] < r["frames_held_all_kept"]
    assert r["noise_left"] > r["noise_left_all_kept"] + 0.1
