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

Three estimators (the third, `shipped`, is the one the service runs: runtime/aux_motion.py):
- `flow`: a pyramidal Lucas–Kanade flow (Lucas & Kanade 1981, Bouguet's pyramid) on the probe,
  with a forward-backward and an aux-reprojection check per pixel;
- `camera`: a rigid camera fitted to the probe by direct alignment (Gauss–Newton on the probe's
  photometric error over a pyramid, Huber-weighted, as in direct visual odometry: Kerl, Sturm &
  Cremers 2013), the field then following from each pixel's own depth, which a free flow
  cannot do at a thin post in front of a far wall.

Result (docs/zoo.md, "Motion from the aux"): neither of the first two was good enough to ship.
The shipped one is the first made cheaper and stricter (no median filter or forward-backward
pass; trusted only where the warped probe matches), and the history follows it only there.
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
from quietframe.runtime.motion_evidence import PROBE_SCALE, _box, probe
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


# --- camera: a rigid camera fitted to the probe --------------------------------------------

CAMERA_LEVELS = 4  # pyramid levels of the probe (the coarsest at 1/8 of its size)
CAMERA_ITERATIONS = (3, 4, 6, 8)  # Gauss–Newton steps, finest level first
HUBER = 0.005  # probe units: residuals beyond this weigh less (moving objects, mixed pixels)
DAMPING = 1e-4  # Levenberg–Marquardt, relative to the normal matrix's diagonal
# The focal length is not fitted: at first order the field sees only focal × rotation and
# focal × translation / depth, and a free focal length ran off (to 140 000 px on a truck).
DEFAULT_FOV_DEG = 60.0
FITTED = 6  # rotation and translation
CAMERA_RESIDUAL_TOLERANCE = 0.05  # mean |aux difference| after the fit: above it, doubtful
DOUBT_WINDOW = 2  # probe pixels: the residual is averaged over (2r + 1)² before the test


@dataclass(frozen=True)
class CameraMotion:  # the rigid camera's fit
    rotation: np.ndarray  # (3,) axis-angle, radians: previous camera = R · current + t
    translation: np.ndarray  # (3,) in depth units
    focal_px: float  # focal length in frame pixels
    motion: np.ndarray  # (2, H, W) float32 backward motion, frame pixels
    doubt: np.ndarray  # (1, H, W) float32, 1 where the field is not the pixel's motion

    @property
    def trusted_share(self) -> float:
        return float(1.0 - self.doubt.mean())


def _rotation(w: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation matrix of axis-angle w."""
    angle = float(np.linalg.norm(w))
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]], np.float64)
    if angle < 1e-12:
        return np.eye(3) + k
    k /= angle
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def motion_field(params: np.ndarray, depth: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(2, h, w) backward motion of an image whose pixel is `scale` frame pixels, for
    params = (rotation 3, translation 3, log focal in frame pixels) and ray depth (h, w)."""
    h, w = depth.shape
    f = np.exp(params[6]) / scale
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (xs + 0.5 - w / 2) / f, (ys + 0.5 - h / 2) / f
    norm = np.sqrt(x * x + y * y + 1)
    z = depth / norm  # along the axis
    points = np.stack((x * z, y * z, z))
    moved = np.tensordot(_rotation(params[:3]), points, 1) + params[3:6, None, None]
    zp = np.maximum(moved[2], 1e-6)
    return np.stack((f * moved[0] / zp + w / 2 - (xs + 0.5),
                     f * moved[1] / zp + h / 2 - (ys + 0.5))).astype(np.float32)


def _warp(previous: np.ndarray, motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The previous probe at p + m, and where p + m lies inside it."""
    _, h, w = previous.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    x, y = xs + motion[0], ys + motion[1]
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    return _sample(previous, x, y), inside


def _camera_step(params, previous, current, depth, scale) -> np.ndarray:
    """One Levenberg–Marquardt update of the 7 parameters at one pyramid level."""
    motion = motion_field(params, depth, scale)
    warped, inside = _warp(previous, motion)
    residual = warped - current  # (C, h, w)
    gx, gy = _gradients(warped)
    # d motion / d param by central differences (the field is smooth in the parameters)
    jac = []
    for k in range(FITTED):
        e = np.zeros(7)
        e[k] = 1e-4 if k < 6 else 1e-3
        dm = (motion_field(params + e, depth, scale) - motion_field(params - e, depth, scale))
        dm /= 2 * e[k]
        jac.append(gx * dm[0] + gy * dm[1])  # (C, h, w): d residual / d param
    j = np.stack(jac, -1)[:, inside]  # (C, n, FITTED)
    r = residual[:, inside]  # (C, n)
    a = np.abs(r)
    weight = np.where(a <= HUBER, 1.0, HUBER / np.maximum(a, 1e-12))  # Huber
    jw = j * weight[..., None]
    normal = np.einsum("cnk,cnl->kl", jw, j)
    rhs = np.einsum("cnk,cn->k", jw, r)
    normal += DAMPING * np.diag(np.diag(normal)) + 1e-12 * np.eye(FITTED)
    update = np.zeros(7)
    update[:FITTED] = np.linalg.solve(normal, rhs)
    return params - update


def _pyramid(x: np.ndarray, levels: int) -> list[np.ndarray]:
    out = [x]
    for _ in range(levels - 1):
        if min(out[-1].shape[1:]) < 16:
            break
        out.append(_box(out[-1], 2))
    return out


def estimate_camera(previous_probe: np.ndarray, current_probe: np.ndarray,
                    depth: np.ndarray, fov_deg: float = DEFAULT_FOV_DEG) -> CameraMotion:
    """The camera motion that carries the previous frame's probe onto this one's, and the
    backward motion field of this (H, W) frame from its ray depth (1, H, W) or (H, W)."""
    depth = np.asarray(depth, np.float32).reshape(depth.shape[-2:])
    height, width = depth.shape
    finite = np.isfinite(depth) & (depth > 0)
    far = float(np.percentile(depth[finite], 99)) if finite.any() else 1.0
    depth = np.where(finite, np.minimum(depth, 1e3 * max(far, 1e-3)), far).astype(np.float32)
    # Averaged as inverse depth: motion goes with 1/depth, so a probe pixel of a thin post
    # and the sky behind it moves as the mean of their motions (a plain mean of 4 m and
    # 1e10 m would put it at infinity)
    probe_depth = 1 / _box(1 / depth[None], PROBE_SCALE)[0]
    depths = [1 / d for d in _pyramid(1 / probe_depth[None], CAMERA_LEVELS)]
    previous = _pyramid(previous_probe.astype(np.float32), CAMERA_LEVELS)
    current = _pyramid(current_probe.astype(np.float32), CAMERA_LEVELS)
    params = np.zeros(7)
    params[6] = np.log(width / (2 * np.tan(np.radians(fov_deg) / 2)))
    for level in reversed(range(min(len(previous), len(depths)))):
        scale = PROBE_SCALE * 2**level
        for _ in range(CAMERA_ITERATIONS[min(level, len(CAMERA_ITERATIONS) - 1)]):
            params = _camera_step(params, previous[level], current[level], depths[level][0], scale)
    motion = motion_field(params, depth, 1.0)
    # doubt: where the fitted field does not carry the aux over (objects, disocclusions)
    probe_motion = motion_field(params, probe_depth, PROBE_SCALE)
    warped, inside = _warp(previous[0], probe_motion)
    residual = np.abs(warped - current[0]).mean(0)[None]
    size = 2 * DOUBT_WINDOW + 1
    pad = np.pad(residual, ((0, 0), (DOUBT_WINDOW,) * 2, (DOUBT_WINDOW,) * 2), mode="edge")
    local = sum(pad[:, i:i + residual.shape[1], j:j + residual.shape[2]]
                for i in range(size) for j in range(size)) / size**2
    bad = (local[0] > CAMERA_RESIDUAL_TOLERANCE) | ~inside
    doubt = np.repeat(np.repeat(bad, PROBE_SCALE, 0), PROBE_SCALE, 1)[:height, :width]
    return CameraMotion(params[:3].copy(), params[3:6].copy(), float(np.exp(params[6])),
                        motion, doubt[None].astype(np.float32))


def _epe(estimate: np.ndarray, truth: np.ndarray, where: np.ndarray) -> float:
    error = np.hypot(*(estimate - truth))[where]
    return float(np.median(error)) if error.size else float("nan")


def score_shot(folder: Path, spp: int, frames: int) -> list[dict]:
    """Per frame t >= 1: median EPE of each estimator over all pixels and its trusted ones."""
    rows, previous = [], None
    for t in range(frames):
        planes = planes_from_hwc(cycles_io.load_inputs(folder, t, spp))
        current = probe(planes)
        if previous is not None:
            truth = np.nan_to_num(planes["motion"][:2]).astype(np.float32)
            _, height, width = truth.shape
            everywhere = np.ones((height, width), bool)
            flow = estimate_flow(previous, current, height, width)
            camera = estimate_camera(previous, current, planes["depth"])
            shipped = aux_motion.estimate(previous, current, height, width)
            row = {"shot": folder.name, "spp": spp, "frame": t,
                   "motion_px": float(np.median(np.hypot(*truth)))}
            for name, est in (("flow", flow), ("camera", camera)):
                trusted = est.doubt[0] < 0.5
                row[name] = {"epe": _epe(est.motion, truth, everywhere),
                             "epe_trusted": _epe(est.motion, truth, trusted),
                             "trusted_share": est.trusted_share}
            row["shipped"] = {"epe": _epe(shipped.estimate, truth, everywhere),
                              "epe_trusted": _epe(shipped.estimate, truth, shipped.trusted),
                              "trusted_share": shipped.share}
            rows.append(row)
            print(f"{folder.name} {spp} spp frame {t}: median motion {row['motion_px']:.2f} px; "
                  + "; ".join(f"{n} EPE {row[n]['epe']:.2f} px, {row[n]['epe_trusted']:.2f} on "
                              f"the {row[n]['trusted_share']:.0%} it trusts"
                              for n in ("flow", "camera", "shipped")), flush=True)
        previous = current
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
