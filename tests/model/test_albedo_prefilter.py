"""The learned tiers' albedo prefilter (NBGConfig / AffinityConfig.albedo_prefilter,
model/albedo_prefilter): a Gaussian of σ₁ · spp^(-1/3) px on the albedo before demodulation.
σ falls with the spp and its taps keep a flat albedo flat; a tier with it is the same tier fed
the blurred albedo; the exported graphs (ai.quietframe::AlbedoPrefilter) compute what PyTorch
does (NBG's here, the shipped files of both in their shipped-export tests), reach further by
the filter's radius and take the setting on export or in a fine-tune."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import onnx
import pytest

torch = pytest.importorskip("torch", reason="the learned tiers (torch) are not installed")

from quietframe.export.affinity_export import example_inputs as affinity_inputs  # noqa: E402
from quietframe.export.affinity_export import export_affinity  # noqa: E402
from quietframe.export.onnx_export import example_inputs, export_nbg  # noqa: E402
from quietframe.model import affinity, nbg, nbg_fused, train  # noqa: E402
from quietframe.model import albedo_prefilter as prefilter  # noqa: E402
from quietframe.runtime import Denoiser  # noqa: E402
from quietframe.runtime.card import SAMPLES_INPUT  # noqa: E402
from quietframe.runtime.receptive import tiling_for  # noqa: E402

SIGMA = 1.0
NBG = replace(nbg.VARIANTS["nbg-2l-3g"], passthrough=True, noise_blend=True,
              resampled_weight_per_doubling=0.134)
AFFINITY = replace(affinity.VARIANTS["affinity-h16-k5gc"], noise_input=True,
                   resampled_weight_per_doubling=0.134)
TIERS = {"nbg": (nbg.NBGDenoiser, NBG, export_nbg),
         "affinity": (affinity.AffinityDenoiser, AFFINITY, export_affinity)}
BUFFERS = ("color", "albedo", "normal", "depth", "motion")


def test_sigma_falls_with_the_spp_and_below_one_counts_as_one() -> None:
    spp = torch.tensor([1.0, 8.0, 64.0, 0.25, float("nan")])
    np.testing.assert_allclose(prefilter.prefilter_sigma(spp, SIGMA).numpy(),
                               [1.0, 0.5, 0.25, 1.0, 1.0], rtol=1e-6)


def test_taps_are_normalised_and_a_vanishing_sigma_is_the_identity() -> None:
    taps = prefilter.gaussian_taps(torch.tensor([1.0, 0.25, 1e-4]))
    np.testing.assert_allclose(taps.sum(dim=1).numpy(), 1.0, rtol=1e-6)
    assert torch.equal(taps[2], torch.eye(2 * prefilter.RADIUS + 1)[prefilter.RADIUS])
    assert float(taps[0, prefilter.RADIUS]) < 0.5 < float(taps[1, prefilter.RADIUS])


def test_off_is_the_albedo_itself_and_the_setting_is_checked() -> None:
    albedo = torch.rand(1, 3, 8, 8)
    assert prefilter.prefilter_albedo(albedo, torch.tensor([1.0]), 0.0) is albedo
    for bad in (-0.1, prefilter.MAX_SIGMA_AT_ONE_SPP + 0.1):
        with pytest.raises(ValueError, match="albedo_prefilter"):
            replace(NBG, albedo_prefilter=bad)
        with pytest.raises(ValueError, match="albedo_prefilter"):
            replace(AFFINITY, albedo_prefilter=bad)


def first_frame(model, seed: int = 1) -> tuple:
    """One frame's inputs (buffers..., reset, state) for the tier's forward."""
    if isinstance(model, affinity.AffinityDenoiser):
        *buffers, reset, state, embedding = affinity_inputs(model, 24, 32, seed=seed)
        return (*buffers, reset, (state, embedding))
    return example_inputs(24, 32, seed=seed)


@pytest.mark.parametrize("tier", sorted(TIERS))
def test_a_tier_with_the_prefilter_is_the_tier_fed_the_blurred_albedo(tier: str) -> None:
    model_type, config, _ = TIERS[tier]
    torch.manual_seed(0)
    filtering = model_type(replace(config, albedo_prefilter=SIGMA)).eval()
    plain = model_type(config).eval()
    plain.load_state_dict(filtering.state_dict())
    inputs = first_frame(plain)
    with torch.no_grad():
        for spp, changes in ((1.0, True), (4.0, True), (1e6, False)):
            samples = torch.tensor([spp])
            got = filtering(*inputs, spp=samples)[0]
            blurred = prefilter.albedo_blur(inputs[1], samples, SIGMA, prefilter.SIGMA_EXPONENT,
                                            prefilter.RADIUS)
            torch.testing.assert_close(got, plain(inputs[0], blurred, *inputs[2:],
                                                  spp=samples)[0], rtol=0, atol=0)
            raw = plain(*inputs, spp=samples)[0]
            assert (float((got - raw).abs().max()) > 1e-3) == changes


def test_fused_nbg_is_the_model_with_the_prefilter() -> None:
    torch.manual_seed(0)
    model = nbg.NBGDenoiser(replace(NBG, albedo_prefilter=SIGMA)).eval()
    inputs = example_inputs(24, 32, seed=3)
    with torch.no_grad():
        expected = model(*inputs, torch.tensor([2.0]))
        got = nbg_fused.fused_forward(model, *inputs, torch.tensor([2.0]))
    for a, b in zip(got, expected, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6)


def test_exported_graph_with_the_prefilter_matches_pytorch(tmp_path) -> None:
    """NBG's graph; the shipped files of both tiers, which have the prefilter on, are held to
    their checkpoints' PyTorch models by test_export's and test_affinity's shipped-export
    tests."""
    model_type, config, export = TIERS["nbg"]
    torch.manual_seed(0)
    model = model_type(replace(config, albedo_prefilter=SIGMA)).eval()
    path = export(model, tmp_path / "prefilter.onnx")
    runtime = Denoiser(path, threads=1)
    assert "AlbedoPrefilter" in {n.op_type for n in onnx.load(str(path)).graph.node}
    card = runtime.info.card
    plain = tiling_for({**card.architecture, "albedo_prefilter": 0.0}, card.inputs, False)
    assert card.tiling.radius == plain.radius + prefilter.RADIUS
    inputs = first_frame(model)
    planes = {k: b[0].numpy() for k, b in zip(BUFFERS, inputs[:5], strict=True)}
    for spp in (1.0, 16.0):
        with torch.no_grad():
            expected = model(*inputs, spp=torch.tensor([spp]))[0][0].numpy()
        result = runtime.denoise(planes, None, options={SAMPLES_INPUT: spp})
        np.testing.assert_allclose(result.color, expected, rtol=1e-4,
                                   atol=1e-4 * float(np.abs(expected).max()))


def test_a_fine_tune_may_switch_the_prefilter_on() -> None:
    """No weights, like the fade: quietframe-train --albedo-prefilter on a checkpoint's model
    (the export's flag: test_export)."""
    flags = train.weightless_flags(train.TrainConfig(albedo_prefilter=1.0))
    assert flags == {"albedo_prefilter": 1.0}
    assert "albedo_prefilter" in train.FINE_TUNE_MAY_CHANGE
    model = nbg.NBGDenoiser(replace(NBG, **flags))
    assert model.reads_spp and model.config.albedo_prefilter == 1.0
