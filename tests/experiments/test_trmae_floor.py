"""experiments/trmae_floor.py's pure parts: the floor from arrays, the cache, a method's TRMAE
at given frames. No rendering."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from quietframe.experiments import trmae_floor
from quietframe.model import metrics

RNG = np.random.default_rng(11)


def truth(change: float, h: int = 64, w: int = 64) -> np.ndarray:
    """(2, H, W, 3) noise-free frames whose temporal difference is `change` everywhere."""
    first = RNG.uniform(0.2, 0.6, (h, w, 3))
    return np.stack([first, first + change])


def test_identical_references_have_no_floor():
    ref = truth(0.3)
    figures = trmae_floor.floor_figures(ref, ref.copy())
    assert figures["second_reference"] == figures["perfect_estimate"] == 0.0


def test_independent_gaussian_references_give_sqrt2_when_signal_dominates():
    # |∂t s| = 1 ≫ the noise's ∂t std (0.02·√2): the denominator does not depend on the noise,
    # so the second reference scores √2 × what the noise-free truth scores.
    s, sigma = truth(1.0), 0.02
    stored = s + RNG.normal(0, sigma, s.shape)
    second = s + RNG.normal(0, sigma, s.shape)
    figures = trmae_floor.floor_figures(stored, second)
    perfect = metrics.trmae(s, stored)
    np.testing.assert_allclose(figures["second_reference"] / perfect, np.sqrt(2), rtol=0.02)
    np.testing.assert_allclose(figures["perfect_estimate"], perfect, rtol=0.02)


def test_estimate_is_off_where_noise_dominates():
    # Static truth: |∂t r| is the noise itself, the perfect output scores ~1 and the √2
    # estimate overshoots (the module docstring's caveat).
    s, sigma = truth(0.0), 0.1
    stored = s + RNG.normal(0, sigma, s.shape)
    second = s + RNG.normal(0, sigma, s.shape)
    perfect = metrics.trmae(s, stored)
    assert 0.8 < perfect < 1.0
    assert trmae_floor.floor_figures(stored, second)["perfect_estimate"] > 1.4 * perfect


def test_frozen_output_scores_the_reference_change_ratio():
    ref = truth(0.0) + RNG.normal(0, 0.05, (2, 64, 64, 3))
    d = np.abs(ref[1] - ref[0])
    got = trmae_floor.floor_figures(ref, ref)["frozen_output"]
    np.testing.assert_allclose(got, np.mean(d / (d + metrics.EPS_RELATIVE)), rtol=1e-12)
    assert got < 1


def test_second_reference_is_rendered_once_then_cached(tmp_path: Path):
    seq = tmp_path / "data" / "3000004"
    calls: list[tuple[Path, int]] = []
    image = RNG.uniform(0, 1, (8, 8, 3)).astype(np.float32)

    def render(seq_dir: Path, frame: int) -> np.ndarray:
        calls.append((seq_dir, frame))
        return image

    root = tmp_path / "second_refs"
    first = trmae_floor.second_reference(seq, "test", 2, root, render)
    again = trmae_floor.second_reference(seq, "test", 2, root, render)
    assert calls == [(seq, 2)]
    np.testing.assert_array_equal(first, image)
    np.testing.assert_array_equal(again, image)
    folder = root / "test" / "3000004"
    assert [p.name for p in folder.iterdir()] == ["frame_0002.npy"]


class Counter:
    """Outputs color + the number of frames since the last reset (checks state and resets)."""

    def __init__(self) -> None:
        self.n = 0

    def reset(self) -> None:
        self.n = 0

    def __call__(self, buffers: dict[str, np.ndarray]) -> np.ndarray:
        self.n += 1
        return buffers["color"] + self.n


def test_method_trmae_runs_from_frame_0_and_resets_at_cuts():
    colors = [RNG.uniform(0.1, 1.0, (16, 16, 3)).astype(np.float32) for _ in range(5)]
    refs = [c * 1.1 for c in colors]
    resets = [True, False, False, True, False]
    frames = [({"color": c}, r, reset) for c, r, reset in zip(colors, refs, resets, strict=True)]
    got = trmae_floor.method_trmae(Counter(), frames, [2, 3])
    # frame 2 is the third since the reset at 0, frame 3 the first after the cut
    want = metrics.trmae(np.stack([colors[2] + 3, colors[3] + 1]), np.stack(refs[2:4]))
    assert got == want
