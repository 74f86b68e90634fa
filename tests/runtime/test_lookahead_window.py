"""runtime/lookahead: the window (push, pop, a constant delay), the blend on synthetic shots
(a translation gains over the causal output, a disocclusion and a cut are not blended), parity
with experiments/lookahead.py, and what a real causal step leaves in the window."""

from __future__ import annotations

import numpy as np
import pytest

from quietframe.runtime import lookahead
from quietframe.runtime.lookahead import (
    BACKWARD,
    FORWARD,
    Popped,
    causal_worth,
    frame_pieces,
    invert,
    pending,
    pop,
    push,
)

H, W = 40, 48


def _texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth (3, H, W) picture of the scene at scene coordinates (x, y)."""
    return np.stack([0.5 + 0.3 * np.sin(0.31 * x + 0.17 * y),
                     0.5 + 0.3 * np.cos(0.23 * x - 0.29 * y),
                     0.5 + 0.2 * np.sin(0.13 * x + 0.41 * y)]).astype(np.float32)


def translation(n: int, v=(1.5, 0.5), sigma=0.05, seed=0, rendered_forward=True):
    """`n` frames of a smooth surface moving by `v` px a frame: (truth, pieces) per frame,
    D and C the truth plus independent noise, C worth one frame."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    frames = []
    for t in range(n):
        truth = _texture(xs - t * v[0], ys - t * v[1])
        field = np.stack([np.full((H, W), v[0]), np.full((H, W), v[1])]).astype(np.float32)
        pieces = {
            "color": truth + rng.normal(0, sigma, truth.shape).astype(np.float32),
            "stage": truth + rng.normal(0, sigma, truth.shape).astype(np.float32),
            "worth": np.ones((1, H, W), np.float32),
            "albedo": _texture(xs - t * v[0], ys - t * v[1]),
            "normal": np.tile(np.array([0, 0, 1], np.float32)[:, None, None], (1, H, W)),
            "depth": np.full((1, H, W), 3.0, np.float32),
            # w(spp) = 0.35 (1-4 spp): a later frame weighs 1; the edge tests off
            lookahead.LIMITS: np.array([0.35, 0.0, 0.0], np.float32),
        }
        if t:
            pieces[BACKWARD] = -field
        if rendered_forward:
            pieces[FORWARD] = field
        frames.append((truth, pieces))
    return frames


def run(frames, k: int, starts=()) -> list[Popped]:
    """Every frame through a window of depth k as the service runs it: pushed, the oldest
    popped once more than k are pending, the rest finished at the end."""
    window, out = {}, []
    for t, (_, pieces) in enumerate(frames):
        window = push(window, pieces, 10 + t, t == 0 or t in starts)
        if len(pending(window)) > k:
            out.append(pop(window))
            window = out[-1].window
    while pending(window):
        out.append(pop(window))
        window = out[-1].window
    return out


def _mse(a, b, inner=(slice(None), slice(6, -6), slice(6, -6))) -> float:
    return float(np.mean((a[inner] - b[inner]) ** 2))


def test_k0_gives_the_causal_output_itself_and_the_delay_is_constant() -> None:
    frames = translation(5)
    popped = run(frames, 0)
    assert [p.index for p in popped] == [10, 11, 12, 13, 14]
    for p, (_, pieces) in zip(popped, frames, strict=True):
        assert p.color is pieces["color"] and p.used == 0  # the same array: bit for bit
    window, indices = {}, []
    for t, (_, pieces) in enumerate(frames):  # k = 2: the reply to t carries t - 2
        window = push(window, pieces, t, t == 0)
        if len(pending(window)) > 2:
            done = pop(window)
            window = done.window
            indices.append((t, done.index))
    assert indices == [(2, 0), (3, 1), (4, 2)] and pending(window) == [3, 4]


@pytest.mark.parametrize("rendered_forward", [True, False])
def test_a_translation_with_exact_motion_gains_over_the_causal_output(rendered_forward) -> None:
    frames = translation(6, rendered_forward=rendered_forward)
    causal = np.mean([_mse(pieces["color"], truth) for truth, pieces in frames[:4]])
    for k, most in ((1, 0.6), (2, 0.45)):
        popped = run(frames, k)
        blended = np.mean([_mse(p.color, truth) for p, (truth, _) in
                           zip(popped[:4], frames[:4], strict=True)])
        assert blended < most * causal, (k, blended, causal)
        assert popped[0].used == k and popped[0].trusted > 0.8
    assert run(frames, 2)[-1].used == 0  # the last frame has nothing to look at


def test_inverted_backward_motion_is_the_forward_motion() -> None:
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    forward = np.stack([1.2 + 0.02 * xs, -0.7 + 0.01 * ys])  # a zoom: varies over the frame
    # frame t+1's pixel q came from p with p + forward(p) = q: its backward motion at q
    backward = np.stack([(xs - 1.2) / 1.02 - xs, (ys + 0.7) / 1.01 - ys]).astype(np.float32)
    got = invert(backward)
    inner = (slice(None), slice(2, -2), slice(2, -4))
    assert np.abs(got - forward)[inner].max() < 0.05


def test_a_disocclusion_is_not_blended() -> None:
    """A square at depth 1 moves 4 px right over a still wall at depth 5: the wall it covers in
    the next frame keeps its causal output exactly, the rest of the wall is blended."""
    frames = translation(2, v=(0.0, 0.0))
    square = np.zeros((H, W), bool)
    for t, (_, pieces) in enumerate(frames):
        moved = np.zeros((H, W), bool)
        moved[10:20, 10 + 4 * t:20 + 4 * t] = True
        pieces["depth"] = np.where(moved, 1.0, 5.0).astype(np.float32)[None]
        pieces["normal"] = np.where(moved, np.array([0, 1, 0], np.float32)[:, None, None],
                                    pieces["normal"]).astype(np.float32)
        pieces[FORWARD] = np.where(moved, np.float32(4), np.float32(0)) * np.array(
            [1, 0], np.float32)[:, None, None]
        if t:
            pieces[BACKWARD] = -np.where(moved, np.float32(4), np.float32(0)) * np.array(
                [1, 0], np.float32)[:, None, None]
        if t == 0:
            square = moved
    popped = run(frames, 1)[0]
    covered = np.zeros((H, W), bool)
    covered[10:20, 20:24] = True  # wall at t, square at t + 1
    covered &= ~square
    causal = frames[0][1]["color"]
    np.testing.assert_array_equal(popped.color[:, covered], causal[:, covered])
    wall = ~square & ~covered
    wall[:, :2] = wall[:, -2:] = wall[:2] = wall[-2:] = False
    assert (np.abs(popped.color - causal)[:, wall] > 0).mean() > 0.9


def test_a_cut_ends_the_run() -> None:
    frames = translation(4)
    popped = run(frames, 2, starts={2})
    assert [p.used for p in popped] == [1, 0, 1, 0]  # frame 1 does not look past the cut
    np.testing.assert_array_equal(popped[1].color, frames[1][1]["color"])


def test_frames_leave_in_order_and_the_window_refuses_an_older_frame() -> None:
    frames = translation(2)
    window = push({}, frames[0][1], 5, True)
    with pytest.raises(ValueError, match="frame 5 after frame 5"):
        push(window, frames[1][1], 5, False)
    with pytest.raises(ValueError, match="no frame is pending"):
        pop({})


def test_the_worth_is_the_output_historys() -> None:
    from quietframe.experiments.lookahead import causal_worth as experiment_worth
    from quietframe.model import temporal
    from quietframe.model.output_history import VARIANTS

    for name in ("MIN_CURRENT_WEIGHT", "ALIGNED_TOLERANCE", "DEPTH_REL_TOLERANCE",
                 "NORMAL_MIN_DOT"):
        assert getattr(lookahead, name) == getattr(temporal, name), name
    rng = np.random.default_rng(3)
    count = rng.integers(0, 7, (H, W)).astype(np.float32)
    motion = rng.uniform(-2, 2, (2, H, W)).astype(np.float32)
    motion[:, :10] = np.rint(motion[:, :10])  # whole-pixel motion: the 0.2 floor
    motion[:, 15, 15] = 1.0  # whole at one pixel alone: not aligned
    architecture = VARIANTS["oidn-history-cleanaux"].to_dict() | {"family": "output-history"}
    for spp in (1, 4, 16, 64):
        floor = lookahead.current_weight_floor(architecture, spp)
        np.testing.assert_allclose(causal_worth(count, motion, floor)[0],
                                   experiment_worth(count, motion, spp), rtol=1e-6)
    assert lookahead.current_weight_floor({"family": "nbg"}, 4) is None


def test_the_blend_is_the_experiments_blend() -> None:
    """experiments/lookahead.py's default rule with the later frames' D (`oidn`) clipped to
    frame t's D's range (the runtime has no separate per-frame stage S: D is S on sub-pixel
    motion) gives the same output and trust on a shot with a disocclusion."""
    from quietframe.experiments.lookahead import Candidate, Frame, look_ahead

    frames = translation(4, v=(1.25, -0.5), seed=7)
    ys, xs = np.mgrid[0:H, 0:W]
    for t, (_, pieces) in enumerate(frames):  # a post at depth 1 the surface moves behind
        post = (xs >= 20 + t) & (xs < 26 + t) & (ys >= 5)
        pieces["depth"] = np.where(post, 1.0, pieces["depth"][0]).astype(np.float32)[None]
        pieces["worth"] = (1 + (xs + ys) % 3).astype(np.float32)[None]
    experiment = [Frame({"albedo": p["albedo"], "normal": p["normal"], "depth": p["depth"]},
                        p[FORWARD], p.get(BACKWARD, -p[FORWARD]), p["color"], p["worth"][0],
                        p["stage"], p["stage"]) for _, p in frames]
    for pieces in (p for _, p in frames):  # the window keeps the 3×3 mean of the normals
        pieces["normal"] = lookahead.box3(pieces["normal"])
    popped = run(frames, 3)
    for t in range(3):
        theirs, share = look_ahead(experiment, t, 3, Candidate(source="oidn"))
        np.testing.assert_allclose(popped[t].color, theirs, atol=2e-6)
        assert popped[t].trusted == pytest.approx(share, abs=1e-9)
        assert 0.3 < share < 0.99  # the post hides part of what the later frames show


def test_what_a_causal_step_leaves_in_the_window() -> None:
    """An output history tier leaves its OIDN output D, the worth from its history length and
    the aux; a model without an OIDN stage its output alone."""
    from quietframe.bench.synthetic import frame_buffers
    from quietframe.runtime import Denoiser, find_model
    from quietframe.runtime.stream import Stream

    planes = frame_buffers(24, 32, seed=0)
    planes["motion"][:] = 0.5
    planes[FORWARD] = np.full((2, 24, 32), -0.5, np.float32)
    tier = Stream(Denoiser(find_model("oidn-history"), threads=1))
    first = tier.step(planes, None, stated_spp=4)
    second = tier.step(planes, first.state, stated_spp=4)
    architecture = tier.info.card.architecture
    a, b = frame_pieces(first, planes, architecture), frame_pieces(second, planes, architecture)
    assert BACKWARD not in a and BACKWARD in b  # the first frame starts a run
    assert b["stage"] is not None and np.array_equal(b["stage"], second.oidn)
    assert second.spp == 4 and second.history_used and not first.history_used
    count = second.state["accumulation"][0, 7]
    np.testing.assert_array_equal(b["worth"], causal_worth(count, planes["motion"],
                                                           lookahead.current_weight_floor(
                                                               architecture, 4)))
    np.testing.assert_array_equal(b[FORWARD], planes[FORWARD])
    learned = Stream(Denoiser(find_model("nbg-2l-1g"), threads=1))
    step = learned.step(planes, None)
    assert set(frame_pieces(step, planes, learned.info.card.architecture)) == {"color"}


def test_cycles_vector_zw_is_read_as_forward_motion() -> None:
    from quietframe.runtime.exr_channels import resolve

    names = [f"ViewLayer.{p}.{c}" for p, cs in (("Combined", "RGBA"), ("Vector", "XYZW"),
                                                 ("Denoising Albedo", "RGB")) for c in cs]
    sources = resolve(names, ["color"], ["albedo", "motion", FORWARD])
    assert sources["motion"].channels == ("ViewLayer.Vector.X", "ViewLayer.Vector.Y")
    assert sources["motion"].motion_scale == (1.0, -1.0)
    assert sources[FORWARD].channels == ("ViewLayer.Vector.Z", "ViewLayer.Vector.W")
    assert sources[FORWARD].motion_scale == (-1.0, 1.0)
    two = [n for n in names if not n.endswith((".Z", ".W"))]  # a Vector of XY alone
    assert FORWARD not in resolve(two, ["color"], ["motion", FORWARD])


def test_motion_estimated_from_the_aux_is_not_looked_along() -> None:
    """Rendered backward motion inverted chains as far as k; where it was estimated from the
    aux (whose forward-backward check the inversion passes by construction) the frame keeps its
    causal output."""
    frames = translation(5, rendered_forward=False)
    assert run(frames, 3)[0].used == 3
    for _, pieces in frames[1:]:
        pieces[lookahead.ESTIMATED] = np.ones(1, np.uint8)
    popped = run(frames, 3)
    assert [p.used for p in popped] == [0, 0, 0, 0, 0]
    for p, (_, pieces) in zip(popped, frames, strict=True):
        np.testing.assert_array_equal(p.color, pieces["color"])
    for _, pieces in frames:  # rendered forward motion: the estimate is checked against it
        pieces[FORWARD] = np.stack([np.full((H, W), 1.5), np.full((H, W), 0.5)]).astype(
            np.float32)
    assert run(frames, 3)[0].used == 3


def _weight_of_later_frames(frames) -> float:
    """The later frame's share in frame 0's output of a two-frame window, from where D_1 is
    set apart: out = (n C + τ F) / (n + τ)."""
    (_, first), (_, second) = frames
    first["color"][:], first["worth"][:] = 0.0, 1.0
    second["stage"][:] = 1.0
    first["stage"][:] = 0.5  # F is clipped to frame 0's D range: [0.5, 0.5]
    out = run(frames, 1)[0].color
    return float(np.median(out[:, 6:-6, 6:-6]) / 0.5)  # τ / (1 + τ)


def test_a_resampled_later_frame_weighs_what_the_tier_lets_a_resampled_history_weigh() -> None:
    """At w(spp) = 0.575 (8 spp) a later frame fetched at a sub-pixel position weighs
    (1 - w) / w against the causal output's 1; above RESAMPLED_FLOOR_MAX (16 spp: 0.65)
    nothing; a whole-pixel fetch weighs 1 at any spp."""
    for floor, weight in ((0.575, 0.425 / 0.575), (0.65, 0.0), (0.8, 0.0)):
        sub = translation(2, v=(1.5, 0.5))
        for _, pieces in sub:
            pieces[lookahead.LIMITS][0] = floor
        assert _weight_of_later_frames(sub) == pytest.approx(weight / (1 + weight), abs=1e-4)
    whole = translation(2, v=(2.0, 1.0))
    for _, pieces in whole:
        pieces[lookahead.LIMITS][0] = 0.8
    assert _weight_of_later_frames(whole) == pytest.approx(0.5, abs=1e-4)


def test_a_resampled_fetch_across_a_depth_edge_or_mixed_motion_is_not_blended() -> None:
    """The tier's own per-pixel trust: a 3×3 depth range beyond edge_depth, or neighbours whose
    forward motion differs by more than edge_motion, keep the causal output there."""
    frames = translation(2, v=(1.5, 0.5))
    for _, pieces in frames:
        pieces[lookahead.LIMITS][1:] = (0.05, 0.25)
        pieces["depth"][0, :, 24:] = 30.0  # a far wall right of column 24
    frames[0][1][FORWARD][0, 30:] = 3.5  # the bottom rows move otherwise from row 30
    popped = run(frames, 1)[0]
    color, kept = popped.color, frames[0][1]["color"]
    np.testing.assert_array_equal(color[:, 10:20, 23:25], kept[:, 10:20, 23:25])  # the edge
    np.testing.assert_array_equal(color[:, 29:31, 8:16], kept[:, 29:31, 8:16])  # mixed motion
    assert not np.array_equal(color[:, 10:20, 8:16], kept[:, 10:20, 8:16])  # smooth: blended
