"""SID Temporal baseline (bench/sid_temporal.py): the motion-compensated median of three frames,
its TED fallback, the fake motion blur, and the look-ahead that keeps output t on frame t.

Tiny synthetic frames; most tests replace OIDN by the identity per-frame stage (the noisy
colour), so that what is measured is the temporal stage alone."""

from __future__ import annotations

import numpy as np
import pytest

from quietframe.bench.harness import Frames, score_sequence
from quietframe.bench.sid_temporal import (
    NEXT,
    SIDTemporal,
    feather,
    vector_blur,
    warp,
    with_next_frame,
)

H = W = 32


def identity(planes: dict[str, np.ndarray]) -> np.ndarray:
    return planes["color"]


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(3, H, W) smooth, periodic colour texture at scene positions x, y."""
    base = 0.5 + 0.2 * np.sin(2 * np.pi * x / 11) * np.cos(2 * np.pi * y / 13)
    return np.stack([base, 0.9 * base, 1.1 * base]).astype(np.float32)


def frame(color: np.ndarray, motion: tuple[float, float] = (0.0, 0.0),
          depth: float = 1.0) -> dict[str, np.ndarray]:
    _, h, w = color.shape
    normal = np.zeros((3, h, w), np.float32)
    normal[2] = 1
    return {"color": color.astype(np.float32), "albedo": np.full((3, h, w), 0.5, np.float32),
            "normal": normal, "depth": np.full((1, h, w), depth, np.float32),
            "motion": np.broadcast_to(np.float32(motion)[:, None, None], (2, h, w)).copy()}


def sequence(n: int, velocity: tuple[float, float], noise: float, seed: int = 0,
             motion: tuple[float, float] | None = None) -> tuple[Frames, list[np.ndarray]]:
    """n frames of the texture moving by `velocity` px per frame, independent Gaussian noise
    per frame; the motion buffer is the true backward motion unless `motion` is given, and
    zero on the first frame (as quietframe's renders store it on a shot's first frame)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    vx, vy = velocity
    backward = (-vx, -vy) if motion is None else motion
    frames, clean = [], []
    for t in range(n):
        ref = texture(x - vx * t, y - vy * t)
        noisy = ref + rng.normal(0, noise, ref.shape).astype(np.float32)
        frames.append((frame(noisy, (0, 0) if t == 0 else backward), ref.transpose(1, 2, 0),
                       t == 0))
        clean.append(ref)
    return frames, clean


def run(method: SIDTemporal, frames: Frames) -> list[np.ndarray]:
    """Outputs (3, H, W) through the harness' own scoring loop, with the look-ahead."""
    score = score_sequence(method, method.look_ahead(frames))
    return [o.transpose(2, 0, 1) for o in score.outputs]


def mse(outputs: list[np.ndarray], clean: list[np.ndarray], frames: slice,
        crop: int = 0) -> float:
    inner = (slice(None), slice(crop, H - crop), slice(crop, W - crop))
    return float(np.mean([np.mean((o[inner] - c[inner]) ** 2)
                          for o, c in zip(outputs[frames], clean[frames], strict=True)]))


def test_static_median_reduces_noise() -> None:
    frames, clean = sequence(6, (0, 0), noise=0.05)
    out = run(SIDTemporal(motion_blur=False, per_frame=identity), frames)
    noisy = [f[0]["color"] for f in frames]
    inner = slice(1, -1)  # frames with both neighbours
    assert mse(out, clean, inner) < 0.75 * mse(noisy, clean, inner)
    # without the TED filter the plain median of three (variance ~0.45x for Gaussian noise)
    plain = run(SIDTemporal(motion_blur=False, threshold=0, per_frame=identity), frames)
    assert mse(plain, clean, inner) < 0.6 * mse(noisy, clean, inner)


@pytest.mark.parametrize("previous_vectors", ["previous", "current"])
def test_translation_is_tracked_without_ghosting(previous_vectors: str) -> None:
    frames, clean = sequence(6, (2, -1), noise=0.05)
    out = run(SIDTemporal(motion_blur=False, threshold=0, previous_vectors=previous_vectors,
                          per_frame=identity), frames)
    noisy = [f[0]["color"] for f in frames]
    inner = slice(1, -1)
    tracked = mse(out, clean, inner, crop=3)  # borders: content enters the frame there
    assert tracked < 0.6 * mse(noisy, clean, inner, crop=3)
    # the same frames with zero vectors: the median of misaligned frames ghosts
    still, _ = sequence(6, (2, -1), noise=0.05, motion=(0, 0))
    ghosted = mse(run(SIDTemporal(motion_blur=False, threshold=0, per_frame=identity), still),
                  clean, inner, crop=3)
    assert ghosted > 2 * tracked  # (measured: ~3x)
    # frame 1: frame 0 carries no vectors, frame 1's align it (no ghost there either)
    assert mse(out, clean, slice(1, 2), crop=3) < 0.7 * mse(noisy, clean, slice(1, 2), crop=3)


def test_next_frame_is_aligned_with_its_vectors_the_other_way() -> None:
    # noise-free texture moving 3 px right: the warped neighbours equal frame t in the interior
    frames, clean = sequence(4, (3, 0), noise=0.0)
    prev, cur, nxt = (f[0] for f in frames[1:])
    assert np.allclose(warp(prev["color"], prev["motion"])[:, :, 4:-4], clean[2][:, :, 4:-4])
    assert np.allclose(warp(nxt["color"], -nxt["motion"])[:, :, 4:-4], clean[2][:, :, 4:-4])
    assert not np.allclose(prev["color"][:, :, 4:-4], clean[2][:, :, 4:-4])  # it did move


def test_fallback_keeps_the_current_frame_where_frames_disagree() -> None:
    # a bright square in frame 1 only (e.g. a disocclusion the vectors do not explain)
    background = np.full((3, H, W), 0.2, np.float32)
    square = background.copy()
    square[:, 10:20, 10:20] = 2.0
    frames = [(frame(c), c.transpose(1, 2, 0), t == 0)
              for t, c in enumerate((background, square, background))]
    out = run(SIDTemporal(motion_blur=False, per_frame=identity), frames)[1]
    assert np.allclose(out[:, 10:20, 10:20], 2.0)  # kept, not the median's 0.2
    assert np.allclose(out, np.where(square > 1, 2.0, 0.2))  # elsewhere all frames agree
    # threshold 0 switches the filter off: the median removes the square
    plain = run(SIDTemporal(motion_blur=False, threshold=0, per_frame=identity), frames)[1]
    assert np.allclose(plain, 0.2)


def test_fallback_catches_wrong_vectors() -> None:
    # high-contrast stripes moving 2 px a frame, vectors pointing the wrong way: the aligned
    # neighbours disagree with frame t, and the filter keeps frame t
    x = np.arange(W, dtype=np.float32)
    frames = []
    for t in range(3):
        stripes = np.where(((x - 2 * t) // 4) % 2 == 0, 3.0, 0.0).astype(np.float32)
        color = np.broadcast_to(stripes, (3, H, W)).copy()
        frames.append((frame(color, motion=(2, 0)), color.transpose(1, 2, 0), t == 0))
    out = run(SIDTemporal(motion_blur=False, per_frame=identity), frames)[1]
    current = frames[1][0]["color"]
    assert np.abs(out - current)[:, :, 6:-6].max() < 1e-5
    plain = run(SIDTemporal(motion_blur=False, threshold=0, per_frame=identity), frames)[1]
    assert np.abs(plain - current)[:, :, 6:-6].max() > 1  # what the fallback prevented


def test_outputs_are_aligned_finite_and_respect_cuts() -> None:
    # frame t's per-frame output is distinct (a level per frame, noise-free): a shifted output
    # would show the wrong level; the median of three equal-step levels is the middle one
    levels = [0.3, 0.31, 0.32, 0.9, 0.91, 0.92]
    cut = 3
    frames = [(frame(np.full((3, H, W), v, np.float32)), np.full((H, W, 3), v, np.float32),
               t in (0, cut)) for t, v in enumerate(levels)]
    method = SIDTemporal(motion_blur=False, per_frame=identity)
    looked = method.look_ahead(frames)
    assert NEXT + "color" not in looked[cut - 1][0]  # nothing crosses the cut ...
    assert NEXT + "color" not in looked[-1][0]  # ... or the end
    assert looked[0][0][NEXT + "color"] is frames[1][0]["color"]
    score = score_sequence(method, looked, ("psnr",))
    for t, out in enumerate(score.outputs):
        assert out.shape == (H, W, 3) and np.isfinite(out).all()
        assert np.allclose(out, levels[t]), t
    assert all(np.isinf(p) or p > 60 for p in score.per_frame["psnr"])


def test_evaluate_registers_both_variants_and_looks_ahead() -> None:
    from quietframe.bench.evaluate import Scores, build_methods, run_sequence

    methods = build_methods(1)
    assert {"sid-temporal", "sid-temporal-default"} <= set(methods)
    frames, clean = sequence(4, (0, 0), noise=0.05)
    # through evaluate.run_sequence: it applies the look-ahead (a causal loop would not)
    method, keep = SIDTemporal(motion_blur=False, per_frame=identity), []
    run_sequence(method, frames, Scores(), keep)
    assert method._prev is not None and method._prev.had_next is False  # last frame
    causal = SIDTemporal(motion_blur=False, per_frame=identity)
    with pytest.warns(UserWarning, match="look-ahead"):
        outputs = score_sequence(causal, frames).outputs
    assert np.allclose(outputs[1], frames[1][0]["color"].transpose(1, 2, 0))


def test_oidn_stage_and_default_variant() -> None:
    pytest.importorskip("pyoidn")
    from quietframe.bench.sid_temporal import oidn_per_frame

    frames, clean = sequence(4, (2, 0), noise=0.05)
    oidn = oidn_per_frame(1)
    per_frame = [oidn(f[0]) for f in frames]
    inner = slice(1, -1)
    alone = mse(per_frame, clean, inner, crop=4)
    median = run(SIDTemporal(motion_blur=False, per_frame=oidn), frames)
    assert mse(median, clean, inner, crop=4) < 0.75 * alone  # (measured: ~0.45x)
    default = run(SIDTemporal(num_threads=1), frames)  # the add-on's defaults: blur on
    assert all(o.shape == (3, H, W) and np.isfinite(o).all() for o in default)
    assert mse(default, clean, inner, crop=4) < alone


def test_vector_blur_smears_along_the_motion_only() -> None:
    x = np.arange(W, dtype=np.float32)
    edge = np.broadcast_to(np.where(x < W // 2, 1.0, 0.0).astype(np.float32), (3, H, W))
    depth = np.ones((H, W), np.float32)
    still = np.zeros((2, H, W), np.float32)
    assert np.array_equal(vector_blur(edge, depth, still, still), edge)  # nothing moves
    moving = np.zeros((2, H, W), np.float32)
    moving[0] = -8  # 8 px a frame to the right: Vector.XY and ZW both (-8, 0)
    out = vector_blur(edge, depth, moving, moving)
    profile = out[0, H // 2]
    assert np.allclose(out, out[:, :1])  # no change along y: rows stay equal
    assert 0.05 < profile[W // 2] < 0.95 and 0.05 < profile[W // 2 - 1] < 0.95  # edge smeared
    assert np.allclose(profile[:10], 1) and np.allclose(profile[-10:], 0)  # far from it: as is
    assert np.all(np.diff(profile) <= 1e-6)


def test_feather_follows_blenders_sphere_falloff() -> None:
    # a vertical line: the y pass leaves columns as they are, the x pass gives, one pixel off,
    # the line times f(1)² plus the blur times (1 - f(1)), f = Sphere falloff, radius 3
    mask = np.zeros((9, 15), np.float32)
    mask[:, 7] = 1
    out = feather(mask, 3)
    gauss = np.exp(-0.5 * np.arange(-3, 4) ** 2)
    f1 = np.sqrt(2 * (2 / 3) - (2 / 3) ** 2)
    expected = f1**2 + gauss[4] / gauss.sum() * (1 - f1)
    assert np.allclose(out[:, 7], 1) and np.allclose(out[:, 6], expected, atol=1e-6)
    assert np.allclose(out[:, 8], expected, atol=1e-6)
    assert np.allclose(out[:, :4], 0) and np.allclose(out[:, 11:], 0)  # beyond the radius
    assert np.array_equal(feather(mask, 0), mask)


def test_with_next_frame_keeps_frames_and_references() -> None:
    frames, _ = sequence(3, (0, 0), noise=0.0)
    frames[1][0]["blender_denoise"] = frames[1][0]["color"]  # a stored output never rides
    looked = with_next_frame(frames)
    assert len(looked) == 3
    assert all(a[1] is b[1] and a[2] == b[2] for a, b in zip(looked, frames, strict=True))
    assert NEXT + "blender_denoise" not in looked[0][0]
    assert "color" in looked[0][0] and looked[0][0]["color"] is frames[0][0]["color"]
