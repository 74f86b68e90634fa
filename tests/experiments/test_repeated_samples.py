"""experiments/repeated_samples.py: repeated aux are told to the last bit, over surface pixels
only, and the mean of repeated point samples stays aliased where independent ones converge."""

from __future__ import annotations

import numpy as np

from quietframe.experiments.repeated_samples import mean_psnr, repeated_share

H, W = 16, 16


def aux(depth: float = 2.0) -> dict[str, np.ndarray]:
    normal = np.zeros((H, W, 3), np.float32)
    normal[:, 4:, 2] = 1  # columns 0-3: background
    return {"depth": np.full((H, W, 1), depth, np.float32), "normal": normal}


def test_repeated_share_counts_bit_equal_surface_pixels():
    a, b = aux(), aux()
    assert repeated_share(a, b) == 1.0
    b["depth"][:, 4:8] = np.nextafter(np.float32(2.0), np.float32(3.0))  # one ulp away
    assert repeated_share(a, b) == 8 / 12  # 4 of the 12 surface columns moved
    b["depth"][:, :4] = 5.0  # the background is not counted
    assert repeated_share(a, b) == 8 / 12


def test_the_mean_of_repeated_point_samples_stays_aliased():
    """A pixel half covered by a thin dark bar: independent samples converge to its mean,
    a sample repeated at one point stays the bar's or the wall's."""
    rng = np.random.default_rng(0)
    reference = np.full((H, W, 3), 0.5, np.float32)  # the pixel's mean: half 1.0, half 0.0
    point = np.where(rng.random((H, W, 1)) < 0.5, 1.0, 0.0).astype(np.float32) * np.ones(3)
    repeated = [point + rng.normal(0, 0.05, point.shape).astype(np.float32) for _ in range(24)]
    independent = [np.where(rng.random((H, W, 1)) < 0.5, 1.0, 0.0) * np.ones(3, np.float32)
                   for _ in range(24)]
    stuck = mean_psnr(repeated, reference, (1, 24))
    converging = mean_psnr(independent, reference, (1, 24))
    assert converging[24] > converging[1] + 10
    assert stuck[24] < stuck[1] + 1
    assert converging[24] > stuck[24] + 10
