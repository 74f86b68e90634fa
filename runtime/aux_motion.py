"""Backward motion estimated from the aux, for frames whose renderer wrote none (Cycles with
motion blur on writes an all-zero `Vector`): a temporal model can then follow the picture
instead of starting its history afresh on every frame of a moving shot.

The estimate works on the motion probes the history gate already keeps (motion_evidence.probe:
albedo luminance and the normal, 2×2 box-averaged; no lighting noise). It is a coarse-to-fine
Lucas–Kanade flow (Lucas & Kanade 1981; Bouguet's pyramid): at each level of a box pyramid the
previous probe is warped by the current estimate, and per pixel the increment that best explains
the remaining difference over a (2r+1)² window is solved in closed form from the summed
products of the mean image's gradients (the normal equations of D ≈ −G·Δv), with a small ridge
so that flat windows stay where they are.

Confidence per pixel: the previous probe warped by the final estimate must match the current
probe within `TRUST_ERROR` (summed over the probe's channels, a 3×3 mean): a wrong vector fetches
another surface's albedo or normal and fails it, as do disocclusions and a window that spans two
motions. An untrusted pixel gets a vector that points outside the frame, which every temporal
model reads as "no history here" (its per-frame stage).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from quietframe.runtime.motion_evidence import PROBE_SCALE, _box

WINDOW_RADIUS = 3  # probe pixels: a 7×7 window (14×14 frame pixels)
ITERATIONS = 5  # per level
FINEST_ITERATIONS = 1  # at the probe's own resolution, below a coarser level
MIN_LEVEL_SIZE = 24  # probe pixels: the pyramid stops before a side gets shorter
MAX_STEP = 1.0  # probe pixels an iteration may move an estimate (the linearisation's reach)
RIDGE = 1e-5  # added to the normal equations' diagonal, per window pixel and channel
TRUST_ERROR = 0.12  # summed |probe difference| after warping, 3×3 mean: above it, untrusted


@dataclass(frozen=True)
class EstimatedMotion:
    motion: np.ndarray  # (2, H, W) float32 backward motion in frame pixels; untrusted: outside
    trusted: np.ndarray  # (H, W) bool
    share: float  # of the frame's pixels, those trusted
    estimate: np.ndarray  # (2, H, W) the estimate everywhere, trusted or not


def _box_sum(x: np.ndarray, r: int) -> np.ndarray:
    """(..., H, W) -> the sum over each pixel's (2r+1)² window (edges: the part inside the
    frame). Running sums along one axis at a time, in float64 (float32 ones lose the small
    differences of large sums)."""
    k = 2 * r + 1
    pad = [(0, 0)] * (x.ndim - 2)
    c = np.cumsum(np.pad(x, [*pad, (r + 1, r), (0, 0)]), axis=-2, dtype=np.float64)
    rows = c[..., k:, :] - c[..., :-k, :]
    c = np.cumsum(np.pad(rows, [*pad, (0, 0), (r + 1, r)]), axis=-1)
    return (c[..., k:] - c[..., :-k]).astype(np.float32)


def warp(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """(C, H, W) image fetched at p + flow(p), bilinear, coordinates clamped to the frame."""
    _, h, w = image.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    x = np.clip(xs + flow[0], 0, w - 1)
    y = np.clip(ys + flow[1], 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.intp), w - 2) if w > 1 else np.zeros_like(x, np.intp)
    y0 = np.minimum(np.floor(y).astype(np.intp), h - 2) if h > 1 else np.zeros_like(y, np.intp)
    fx, fy = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    top = image[:, y0, x0] * (1 - fx) + image[:, y0, x1] * fx
    bottom = image[:, y1, x0] * (1 - fx) + image[:, y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


def _refine(previous: np.ndarray, current: np.ndarray, flow: np.ndarray,
            iterations: int) -> np.ndarray:
    """Lucas–Kanade steps of `flow` (2, h, w) at one level."""
    area = (2 * WINDOW_RADIUS + 1) ** 2 * previous.shape[0]
    for _ in range(iterations):
        warped = warp(previous, flow)
        mean = (warped + current) / 2
        gy, gx = np.gradient(mean, axis=(1, 2))
        d = warped - current  # want warped + G·Δ ≈ current: G·Δ = −d
        products = np.stack([(a * b).sum(0) for a, b in
                             ((gx, gx), (gy, gy), (gx, gy), (gx, d), (gy, d))])
        sxx, syy, sxy, sxd, syd = _box_sum(products, WINDOW_RADIUS)
        sxx, syy = sxx + RIDGE * area, syy + RIDGE * area
        det = sxx * syy - sxy * sxy
        du = -(syy * sxd - sxy * syd) / det
        dv = -(sxx * syd - sxy * sxd) / det
        flow = flow + np.clip(np.stack((du, dv)), -MAX_STEP, MAX_STEP)
    return flow


def probe_flow(previous: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Backward flow (2, h, w) between two probes of one size, in probe pixels."""
    pyramid = [(previous, current)]
    while min(pyramid[-1][1].shape[1:]) >= 2 * MIN_LEVEL_SIZE:
        p, c = pyramid[-1]
        pyramid.append((_box(p, 2), _box(c, 2)))
    flow = np.zeros((2, *pyramid[-1][1].shape[1:]), np.float32)
    for level, (p, c) in enumerate(reversed(pyramid)):
        if level:  # up from the coarser level: twice the vectors, on twice the pixels
            h, w = c.shape[1:]
            flow = 2 * np.repeat(np.repeat(flow, 2, axis=1), 2, axis=2)[:, :h, :w]
        # the probe's own level (a quarter of the pyramid's cost each) gets one step where a
        # coarser level found the motion already
        finest = level == len(pyramid) - 1 and len(pyramid) > 1
        flow = _refine(p, c, flow, FINEST_ITERATIONS if finest else ITERATIONS)
    return flow


def estimate(previous: np.ndarray, current: np.ndarray, height: int, width: int
             ) -> EstimatedMotion:
    """Backward motion of an H×W frame from the previous frame's probe and its own (probes of
    one shape: motion_evidence.probe), with its per-pixel trust (module docstring)."""
    flow = probe_flow(previous, current)
    error = np.abs(warp(previous, flow) - current).sum(0)
    error = _box_sum(error, 1) / _box_sum(np.ones_like(error), 1)
    trusted_probe = error <= TRUST_ERROR
    up = np.repeat(np.repeat(flow, PROBE_SCALE, axis=1), PROBE_SCALE, axis=2)[:, :height, :width]
    trusted = np.repeat(np.repeat(trusted_probe, PROBE_SCALE, 0), PROBE_SCALE, 1)[:height, :width]
    everywhere = (PROBE_SCALE * up).astype(np.float32)
    motion = everywhere.copy()
    motion[0][~trusted] = 4.0 * (height + width)  # outside the frame: no history here
    motion[1][~trusted] = 0.0
    return EstimatedMotion(motion, trusted, float(trusted.mean()), everywhere)
