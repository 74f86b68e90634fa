"""The learned tiers' resampled history fades with the frame's spp
(NBGConfig / AffinityConfig.resampled_weight_per_doubling,
model/temporal.fading_floor and resampled_trust): where the motion is not a whole number of
pixels NBG's current frame weighs at least w(spp) = clamp(0.2 + k · log2 spp, 0.2, 1), the
affinity tier's λ (eq. 5) is at most 1 - w and from 2 spp its temporal kernel (eq. 8) gathers
nothing there; an exact (pixel-aligned) fetch keeps its history; the fused graph and the
exported files compute what the PyTorch models do."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the NBG model (torch) is not installed")

from quietframe.export.affinity_export import example_inputs as affinity_inputs  # noqa: E402
from quietframe.export.affinity_export import export_affinity  # noqa: E402
from quietframe.export.onnx_export import example_inputs, export_nbg  # noqa: E402
from quietframe.model import affinity, nbg, nbg_fused, temporal  # noqa: E402
from quietframe.runtime import Denoiser  # noqa: E402
from quietframe.runtime.card import SAMPLES_INPUT  # noqa: E402

PER_DOUBLING = 0.134  # w: 0.2 at 1 spp, 0.47 at 4, 0.74 at 16, 1 at 64
NOISE = replace(nbg.VARIANTS["nbg-2l-3g"], passthrough=True, noise_blend=True)
FADING = replace(NOISE, resampled_weight_per_doubling=PER_DOUBLING)


def floor_at(spp: float) -> torch.Tensor:
    return temporal.weight_floor(torch.tensor([spp]), temporal.MIN_CURRENT_WEIGHT,
                                 PER_DOUBLING, 1.0)


def test_floor_rises_with_the_spp_from_the_fixed_weight_to_one() -> None:
    got = [float(floor_at(spp)) for spp in (0.5, 1.0, 4.0, 16.0, 64.0, 1024.0)]
    np.testing.assert_allclose(got, [0.2, 0.2, 0.468, 0.736, 1.0, 1.0], atol=1e-6)


def half_pixel_motion(height: int, width: int, aligned_columns: int) -> torch.Tensor:
    """Motion of half a pixel, except the first `aligned_columns` columns: one whole pixel."""
    motion = torch.full((1, 2, height, width), 0.5)
    motion[..., :aligned_columns] = 1.0
    return motion


@pytest.mark.parametrize("spp", [1.0, 4.0, 16.0, 64.0])
def test_trust_caps_the_history_so_the_frame_weighs_the_floor(spp: float) -> None:
    floor = floor_at(spp)
    motion = half_pixel_motion(8, 12, aligned_columns=4)
    previous = torch.full((1, 1, 8, 12), 5.0)  # a long history
    share = temporal.resampled_trust(motion, previous, floor)
    # pixel_aligned asks every 3×3 neighbour to be whole and alike its own 3×3: columns 0-1
    # are, columns 2-3 are within two pixels of the half-pixel ones
    assert torch.all(share[..., :2] == 1)
    alpha, count = temporal.history_weights(share, previous)
    resampled = alpha[..., 5:]
    expected = max(float(floor), temporal.MIN_CURRENT_WEIGHT)
    torch.testing.assert_close(resampled, torch.full_like(resampled, expected))
    if spp <= 1:  # the fixed weight: the history as it always was (n + 1 = 6 frames)
        assert torch.all(share == 1)
    else:  # 1/w frames of history
        torch.testing.assert_close(count[..., 5:], 1 / resampled)


def test_a_short_history_under_the_cap_is_kept_whole() -> None:
    motion = half_pixel_motion(6, 6, aligned_columns=0)
    share = temporal.resampled_trust(motion, torch.ones(1, 1, 6, 6), floor_at(4.0))
    assert torch.all(share == 1)  # 1 frame of history + this one: 1/0.468 > 2


def test_accumulate_drops_a_resampled_history_at_64_spp_and_keeps_an_exact_one() -> None:
    color = example_inputs(10, 12)[0]
    depth = torch.full((1, 1, 10, 12), 2.0)  # one flat surface: every fetch passes the
    normal = torch.zeros(1, 3, 10, 12)  # disocclusion test
    normal[:, 2] = 1
    motion = torch.zeros(1, 2, 10, 12)  # still: every fetch exact
    moving = half_pixel_motion(10, 12, aligned_columns=0)
    state = torch.cat((color * 3, depth, normal, torch.full_like(depth, 5.0)), dim=1)
    kept, _ = temporal.accumulate(color, depth, normal, motion, torch.zeros(1), state,
                                  floor=floor_at(64.0))
    dropped, new_state = temporal.accumulate(color, depth, normal, moving, torch.zeros(1),
                                             state, floor=floor_at(64.0))
    # moving by half a pixel: the nearest fetch is valid (the same surface) but resampled,
    # and at 64 spp not kept (inside the frame; the border's fetch falls outside anyway)
    torch.testing.assert_close(dropped, color)
    without, _ = temporal.accumulate(color, depth, normal, moving, torch.zeros(1), state)
    assert float((without - color).abs().max()) > 0.1  # without the floor it was kept
    assert torch.all(new_state[:, temporal.HISTORY_LENGTH] == 1)
    assert float((kept - color).abs().max()) > 0.1  # the exact history weighs 0.8


def test_a_model_with_the_floor_reads_the_spp() -> None:
    plain = nbg.NBGDenoiser(replace(nbg.VARIANTS["nbg-2l-3g"], resampled_weight_per_doubling=0.1))
    assert plain.reads_spp
    assert [i["name"] for i in plain.run_time_inputs()] == [SAMPLES_INPUT]
    assert not nbg.NBGDenoiser(nbg.VARIANTS["nbg-2l-3g"]).reads_spp


def two_frames(model: nbg.NBGDenoiser, spp: float, fused: bool = False):
    """Outputs and states of two frames (the second moving by half a pixel over most of it)."""
    first = example_inputs(24, 32, seed=1)
    motion = half_pixel_motion(24, 32, aligned_columns=8)
    forward = (lambda *a: nbg_fused.fused_forward(model, *a)) if fused else model
    with torch.no_grad():
        out1, state = forward(*first, torch.tensor([spp]))
        second = (*example_inputs(24, 32, seed=2)[:4], motion, torch.zeros(1), state)
        out2, state2 = forward(*second, torch.tensor([spp]))
    return (first, out1), (second, out2, state2)


@pytest.mark.parametrize("spp", [1.0, 16.0, 64.0])
def test_fused_forward_is_the_model_with_the_floor(spp: float) -> None:
    torch.manual_seed(0)
    model = nbg.NBGDenoiser(FADING).eval()
    assert nbg_fused.fusable(model)
    (_, out1), (_, out2, state2) = two_frames(model, spp)
    (_, got1), (_, got2, got_state2) = two_frames(model, spp, fused=True)
    torch.testing.assert_close(got1, out1, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(got2, out2, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(got_state2, state2, rtol=1e-6, atol=1e-6)


# ---- the affinity tier (AffinityConfig.resampled_weight_per_doubling) -------------------------

AFFINITY = replace(affinity.VARIANTS["affinity-h16-k5gc"], noise_input=True)
AFFINITY_FADING = replace(AFFINITY, resampled_weight_per_doubling=PER_DOUBLING)


def test_fade_caps_the_blend_and_hides_resampled_features_above_one_sample() -> None:
    motion = half_pixel_motion(8, 12, aligned_columns=4)
    blend = torch.full((1, 1, 8, 12), 0.9)
    features = torch.zeros(1, affinity.FEATURE_CHANNELS, 8, 12)
    for spp, hidden in ((1.0, False), (16.0, True), (64.0, True)):
        floor = floor_at(spp)
        capped, shifted = affinity.fade_resampled(blend, features, motion, floor)
        assert torch.all(capped[..., :2] == 0.9) and torch.all(shifted[..., :2] == 0)  # exact
        torch.testing.assert_close(capped[..., 5:], torch.full_like(capped[..., 5:],
                                                                    min(0.9, 1 - float(floor))))
        assert bool(torch.all(shifted[..., 5:] == affinity.STALE_FEATURE_OFFSET)) == hidden


def two_affinity_frames(model: affinity.AffinityDenoiser, spp: float):
    *buffers, reset, state, embedding = affinity_inputs(model, 24, 32, seed=1)
    second = example_inputs(24, 32, seed=2)[:4]
    motion = half_pixel_motion(24, 32, aligned_columns=8)
    with torch.no_grad():
        out1, new = model(*buffers, reset, (state, embedding), spp=torch.tensor([spp]))
        out2, _ = model(*second, motion, torch.zeros(1), new, spp=torch.tensor([spp]))
    return (buffers, out1), ((*second, motion), out2)


BUFFERS = ("color", "albedo", "normal", "depth", "motion")
# tier -> (model class, config keeping every history, config fading it, exporter)
TIERS = {
    "nbg": (nbg.NBGDenoiser, NOISE, FADING, export_nbg),
    "affinity": (affinity.AffinityDenoiser, AFFINITY, AFFINITY_FADING, export_affinity),
}


def frames_of(model, spp: float) -> list[tuple[dict[str, np.ndarray], torch.Tensor]]:
    """Two frames through the PyTorch model (the second moving by half a pixel over most of
    it): each frame's buffers by name and its output."""
    if isinstance(model, affinity.AffinityDenoiser):
        pairs = two_affinity_frames(model, spp)
    else:
        (first, out1), (second, out2, _) = two_frames(model, spp)
        pairs = ((first, out1), (second, out2))
    return [({k: b[0].numpy() for k, b in zip(BUFFERS, inputs[:5], strict=True)}, out)
            for inputs, out in pairs]


@pytest.mark.parametrize("tier", sorted(TIERS))
def test_fading_changes_only_frames_of_more_than_one_sample(tier: str) -> None:
    model_type, keeping_config, fading_config, _ = TIERS[tier]
    torch.manual_seed(0)
    fading = model_type(fading_config).eval()
    keeping = model_type(keeping_config).eval()
    keeping.load_state_dict(fading.state_dict())
    assert fading.reads_spp and fading.run_time_inputs()[0]["name"] == SAMPLES_INPUT
    for spp, differs in ((1.0, False), (64.0, True)):
        (_, a1), (_, a2) = frames_of(fading, spp)
        (_, b1), (_, b2) = frames_of(keeping, spp)
        torch.testing.assert_close(a1, b1, rtol=0, atol=0)  # no history yet
        assert (float((a2 - b2).abs().max()) > 1e-3) == differs


@pytest.mark.parametrize("tier", sorted(TIERS))
def test_exported_graph_with_the_fading_history_matches_pytorch(tier: str, tmp_path) -> None:
    model_type, _, fading_config, export = TIERS[tier]
    torch.manual_seed(0)
    model = model_type(fading_config).eval()
    runtime = Denoiser(export(model, tmp_path / "fading.onnx"), threads=1)
    for spp in (4.0, 64.0):
        state = None
        for planes, expected in frames_of(model, spp):
            result = runtime.denoise(planes, state, options={SAMPLES_INPUT: spp})
            state = result.state
            expected = expected[0].numpy()
            np.testing.assert_allclose(result.color, expected, rtol=1e-4,
                                       atol=1e-4 * float(np.abs(expected).max()))
