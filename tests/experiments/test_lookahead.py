"""experiments/lookahead: Cycles' Vector signs, the carry along forward motion with its
forward-backward check, the bicubic fetch (the tier's own), and the blend's trust."""

from __future__ import annotations

import numpy as np

from quietframe.experiments.lookahead import (
    Candidate,
    Frame,
    backward_motion,
    carry,
    forward_motion,
    look_ahead,
    sample_bicubic,
)

H, W = 24, 32


def _frame(colour: float, shift: float, rng, causal: float | None = None) -> Frame:
    """A frame of a flat surface moving `shift` px right per frame (forward +shift, backward
    −shift), its outputs all `colour` (the causal one `causal`)."""
    planes = {"albedo": np.full((3, H, W), 0.5, np.float32),
              "normal": np.tile(np.array([0, 0, 1], np.float32)[:, None, None], (1, H, W)),
              "depth": np.full((1, H, W), 3.0, np.float32),
              "motion": np.zeros((2, H, W), np.float32)}
    forward = np.zeros((2, H, W), np.float32)
    forward[0] = shift
    image = np.full((3, H, W), colour, np.float32)
    return Frame(planes, forward, -forward, image if causal is None else
                 np.full((3, H, W), causal, np.float32), np.full((H, W), 2.0, np.float32),
                 image + rng.normal(0, 1e-4, image.shape).astype(np.float32))


def test_vector_signs_follow_cycles_convention() -> None:
    # Cycles: XY = pos(t-1) - pos(t), ZW = pos(t) - pos(t+1), raster y up. A point moving
    # right by 2 px and down (rows) by 1 px per frame:
    vector = np.zeros((4, 1, 1), np.float32)
    vector[:, 0, 0] = (-2.0, 1.0, -2.0, 1.0)
    assert forward_motion(vector)[:, 0, 0].tolist() == [2.0, 1.0]  # where it is at t + 1
    assert backward_motion(vector)[:, 0, 0].tolist() == [-2.0, -1.0]  # where it was at t - 1


def test_carry_chains_hops_and_flags_frame_exits_and_broken_round_trips() -> None:
    rng = np.random.default_rng(0)
    frames = [_frame(0.5, 1.5, rng) for _ in range(3)]
    frames[2].backward[:, 5, 10:] = 3.0  # frame 2 disagrees about where row 5 came from
    hops = list(carry(frames, 0, 2))
    x, y, ok = hops[1]
    xs = np.arange(W, dtype=np.float32)
    np.testing.assert_allclose(x[0], xs + 3.0)  # two hops of 1.5 px
    np.testing.assert_allclose(y[:, 0], np.arange(H))
    assert ok[0, : W - 3].all() and not ok[0, W - 3:].any()  # carried out of the frame
    assert not ok[5, 7:W - 3].any() and ok[6, : W - 3].all()  # round trip off by ~4 px
    _, _, unchecked = list(carry(frames, 0, 2, fb_check=False))[1]
    assert unchecked[5, : W - 3].all()


def test_bicubic_fetch_is_exact_on_pixels_and_matches_the_tiers_history_fetch() -> None:
    import torch

    from quietframe.model.temporal import backward_warp

    rng = np.random.default_rng(1)
    image = rng.uniform(0, 1, (2, H, W)).astype(np.float32)
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    np.testing.assert_allclose(sample_bicubic(image, xs, ys), image, atol=1e-6)
    motion = rng.uniform(-1.5, 1.5, (2, H, W)).astype(np.float32)
    ours = sample_bicubic(image, xs + motion[0], ys + motion[1])
    theirs, _ = backward_warp(torch.from_numpy(image)[None], torch.from_numpy(motion)[None],
                              mode="bicubic")
    inner = (slice(None), slice(4, -4), slice(4, -4))  # the frame's border is clamped alike
    np.testing.assert_allclose(ours[inner], theirs[0].numpy()[inner], atol=1e-5)


def test_blend_weights_trusted_later_frames_and_ignores_other_surfaces() -> None:
    rng = np.random.default_rng(2)
    # causal 0.2 worth 2 frames, two later frames' stages 0.5: (2·0.2 + 0.5 + 0.5) / 4
    frames = [_frame(0.5, 0.0, rng, causal=0.2), _frame(0.5, 0.0, rng), _frame(0.5, 0.0, rng)]
    out, share = look_ahead(frames, 0, 2, Candidate(clamp=False))
    np.testing.assert_allclose(out, 0.35, atol=1e-3)
    assert share == 1.0
    frames[1].planes["depth"][:] = 6.0  # frame 1 shows another surface: untrusted
    frames[2].planes["normal"][:] = np.array([1, 0, 0], np.float32)[:, None, None]
    out, share = look_ahead(frames, 0, 2, Candidate(clamp=False))
    np.testing.assert_allclose(out, 0.2, atol=1e-6)
    assert share == 0.0
    out, _ = look_ahead(frames, 2, 2, Candidate())  # the last frame: nothing to look at
    assert out is frames[2].causal
