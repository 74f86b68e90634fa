"""The learned tiers' noise level: NBG's noise-aware blend (NBGConfig.noise_blend, model/nbg.py:
the blend logits move with log2(spp · history length) on [0, 1]) and the affinity U-Net's noise
input (AffinityConfig.noise_input: log2(spp) as one more channel). A fine-tune that switches
either on starts at the model it extends; a learned weight makes the frame's spp matter;
training, the checkpoint selection and the exported graph through the runtime feed each frame's
spp."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the NBG model (torch) is not installed")

from dataset_support import write_generator_splits  # noqa: E402

from quietframe.export.affinity_export import example_inputs as affinity_inputs  # noqa: E402
from quietframe.export.affinity_export import export_affinity  # noqa: E402
from quietframe.export.onnx_export import example_inputs  # noqa: E402
from quietframe.model import affinity, nbg  # noqa: E402
from quietframe.model import train as qt  # noqa: E402
from quietframe.model.train import unroll  # noqa: E402
from quietframe.model.zoo_selection import TorchDenoiser  # noqa: E402
from quietframe.runtime import Denoiser  # noqa: E402
from quietframe.runtime.card import SAMPLES_INPUT  # noqa: E402

PASS = replace(nbg.VARIANTS["nbg-2l-3g"], passthrough=True)
NOISE = replace(PASS, noise_blend=True)
FRAME = -1  # the frame's own candidate: the last blend logit


def pair(seed: int = 0) -> tuple[nbg.NBGDenoiser, nbg.NBGDenoiser]:
    """A random pass-through model and the same weights in the noise-aware one."""
    torch.manual_seed(seed)
    plain = nbg.NBGDenoiser(PASS).eval()
    noisy = nbg.NBGDenoiser(NOISE).eval()
    noisy.load_state_dict(noisy.adapt_state_dict(plain.state_dict()))  # strict
    return plain, noisy


def test_noise_level_is_log2_samples_over_the_range_clamped() -> None:
    count = torch.tensor([1.0, 4.0, 16.0, 0.0]).view(1, 4, 1, 1)
    level = nbg.noise_level(torch.tensor([4.0]), count)
    # 4, 16, 64 samples; a count of 0 (no sample yet) is clamped to one sample: level 0
    torch.testing.assert_close(level.flatten(), torch.tensor([0.2, 0.4, 0.6, 0.0]))
    many = nbg.noise_level(torch.tensor([1024.0, 1.0]), torch.full((2, 1, 1, 1), 8.0))
    torch.testing.assert_close(many.flatten(), torch.tensor([1.0, 0.3]))  # 8192 samples: 1


@pytest.mark.parametrize("spp", [1.0, 64.0])
def test_extended_model_starts_as_the_one_it_extends(spp: float) -> None:
    plain, noisy = pair()
    inputs = example_inputs(40, 56)
    with torch.no_grad():
        before, state_before = plain(*inputs)
        after, state_after = noisy(*inputs, torch.tensor([spp]))
    torch.testing.assert_close(after, before, rtol=0, atol=0)
    torch.testing.assert_close(state_after, state_before, rtol=0, atol=0)


def test_a_learned_shift_passes_the_frame_through_at_high_spp_only() -> None:
    _, model = pair()
    with torch.no_grad():
        model.guide_net.noise_shift[FRAME] = 200.0  # the frame's logit grows with the level
    color, albedo, normal, depth, motion, reset, state = example_inputs(32, 40)
    frame, safe_albedo = nbg.frame_irradiance(color, albedo, model.config.outlier_sigmas,
                                              model.config.outlier_floor)
    with torch.no_grad():
        high, _ = model(color, albedo, normal, depth, motion, reset, state, torch.tensor([256.0]))
        low, _ = model(color, albedo, normal, depth, motion, reset, state, torch.tensor([1.0]))
    torch.testing.assert_close(high, frame * safe_albedo)  # level 0.8: the frame's own
    assert float((low - frame * safe_albedo).abs().mean()) > 0.05 * float(low.abs().mean())


def test_modulation_trains() -> None:
    _, model = pair()
    model.train()
    inputs = example_inputs(24, 32)
    out, _ = model(*inputs, torch.tensor([16.0]))
    out.square().mean().backward()
    for p in (model.guide_net.noise_scale, model.guide_net.noise_shift):
        assert p.grad is not None and float(p.grad.abs().sum()) > 0


def test_noise_blend_model_asks_for_the_spp_input_and_a_plain_one_does_not() -> None:
    plain, noisy = pair()
    assert noisy.reads_spp and not plain.reads_spp
    assert [i["name"] for i in noisy.run_time_inputs()] == [SAMPLES_INPUT]
    assert plain.run_time_inputs() == []


def batch_of(spp: list[float], frames: int = 2) -> dict:
    color, albedo, normal, depth, motion, _, _ = example_inputs(16, 24)
    b = len(spp)
    stack = {k: v.expand(b, *v.shape[1:]).unsqueeze(1).expand(b, frames, *v.shape[1:])
             for k, v in (("color", color), ("albedo", albedo), ("normal", normal),
                          ("depth", depth), ("motion", motion))}
    return {**stack, "reset": torch.zeros(b, frames), "spp": torch.tensor(spp)}


def test_training_feeds_each_items_spp() -> None:
    _, model = pair()
    with torch.no_grad():
        model.guide_net.noise_shift[FRAME] = 200.0
        outputs = unroll(model, batch_of([1.0, 256.0]))
    low, high = outputs[-1][0], outputs[-1][1]  # the same frames, 1 and 256 spp
    assert float((low - high).abs().mean()) > 1e-3


def test_selection_scores_with_the_streams_spp() -> None:
    _, model = pair()
    with torch.no_grad():
        model.guide_net.noise_shift[FRAME] = 200.0
    denoiser = TorchDenoiser(model)
    assert [i.name for i in denoiser.info.inputs] == [SAMPLES_INPUT]
    color, albedo, normal, depth, motion, _, _ = example_inputs(16, 24)
    planes = {k: v[0].numpy() for k, v in (("color", color), ("albedo", albedo),
                                           ("normal", normal), ("depth", depth),
                                           ("motion", motion))}
    with torch.no_grad():  # as the selection runs
        low = denoiser.denoise(planes, None, {SAMPLES_INPUT: 1.0}).color
        high = denoiser.denoise(planes, None, {SAMPLES_INPUT: 256.0}).color
    assert float(np.abs(low - high).mean()) > 1e-3


AFFINITY = affinity.VARIANTS["affinity-h16-k5gc"]


def affinity_pair(seed: int = 0) -> tuple[affinity.AffinityDenoiser, affinity.AffinityDenoiser]:
    """A random shipped-architecture affinity model and the same weights with noise_input."""
    torch.manual_seed(seed)
    plain = affinity.AffinityDenoiser(AFFINITY).eval()
    noisy = affinity.AffinityDenoiser(replace(AFFINITY, noise_input=True)).eval()
    noisy.load_state_dict(noisy.adapt_state_dict(plain.state_dict()))  # strict
    return plain, noisy


def run_affinity(model: affinity.AffinityDenoiser, spp: float | None) -> torch.Tensor:
    *buffers, reset, state, embedding = affinity_inputs(model, 24, 32)
    extra = {} if spp is None else {"spp": torch.tensor([spp])}
    with torch.no_grad():
        return model(*buffers, reset, (state, embedding), **extra)[0]


@pytest.mark.parametrize("spp", [1.0, 64.0])
def test_affinity_with_the_noise_input_starts_as_the_one_it_extends(spp: float) -> None:
    plain, noisy = affinity_pair()
    torch.testing.assert_close(run_affinity(noisy, spp), run_affinity(plain, None),
                               rtol=0, atol=0)


def test_affinity_noise_input_trains_and_makes_the_spp_matter() -> None:
    _, model = affinity_pair()
    model.train()
    *buffers, reset, state, embedding = affinity_inputs(model, 24, 32)
    out, _ = model(*buffers, reset, (state, embedding), spp=torch.tensor([16.0]))
    out.square().mean().backward()
    grad = model.unet.down[0][0].weight.grad[:, -1]  # the noise level's input channel
    assert float(grad.abs().sum()) > 0
    model.eval()
    with torch.no_grad():
        model.unet.down[0][0].weight[:, -1] = 2.0
    assert float((run_affinity(model, 1.0) - run_affinity(model, 64.0)).abs().max()) > 1e-3


def test_the_unet_reads_the_noise_plane_as_its_first_convolutions_last_channel() -> None:
    # the two-convolution form (kept for onnxruntime's channel blocks) is the same function
    unet = affinity.UNet((8, 16), noise_input=True)
    x = torch.randn(2, 2 * affinity.EMBEDDING_CHANNELS, 12, 10)
    noise = torch.rand(2, 1, 1, 1).expand(2, 1, 12, 10)
    first = unet.down[0][0]
    with torch.no_grad():
        split = unet._first(first, x, noise)
        joined = first(torch.cat((x, noise), dim=1))
    torch.testing.assert_close(split, joined, rtol=1e-5, atol=1e-5)
    assert float((split - unet._first(first, x, noise + 0.5)).abs().max()) > 1e-3


def test_exported_affinity_takes_the_spp_and_matches_pytorch(tmp_path) -> None:
    _, model = affinity_pair()
    with torch.no_grad():
        # enough for the spp to move the output, not so much that log2(64)·w saturates the
        # first layer: at 2.0 one pixel's kernel weights differed by 0.5% between onnxruntime's
        # float32 and PyTorch's on an AMD EPYC (rounding amplified, not a wrong graph)
        model.unet.down[0][0].weight[:, -1] = 0.5
    assert float((run_affinity(model, 1.0) - run_affinity(model, 64.0)).abs().max()) > 1e-3
    runtime = Denoiser(export_affinity(model, tmp_path / "noisy.onnx"), threads=1)
    assert SAMPLES_INPUT in [i.name for i in runtime.info.inputs]
    *buffers, _, _, _ = affinity_inputs(model, 24, 32)
    planes = {k: b[0].numpy() for k, b in
              zip(("color", "albedo", "normal", "depth", "motion"), buffers, strict=True)}
    for spp in (1.0, 64.0):
        expected = run_affinity(model, spp)[0].numpy()
        got = runtime.denoise(planes, None, options={SAMPLES_INPUT: spp}).color
        np.testing.assert_allclose(got, expected, rtol=1e-4,
                                   atol=1e-4 * float(np.abs(expected).max()))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    write_generator_splits(root)
    return root


@pytest.mark.parametrize(("variant", "switch", "key"), [
    ("nbg-2l-3g", {"passthrough": 1, "noise_blend": 1}, "guide_net.noise_shift"),
    ("affinity-h8", {"noise_input": 1}, "unet.down.0.0.weight"),
])
def test_a_fine_tune_switches_the_noise_level_on(data, tmp_path, variant, switch, key) -> None:
    base = dict(variant=variant, data=str(data), crop=24, frames=2, batch=2, steps=1,
                eval_every=1, log_every=1, threads=1, seed=5)
    qt.train(qt.TrainConfig(**base), tmp_path / "base")
    flags = {"init": str(tmp_path / "base" / "checkpoint.pt"), "data": str(data), "crop": 24,
             "frames": 2, "batch": 2, "steps": 1, "threads": 1, **switch}
    qt.train(qt.resume_config(tmp_path / "tuned", flags), tmp_path / "tuned")
    tuned = torch.load(tmp_path / "tuned" / "checkpoint.pt", weights_only=False)
    assert all(tuned["config"][k] for k in switch)
    assert key in tuned["model"]
    if key.startswith("unet"):  # the first conv read the noise level: one more input channel
        assert tuned["model"][key].shape[1] == 2 * affinity.EMBEDDING_CHANNELS + 1


@pytest.mark.parametrize("variant", ["nbg-2l-3g", "affinity-h8"])
def test_a_fine_tune_trains_with_the_fading_history_and_its_checkpoint_keeps_it(
        data, tmp_path, variant) -> None:
    base = dict(variant=variant, data=str(data), crop=24, frames=2, batch=2, steps=1,
                eval_every=1, log_every=1, threads=1, seed=5)
    qt.train(qt.TrainConfig(**base), tmp_path / "base")
    flags = {"init": str(tmp_path / "base" / "checkpoint.pt"), "data": str(data), "crop": 24,
             "frames": 2, "batch": 2, "steps": 1, "threads": 1,
             "resampled_weight_per_doubling": 0.134}
    cfg = qt.resume_config(tmp_path / "tuned", flags)
    assert qt.build_model(cfg).reads_spp  # training feeds each item's spp to the fade
    qt.train(cfg, tmp_path / "tuned")
    tuned = torch.load(tmp_path / "tuned" / "checkpoint.pt", weights_only=False)
    assert tuned["config"]["resampled_weight_per_doubling"] == pytest.approx(0.134)
    rebuilt = qt.build_model(cfg, tuned["config"])
    assert rebuilt.config.resampled_weight_per_doubling == pytest.approx(0.134)
    # the run, once started, keeps it: a resumed run cannot switch it off
    with pytest.raises(ValueError, match="resampled_weight_per_doubling"):
        qt.resume_config(tmp_path / "tuned", {**flags, "resampled_weight_per_doubling": 0.0})
