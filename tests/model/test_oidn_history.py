"""The oidn-history tiers (model/output_history.py): the stage's behaviour in PyTorch, the
composition (aligned accumulation -> OIDN -> output history) through the runtime against the
same steps in PyTorch, and the stage against the ablation row it ships
(experiments/output_history)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
from quietframe.export.onnx_export import export_nbg  # noqa: E402
from quietframe.model import output_history as oh  # noqa: E402
from quietframe.model.nbg import AccumulationDenoiser  # noqa: E402
from quietframe.model.temporal import MIN_CURRENT_WEIGHT  # noqa: E402

H, W = 20, 28


def surface(frames: int, motion: tuple[float, float], seed: int = 0) -> list[dict]:
    """Noisy 'OIDN outputs' of one flat surface under a constant motion, as (1, C, H, W)
    tensors: the stage's inputs."""
    gen = torch.Generator().manual_seed(seed)
    normal = torch.zeros(1, 3, H, W)
    normal[:, 2] = 1
    move = torch.tensor(motion, dtype=torch.float32).view(1, 2, 1, 1).expand(1, 2, H, W)
    return [{"oidn": 0.5 + 0.2 * torch.rand(1, 3, H, W, generator=gen),
             "albedo": torch.full((1, 3, H, W), 0.5), "normal": normal,
             "depth": torch.full((1, 1, H, W), 3.0), "motion": move.contiguous()}
            for _ in range(frames)]


def run_stage(stage, frames: list[dict], reset_at: tuple[int, ...] = (0,)) -> list[torch.Tensor]:
    state, outputs = stage.initial_state(1, H, W), []
    for index, f in enumerate(frames):
        reset = torch.tensor([1.0 if index in reset_at else 0.0])
        with torch.no_grad():
            out, state = stage(f["oidn"], f["albedo"], f["normal"], f["depth"], f["motion"],
                               reset, state)
        outputs.append(out)
    return outputs


def test_locked_off_history_is_the_running_mean_then_exponential():
    frames = surface(8, (0.0, 0.0))
    outputs = run_stage(oh.OutputHistory(), frames)
    torch.testing.assert_close(outputs[0], frames[0]["oidn"])  # a first frame: no history
    expected = frames[0]["oidn"]
    for n, f in enumerate(frames[1:], start=2):
        alpha = max(1 / n, MIN_CURRENT_WEIGHT)
        expected = alpha * f["oidn"] + (1 - alpha) * expected
        torch.testing.assert_close(outputs[n - 1], expected, rtol=1e-5, atol=1e-6)
    noise = torch.stack([f["oidn"] for f in frames[3:]]).std(dim=0).mean()
    assert torch.stack(outputs[3:]).std(dim=0).mean() < 0.5 * noise


def test_sub_pixel_history_stays_within_the_frame_neighbourhood():
    frames = surface(5, (0.37, -0.61))
    frames[0]["oidn"] = frames[0]["oidn"] * 40  # a history the later frames do not support
    outputs = run_stage(oh.OutputHistory(), frames)
    for f, out in zip(frames[1:], outputs[1:], strict=True):
        low = -torch.nn.functional.max_pool2d(-f["oidn"], 3, 1, 1)
        high = torch.nn.functional.max_pool2d(f["oidn"], 3, 1, 1)
        assert bool(((out >= low - 1e-6) & (out <= high + 1e-6)).all())


def test_reset_and_disocclusion_drop_the_history():
    frames = surface(3, (0.0, 0.0))
    frames[1]["oidn"] = frames[1]["oidn"] + 5  # differs from frame 0 everywhere
    outputs = run_stage(oh.OutputHistory(), frames, reset_at=(0, 1))
    torch.testing.assert_close(outputs[1], frames[1]["oidn"])
    moved = surface(2, (0.0, 0.0))
    moved[1]["depth"][..., :, :10] = 9.0  # another surface came into view on the left
    out = run_stage(oh.OutputHistory(), moved)[1]
    torch.testing.assert_close(out[..., :, :10], moved[1]["oidn"][..., :, :10])
    assert not torch.allclose(out[..., 1:, 12:], moved[1]["oidn"][..., 1:, 12:])
    assert bool(torch.isfinite(out).all())


def test_resampled_history_is_weighted_less_than_exact_history():
    """Under sub-pixel motion the current frame weighs at least resampled_weight; under
    whole-pixel motion the history keeps the accumulation's weights (here 1/6 -> 0.2)."""
    stripes = torch.where(torch.arange(W) % 2 == 0, 1.0, 0.4).expand(1, 3, H, W)
    for shift, alpha in ((1.0, MIN_CURRENT_WEIGHT), (0.5, 0.5)):
        frames = surface(6, (shift, 0.0))
        frames[0]["motion"] = torch.zeros_like(frames[0]["motion"])
        for f in frames[:-1]:  # a constant history: any fetch of it reads 0.5
            f["oidn"] = torch.full_like(f["oidn"], 0.5)
        frames[-1]["oidn"] = stripes.contiguous()  # its 3x3 range [0.4, 1] does not clip 0.5
        config = oh.OutputHistoryConfig(resampled_weight=0.5, resampled_weight_per_doubling=0)
        out = run_stage(oh.OutputHistory(config), frames)[-1]
        centre = out[0, 0, H // 2, W // 2].item()  # an even column: the frame has 1.0 there
        assert centre == pytest.approx(alpha * 1.0 + (1 - alpha) * 0.5, abs=1e-5)


def test_resampled_floor_rises_with_spp_within_its_bounds():
    config = oh.OutputHistoryConfig()
    floor = {spp: config.resampled_floor(torch.tensor([float(spp)])).item()
             for spp in (0.25, 1, 4, 64, 1e6)}
    assert floor[0.25] == pytest.approx(floor[1]) == pytest.approx(config.resampled_weight)
    assert floor[4] == pytest.approx(0.5)  # the constant shipped before: the default spp
    assert floor[1] < floor[4] < floor[64] < floor[1e6] == pytest.approx(
        config.resampled_weight_max)


# the shipped weights without the shading and detail tests
FLOOR_ALONE = oh.OutputHistoryConfig(shading_change=0.0, resampling_detail=0.0)


def test_a_cleaner_frame_keeps_less_resampled_history():
    """Under sub-pixel motion the current frame weighs w(spp); the default spp is 4 spp's;
    under whole-pixel motion the spp changes nothing."""
    stripes = torch.where(torch.arange(W) % 2 == 0, 1.0, 0.4).expand(1, 3, H, W)

    def centre(spp: float | None, shift: float) -> float:
        frames = surface(6, (shift, 0.0))
        frames[0]["motion"] = torch.zeros_like(frames[0]["motion"])
        for f in frames[:-1]:  # a constant history: any fetch of it reads 0.5
            f["oidn"] = torch.full_like(f["oidn"], 0.5)
        frames[-1]["oidn"] = stripes.contiguous()  # its 3x3 range [0.4, 1] does not clip 0.5
        # the floor alone: the shading and detail tests would reject the history, which
        # differs from the stripes by more than they allow at 64 spp
        stage = oh.OutputHistory(FLOOR_ALONE)
        state, given = stage.initial_state(1, H, W), None if spp is None else torch.tensor([spp])
        for index, f in enumerate(frames):
            with torch.no_grad():
                out, state = stage(f["oidn"], f["albedo"], f["normal"], f["depth"],
                                   f["motion"], torch.tensor([float(index == 0)]), state, given)
        return out[0, 0, H // 2, W // 2].item()  # an even column: the frame has 1.0 there

    floor = oh.OutputHistoryConfig().resampled_floor
    for spp in (1.0, 64.0):
        alpha = floor(torch.tensor([spp])).item()
        assert centre(spp, 0.5) == pytest.approx(alpha + (1 - alpha) * 0.5, abs=1e-5)
        assert centre(spp, 1.0) == pytest.approx(0.2 + 0.8 * 0.5, abs=1e-5)
    assert centre(None, 0.5) == pytest.approx(centre(4.0, 0.5))
    assert centre(1.0, 0.5) < centre(4.0, 0.5) < centre(64.0, 0.5)


TRUSTING = oh.OutputHistoryConfig()  # the shipped per-pixel trust (version 4)
VERSION2 = oh.OutputHistoryConfig(edge_depth=0, edge_motion=0, exact_edge_motion=0,
                                   shading_change=0, resampling_detail=0)  # none


def _constant_history_then(frames: list[dict], last: torch.Tensor) -> list[dict]:
    for f in frames[:-1]:  # a constant history: any fetch of it reads 0.5
        f["oidn"] = torch.full_like(f["oidn"], 0.5)
    frames[-1]["oidn"] = last.contiguous()
    return frames


def test_a_resampled_history_is_not_trusted_across_a_depth_edge():
    """Under sub-pixel motion a pixel within a pixel of a depth edge (now, or around where it
    was in the previous frame) is its per-frame stage; a pixel on one flat surface keeps the
    history; pixel-aligned motion keeps it at the edge too (nearest is exact there)."""
    stripes = torch.where(torch.arange(W) % 2 == 0, 1.0, 0.4).expand(1, 3, H, W)
    for shift, trusted_at_edge in ((0.5, False), (1.0, True)):
        frames = _constant_history_then(surface(4, (shift, 0.0)), stripes)
        for f in frames:  # a thin post 2 px wide at columns 12-13, far wall elsewhere
            f["depth"][..., 12:14] = 1.0
        out = run_stage(oh.OutputHistory(TRUSTING), frames)[-1]
        untrusted = run_stage(oh.OutputHistory(VERSION2), frames)[-1]
        edge = out[0, 0, H // 2, 14]  # beside the post: its 3x3 depth range spans both
        flat = out[0, 0, H // 2, 20]  # an even column on the wall, 6 px from the post
        frame = frames[-1]["oidn"]
        if trusted_at_edge:
            torch.testing.assert_close(edge, untrusted[0, 0, H // 2, 14])
        else:
            torch.testing.assert_close(edge, frame[0, 0, H // 2, 14])
            assert not torch.isclose(untrusted[0, 0, H // 2, 14], frame[0, 0, H // 2, 14])
        torch.testing.assert_close(flat, untrusted[0, 0, H // 2, 20])
        assert not torch.isclose(flat, frame[0, 0, H // 2, 20])


def test_the_previous_frames_edge_at_the_fetch_is_tested_too():
    """A post that was at columns 12-13 in the previous frame and has left: the pixels whose
    fetch lands beside where it was take the frame, though their own depth is flat now."""
    stripes = torch.where(torch.arange(W) % 2 == 0, 1.0, 0.4).expand(1, 3, H, W)
    frames = _constant_history_then(surface(4, (0.4, 0.0)), stripes)
    for f in frames[:-1]:
        f["depth"][..., 12:14] = 1.0
    out = run_stage(oh.OutputHistory(TRUSTING), frames)[-1]
    frame = frames[-1]["oidn"]
    # p + 0.4 is nearest p: columns 11 and 14 pass the surface test at their own pixel, but
    # their target's 3x3 touches the post (12-13 fail it: the post was there)
    torch.testing.assert_close(out[..., 11:15], frame[..., 11:15])
    before = run_stage(oh.OutputHistory(VERSION2), frames)[-1]
    assert not torch.allclose(before[..., 11], frame[..., 11])
    assert not torch.allclose(out[..., 18:22], frame[..., 18:22])


def _halves_moving(left: float, right: float) -> list[dict]:
    """A constant history, then stripes; the left half moves `left` px a frame, the right half
    `right` (from the second frame on)."""
    stripes = torch.where(torch.arange(W) % 2 == 0, 1.0, 0.4).expand(1, 3, H, W)
    frames = _constant_history_then(surface(4, (left, 0.0)), stripes)
    for f in frames[1:]:
        f["motion"][:, 0, :, W // 2:] = right
    return frames


def test_a_resampled_history_is_not_trusted_where_neighbours_move_differently():
    """Parallax: the left half moves 0.3 px a frame, the right half 1.3 px: the pixels at the
    seam take the frame, each half keeps its history."""
    frames = _halves_moving(0.3, 1.3)
    out = run_stage(oh.OutputHistory(TRUSTING), frames)[-1]
    frame = frames[-1]["oidn"]
    torch.testing.assert_close(out[..., W // 2 - 1:W // 2 + 1], frame[..., W // 2 - 1:W // 2 + 1])
    assert not torch.allclose(out[..., 4:8], frame[..., 4:8])
    assert not torch.allclose(out[..., W - 8:W - 4], frame[..., W - 8:W - 4])


def test_an_exact_fetch_beside_pixels_that_move_otherwise_is_not_trusted():
    """A still wall (zero motion: exact fetches) beside a turning object (the right half moves
    2 px a frame): the wall's pixels at the seam held what passed over them and take the frame;
    the wall away from it keeps its history, and a locked-off frame keeps it everywhere."""
    frames = _halves_moving(0.0, 2.0)
    out = run_stage(oh.OutputHistory(TRUSTING), frames)[-1]
    frame = frames[-1]["oidn"]
    torch.testing.assert_close(out[..., W // 2 - 1], frame[..., W // 2 - 1])  # the wall's seam
    assert not torch.allclose(out[..., 4:8], frame[..., 4:8])
    before = run_stage(oh.OutputHistory(VERSION2), frames)[-1]
    assert not torch.allclose(before[..., W // 2 - 1], frame[..., W // 2 - 1])
    still = _halves_moving(0.0, 0.0)  # locked off: no motion anywhere
    torch.testing.assert_close(run_stage(oh.OutputHistory(TRUSTING), still)[-1],
                               run_stage(oh.OutputHistory(VERSION2), still)[-1])


def _stage_at(spp: float, frames: list[dict], config: oh.OutputHistoryConfig = TRUSTING
              ) -> torch.Tensor:
    stage, state = oh.OutputHistory(config), None
    state = stage.initial_state(1, H, W)
    for index, f in enumerate(frames):
        with torch.no_grad():
            out, state = stage(f["oidn"], f["albedo"], f["normal"], f["depth"], f["motion"],
                               torch.tensor([float(index == 0)]), state, torch.tensor([spp]))
    return out


def test_a_shading_change_the_motion_does_not_follow_takes_the_frame_at_high_spp():
    """A caustic moving over a still-shaded surface: the history (0.5) and the frame (stripes
    1.0 / 0.4, inside the clip's range) differ by far more than a clean 64-spp frame's error,
    so the pixel is its stage there; at 1 spp the same difference is the frame's noise and the
    history is kept, and a frame within a few per cent of its history keeps it at 64 spp."""
    no_detail = oh.OutputHistoryConfig(resampling_detail=0.0)  # the shading test alone
    stripes = torch.where(torch.arange(W) % 2 == 0, 1.0, 0.4).expand(1, 3, H, W)
    frames = _constant_history_then(surface(4, (0.5, 0.0)), stripes)
    frame = frames[-1]["oidn"]
    centre = (..., slice(H // 2 - 2, H // 2 + 2), slice(10, 18))
    torch.testing.assert_close(_stage_at(64.0, frames, no_detail)[centre], frame[centre])
    assert not torch.allclose(_stage_at(1.0, frames, no_detail)[centre], frame[centre])
    assert not torch.allclose(_stage_at(64.0, frames, VERSION2)[centre], frame[centre])
    close = _constant_history_then(surface(4, (0.5, 0.0)),
                                   torch.full((1, 3, H, W), 0.5) + 0.005 * (stripes - 0.7))
    assert not torch.allclose(_stage_at(64.0, close, no_detail)[centre],
                              close[-1]["oidn"][centre])
    at = [TRUSTING.shading_threshold(torch.tensor([s])).item() for s in (1.0, 16.0, 64.0)]
    assert at[0] > at[1] > at[2] and at[1] == pytest.approx(TRUSTING.shading_change)


def test_detail_a_bicubic_fetch_blurs_takes_the_frame_at_high_spp():
    """One-pixel stripes under half-pixel motion: a fetch of their history blurs them, so at
    64 spp each pixel is its stage; a smooth ramp under the same motion keeps its history, and
    so do the stripes at 1 spp (the history's averaging is worth the blur there)."""
    no_shading = oh.OutputHistoryConfig(shading_change=0.0)  # the detail test alone
    stripes = torch.where(torch.arange(W) % 2 == 0, 1.0, 0.4).expand(1, 3, H, W)
    frames = _constant_history_then(surface(4, (0.5, 0.0)), stripes)
    centre = (..., slice(H // 2 - 2, H // 2 + 2), slice(10, 18))
    frame = frames[-1]["oidn"]
    torch.testing.assert_close(_stage_at(64.0, frames, no_shading)[centre], frame[centre])
    assert not torch.allclose(_stage_at(1.0, frames, no_shading)[centre], frame[centre])
    ramp = (0.4 + 0.01 * torch.arange(W, dtype=torch.float32)).expand(1, 3, H, W)
    smooth = _constant_history_then(surface(4, (0.5, 0.0)), ramp)
    assert not torch.allclose(_stage_at(64.0, smooth, no_shading)[centre], ramp[centre])
    mapped = oh.grey_level(stripes)
    blur = oh.resampling_blur(mapped, frames[-1]["motion"])
    whole = oh.resampling_blur(mapped, torch.ones_like(frames[-1]["motion"]))
    assert blur[centre].min() > 0.05 and whole.max() < 1e-5  # float rounding of whole shifts


def test_a_still_pixel_keeps_its_history_through_noisy_aux_but_not_behind_a_mover():
    """A locked-off shot whose aux flicker (normals 50° apart, depth 20% apart from frame to
    frame, as a few samples' averages of a rough surface do) keeps its history; a square
    sliding 3 px a frame across the wall, 20% nearer, leaves no trail: where it uncovered the
    wall the pixel takes the frame (its moving pixels are within the still radius)."""
    frames = surface(6, (0.0, 0.0))
    tilt = torch.tensor([0.0, 0.766, 0.643]).view(1, 3, 1, 1)  # 50° from (0, 0, 1)
    for i, f in enumerate(frames):
        f["normal"] = f["normal"] if i % 2 else tilt.expand_as(f["normal"]).contiguous()
        f["depth"] = f["depth"] * (1.2 if i % 2 else 1.0)
    out = run_stage(oh.OutputHistory(TRUSTING), frames)[-1]
    strict = run_stage(oh.OutputHistory(oh.OutputHistoryConfig(still_radius=0)), frames)[-1]
    torch.testing.assert_close(strict, frames[-1]["oidn"])  # restarted every frame
    assert (out - frames[-1]["oidn"]).abs().mean() > 0.01  # kept: the frames' mean

    mover = surface(5, (0.0, 0.0))
    for i, f in enumerate(mover):
        x = 2 + 3 * i
        f["oidn"] = torch.full_like(f["oidn"], 0.5)
        f["oidn"][..., 6:12, x:x + 6] = 5.0  # a bright square, 20% nearer than the wall
        f["depth"][..., 6:12, x:x + 6] *= 0.8
        f["motion"] = torch.zeros_like(f["motion"])
        if i:
            f["motion"][:, 0, 6:12, x:x + 6] = -3.0  # it came from 3 px to the left
    last = run_stage(oh.OutputHistory(TRUSTING), mover)[-1]
    uncovered = (..., slice(6, 12), slice(2 + 3 * 3, 2 + 3 * 4))  # where it was last frame
    torch.testing.assert_close(last[uncovered], mover[-1]["oidn"][uncovered])


def test_pixel_alignment_needs_every_neighbour_moving_by_the_same_whole_pixels():
    """A pan by whole pixels is aligned everywhere, the frame's border included; a smooth
    sub-pixel motion field that crosses a whole value at a few pixels (a camera orbit) is not
    aligned there; nor is the seam between two halves moving by different whole pixels."""
    from quietframe.model.temporal import pixel_aligned

    pan = torch.zeros(1, 2, H, W)
    pan[:, 0] = -3.0
    assert pixel_aligned(pan).all()
    smooth = pan.clone()
    smooth[:, 0] += torch.linspace(-0.3, 0.3, W)  # crosses -3 exactly between two columns
    smooth[:, 0, :, W // 2] = -3.0  # and one column lands on it
    whole_alone = ((smooth - smooth.round()).abs().amax(1) <= 1 / 64).any()
    assert whole_alone and not pixel_aligned(smooth).any()
    seam = pan.clone()
    seam[:, 0, :, W // 2:] = -4.0
    aligned = pixel_aligned(seam)[0, 0]
    assert not aligned[:, W // 2 - 1: W // 2 + 1].any()
    assert aligned[:, : W // 2 - 2].all() and aligned[:, W // 2 + 2:].all()
    nan = pan.clone()
    nan[:, 1, 5, 5] = float("nan")
    assert not pixel_aligned(nan)[0, 0, 4:7, 4:7].any() and pixel_aligned(nan)[0, 0, 10:, :].all()


class _Given:
    """A per-frame 'method' that returns the stage's given OIDN output (bench interface)."""

    def __init__(self, frames: list[dict]) -> None:
        self.frames, self.index = frames, 0

    def reset(self) -> None:
        self.index = 0

    def __call__(self, planes) -> np.ndarray:
        self.index += 1
        return self.frames[self.index - 1]["oidn"][0].numpy()


def repeated_frames() -> list[dict[str, torch.Tensor]]:
    """Two frames of a locked-off shot whose aux repeat to the last bit (Cycles' 1-spp frames)
    except in columns 8-11, where the second frame's depth moved by 0.1% (another sample of the
    pixel); the colour is noisy in each."""
    gen = torch.Generator().manual_seed(7)
    frames = []
    for index in range(2):
        normal = torch.zeros(1, 3, H, W)
        normal[:, 2] = 1
        depth = torch.full((1, 1, H, W), 3.0)
        depth[..., 8:12] *= 1.001 if index else 1.0
        frames.append({"color": 0.2 + torch.rand(1, 3, H, W, generator=gen),
                       "albedo": torch.full((1, 3, H, W), 0.6), "normal": normal,
                       "depth": depth, "motion": torch.zeros(1, 2, H, W)})
    return frames


def accumulate_frames(frames: list[dict[str, torch.Tensor]], spp: float) -> torch.Tensor:
    model, state = AccumulationDenoiser(aligned_history=True), torch.zeros(1, 8, H, W)
    for index, f in enumerate(frames):
        with torch.no_grad():
            out, state = model(f["color"], f["albedo"], f["normal"], f["depth"], f["motion"],
                               torch.tensor([1.0 if index == 0 else 0.0]), state,
                               torch.tensor([spp]))
    return out


def test_a_repeated_sample_restarts_the_aligned_accumulation_at_one_sample_a_pixel():
    """At 1 spp, aux equal to last frame's to the last bit mean the renderer sampled the same
    point of the pixel again (Cycles does), and a mean of one point's samples stays that
    point's (aliased thin geometry): the accumulation restarts there, but not where the aux
    changed, and not at 4 spp, where repeating aux are a pixel-centre G-buffer's and say
    nothing of the colour's samples."""
    frames = repeated_frames()
    mean = (frames[0]["color"] + frames[1]["color"]) / 2
    one = accumulate_frames(frames, 1.0)
    torch.testing.assert_close(one[..., 12:], frames[1]["color"][..., 12:])  # restarted
    torch.testing.assert_close(one[..., :8], frames[1]["color"][..., :8])
    torch.testing.assert_close(one[..., 8:12], mean[..., 8:12])  # another sample: accumulates
    torch.testing.assert_close(accumulate_frames(frames, 4.0), mean)
    old = AccumulationDenoiser(aligned_history=True, restart_repeated=False)  # version 2
    assert old.run_time_inputs() == [] and not old.config.restart_repeated


def test_the_shipped_aligned_accumulation_restarts_repeated_samples_as_pytorch_does():
    from quietframe.runtime import Denoiser, find_model

    runtime = Denoiser(find_model("aligned-accumulation"), threads=1)
    assert [i.name for i in runtime.info.inputs] == ["spp"]
    frames = repeated_frames()
    planes = [{k: v[0].numpy() for k, v in f.items()} for f in frames]
    for spp in (1.0, 4.0):
        state = runtime.denoise(planes[0], None, {"spp": spp}).state
        result = runtime.denoise(planes[1], state, {"spp": spp})
        np.testing.assert_allclose(result.color, accumulate_frames(frames, spp)[0].numpy(),
                                   rtol=1e-5, atol=1e-6)


def test_the_stage_is_the_ablation_row_it_ships():
    """The shipped stage computes what experiments/output_history's `+hybrid` history measured."""
    from quietframe.experiments.output_history import OutputHistory as AblationRow

    frames = surface(3, (0.0, 0.0)) + surface(3, (0.5, 1.25), seed=1)[1:] + surface(
        2, (-2.0, 1.0), seed=2)[1:]
    ablation = oh.OutputHistoryConfig(resampled_weight=MIN_CURRENT_WEIGHT,  # the row's weights
                                      resampled_weight_per_doubling=0)
    ours = run_stage(oh.OutputHistory(ablation), frames)
    row = AblationRow(_Given(frames), resample="hybrid")
    for f, out in zip(frames, ours, strict=True):
        planes = {k: f[k][0].numpy() for k in ("depth", "normal", "motion")}
        planes["color"] = f["oidn"][0].numpy()  # not read by the row (its base gives OIDN's)
        np.testing.assert_allclose(row(planes), out[0].numpy(), rtol=1e-5, atol=1e-6)


needs_pyoidn = pytest.mark.skipif(importlib.util.find_spec("pyoidn") is None,
                                  reason="pyoidn not installed")


@pytest.fixture(scope="module")
def history_folder(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("history")
    export_nbg(AccumulationDenoiser(aligned_history=True), folder / "aligned-accumulation.onnx")
    return folder


# oidn-fast-history differs from oidn-history only in OIDN's quality
@pytest.fixture(scope="module", params=["oidn-history", "oidn-history-cleanaux"])
def composed(request, history_folder) -> tuple[str, Path]:
    folder = history_folder
    stage = oh.OutputHistory(oh.VARIANTS[request.param])
    return request.param, export_nbg(stage, folder / f"{request.param}.onnx", version="t")


def moving_planes(index: int) -> dict[str, np.ndarray]:
    """A textured scene moving by whole pixels in one half of the frame and by fractions of a
    pixel in the other, with noise of its own in every frame."""
    rng = np.random.default_rng(index)
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    shift = 0.3 * index
    pattern = 0.5 + 0.4 * np.sin(0.7 * (xs + shift)) * np.cos(0.5 * ys)
    color = pattern[None].repeat(3, 0) * rng.uniform(0.6, 1.4, (3, H, W))
    normal = np.zeros((3, H, W), np.float32)
    normal[2] = 1
    motion = np.zeros((2, H, W), np.float32)
    motion[0, :, : W // 2] = -1.0 if index else 0.0
    motion[0, :, W // 2:] = -0.3 if index else 0.0
    return {"color": color.astype(np.float32), "albedo": np.full((3, H, W), 0.6, np.float32),
            "normal": normal, "depth": np.full((1, H, W), 2.0, np.float32), "motion": motion}


@needs_pyoidn
def test_runtime_composition_matches_pytorch_with_state_carried(composed):
    from quietframe.runtime import Denoiser
    from quietframe.runtime.oidn_prepass import OIDNPrepass

    name, path = composed
    runtime = Denoiser(path, threads=1)
    assert [s.name for s in runtime.info.state_specs] == ["accumulation",
                                                          "color_from.accumulation"]
    accumulation, stage = AccumulationDenoiser(aligned_history=True), oh.OutputHistory(
        oh.VARIANTS[name])
    oidn = OIDNPrepass(runtime.card.prepass, num_threads=1)
    acc_state, stage_state, state = torch.zeros(1, 8, H, W), torch.zeros(1, 8, H, W), None
    for index in range(5):
        planes = moving_planes(index)
        t = {k: torch.from_numpy(v)[None] for k, v in planes.items()}
        reset = torch.tensor([1.0 if index == 0 else 0.0])
        with torch.no_grad():
            acc, acc_state = accumulation(t["color"], t["albedo"], t["normal"], t["depth"],
                                          t["motion"], reset, acc_state)
            denoised = torch.from_numpy(oidn({**planes, "color": acc[0].numpy()}))
            expected, stage_state = stage(denoised, t["albedo"], t["normal"], t["depth"],
                                          t["motion"], reset, stage_state)
        result = runtime.denoise(planes, state)
        state = result.state
        np.testing.assert_allclose(result.color, expected[0].numpy(), rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(state["accumulation"], stage_state.numpy(), rtol=1e-4,
                                   atol=1e-4)
    assert runtime.info.inputs[0].name == "spp"  # the frame's spp changes the blend
    clean = runtime.denoise(planes, state, {"spp": 64}).color
    assert np.abs(clean - runtime.denoise(planes, state, {"spp": 1}).color).max() > 1e-4
    fresh = runtime.denoise(planes, None)  # the history was used
    assert np.abs(fresh.color - result.color).max() > 1e-3
    planes["motion"][:, 3, 5] = np.nan  # sanitised to no motion; the fetch stays in the image
    assert np.isfinite(runtime.denoise(planes, state).color).all()


def test_the_weight_ablations_spp_row_is_the_shipped_stage():
    """experiments/history_weight's `w(spp)` row computes what the shipped stage without its
    shading and detail tests (which came after that ablation) does at that spp."""
    from quietframe.experiments.history_weight import HistoryRule

    frames = surface(3, (0.0, 0.0)) + surface(3, (0.5, 1.25), seed=1)[1:]
    stage = oh.OutputHistory(FLOOR_ALONE)
    for spp in (1.0, 64.0):
        state, shipped = stage.initial_state(1, H, W), []
        for index, f in enumerate(frames):
            with torch.no_grad():
                out, state = stage(
                    f["oidn"], f["albedo"], f["normal"], f["depth"], f["motion"],
                    torch.tensor([float(index == 0)]), state, torch.tensor([spp]))
            shipped.append(out[0].numpy())
        planes = [{k: f[k][0].numpy().copy() for k in ("depth", "normal", "motion")}
                  | {"color": f["oidn"][0].numpy().copy()} for f in frames]
        base = {p["color"].ctypes.data: f["oidn"][0].numpy()
                for p, f in zip(planes, frames, strict=True)}
        rule = HistoryRule(base, {}, "spp")
        rule.header_spp = spp
        for p, expected in zip(planes, shipped, strict=True):
            np.testing.assert_allclose(rule(p), expected, rtol=1e-5, atol=1e-6)


def test_variance_clipping_is_tighter_than_the_range_and_off_by_default():
    torch = pytest.importorskip("torch")
    current = torch.full((1, 1, 5, 5), 1.0)
    current[0, 0, 2, 2] = 9.0  # one bright pixel: the 3×3 range reaches 9, the mean ± σ less
    previous = torch.full((1, 1, 5, 5), 8.0)
    ranged = oh.clamp_to_neighbourhood(previous, current)
    assert ranged[0, 0, 2, 2] == 8.0 and ranged[0, 0, 0, 0] == 1.0
    tight = oh.clamp_to_neighbourhood(previous, current, sigma=1.0)
    mean, std = 17 / 9, (8 / 9 * 64 / 9) ** 0.5  # 3×3 around the bright pixel
    assert tight[0, 0, 2, 2].item() == pytest.approx(mean + std, rel=1e-5)
    assert (tight <= ranged).all()
    assert oh.OutputHistoryConfig().clip_sigma == 0  # the shipped tiers keep the range
