"""NBG pre-stage: albedo demodulation rule and the firefly clamp (model/nbg.py)."""

import pytest

torch = pytest.importorskip("torch", reason="the NBG model (torch) is not installed")

from quietframe.model import nbg  # noqa: E402


def test_demodulation_divides_by_albedo_plus_epsilon_on_ordinary_surfaces():
    albedo = torch.tensor([0.8, 0.05, 0.3]).view(1, 3, 1, 1)
    divisor = nbg.demodulation_divisor(albedo)
    torch.testing.assert_close(divisor, albedo + nbg.ALBEDO_EPSILON)


def test_zero_albedo_sky_is_not_amplified():
    # sky / emitters have albedo 0: dividing by ε would make them 100× brighter than their
    # neighbours before the grid blur; they pass through with divisor 1 instead
    albedo = torch.zeros(1, 3, 1, 1)
    assert torch.equal(nbg.demodulation_divisor(albedo), torch.ones(1, 3, 1, 1))
    negative = torch.full((1, 3, 1, 1), -0.5)  # bad input is treated like 0
    assert torch.equal(nbg.demodulation_divisor(negative), torch.ones(1, 3, 1, 1))


def test_divisor_fades_continuously_through_the_floor():
    levels = torch.linspace(0, 2 * nbg.ALBEDO_DEMODULATION_FLOOR, 401)
    albedo = levels.view(1, 1, -1, 1).expand(1, 3, -1, 1)
    divisor = nbg.demodulation_divisor(albedo)[0, 0, :, 0]
    assert divisor.diff().abs().max() < 0.01  # no jump anywhere along the ramp
    assert torch.all(divisor > 0)


def test_prestage_keeps_a_bright_sky_at_its_own_scale():
    color = torch.ones(1, 3, 4, 4) * 0.5
    albedo = torch.full((1, 3, 4, 4), 0.5)
    albedo[..., :2] = 0  # left half is sky
    color[..., :2] = 3.0
    depth, normal = torch.ones(1, 1, 4, 4), torch.zeros(1, 3, 4, 4)
    irradiance, divisor, _ = nbg.prestage(color, albedo, normal, depth, torch.zeros(1, 2, 4, 4),
                                          torch.ones(1), torch.zeros(1, 8, 4, 4), temporal=False)
    assert irradiance[..., :2].max() <= 3.0 + 1e-6
    torch.testing.assert_close(irradiance * divisor, color)  # remodulation inverts it


def _sparse_frame(seed: int = 0) -> torch.Tensor:
    """A 1-spp frame of a sunlit room: ~90% of pixels black, the rest carry all the energy."""
    gen = torch.Generator().manual_seed(seed)
    lit = torch.rand(1, 1, 32, 32, generator=gen) < 0.1
    energy = -torch.log(torch.rand(1, 1, 32, 32, generator=gen)) * 5  # heavy-tailed samples
    return lit * energy * torch.tensor([1.0, 0.9, 0.7]).view(1, 3, 1, 1)


def _prestage_output(color: torch.Tensor, sigmas: float, floor: float = 0.0) -> torch.Tensor:
    n, _, h, w = color.shape
    albedo = torch.full_like(color, 0.5)
    irradiance, divisor, _ = nbg.prestage(
        color, albedo, torch.zeros_like(color), torch.ones(n, 1, h, w), torch.zeros(n, 2, h, w),
        torch.ones(n), torch.zeros(n, 8, h, w), temporal=False, outlier_sigmas=sigmas,
        outlier_floor=floor)
    return irradiance * divisor


def test_clamp_floor_keeps_a_sparse_frame_and_still_pulls_back_a_firefly():
    """With a floor (a multiple of the frame's mean luminance) the sparse lit pixels of a
    1-spp frame pass, while a 10^4× firefly is pulled back to the floor."""
    color = _sparse_frame()
    floored = _prestage_output(color, 3.0, floor=128.0)
    assert floored.mean() > 0.97 * color.mean()
    hot = color.clone()
    hot[..., 5, 7] = hot.mean() * 1e4
    out = _prestage_output(hot, 3.0, floor=128.0)
    bound = 128.0 * nbg.luminance(hot).mean()  # a constant albedo scales frame and pixel alike
    assert nbg.luminance(out)[..., 5, 7] == pytest.approx(float(bound), rel=1e-3)
    # (the firefly lifts the frame's mean too: in 32×32 pixels the floor is 1/8 of it)
    assert nbg.luminance(out)[..., 5, 7] < 0.2 * nbg.luminance(hot)[..., 5, 7]


def test_firefly_clamp_takes_the_energy_of_a_sparse_frame_and_off_keeps_it():
    color = _sparse_frame()
    clamped = _prestage_output(color, 3.0)
    assert clamped.mean() < 0.75 * color.mean()  # why the accumulation ships without it
    torch.testing.assert_close(_prestage_output(color, 0.0), color)


def test_accumulation_model_has_no_clamp_and_nbg_variants_keep_theirs():
    assert nbg.AccumulationDenoiser().config.outlier_sigmas == 0
    assert nbg.VARIANTS["nbg-2l-3g"].outlier_sigmas == nbg.OUTLIER_SIGMAS
    off = nbg.NBGDenoiser(nbg.NBGConfig(outlier_sigmas=0))
    on = nbg.NBGDenoiser(nbg.NBGConfig(outlier_sigmas=3))
    on.load_state_dict(off.state_dict())
    color = _sparse_frame(1)
    args = (torch.full_like(color, 0.5), torch.zeros_like(color), torch.ones(1, 1, 32, 32),
            torch.zeros(1, 2, 32, 32), torch.ones(1), torch.zeros(1, 8, 32, 32))
    with torch.no_grad():
        assert off(color, *args)[0].mean() > on(color, *args)[0].mean() * 1.3


def test_clamp_energy_bench_measures_the_pre_stage_clamp():
    """experiments/clamp_energy.py: no clamp keeps the frame; the floored clamp keeps more of a
    sparse frame's energy than the plain 3σ one; a frame scored against itself is exact."""
    from quietframe.experiments.clamp_energy import clamped, figures

    color = _sparse_frame(2)
    albedo = torch.full_like(color, 0.5)
    assert figures(clamped(color, albedo, None), color) == (pytest.approx(1.0), 0.0)
    plain = figures(clamped(color, albedo, 0.0), color)[0]
    floored = figures(clamped(color, albedo, 128.0), color)[0]
    assert plain < 0.75 < 0.97 < floored
