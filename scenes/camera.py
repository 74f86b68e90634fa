"""Camera animation, Mitsuba-compatible projection, and backward motion vectors.

Conventions (same as Mitsuba's `perspective` sensor with `fov_axis="x"` built by `look_at`):
camera-to-world columns are (left, up, forward, origin); the film's x grows to the right
(against `left`), y grows downwards, and pixel (i, j) covers [j, j+1] x [i, i+1], so its centre
is at (j + 0.5, i + 0.5). Motion is backward, in pixels, as every quietframe buffer's: "pixel p
of frame t was at p + motion in frame t-1".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class Camera:
    origin: list[float]
    target: list[float]
    up: list[float]
    fov_x: float  # degrees, horizontal

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(left, up, forward) unit vectors, exactly as Mitsuba's look_at builds them."""
        fwd = np.subtract(self.target, self.origin).astype(np.float64)
        fwd /= np.linalg.norm(fwd)
        left = np.cross(self.up, fwd)
        left /= np.linalg.norm(left)
        return left, np.cross(fwd, left), fwd

    def to_world(self) -> np.ndarray:
        left, up, fwd = self.basis()
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, up, fwd, self.origin
        return m

    def world_to_pixel(self, width: int, height: int) -> np.ndarray:
        """3x4 matrix P with (x*w, y*w, w) = P @ (X, Y, Z, 1); w is the forward distance."""
        tan_x = np.tan(np.radians(self.fov_x) / 2)
        fx = width / (2 * tan_x)  # square pixels: the same focal length in pixels for y
        k = np.array([[-fx, 0, width / 2], [0, -fx, height / 2], [0, 0, 1]])
        left, up, fwd = self.basis()
        r = np.stack([left, up, fwd])  # world -> camera rows
        return k @ np.concatenate([r, -(r @ np.asarray(self.origin))[:, None]], axis=1)

    def as_dict(self) -> dict:
        return {
            k: (list(map(float, v)) if isinstance(v, list | np.ndarray) else float(v))
            for k, v in asdict(self).items()
        }


def project(points: np.ndarray, cam: Camera, width: int, height: int) -> tuple[np.ndarray, ...]:
    """Continuous film coordinates (x, y) and forward distance w of world points (..., 3)."""
    p = cam.world_to_pixel(width, height)
    h = points @ p[:, :3].T + p[:, 3]
    w = h[..., 2]
    safe = np.where(np.abs(w) > 1e-9, w, 1e-9)
    return h[..., 0] / safe, h[..., 1] / safe, w


def pixel_directions(cam: Camera, width: int, height: int) -> np.ndarray:
    """World-space unit directions through pixel centres, (H, W, 3)."""
    tan_x = np.tan(np.radians(cam.fov_x) / 2)
    fx = width / (2 * tan_x)
    j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    left, up, fwd = cam.basis()
    d = (
        fwd[None, None] * fx
        - left[None, None] * (j - width / 2)[..., None]
        - up[None, None] * (i - height / 2)[..., None]
    )
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# Animation

MOVES = ("pan", "truck", "dolly", "orbit", "free", "pedestal", "handheld")


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _rotate_y(v: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([c * v[0] + s * v[2], v[1], -s * v[0] + c * v[2]])


def _path(
    rng: np.random.Generator,
    start: np.ndarray,
    target: np.ndarray,
    fov: float,
    n: int,
) -> tuple[str, list[Camera]]:
    """One continuous shot of n frames starting at `start` looking at `target`."""
    move = str(rng.choice(MOVES))
    view = target - start
    fwd_flat = _unit(np.array([view[0], 0.0, view[2]]) + 1e-9)
    side = np.cross([0.0, 1.0, 0.0], fwd_flat)
    speed = float(np.exp(rng.uniform(np.log(0.015), np.log(0.15))))  # metres per frame
    turn = np.radians(rng.uniform(0.5, 5.0)) * rng.choice([-1, 1])  # radians per frame
    tilt = rng.uniform(-0.02, 0.02) * np.linalg.norm(view)  # aim drift, metres per frame
    zoom = rng.uniform(-0.02, 0.02) if rng.random() < 0.15 else 0.0  # relative fov per frame
    # Hand-held: a slow random walk of the position and the aim (smooth, not white jitter).
    shake = rng.uniform(0.002, 0.008) if move == "handheld" or rng.random() < 0.3 else 0.0
    heading = _unit(rng.normal(0, 1, 3) * np.array([1, 0.2, 1]))
    end_target = target + rng.normal(0, 0.6, 3) * np.array([1, 0.3, 1])
    jitter = np.cumsum(rng.normal(0, shake, (n, 3)), 0)
    aim_jitter = np.cumsum(rng.normal(0, shake * 3, (n, 3)), 0)
    cams = []
    for k in range(n):
        o, t = start.copy(), target.copy()
        if move == "pan":
            t = start + _rotate_y(view, turn * k) + np.array([0, tilt * k, 0])
        elif move == "truck":
            o, t = start + side * speed * k, target + side * speed * k
        elif move == "dolly":
            o = start + _unit(view) * speed * k
        elif move == "orbit":
            o = target - _rotate_y(view, turn * k)
        elif move == "pedestal":
            o = start + np.array([0, speed * 0.5 * k, 0])
        elif move == "handheld":
            pass  # only the drift below
        else:  # free flight while the aim drifts to another point
            s = k / max(n - 1, 1)
            o = start + heading * speed * k
            t = target * (1 - s) + end_target * s
        o, t = o + jitter[k], t + aim_jitter[k]
        cams.append(Camera(o.tolist(), t.tolist(), [0.0, 1.0, 0.0], float(fov * (1 + zoom) ** k)))
    return move, cams


def animate(
    rng: np.random.Generator,
    inside: Callable[[np.ndarray], np.ndarray],
    sample_point: Callable[[np.random.Generator], np.ndarray],
    n_frames: int,
    cut_prob: float = 0.2,
    tries: int = 200,
    sample_target: Callable[[np.random.Generator, np.ndarray], np.ndarray] | None = None,
) -> dict:
    """Camera frames for a sequence, possibly with one cut. `inside(points)` says which points
    (N, 3) are at a safe distance inside the room; `sample_point(rng)` draws such a point (the
    camera's start), `sample_target(rng, start)` what it looks at (default: sample_point)."""
    cut = int(rng.integers(2, n_frames - 1)) if n_frames >= 6 and rng.random() < cut_prob else 0
    lengths = [cut, n_frames - cut] if cut else [n_frames]
    shots, frames = [], []
    for length in lengths:
        for _ in range(tries):
            start = sample_point(rng)
            target = sample_target(rng, start) if sample_target else sample_point(rng)
            if np.linalg.norm(target - start) < 1.5:
                continue
            fov = float(rng.uniform(35, 90))
            move, cams = _path(rng, start, target, fov, length)
            origins = np.array([c.origin for c in cams])
            dist = np.linalg.norm(np.array([c.target for c in cams]) - origins, axis=1)
            if inside(origins).all() and (dist > 0.5).all():
                break
        else:
            raise RuntimeError("no camera path fits inside the room")
        shots.append({"first_frame": len(frames), "move": move})
        frames.extend(cams)
    return {"frames": frames, "shots": shots, "cuts": [s["first_frame"] for s in shots[1:]]}


# ---------------------------------------------------------------------------------------------
# Motion vectors


def motion_for_pass(
    position: np.ndarray,
    hit: np.ndarray,
    normal: np.ndarray,
    cam: Camera,
    prev_cam: Camera,
    prev_position: np.ndarray,
    prev_normal: np.ndarray,
    prev_hit: np.ndarray,
    position_prev: np.ndarray | None = None,
    normal_prev: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Backward motion (H, W, 2) and visibility (H, W) of one one-sample pass.

    Each pixel's sample point is reprojected exactly (both cameras are known). On moving
    objects the point itself moved: `position_prev` / `normal_prev` are where it was and how it
    faced at t-1 (the object's rigid motion applied backwards; default: static scene), and the
    point is projected and compared there. Visibility is the
    paper's test (Isik et al. 2021, 4.1): the point must land inside frame t-1 and agree in
    position and normal with one of the 2x2 pixels of t-1 around where it lands. Environment
    samples move by camera rotation only and are visible where t-1 also saw the environment.
    """
    h, w = hit.shape
    # Hit samples: project the sample point into both cameras.
    x_t, y_t, _ = project(position, cam, w, h)
    pos_p = position if position_prev is None else position_prev
    nrm_p = normal if normal_prev is None else normal_prev
    x_p, y_p, z_p = project(pos_p, prev_cam, w, h)
    # Misses: directions through pixel centres, carried by the previous camera's rotation.
    d = pixel_directions(cam, w, h)
    far = np.asarray(prev_cam.origin) + d * 1e6
    ex, ey, ez = project(far, prev_cam, w, h)
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    mx = np.where(hit, x_p - x_t, ex - jj)
    my = np.where(hit, y_p - y_t, ey - ii)
    qx, qy = jj + mx, ii + my
    onscreen = (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h) & (np.where(hit, z_p, ez) > 0)

    tan_x = np.tan(np.radians(prev_cam.fov_x) / 2)
    dist_prev = np.linalg.norm(pos_p - np.asarray(prev_cam.origin), axis=-1)
    # A pixel spans dist*2*tan/W in world space; allow 2 of them plus 1% for depth slope.
    tol = dist_prev * (4 * tan_x / w + 0.01)
    n_len = np.linalg.norm(prev_normal, axis=-1, keepdims=True)
    prev_n = prev_normal / np.maximum(n_len, 1e-6)
    agree = np.zeros((h, w), bool)
    env_ok = np.zeros((h, w), bool)
    x0 = np.floor(qx - 0.5).astype(int)
    y0 = np.floor(qy - 0.5).astype(int)
    for dy in (0, 1):
        for dx in (0, 1):
            xs = np.clip(x0 + dx, 0, w - 1)
            ys = np.clip(y0 + dy, 0, h - 1)
            near = np.linalg.norm(prev_position[ys, xs] - pos_p, axis=-1) < tol
            facing = np.sum(prev_n[ys, xs] * nrm_p, axis=-1) > 0.8
            agree |= prev_hit[ys, xs] & near & facing
            env_ok |= ~prev_hit[ys, xs]
    visible = onscreen & np.where(hit, agree, env_ok)
    return np.stack([mx, my], -1).astype(np.float32), visible
