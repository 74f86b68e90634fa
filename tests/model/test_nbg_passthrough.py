"""NBG's pass-through candidates (NBGConfig.passthrough, model/nbg.py): add_passthrough extends a
model trained without them so that it starts as that model, and each pass-through logit, when it
dominates, passes its candidate through: the accumulated irradiance, or the frame's own."""

from __future__ import annotations

from dataclasses import replace

import pytest

torch = pytest.importorskip("torch", reason="the NBG model (torch) is not installed")

from sequence_support import moving_frame  # noqa: E402

from quietframe.export.onnx_export import example_inputs  # noqa: E402
from quietframe.model import nbg  # noqa: E402

VARIANTS = ["nbg-2l-1g", "nbg-2l-3g"]


def extended(name: str, seed: int = 0) -> tuple[nbg.NBGDenoiser, nbg.NBGDenoiser]:
    """A random-weight model without the pass-through, and the same weights through
    adapt_state_dict into the model with it."""
    torch.manual_seed(seed)
    without = nbg.NBGDenoiser(nbg.VARIANTS[name]).eval()
    with_pass = nbg.NBGDenoiser(replace(nbg.VARIANTS[name], passthrough=True)).eval()
    with_pass.load_state_dict(with_pass.adapt_state_dict(without.state_dict()))  # strict
    return without, with_pass


@pytest.mark.parametrize("name", VARIANTS)
def test_extended_model_starts_within_a_percent_of_the_one_it_extends(name: str) -> None:
    without, with_pass = extended(name)
    inputs = example_inputs(40, 56)  # per-pixel noise: the input far from the blend
    with torch.no_grad():
        before, state_before = without(*inputs)
        after, state_after = with_pass(*inputs)
    change = float((after - before).abs().mean() / before.abs().mean())
    # the candidates are there, each weighed exp(-4)/(1 + 2 exp(-4)) ~ 1.8% at most (a lone
    # grid, whose logit is 0), and close to the model's own output where it is smooth
    assert 0 < change < 0.03
    torch.testing.assert_close(state_after, state_before)


@pytest.mark.parametrize("name", VARIANTS)
def test_extended_guide_net_keeps_its_guides_and_the_grids_weight_ratios(name: str) -> None:
    without, with_pass = extended(name)
    gen = torch.Generator().manual_seed(1)
    features = torch.rand(2, nbg.GUIDE_INPUT_CHANNELS, 24, 32, generator=gen)
    with torch.no_grad():
        guides, weights = without.guide_net(features)
        new_guides, new_weights = with_pass.guide_net(features)
    torch.testing.assert_close(new_guides, guides, rtol=0, atol=0)
    kept = 1 - new_weights[:, -2:].sum(dim=1, keepdim=True)  # what the pass-through leaves
    grid_weights = torch.ones_like(kept) if weights is None else weights  # a lone grid: all
    torch.testing.assert_close(new_weights[:, :-2], grid_weights * kept)
    torch.testing.assert_close(new_weights[:, -2], new_weights[:, -1])  # both start alike


def test_add_passthrough_rejects_a_last_conv_of_another_model() -> None:
    three = replace(nbg.VARIANTS["nbg-2l-3g"], passthrough=True)
    one = replace(nbg.VARIANTS["nbg-2l-1g"], passthrough=True)
    two = replace(nbg.VARIANTS["nbg-2l-3g"], grids=2)
    for config, saved in ((three, nbg.VARIANTS["nbg-2l-1g"]), (one, nbg.VARIANTS["nbg-2l-3g"]),
                          (three, two)):
        state = nbg.NBGDenoiser(saved).state_dict()
        with pytest.raises(ValueError, match=f"is not a {config.grids}-grid GuideNet"):
            nbg.add_passthrough(state, config)


@pytest.mark.parametrize("name", VARIANTS)
def test_a_checkpoint_with_the_pass_through_is_kept_as_it_is(name: str) -> None:
    _, with_pass = extended(name)
    state = with_pass.state_dict()
    assert with_pass.adapt_state_dict(state) is state


@pytest.mark.parametrize("name", VARIANTS)
@pytest.mark.parametrize("candidate", ["accumulated", "frame"])
def test_a_dominant_pass_through_logit_passes_its_candidate(name: str, candidate: str) -> None:
    torch.manual_seed(0)
    config = replace(nbg.VARIANTS[name], passthrough=True, outlier_sigmas=0.0)  # no clamp
    model = nbg.NBGDenoiser(config).eval()
    height, width = 24, 32
    state = model.initial_state(1, height, width)
    with torch.no_grad():
        # the grids' weights (and the other candidate's) underflow beside it
        model.guide_net.last.bias[-2 if candidate == "accumulated" else -1] = 50.0
        for index in range(2):
            frame = (*moving_frame(index, height, width), torch.tensor([float(index == 0)]),
                     state)
            output, state = model(*frame)
            irradiance, safe_albedo, _ = nbg.prestage(*frame, outlier_sigmas=0.0)
            if candidate == "frame" or index == 0:  # nothing accumulated yet at frame 1
                torch.testing.assert_close(output, frame[0])  # the input itself
            torch.testing.assert_close(output, irradiance * safe_albedo
                                       if candidate == "accumulated" else frame[0])
    if candidate == "accumulated":  # the second frame's is its accumulation
        assert (output - frame[0]).abs().max() > 1e-2
