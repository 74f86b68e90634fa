"""Metrics (numpy) and losses (torch) on known values."""

import numpy as np
import pytest
import torch

from quietframe.model import losses, metrics

RNG = np.random.default_rng(7)


def tau_inverse(y: np.ndarray) -> np.ndarray:
    """Linear radiance whose τ is y (for building cases in the tonemapped domain)."""
    p = np.asarray(y, np.float64) ** 2.4
    return p / (1 - p)


def image(h: int = 24, w: int = 32) -> np.ndarray:
    return RNG.gamma(2.0, 0.5, (h, w, 3)).astype(np.float32)


def test_tonemap_tau_known_values():
    x = np.array([-1.0, 0.0, 1.0, 3.0, np.inf])
    want = [0.0, 0.0, 0.5 ** (1 / 2.4), 0.75 ** (1 / 2.4), 1.0]
    np.testing.assert_allclose(metrics.tonemap_tau(x), want, rtol=1e-12)
    np.testing.assert_allclose(metrics.tonemap_tau(tau_inverse([0.2, 0.7])), [0.2, 0.7])


def test_identical_images():
    a = image()
    assert metrics.psnr(a, a) == float("inf")
    assert metrics.ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert metrics.smape(a, a) == 0.0
    assert metrics.relmse(a, a) == 0.0


def test_psnr_of_a_constant_offset_in_tau():
    ref = tau_inverse(np.full((8, 8, 3), 0.5))
    pred = tau_inverse(np.full((8, 8, 3), 0.6))  # τ error 0.1 everywhere → MSE 0.01 → 20 dB
    assert metrics.psnr(pred, ref) == pytest.approx(20.0, abs=1e-9)
    # Işık eq. 14 averages over channels: an error in one channel of three is a third of the MSE
    pred_one = ref.copy()
    pred_one[..., 1] = pred[..., 1]
    assert metrics.psnr(pred_one, ref) == pytest.approx(20.0 + 10 * np.log10(3), abs=1e-9)


def test_smape_and_relmse_hand_computed():
    pred = np.array([[[1.0, 2.0, 0.0]]], np.float32)
    ref = np.array([[[1.0, 1.0, 0.0]]], np.float32)
    # elements: 0, |2-1| / (2+1+0.01), 0 / 0.01; mean over the 3
    assert metrics.smape(pred, ref) == pytest.approx((1 / 3.01) / 3)
    assert metrics.smape(pred, ref, eps=0.0 + 1e-12) == pytest.approx((1 / 3) / 3)
    assert metrics.relmse(pred, ref) == pytest.approx((1 / 1.01) / 3)
    assert metrics.smape(ref, pred) == metrics.smape(pred, ref)  # symmetric


def test_ssim_constant_images_closed_form():
    # zero variance: SSIM = (2 μx μy + C1) / (μx² + μy² + C1) · C2 / C2
    mx, my = 0.4, 0.6
    s = metrics.ssim(tau_inverse(np.full((16, 16, 3), mx)), tau_inverse(np.full((16, 16, 3), my)))
    c1 = 0.01**2
    assert s == pytest.approx((2 * mx * my + c1) / (mx**2 + my**2 + c1), rel=1e-9)


def test_ssim_matches_brute_force_single_window():
    # An 11×11 image has exactly one valid window: compare to an explicit 2-D Gaussian sum.
    a, b = image(11, 11), image(11, 11)
    x, y = metrics.tonemap_tau(a), metrics.tonemap_tau(b)
    off = np.arange(-5, 6)
    g = np.exp(-(off[:, None] ** 2 + off[None, :] ** 2) / (2 * 1.5**2))
    g /= g.sum()
    want = []
    for c in range(3):
        mx, my = (g * x[..., c]).sum(), (g * y[..., c]).sum()
        vx = (g * (x[..., c] - mx) ** 2).sum()
        vy = (g * (y[..., c] - my) ** 2).sum()
        cov = (g * (x[..., c] - mx) * (y[..., c] - my)).sum()
        c1, c2 = 0.01**2, 0.03**2
        want.append((2 * mx * my + c1) * (2 * cov + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
    assert metrics.ssim(a, b) == pytest.approx(np.mean(want), rel=1e-9)


def test_ssim_symmetric_and_below_one_for_noise():
    clean = image()
    noisy = clean * RNG.gamma(4.0, 0.25, clean.shape).astype(np.float32)
    s = metrics.ssim(noisy, clean)
    assert s == pytest.approx(metrics.ssim(clean, noisy), rel=1e-12)
    assert 0.0 < s < 0.99
    assert metrics.ssim(clean[..., 0], clean[..., 0]) == pytest.approx(1.0)  # (H, W) accepted


def test_shape_errors():
    with pytest.raises(ValueError, match="psnr"):
        metrics.psnr(image(8, 8), image(8, 9))
    with pytest.raises(ValueError, match="ssim"):
        metrics.ssim(image(8, 8), image(8, 8))  # smaller than the 11×11 window
    with pytest.raises(ValueError, match="2 frames"):
        metrics.trmae(image()[None], image()[None])


def test_trmae_static_and_flicker():
    frame = image()
    static = np.stack([frame] * 4)
    assert metrics.trmae(static, static) == 0.0
    # a static reference (∂t = 0) and a prediction flickering by ±0.1: |0.1| / (0 + 0.01) = 10
    ref = np.ones((4, 8, 8, 3), np.float32)
    pred = ref + np.array([0.0, 0.1, 0.0, 0.1], np.float32)[:, None, None, None]
    assert metrics.trmae(pred, ref) == pytest.approx(10.0, rel=1e-6)
    # plain (not motion-compensated) differences: a list of frames is accepted like an array
    assert metrics.trmae(list(pred), list(ref)) == pytest.approx(10.0, rel=1e-6)


def test_torch_smape_equals_numpy():
    a, b = image(), image()
    got = losses.smape_loss(torch.from_numpy(a), torch.from_numpy(b)).item()
    assert got == pytest.approx(metrics.smape(a, b), rel=1e-5)


def test_torch_temporal_loss_is_smape_of_differences():
    preds = RNG.gamma(2.0, 0.5, (2, 5, 3, 8, 8)).astype(np.float32)  # (N, T, C, H, W)
    refs = RNG.gamma(2.0, 0.5, (2, 5, 3, 8, 8)).astype(np.float32)
    got = losses.temporal_loss(torch.from_numpy(preds), torch.from_numpy(refs)).item()
    want = metrics.smape(np.diff(preds, axis=1), np.diff(refs, axis=1))
    assert got == pytest.approx(want, rel=1e-5)
    assert losses.temporal_loss(torch.from_numpy(refs), torch.from_numpy(refs)).item() == 0.0
    with pytest.raises(ValueError, match="2 frames"):
        losses.temporal_loss(torch.zeros(1, 1, 3, 4, 4), torch.zeros(1, 1, 3, 4, 4))


def test_l1_tonemapped_loss_hand_computed_and_differentiable():
    pred = torch.tensor([0.25, 2.0, 0.0, -1.0], requires_grad=True)
    ref = torch.tensor([1.0, 0.5, 0.0, 0.0])
    # S clamps to [0, 1] then x^(1/2.2): |0.25^(1/2.2) - 1|, |1 - 0.5^(1/2.2)|, 0, 0
    g = 1 / 2.2
    want = (abs(0.25**g - 1) + abs(1 - 0.5**g)) / 4
    loss = losses.l1_tonemapped_loss(pred, ref)
    assert loss.item() == pytest.approx(want, rel=1e-5)
    loss.backward()
    assert torch.isfinite(pred.grad).all()  # no infinite slope at 0
    assert pred.grad[1] == 0 and pred.grad[3] == 0  # clamped: HDR above 1 / negatives


def test_losses_zero_for_identical_and_backprop():
    a = torch.rand(1, 3, 6, 6, requires_grad=True)
    for fn in (losses.smape_loss, losses.l1_tonemapped_loss):
        assert fn(a, a.detach()).item() == 0.0
        fn(a, torch.rand(1, 3, 6, 6)).backward()
        assert torch.isfinite(a.grad).all()
        a.grad = None


def _fit_constant(loss, targets: torch.Tensor, steps: int = 1500) -> float:
    """The constant prediction that minimises `loss` against a set of noisy targets (Adam)."""
    p = torch.full((1,), float(targets.mean()), requires_grad=True)
    with torch.no_grad():
        p.mul_(2.0)  # start away from the answer
    opt = torch.optim.Adam([p], lr=0.02)
    for _ in range(steps):
        opt.zero_grad()
        loss(p.expand_as(targets), targets).backward()
        opt.step()
    return p.item()


def test_relmse_unbiased_loss_recovers_the_mean_of_noisy_targets():
    # Monte Carlo radiance: skewed, heavy-tailed noise around a clean value of 1 (fireflies).
    # Against such targets the unbiased loss converges to their mean (the clean value); SMAPE
    # to a median-like value far below it: the bias the noise-robust loss removes.
    gen = torch.Generator().manual_seed(3)
    targets = -torch.log(torch.rand(20000, generator=gen))  # Exp(1): mean 1, median ln 2
    mean = targets.mean().item()
    assert _fit_constant(losses.relmse_unbiased_loss, targets) == pytest.approx(mean, rel=0.02)
    assert _fit_constant(losses.smape_loss, targets) < 0.8 * mean


def test_relmse_unbiased_loss_weight_is_the_prediction_without_gradient():
    pred = torch.tensor([2.0, 0.0], requires_grad=True)
    ref = torch.tensor([1.0, 0.5])
    loss = losses.relmse_unbiased_loss(pred, ref)
    eps = metrics.EPS_RELATIVE
    want = ((1.0 / (2 + eps)) ** 2 + (0.5 / eps) ** 2) / 2
    assert loss.item() == pytest.approx(want, rel=1e-6)
    loss.backward()  # d/dp (p - r)² / w² with w fixed
    assert pred.grad.tolist() == pytest.approx([2 * 1.0 / (2 + eps) ** 2 / 2,
                                                 2 * -0.5 / eps**2 / 2], rel=1e-6)


def test_temporal_relmse_weights_differences_by_the_later_output_frame():
    preds = torch.tensor([1.0, 3.0]).reshape(1, 2, 1)
    refs = torch.tensor([1.0, 2.0]).reshape(1, 2, 1)
    got = losses.temporal_relmse_unbiased_loss(preds, refs).item()
    assert got == pytest.approx((1.0 / (3 + metrics.EPS_RELATIVE)) ** 2, rel=1e-6)
    with pytest.raises(ValueError):
        losses.temporal_relmse_unbiased_loss(preds[:, :1], refs[:, :1])


def test_tau_mse_loss_is_the_error_psnr_reports():
    rng = np.random.default_rng(3)
    ref = rng.gamma(0.5, 0.4, (16, 16, 3))
    pred = ref * rng.uniform(0.5, 1.5, ref.shape) + 0.01
    loss = losses.tau_mse_loss(torch.from_numpy(pred), torch.from_numpy(ref)).item()
    assert -10 * np.log10(loss) == pytest.approx(metrics.psnr(pred, ref), abs=1e-9)
    # the floor: a zero or negative prediction keeps a finite gradient
    p = torch.tensor([0.0, -1.0, 0.3], dtype=torch.float64, requires_grad=True)
    losses.tau_mse_loss(p, torch.tensor([0.2, 0.2, 0.3], dtype=torch.float64)).backward()
    assert torch.isfinite(p.grad).all()


def test_temporal_tau_mse_is_the_error_of_tau_differences():
    preds = torch.rand(2, 3, 3, 4, 4, dtype=torch.float64)
    refs = torch.rand(2, 3, 3, 4, 4, dtype=torch.float64)
    tp, tr = losses.tonemap_tau(preds), losses.tonemap_tau(refs)
    expected = ((tp[:, 1:] - tp[:, :-1]) - (tr[:, 1:] - tr[:, :-1])).square().mean()
    assert losses.temporal_tau_mse_loss(preds, refs).item() == pytest.approx(expected.item())
    assert losses.temporal_tau_mse_loss(refs, refs).item() == 0.0
    with pytest.raises(ValueError, match="2 frames"):
        losses.temporal_tau_mse_loss(preds[:, :1], refs[:, :1])
