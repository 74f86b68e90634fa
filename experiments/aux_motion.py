"""Experiment: can backward motion be estimated from the aux buffers well enough for
a temporal tier to use it where the renderer wrote none (Cycles with motion blur on writes an
all-zero `Vector`; Arnold without a motion AOV)?

    python -m quietframe.experiments.aux_motion --zoo zoo2 --split validation \
        [--shots fence-truck] [--spp 4] [--frames 6]

Scored on shots whose renderer did write motion: the estimate from the aux probes of frames
t - 1 and t (runtime/motion_evidence.probe, what the gate already keeps) against Cycles'
`Vector` of frame t. The end-point error (EPE, frame pixels) is reported over all pixels and
over those each estimator trusts, with the trusted share. A temporal tier could follow an
estimate only where its trusted EPE is well under a pixel (a bicubic history fetch half a pixel
off already blurs the fine detail the zoo's round 2 is made of).

Two estimators:
- `flow`: a pyramidal Lucas–Kanade flow (Lucas & Kanade 1981, Bouguet's pyramid) on the probe,
  with a forward-backward and an aux-reprojection check per pixel;
- `camera`: the one the service runs (runtime/aux_motion.py), a rigid camera fitted to the
  probe by direct alignment, the field then following from each pixel's own depth, which a
  free flow cannot do at a thin post in front of a far wall.

Result (docs/zoo.md, "Motion from the aux"): the flow's window-to-window noise (0.5–1.8 px) rules
it out; the camera is 0.1–0.25 px off Cycles' vectors on a slow dolly and ships, trusted per
pixel. It cannot follow an object of its own (such pixels take their per-frame stage).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.harness import planes_from_hwc
from quietframe.runtime import aux_motion
from quietframe.runtime.motion_evidence import PROBE_SCALE, probe
from quietframe.scenes import cycles_io
from quietframe.scenes.zoo_shots import shots, zoo_dir

# --- flow: pyramidal Lucas–Kanade on the probe ---------------------------------------------

WINDOW = 9  # probe pixels a side of the least-squares window (18 frame pixels)
ITERATIONS = 3  # warps per pyramid level
MIN_LEVEL_SIZE = 12  # the coarsest level's shorter side, probe pixels
# Tikhonov weight on the update, relative to the window's mean gradient energy: a flat window
# keeps the coarser level's motion instead of fitting noise.
REGULARISATION = 1e-3
MAX_STEP = 0.5  # probe pixels per warp and level
FB_TOLERANCE = 1.0  # frame pixels: forward-backward round trip
RESIDUAL_TOLERANCE = 0.06  # mean |warped previous - current| over the probe's channels


@dataclass(frozen=True)
class MotionEstimate:
    motion: np.ndarray  # (2, H, W) float32, frame pixels, backward (p was at p + m)
    doubt: np.ndarray  # (1, H, W) float32: 1 where the estimate is not trusted, else 0

    @property
    def trusted_share(self) -> float:
        return float(1.0 - self.doubt.mean())


def _box_filter(x: np.ndarray, size: int) -> np.ndarray:
    """Mean over a size × size window per pixel (edges: the window's part inside the frame),
    separable running sums; x (C, H, W)."""
    r = size // 2
    out = x
    for axis in (1, 2):
        n = out.shape[axis]
        pad = [(0, 0)] * 3
        pad[axis] = (r + 1, r)
        c = np.cumsum(np.pad(out, pad), axis=axis, dtype=np.float64)
        hi = np.take(c, np.arange(size, size + n), axis=axis)
        lo = np.take(c, np.arange(0, n), axis=axis)
        idx = np.arange(n)
        count = (np.minimum(idx + r, n - 1) - np.maximum(idx - r, 0) + 1).astype(np.float64)
        shape = [1, 1, 1]
        shape[axis] = n
        out = ((hi - lo) / count.reshape(shape)).astype(np.float32)
    return out


def _sample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear fetch of (C, H, W) `image` at float pixel coordinates (H', W'), clamped to the
    frame."""
    _, h, w = image.shape
    x = np.clip(x, 0.0, w - 1.0)
    y = np.clip(y, 0.0, h - 1.0)
    x0 = np.minimum(x.astype(np.intp), w - 2) if w > 1 else np.zeros_like(x, np.intp)
    y0 = np.minimum(y.astype(np.intp), h - 2) if h > 1 else np.zeros_like(y, np.intp)
    fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    top = image[:, y0, x0] * (1 - fx) + image[:, y0, x1] * fx
    bottom = image[:, y1, x0] * (1 - fx) + image[:, y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def _half(x: np.ndarray) -> np.ndarray:
    """2× box downsampling (an odd last row or column is dropped)."""
    c, h, w = x.shape
    x = x[:, : h - h % 2, : w - w % 2]
    return 0.25 * (x[:, 0::2, 0::2] + x[:, 1::2, 0::2] + x[:, 0::2, 1::2] + x[:, 1::2, 1::2])


def _upsample_flow(flow: np.ndarray, h: int, w: int) -> np.ndarray:
    """A coarser level's flow at the next level's (h, w): doubled in value, repeated 2×2."""
    up = 2.0 * np.repeat(np.repeat(flow, 2, axis=1), 2, axis=2)
    up = np.pad(up, ((0, 0), (0, max(0, h - up.shape[1])), (0, max(0, w - up.shape[2]))),
                mode="edge")
    return up[:, :h, :w]


def _gradients(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gx = np.zeros_like(x)
    gy = np.zeros_like(x)
    gx[:, :, 1:-1] = 0.5 * (x[:, :, 2:] - x[:, :, :-2])
    gy[:, 1:-1, :] = 0.5 * (x[:, 2:, :] - x[:, :-2, :])
    return gx, gy


def _median3(flow: np.ndarray) -> np.ndarray:
    """Per component, the median of each pixel's 3×3 neighbourhood (edges replicated)."""
    _, h, w = flow.shape
    padded = np.pad(flow, ((0, 0), (1, 1), (1, 1)), mode="edge")
    taps = np.stack([padded[:, i:i + h, j:j + w] for i in range(3) for j in range(3)])
    return np.median(taps, axis=0).astype(np.float32)


def lucas_kanade(previous: np.ndarray, current: np.ndarray) -> np.ndarray:
    """(2, H, W) backward flow in probe pixels: current(p) ≈ previous(p + flow(p))."""
    pyramid = [(previous.astype(np.float32), current.astype(np.float32))]
    while min(pyramid[-1][1].shape[1:]) >= 2 * MIN_LEVEL_SIZE:
        p, c = pyramid[-1]
        pyramid.append((_half(p), _half(c)))
    flow = np.zeros((2, *pyramid[-1][1].shape[1:]), np.float32)
    for p, c in reversed(pyramid):
        _, h, w = c.shape
        if flow.shape[1:] != (h, w):
            flow = _upsample_flow(flow, h, w)
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
        for _ in range(ITERATIONS):
            warped = _sample(p, cols + flow[0], rows + flow[1])
            gx, gy = _gradients(warped)
            dt = warped - c
            sums = _box_filter(np.stack(((gx * gx).sum(0), (gx * gy).sum(0), (gy * gy).sum(0),
                                         (gx * dt).sum(0), (gy * dt).sum(0))), WINDOW)
            sxx, sxy, syy, sxt, syt = sums
            lam = REGULARISATION * max(float((sxx + syy).mean()), 1e-12)
            sxx, syy = sxx + lam, syy + lam
            det = sxx * syy - sxy * sxy
            # warped(p + d) ≈ warped + g·d = current: g·d = -dt, least squares per window;
            # at most MAX_STEP a warp, so that a periodic structure (pickets, spines) is not
            # matched to the next period: the coarser level brought the motion near
            step = np.stack((syy * sxt - sxy * syt, sxx * syt - sxy * sxt)) / det
            flow -= np.clip(step, -MAX_STEP, MAX_STEP)
        flow = _median3(flow)  # one level's outliers do not seed the next
    return flow


def estimate_flow(previous_probe: np.ndarray, current_probe: np.ndarray,
                  height: int, width: int) -> MotionEstimate:
    """Backward motion of an H×W frame from two motion probes (motion_evidence.probe), with
    per-pixel doubt (the module docstring)."""
    backward = lucas_kanade(previous_probe, current_probe)
    forward = lucas_kanade(current_probe, previous_probe)
    _, h, w = current_probe.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
    x, y = cols + backward[0], rows + backward[1]
    # forward-backward: p -> p + b(p) in the previous frame -> + f there should come back to p
    round_trip = backward + _sample(forward, x, y)
    fb = np.hypot(round_trip[0], round_trip[1]) * PROBE_SCALE
    residual = np.abs(_sample(previous_probe, x, y) - current_probe).mean(0)
    outside = (x < 0) | (x > w - 1) | (y < 0) | (y > h - 1)
    doubt = (fb > FB_TOLERANCE) | (residual > RESIDUAL_TOLERANCE) | outside
    # to frame pixels: probe pixel i covers frame pixels 2i, 2i + 1 (centre 2i + 0.5)
    fr, fc = np.mgrid[0:height, 0:width].astype(np.float32)
    motion = PROBE_SCALE * _sample(backward, (fc + 0.5) / PROBE_SCALE - 0.5,
                                   (fr + 0.5) / PROBE_SCALE - 0.5)
    doubt_full = np.repeat(np.repeat(doubt[None], PROBE_SCALE, 1), PROBE_SCALE, 2)
    return MotionEstimate(np.ascontiguousarray(motion[:, :height, :width], np.float32),
                          np.ascontiguousarray(doubt_full[:, :height, :width], np.float32))


def _epe(estimate: np.ndarray, truth: np.ndarray, where: np.ndarray) -> float:
    error = np.hypot(*(estimate - truth))[where]
    return float(np.median(error)) if error.size else float("nan")


def score_shot(folder: Path, spp: int, frames: int) -> list[dict]:
    """Per frame t >= 1: median EPE of each estimator over all pixels and its trusted ones."""
    rows, previous, previous_depth = [], None, None
    for t in range(frames):
        planes = planes_from_hwc(cycles_io.load_inputs(folder, t, spp))
        current, depth = probe(planes), aux_motion.depth_probe(planes["depth"])
        if previous is not None:
            truth = np.nan_to_num(planes["motion"][:2]).astype(np.float32)
            _, height, width = truth.shape
            everywhere = np.ones((height, width), bool)
            flow = estimate_flow(previous, current, height, width)
            camera = aux_motion.estimate(previous, current, height, width, planes["depth"],
                                         previous_depth)
            row = {"shot": folder.name, "spp": spp, "frame": t,
                   "motion_px": float(np.median(np.hypot(*truth)))}
            trusted = flow.doubt[0] < 0.5
            row["flow"] = {"epe": _epe(flow.motion, truth, everywhere),
                           "epe_trusted": _epe(flow.motion, truth, trusted),
                           "trusted_share": flow.trusted_share}
            if camera is not None:
                row["camera"] = {"epe": _epe(camera.estimate, truth, everywhere),
                                 "epe_trusted": _epe(camera.estimate, truth, camera.trusted),
                                 "trusted_share": camera.share}
            rows.append(row)
            print(f"{folder.name} {spp} spp frame {t}: median motion {row['motion_px']:.2f} px; "
                  + "; ".join(f"{n} EPE {row[n]['epe']:.2f} px, {row[n]['epe_trusted']:.2f} on "
                              f"the {row[n]['trusted_share']:.0%} it trusts"
                              for n in ("flow", "camera") if n in row), flush=True)
        previous, previous_depth = current, depth
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_zoo_shots(p, zoo="zoo2")
    p.add_argument("--spp", type=int, default=4)
    p.add_argument("--frames", type=int, default=6)
    args = p.parse_args(argv)
    root = zoo_dir(args.data, args.split, args.zoo)
    for shot in shots(args.split, args.zoo):
        if args.shots and shot.name not in args.shots:
            continue
        if shot.camera == "locked" or shot.motion_blur or not (root / shot.name).exists():
            continue  # no motion, or no rendered motion to score against
        score_shot(root / shot.name, args.spp, args.frames)
    return 0


if __name__ == "__main__":
    sys.exit(main())
