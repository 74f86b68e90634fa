"""Is a frame without usable motion vectors a locked-off camera or a moving one? The one rule
that decides whether a history may be reprojected with zero motion, for `auto` and fixed models.

A frame's `Vector` can be all zero for two opposite reasons: the camera and scene did not move
(a locked-off shot: Blender writes zeros, and zero motion is exactly right), or the renderer
could not fill it (Cycles with motion blur on, or the first frame of a sequence, which has no
previous frame) while the image moves. Reprojecting a history with zero motion is the best a
locked-off shot can get and ghosts on a moving one. The frames themselves tell the two apart:
the auxiliary buffers (albedo, normal), which hold no lighting noise, stay put on a locked-off
shot up to their sampling noise (pixel-filter jitter, depth of field) and move with the image
otherwise.

The test (`judge`): a probe of each frame (`probe`: albedo luminance and normal, 2×2 box-averaged;
the colour's luminance where a frame has no albedo) is compared with the previous frame's. In
tiles of the probe, the frame difference D is regressed on the spatial gradient G of the two
frames' mean (brightness constancy, Lucas & Kanade 1981: D ≈ -v·G for a displacement v).
Sampling noise is independent between frames and of the neighbouring pixels a central
difference reads, so it does not correlate with G: under no motion the Wald statistic of the
fitted displacement (with White's heteroscedasticity-consistent covariance, since the noise is
largest at edges, where G is) follows χ²(2), about 2. A shift of a fraction of a pixel over any
texture or edge explains D and drives it up. A tile is moving where the statistic exceeds
MOTION_WALD, or where D's energy is far above what noise gives beside the gradient's (a shift
larger than the texture's scale, e.g. a fast pan, breaks the linearisation but not this); the
frame is `moving` where at least MOVING_SHARE of its tiles with structure move, `static`
otherwise.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

PROBE_SCALE = 2  # box-average factor: quarters the pixel noise's variance, and the probe's size
PROBE_CHANNELS = 4  # albedo (or colour) luminance, normal x, y, z
TILE = 8  # probe pixels (16 frame pixels) a side
# The robust Wald statistic is χ²(2) under no motion: above 25 with probability 4e-6, so a
# locked-off 1080p frame (~8000 tiles) has well under one false tile on average. Real
# locked-off Cycles frames stay below ~15 (tests/fixtures/blender_sequences); a pan of 3 px a
# frame under motion blur puts half the tiles above 30 and most of those above 100.
MOTION_WALD = 25.0
MOVING_SHARE = 0.05  # of tiles with structure; a small moving object counts too
# Ratios of a tile's difference energy to its gradient energy (4 for pure noise on a static
# tile): above CHANGE_RATIO it changed, below STRUCTURE_RATIO it has structure to show motion.
CHANGE_RATIO = 8.0
STRUCTURE_RATIO = 2.0
MIN_TILES = 4  # fewer tiles with structure than this: the frame cannot tell (`unknown`)
MIN_MOVING_TILES = 2  # one odd tile (a firefly in the albedo of glass) is not motion
# A cut under motion vectors (judge_cut): a tile changed where the L1 distance of its mean
# (albedo luminance, normal x, y, z) to the warped previous frame's exceeds this; a cut where
# at least CUT_SHARE of all tiles changed.
CUT_TILE_CHANGE = 0.25
CUT_SHARE = 0.5

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


@dataclass(frozen=True)
class MotionEvidence:
    """What a frame without usable motion vectors shows, against the previous frame.

    verdict: `static` (zero motion is right: keep the history), `moving` (the history would
    ghost: start it afresh), `unknown` (no previous frame, another frame size, or too little
    structure to tell), `locked` (the session says the camera is locked off: not judged);
    `cut` (the aux changed everywhere: a camera switch the vectors do not show)."""

    verdict: str
    moving_share: float | None = None  # of the tiles with structure, those that moved
    tiles: int = 0  # tiles with structure

    def describe(self) -> str:
        if self.verdict == "locked":
            return "locked-off (session camera: locked)"
        if self.moving_share is None:
            return self.verdict
        what = "changed" if self.verdict == "cut" else "moved"
        return f"{self.verdict} ({100 * self.moving_share:.0f}% of {self.tiles} tiles {what})"


def _box(x: np.ndarray, k: int) -> np.ndarray:
    """(C, H, W) -> (C, ceil(H/k), ceil(W/k)) block means (edge blocks padded by replication).
    Summed from the k² strided views: a reshape-and-mean over the block axes reads the frame
    with strides and cost ~3x as much at 1080p (the probe runs on every temporal frame)."""
    c, h, w = x.shape
    ph, pw = -h % k, -w % k
    if ph or pw:
        x = np.pad(x, ((0, 0), (0, ph), (0, pw)), mode="edge")
    out = np.zeros((c, (h + ph) // k, (w + pw) // k), np.float32)
    for i in range(k):
        for j in range(k):
            out += x[:, i::k, j::k]
    return out * np.float32(1 / (k * k))


def probe(buffers: Mapping[str, np.ndarray]) -> np.ndarray:
    """A frame's motion probe, (PROBE_CHANNELS, ceil(H/2), ceil(W/2)) float32, from its (C, H, W)
    planes: albedo luminance (else the colour's, log-compressed: it carries lighting noise and
    HDR range) and the normal (zeros without one). Non-finite values count as 0."""
    color = buffers["color"]
    h, w = color.shape[-2:]
    out = np.zeros((PROBE_CHANNELS, h, w), np.float32)
    albedo = buffers.get("albedo")
    if albedo is not None:
        out[0] = np.tensordot(LUMA, np.asarray(albedo[:3], np.float32), 1)
    else:
        out[0] = np.log1p(np.maximum(np.tensordot(LUMA, np.asarray(color[:3], np.float32), 1), 0))
    normal = buffers.get("normal")
    if normal is not None:
        out[1:4] = np.asarray(normal[:3], np.float32)
    np.nan_to_num(out, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    return _box(out, PROBE_SCALE).astype(np.float32)


def _tiles(x: np.ndarray) -> np.ndarray:
    """(C, H, W) -> (C, H // TILE, W // TILE, TILE, TILE), the remainder cropped."""
    c, h, w = x.shape
    th, tw = h // TILE, w // TILE
    return x[:, : th * TILE, : tw * TILE].reshape(c, th, TILE, tw, TILE).transpose(0, 1, 3, 2, 4)


def _sum(x: np.ndarray) -> np.ndarray:
    """Per tile: the sum over channels and the tile's pixels."""
    return x.sum(axis=(0, 3, 4))


def judge(previous: np.ndarray | None, current: np.ndarray) -> MotionEvidence:
    """Whether the image moved between two probes (see the module docstring)."""
    if previous is None or previous.shape != current.shape:
        return MotionEvidence("unknown")
    if min(current.shape[1:]) < TILE + 2:
        return MotionEvidence("unknown")
    mean = (previous + current) / 2
    d = _tiles((current - previous)[:, 1:-1, 1:-1]).astype(np.float64)
    # central differences: they read neither pixel's own noise, so noise and G are independent
    gx = _tiles((mean[:, 1:-1, 2:] - mean[:, 1:-1, :-2]) / 2).astype(np.float64)
    gy = _tiles((mean[:, 2:, 1:-1] - mean[:, :-2, 1:-1]) / 2).astype(np.float64)
    sxx, sxy, syy = _sum(gx * gx), _sum(gx * gy), _sum(gy * gy)
    sxd, syd, sdd = _sum(gx * d), _sum(gy * d), _sum(d * d)
    det = sxx * syy - sxy * sxy
    ok = det > 1e-9 * np.maximum(sxx * syy, 1e-30)
    safe = np.where(ok, det, 1.0)
    # Least squares D ≈ -(vx Gx + vy Gy) per tile, and its residual per pixel
    vx = -(syy * sxd - sxy * syd) / safe
    vy = -(sxx * syd - sxy * sxd) / safe
    r2 = (d + vx[None, :, :, None, None] * gx + vy[None, :, :, None, None] * gy) ** 2
    # Wald statistic of v = 0 with the heteroscedasticity-consistent covariance (White 1980):
    # the noise is larger at edges (pixel-filter jitter), where G is large, which inflates a
    # plain F test on a locked-off shot. W = b^T M^-1 b, b = (ΣGxD, ΣGyD), M = Σ G G^T r².
    mxx, mxy, myy = _sum(gx * gx * r2), _sum(gx * gy * r2), _sum(gy * gy * r2)
    mdet = mxx * myy - mxy * mxy
    wald = np.where(ok & (mdet > 0), (myy * sxd**2 - 2 * mxy * sxd * syd + mxx * syd**2)
                    / np.where(mdet > 0, mdet, 1.0), 0.0)
    gradient = sxx + syy
    # Pure noise gives ΣD² = 4 × gradient energy in expectation (D's variance is 2σ², a central
    # difference of the mean's σ²/2 per axis pair): a tile whose difference is far above that
    # changed beyond what a linear fit sees (a shift of more than the texture's scale).
    moving = ok & ((wald > MOTION_WALD) | (sdd > CHANGE_RATIO * gradient))
    # Tiles that could show motion: moving ones, and static ones whose gradient energy is well
    # above what noise alone gives (a flat wall or the sky shows nothing either way).
    counted = moving | (ok & (sdd < STRUCTURE_RATIO * gradient))
    tiles = int(counted.sum())
    if tiles < MIN_TILES:
        return MotionEvidence("unknown", None, tiles)
    moved = int(moving.sum())
    share = moved / tiles
    verdict = "moving" if share >= MOVING_SHARE and moved >= MIN_MOVING_TILES else "static"
    return MotionEvidence(verdict, share, tiles)


# ---- the history gate: one rule for the service and the evaluation ------------------------------

PROBE_STATE = "motion_probe"  # the previous frame's probe, kept beside a temporal model's state
# The previous frame's inverse depth at the probe's size (aux_motion.depth_probe), kept where a
# frame without vectors had a depth: the estimate's occlusion check reads it.
DEPTH_STATE = "motion_depth"
STREAM_STATES = (PROBE_STATE, DEPTH_STATE)  # kept by the stream, never given to the model


def probe_shape(height: int, width: int) -> tuple[int, int, int]:
    return (PROBE_CHANNELS, -(-height // PROBE_SCALE), -(-width // PROBE_SCALE))


def has_motion(planes: Mapping[str, np.ndarray]) -> bool:
    """Whether the frame carries motion vectors a reprojection can use: a motion buffer with
    one finite nonzero vector (an all-zero Vector is what Cycles writes with motion blur on)."""
    motion = planes.get("motion")
    return motion is not None and bool(np.any((motion != 0) & np.isfinite(motion)))


@dataclass(frozen=True)
class HistoryGate:
    state: dict[str, np.ndarray] | None  # what the model gets: None starts its history afresh
    probe: np.ndarray  # this frame's probe, to keep with the model's new state (keep_probe)
    evidence: MotionEvidence | None  # None: the frame has motion vectors
    dropped: bool  # a history existed and is not used: the image moved without vectors


def warp_probe(previous: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """The previous frame's probe fetched along this frame's motion (pixel p was at p + m in
    the previous frame), nearest probe pixel, clamped to the frame."""
    return fetch_nearest(previous,
                         _box(np.asarray(motion[:2], np.float32), PROBE_SCALE) / PROBE_SCALE)


def fetch_nearest(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """(C, h, w) image at the nearest pixel to p + flow(p), clamped to the frame (a non-finite
    flow counts as 0): nothing is blended across an edge."""
    _, h, w = image.shape
    rows, cols = np.mgrid[0:h, 0:w]
    x = np.clip(np.rint(cols + np.nan_to_num(flow[0])), 0, w - 1).astype(np.intp)
    y = np.clip(np.rint(rows + np.nan_to_num(flow[1])), 0, h - 1).astype(np.intp)
    return image[:, y, x]


def judge_cut(previous: np.ndarray | None, current: np.ndarray,
              motion: np.ndarray) -> MotionEvidence | None:
    """A cut the motion vectors do not show: a renderer writes the new camera's own motion on
    the first frame after a camera switch, so reprojection would fetch the other shot's
    surfaces wherever their depth and normal happen to match. Along correct vectors each tile's
    mean albedo and normal stays within a few hundredths (camera-space normals turn with the
    camera: 0.04 at 2.3° a frame); across a cut most tiles change by far more (1.9 median,
    measured on zoo frames). `cut` where at least CUT_SHARE of the tiles changed by more than
    CUT_TILE_CHANGE; None otherwise (or when the frames cannot be compared)."""
    if previous is None or previous.shape != current.shape or min(current.shape[1:]) < TILE:
        return None
    change = np.abs(_tile_means(warp_probe(previous, motion)) - _tile_means(current)).sum(0)
    share = float((change > CUT_TILE_CHANGE).mean())
    return MotionEvidence("cut", share, int(change.size)) if share >= CUT_SHARE else None


def _tile_means(x: np.ndarray) -> np.ndarray:
    return _tiles(x).mean(axis=(3, 4))


CAMERAS = ("auto", "locked")  # a session's `camera`: judged per frame, or locked off by the TD


def gate_history(planes: Mapping[str, np.ndarray], state: Mapping[str, np.ndarray] | None,
                 camera: str = "auto") -> HistoryGate:
    """The history a temporal model may read for this frame. With motion vectors: all of it,
    unless the aux show a cut the vectors do not (judge_cut). Without: all of it where the
    image stayed put (a locked-off shot: zero motion is exact), none where it moved
    (reprojecting with zero motion would ghost), all of it where the frame cannot tell (too
    little structure to show either, so nothing to ghost visibly).

    `camera="locked"` (the session says the camera is locked off): zero motion is trusted
    without the judge, whose low-spp aux noise can pass for motion, and only a cut the aux
    show (judge_cut along zero motion) starts the history afresh."""
    if camera not in CAMERAS:
        raise ValueError(f"camera must be one of {CAMERAS}, got {camera!r}")
    current = probe(planes)
    model_state = None if state is None else {k: v for k, v in state.items()
                                              if k not in STREAM_STATES}
    previous = None if state is None else state.get(PROBE_STATE)
    if has_motion(planes):
        cut = judge_cut(previous, current, planes["motion"])
        if cut is not None:
            return HistoryGate(None, current, cut, model_state is not None)
        return HistoryGate(model_state, current, None, False)
    if camera == "locked":
        h, w = planes["color"].shape[-2:]
        cut = judge_cut(previous, current, np.zeros((2, h, w), np.float32))
        if cut is not None:
            return HistoryGate(None, current, cut, model_state is not None)
        return HistoryGate(model_state, current, MotionEvidence("locked"), False)
    evidence = judge(previous, current)
    if evidence.verdict == "moving":
        return HistoryGate(None, current, evidence, model_state is not None)
    return HistoryGate(model_state, current, evidence, False)


def keep_probe(state: Mapping[str, np.ndarray], probe_: np.ndarray,
               depth: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The model's new state with this frame's probe (and inverse-depth probe, where one was
    made) beside it, for the next frame's gate and estimate."""
    kept = {**state, PROBE_STATE: probe_}
    if depth is not None:
        kept[DEPTH_STATE] = depth
    return kept


def history_shapes(state_specs, height: int, width: int) -> dict[str, tuple[int, ...]]:
    """Every tensor a temporal model's session may keep between frames: the model's state and
    the probes beside it (nothing for a model without state)."""
    shapes = {s.name: tuple(s.shape(height, width)) for s in state_specs}
    if shapes:
        shapes[PROBE_STATE] = probe_shape(height, width)
        shapes[DEPTH_STATE] = (1, *probe_shape(height, width)[1:])
    return shapes


def history_nbytes(state_specs, height: int, width: int) -> int:
    """Bytes of history_shapes (float32)."""
    return sum(4 * int(np.prod(s)) for s in history_shapes(state_specs, height, width).values())
