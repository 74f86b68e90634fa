"""Backward motion estimated from the aux, for frames whose renderer wrote none (Cycles with
motion blur on writes an all-zero `Vector`): a temporal model can then follow the picture
instead of starting its history afresh on every frame of a moving shot.

The estimate is a rigid camera fitted by direct alignment (Gauss–Newton on the photometric
error of the aux over a pyramid, Huber-weighted, as in direct visual odometry: Kerl, Sturm &
Cremers 2013) to the motion probes the history gate already keeps (motion_evidence.probe:
albedo luminance and the normal, 2×2 box-averaged; no lighting noise), the field then following
from each pixel's own depth. A camera has six parameters, so the fit is not carried by noise
from window to window the way a free optical flow is (a Lucas–Kanade flow on the same probes
was 0.5–1.1 px off Cycles' vectors on a slow dolly, this fit 0.08–0.19 px: docs/zoo.md, "Motion
from the aux"), and a history fetched half a pixel off costs more than it gains.

Confidence per pixel, two checks, both needed:
- aux reprojection: the previous probe warped by the camera's field must match the current
  probe within TRUST_ERROR (mean |difference| over the probe's channels and a (2r+1)² window):
  an object that moves on its own, a disocclusion or a frame edge fails it;
- forward-backward: the previous frame's own depth (kept by the stream, `depth_probe`) carried
  forward by the same camera must land back where the pixel came from, within FB_PIXELS (3×3
  worst): where the previous frame saw something nearer at p + m (a post the camera trucked
  past, a disocclusion whose surfaces share an albedo and a normal) the two fields disagree by
  the parallax, and the aux alone cannot tell.
An untrusted pixel gets a vector that points outside the frame, which every temporal model
reads as "no history here" (its per-frame stage). A frame without a depth buffer gets no
estimate; one whose previous frame kept no depth gets the aux check only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from quietframe.runtime.motion_evidence import PROBE_SCALE, _box, fetch_nearest

LEVELS = 4  # pyramid levels of the probe (the coarsest at 1/8 of its size)
# Gauss–Newton steps per level, finest (the probe's own size) first. The fit runs from the
# coarsest level down to the first that holds PIN_PIXELS (its pixels pin the camera: the error
# goes as the level's pixel size over √pixels), or the finest: a 1080p or 720p frame's fit ends
# at a quarter of its size (130k and 58k pixels), a small frame's on the probe itself. Ending a
# 256×144 frame's fit at a quarter of its size (2 300 pixels) left 0.4–0.7 px of error against
# Cycles' vectors on a fast pan over fine brick, 0.1–0.25 px with the finest level, and across
# a motion-blurred pan the camera wandered ±0.2 px from frame to frame, where motion blur leaves
# the picture sharp (docs/zoo.md, "Motion from the aux").
ITERATIONS = (4, 4, 6, 8)
PIN_PIXELS = 50_000
HUBER = 0.005  # probe units: residuals beyond this weigh less (moving objects, mixed pixels)
DAMPING = 1e-4  # Levenberg–Marquardt, relative to the normal matrix's diagonal
# The focal length is not fitted: at first order the field sees only focal × rotation and
# focal × translation / depth, and a free focal length runs off (to 140 000 px on a truck).
FOV_DEG = 60.0
TRUST_ERROR = 0.05  # mean |aux difference| after the fit over the window: above it, untrusted
TRUST_RADIUS = 2  # probe pixels: the window's radius
FB_PIXELS = 0.5  # frame pixels: forward-backward disagreement above this is untrusted
# Memory: the fit runs only on levels of at most FIT_PIXELS (a camera has six parameters), the
# trust check on the first level of at most TRUST_PIXELS (a 4K frame's probe), and the frame's
# field in bands of BAND_ROWS rows, so an 8K frame holds tens of MB here, not gigabytes.
FIT_PIXELS = 300_000
TRUST_PIXELS = 1920 * 1080
BAND_ROWS = 64


@dataclass(frozen=True)
class EstimatedMotion:
    motion: np.ndarray  # (2, H, W) float32 backward motion in frame pixels; untrusted: outside
    trusted: np.ndarray  # (H, W) bool
    share: float  # of the frame's pixels, those trusted
    estimate: np.ndarray  # (2, H, W) the camera's field everywhere, trusted or not
    depth: np.ndarray  # (1, h, w) this frame's depth_probe, for the next frame's check


def working_set_bytes(height: int, width: int) -> int:
    """About the most an estimate holds for an H×W frame: its two fields and trust mask
    (17 B a pixel), the probe pyramid's depths and the forward-backward check's fields and error
    (~80 B a probe pixel), one band's float64 temporaries, and a fitting step's Jacobian and weights
    (~400 B a pixel of the largest level it fits on)."""
    sizes = [h * w for h, w in _level_shapes(-(-height // PROBE_SCALE), -(-width // PROBE_SCALE))]
    fitted = sizes[min(_fitted_levels(sizes), default=len(sizes) - 1)]
    band = 16 * 8 * min(BAND_ROWS, height) * width
    return 17 * height * width + 80 * sizes[0] + band + 400 * fitted


def _fitted_levels(sizes: list[int]) -> list[int]:
    """The pyramid levels the fit runs on, coarsest first, from the levels' pixel counts
    (finest first): down to the first that holds PIN_PIXELS, none above FIT_PIXELS."""
    levels = []
    for level in reversed(range(len(sizes))):
        if sizes[level] > FIT_PIXELS:
            break  # the camera is known from the coarser levels
        levels.append(level)
        if sizes[level] >= PIN_PIXELS:
            break
    return levels


def _rotation(w: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation matrix of axis-angle w."""
    angle = float(np.linalg.norm(w))
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]], np.float64)
    if angle < 1e-12:
        return np.eye(3) + k
    k /= angle
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def motion_field(params: np.ndarray, depth: np.ndarray, focal: float) -> np.ndarray:
    """(2, h, w) backward motion of an image with focal length `focal` (its pixels), for
    params = (rotation 3, translation 3: previous camera = R · current + t) and ray depth;
    computed in bands of BAND_ROWS rows (float64 temporaries of one band at a time)."""
    h, w = depth.shape
    out = np.empty((2, h, w), np.float32)
    for top in range(0, h, BAND_ROWS):
        rows = slice(top, min(top + BAND_ROWS, h))
        out[:, rows] = _field_rows(params, depth[rows], focal, top, h)
    return out


def _field_rows(params: np.ndarray, depth: np.ndarray, focal: float, top: int,
                height: int) -> np.ndarray:
    """motion_field's rows top … top + len(depth) of an image `height` rows tall."""
    h, w = depth.shape
    ys, xs = np.mgrid[top:top + h, 0:w].astype(np.float64)
    x, y = (xs + 0.5 - w / 2) / focal, (ys + 0.5 - height / 2) / focal
    z = depth / np.sqrt(x * x + y * y + 1)  # along the axis
    moved = np.tensordot(_rotation(params[:3]), np.stack((x * z, y * z, z)), 1)
    moved += params[3:6, None, None]
    zp = np.maximum(moved[2], 1e-6)
    return np.stack((focal * moved[0] / zp + w / 2 - (xs + 0.5),
                     focal * moved[1] / zp + height / 2 - (ys + 0.5))).astype(np.float32)


def warp(image: np.ndarray, flow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C, H, W) image fetched at p + flow(p), bilinear, coordinates clamped to the frame; and
    where p + flow lies inside it."""
    _, h, w = image.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    x, y = xs + flow[0], ys + flow[1]
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    x, y = np.clip(x, 0, w - 1), np.clip(y, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.intp), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.intp), max(h - 2, 0))
    fx, fy = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    top = image[:, y0, x0] * (1 - fx) + image[:, y0, x1] * fx
    bottom = image[:, y1, x0] * (1 - fx) + image[:, y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32), inside


def _step(params: np.ndarray, previous: np.ndarray, current: np.ndarray, depth: np.ndarray,
          focal: float) -> np.ndarray:
    """One Levenberg–Marquardt update of the six parameters at one pyramid level."""
    motion = motion_field(params, depth, focal)
    warped, inside = warp(previous, motion)
    residual = warped - current  # (C, h, w)
    gy, gx = np.gradient(warped, axis=(1, 2))
    jac = []
    for k in range(6):  # d motion / d param by central differences (smooth in the params)
        e = np.zeros(6)
        e[k] = 1e-4
        dm = (motion_field(params + e, depth, focal) - motion_field(params - e, depth, focal))
        dm /= 2e-4
        jac.append(gx * dm[0] + gy * dm[1])  # (C, h, w): d residual / d param
    j = np.stack(jac, -1)[:, inside]  # (C, n, 6)
    r = residual[:, inside]  # (C, n)
    a = np.abs(r)
    weight = np.where(a <= HUBER, 1.0, HUBER / np.maximum(a, 1e-12))
    jw = j * weight[..., None]
    normal = np.einsum("cnk,cnl->kl", jw, j)
    normal += DAMPING * np.diag(np.diag(normal)) + 1e-12 * np.eye(6)
    return params - np.linalg.solve(normal, np.einsum("cnk,cn->k", jw, r))


def _inverse(params: np.ndarray) -> np.ndarray:
    """The parameters of the opposite move: previous = R·current + t <=> current = Rᵀ·previous
    - Rᵀt (the rotation's axis-angle negated)."""
    return np.concatenate((-params[:3], -_rotation(params[:3]).T @ params[3:6]))


def _forward_backward_error(params: np.ndarray, back: np.ndarray, previous_depth: np.ndarray,
                            focal: float) -> np.ndarray:
    """(h, w) worst |b(p) + f(p + b(p))| over each pixel's 3×3, pixels of this level: b the
    camera's backward field of this frame (motion_field), f the forward field of the previous
    frame's depth. The nearest f: a post's motion and the sky's would average to neither."""
    forward = motion_field(_inverse(params), previous_depth, focal)
    error = np.hypot(*(back + fetch_nearest(forward, back)))
    padded = np.pad(error, 1, mode="edge")
    h, w = error.shape
    for i in range(3):
        for j in range(3):
            np.maximum(error, padded[i:i + h, j:j + w], out=error)
    return error


def _level_shapes(height: int, width: int) -> list[tuple[int, int]]:
    """(h, w) of each pyramid level of an image of this size, finest first: halved (rounded
    up) while both sides are at least 16, at most LEVELS levels."""
    shapes = [(height, width)]
    while len(shapes) < LEVELS and min(shapes[-1]) >= 16:
        shapes.append((-(-shapes[-1][0] // 2), -(-shapes[-1][1] // 2)))
    return shapes


def _pyramid(x: np.ndarray) -> list[np.ndarray]:
    out = [x]
    for _ in _level_shapes(*x.shape[1:])[1:]:
        out.append(_box(out[-1], 2))
    return out


def _ray_depth(depth: np.ndarray) -> np.ndarray | None:
    """(H, W) depth with the sky and missing values put far away; None without finite depth."""
    depth = np.asarray(depth, np.float32).reshape(depth.shape[-2:])
    finite = np.isfinite(depth) & (depth > 0)
    if not finite.any():
        return None
    far = float(np.percentile(depth[finite], 99))
    return np.where(finite, np.minimum(depth, 1e3 * max(far, 1e-3)), far).astype(np.float32)


def depth_probe(depth: np.ndarray | None) -> np.ndarray | None:
    """(1, ceil(H/2), ceil(W/2)) inverse ray depth of a (1, H, W) depth at the probe's size
    (motion_evidence.DEPTH_STATE); None without a usable depth. Averaged as inverse depth:
    motion goes with 1/depth, so a probe pixel of a thin post and the sky behind it moves as
    the mean of their motions (a plain mean of depths would put it far off)."""
    ray = _ray_depth(depth) if depth is not None else None
    return None if ray is None else _inverse_probe(ray)


def _inverse_probe(ray: np.ndarray) -> np.ndarray:
    """depth_probe of an (H, W) ray depth already put through _ray_depth."""
    return _box(1 / ray[None], PROBE_SCALE)


def estimate(previous: np.ndarray, current: np.ndarray, height: int, width: int,
             depth: np.ndarray | None, previous_depth: np.ndarray | None = None
             ) -> EstimatedMotion | None:
    """Backward motion of an H×W frame from the previous frame's probe and its own (probes of
    one shape: motion_evidence.probe) and its ray depth (1, H, W); None without a usable depth.
    `previous_depth`: the previous frame's depth_probe, for the forward-backward check (skipped
    without one). Per-pixel trust: module docstring."""
    depth = _ray_depth(depth) if depth is not None else None
    if depth is None:
        return None
    inverse = _inverse_probe(depth)  # this frame's depth_probe
    depths = [1 / d[0] for d in _pyramid(inverse)]
    previous_levels, current_levels = _pyramid(previous), _pyramid(current)
    focal = width / (2 * np.tan(np.radians(FOV_DEG) / 2))  # frame pixels
    params = np.zeros(6)
    levels = min(len(previous_levels), len(depths))
    for level in _fitted_levels([d.size for d in depths[:levels]]):
        for _ in range(ITERATIONS[min(level, len(ITERATIONS) - 1)]):
            params = _step(params, previous_levels[level], current_levels[level],
                           depths[level], focal / (PROBE_SCALE * 2**level))
    field = motion_field(params, depth, focal)
    # the trust check on the probe (or, for frames beyond 4K, the first level that fits)
    level = next((i for i in range(levels) if depths[i].size <= TRUST_PIXELS), levels - 1)
    scale = PROBE_SCALE * 2**level
    level_field = motion_field(params, depths[level], focal / scale)
    warped, inside = warp(previous_levels[level], level_field)
    error = np.abs(warped - current_levels[level]).mean(0)
    k = 2 * TRUST_RADIUS + 1
    padded = np.pad(error, TRUST_RADIUS, mode="edge")
    local = sum(padded[i:i + error.shape[0], j:j + error.shape[1]]
                for i in range(k) for j in range(k)) / k**2
    good = (local <= TRUST_ERROR) & inside
    if previous_depth is not None and previous_depth.shape == inverse.shape:
        previous_depths = _pyramid(previous_depth)
        if len(previous_depths) > level:
            good &= _forward_backward_error(params, level_field, 1 / previous_depths[level][0],
                                            focal / scale) <= FB_PIXELS / scale
    trusted = np.repeat(np.repeat(good, scale, 0), scale, 1)[:height, :width]
    motion = field.copy()
    motion[0][~trusted] = 4.0 * (height + width)  # outside the frame: no history here
    motion[1][~trusted] = 0.0
    return EstimatedMotion(motion, trusted, float(trusted.mean()), field, inverse)
