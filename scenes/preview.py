"""The scene-choice rule both renderers apply to their previews (one place for it): reject a
shot that starts blocked or near black, expose the sequence, measure how indirect its light is.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)
PREVIEW_SPP = 8
MIN_LIT_FRACTION = 0.2  # of pixels with any light in the 8-spp preview
NEAR_M, MAX_NEAR_FRACTION = 0.25, 0.2  # blocked: > 20% of pixels nearer than 0.25 m


def rejected(luminance: np.ndarray, depth: np.ndarray) -> bool:
    """A shot's first-frame preview is blocked or almost black. Sunlit rooms are mostly black
    at 1 spp by design; only the near-black are rejected. `depth`: inf where no ray hit."""
    return bool(np.mean(depth < NEAR_M) > MAX_NEAR_FRACTION
                or np.mean(luminance > 0) < MIN_LIT_FRACTION)


def first_acceptable(
    seed: int, tries: int, shot_previews: Callable[[int], Iterable[tuple[np.ndarray, np.ndarray]]]
) -> tuple[int, list[np.ndarray]]:
    """The first attempt (0, 1, ...) whose every shot preview passes, and those previews'
    luminances. `shot_previews(attempt)` builds that attempt's scene and yields (luminance,
    depth) per shot; it is stopped at the first rejected shot."""
    for attempt in range(tries):
        lum = []
        for rad, depth in shot_previews(attempt):
            if rejected(rad, depth):
                break
            lum.append(rad)
        else:
            return attempt, lum
    raise RuntimeError(f"seed {seed}: {tries} generated scenes were all blocked or black")


def exposure(luminances: list[np.ndarray], seed: int) -> tuple[float, float]:
    """(radiance scale, clip): maps the previews' mean luminance, clipped at its 99th
    percentile, to a seeded 0.15-0.6."""
    lum_all = np.concatenate([x.ravel() for x in luminances])
    clip = float(np.percentile(lum_all, 99))
    robust = float(np.mean(np.minimum(lum_all, clip)))
    target = float(np.exp(np.random.default_rng([seed, 2]).uniform(np.log(0.15), np.log(0.6))))
    return target / max(robust, 1e-12), clip


def lighting_stats(direct: np.ndarray, full: np.ndarray, clip: float,
                   black_fraction: float) -> dict[str, float]:
    """How indirect the light is: the share of the (clipped) preview luminance that direct
    light alone (emitters seen directly or after one bounce) explains, and the share of pixels
    black in one 1-spp pass (Cycles: in the 8-spp preview)."""
    return {
        "direct_fraction": float(
            np.minimum(direct, clip).mean() / max(np.minimum(full, clip).mean(), 1e-12)),
        "preview_black_fraction": float(black_fraction),
    }
