"""NBG pre-stage: albedo demodulation rule (model/nbg.py)."""

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
