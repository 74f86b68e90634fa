"""model/learned_blend.py: the learned per-pixel blend of the output history (an
ablation row), and experiments/learned_blend.py's training step."""

from __future__ import annotations

import random

import pytest

torch = pytest.importorskip("torch")
from quietframe.experiments import learned_blend as bench  # noqa: E402
from quietframe.model.learned_blend import LearnedBlendHistory  # noqa: E402
from quietframe.model.output_history import OutputHistory  # noqa: E402


def frame(seed: int, h: int = 10, w: int = 12, motion: float = 0.0) -> dict:
    g = torch.Generator().manual_seed(seed)
    normal = torch.zeros(1, 3, h, w)
    normal[:, 2] = 1
    return {"oidn": torch.rand(1, 3, h, w, generator=g) * 2,
            "albedo": torch.rand(1, 3, h, w, generator=g), "normal": normal,
            "depth": torch.full((1, 1, h, w), 3.0),
            # left half pixel-aligned (exact history), right half sub-pixel (resampled)
            "motion": torch.cat((torch.zeros(1, 2, h, w // 2),
                                 torch.full((1, 2, h, w - w // 2), motion)), dim=3)}


def run(model, frames: list[dict], spp: float | None = 16.0) -> list[torch.Tensor]:
    state = model.initial_state(1, *frames[0]["oidn"].shape[-2:])
    outs = []
    for t, f in enumerate(frames):
        out, state = model(f["oidn"], f["albedo"], f["normal"], f["depth"], f["motion"],
                           torch.tensor([float(t == 0)]), state,
                           None if spp is None else torch.tensor([spp]))
        outs.append(out)
    return outs


@pytest.mark.parametrize("spp", [None, 1.0, 64.0])
def test_untrained_blend_is_the_shipped_rule_exactly(spp):
    frames = [frame(s, motion=0.4) for s in range(3)]
    with torch.no_grad():
        learned = run(LearnedBlendHistory(), frames, spp)
        shipped = run(OutputHistory(), frames, spp)
    for a, b in zip(learned, shipped, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_no_history_where_the_rule_takes_none_whatever_the_net_says():
    model = LearnedBlendHistory()
    torch.nn.init.constant_(model.net.layers[-1].bias, -8.0)  # pull α towards 0: all history
    frames = [frame(0), frame(1)]
    frames[1]["depth"][..., :, :3] = 30.0  # a disocclusion: another surface there
    with torch.no_grad():
        first, second = run(model, frames)
    torch.testing.assert_close(first, frames[0]["oidn"], rtol=0, atol=0)  # first frame
    torch.testing.assert_close(second[..., :3], frames[1]["oidn"][..., :3], rtol=0, atol=0)
    assert not torch.allclose(second[..., 3:], frames[1]["oidn"][..., 3:])  # history used


def test_training_step_reaches_every_weight_through_the_unrolled_history():
    torch.manual_seed(0)
    h, w, t = 12, 14, bench.WINDOW + 1

    def item(spp):
        f = [frame(s, h, w, motion=0.3) for s in range(t)]
        cat = lambda k: torch.cat([x[k] for x in f])  # noqa: E731
        return bench.Item(cat("oidn"), cat("albedo"), cat("normal"), cat("depth"),
                          cat("motion"), cat("oidn") * 0.9, [False] * t, spp)

    model = LearnedBlendHistory(width=4)
    torch.nn.init.normal_(model.net.layers[-1].weight, std=0.1)  # a non-zero correction
    cut = item(None)
    cut.resets = [False, False, True, False, False]  # a cut: every window holds a reset there
    frames = bench.batch([item(4.0), cut], 2, 8, random.Random(0))
    assert len(frames) == bench.WINDOW and frames[0]["base"].shape == (2, 3, 8, 8)
    assert frames[0]["reset"].tolist() == [1.0, 1.0]
    assert sum(f["reset"].sum() for f in frames) > 2  # the cut, wherever the windows start
    loss = bench.unrolled_loss(model, frames)
    loss.backward()
    assert torch.isfinite(loss)
    for name, p in model.net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name
