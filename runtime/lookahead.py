"""Look-ahead: frame t finished with the frames t + 1 … t + k that followed it, for a session
that may hold k frames back (a farm has the whole shot on disk). The causal step is unchanged
(history, motion evidence, auto's choice: runtime/stream.py): the blend is a post-step over a
queue of finished causal steps and never feeds back, so k = 0 is today's output bit for bit.

For frame t, with m ≤ k later frames of the same history run in the window:

    out_t = (n_t · C_t + Σ_{j=1..m} τ_j · F_j) / (n_t + Σ_j τ_j)

- C_t: the causal output; n_t its worth in frames, per pixel, from the output history's own
  state (`causal_worth`: history length n and the current frame's weight α = max(1/n, w(spp))
  where the motion is sub-pixel, MIN_CURRENT_WEIGHT where it is whole pixels):
  min(n, (2 − α)/α), an exponential history's noise reduction.
- F_j = clip(max(bicubic(D_{t+j}, p_j), 0), min₃ₓ₃ D_t, max₃ₓ₃ D_t): the later frame's OIDN
  output D (free: the tier computes it anyway) fetched where frame t's pixel p lands in frame
  t + j, p_j = p_{j−1} + f_{t+j−1}(p_{j−1}) (the forward motion chained hop by hop, each hop the
  nearest pixel's vector so no field is blended across a depth edge), bicubically (Keys,
  a = −0.75: the tier's own history fetch) and clipped to frame t's D's 3×3 range.
- τ_j: 0 unless every hop so far landed inside the frame and passed the forward-backward check
  (|f_{t+i}(p_i) + b_{t+i+1}(p_{i+1})| ≤ FB_PIXELS, b the backward motion frame t + i + 1's
  history followed), and the aux of t + j at p_j show frame t's surface (experiments/lookahead's
  `aux_agree`, its `range` rule: depth of the nearest pixel within 10%, 3×3-mean normals within
  cos 0.9, the albedo (bilinear) within frame t's 3×3 albedo range ± TRUST_ERROR). Then 1 where
  every hop is whole pixels (an exact fetch); where the fetch is resampled, the tier's own trust
  of a resampled history (`_smooth_here` and the depth range where it lands) and the weight it
  lets such a history have, (1 − w(spp)) / w(spp) up to 1, nothing above RESAMPLED_FLOOR_MAX.

The forward motion f_t: the renderer's (Cycles' Vector.ZW: buffers.FORWARD, exr_channels), else
frame t + 1's backward motion inverted by a fixed point (`invert`: f(p) = −b(p + f(p)), which the
forward-backward check then holds to), whether that motion was rendered or estimated from the
aux (aux_motion: its untrusted pixels point outside the frame, so nothing lands on them); along
an estimate inverted so a frame chains at most ESTIMATED_HOPS (0) hops, since the inversion
passes its own forward-backward check by construction. A frame whose history did not continue
(a cut, a gap, a detected cut, a dropped history) starts a new run: no frame looks across it.
Measured in
experiments/lookahead.py (the same rule with the per-frame stage S in place of D: identical on
sub-pixel motion, experiments/README.md).

A model without an OIDN stage and an output history (the learned tiers, oidn-frame, oidn-acc)
queues its causal output alone and gets it back unchanged: the delay is the same for every model.

The window is a dict of named arrays the caller keeps like the stream's state (the service per
session, in its store; the evaluation in memory): `<slot>.<piece>`, slot 0 the oldest pending
frame. Functions here are pure: `push` and `pop` return a new dict and never change theirs.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from quietframe.runtime.aux_motion import FB_PIXELS, TRUST_ERROR
from quietframe.runtime.buffers import FORWARD
from quietframe.runtime.sanitize import DEPTH_NO_HIT, sanitize_buffer
from quietframe.runtime.stream import Step

__all__ = ["Popped", "Window", "bicubic", "box3", "causal_worth", "current_weight_floor",
           "frame_pieces", "invert", "pending", "pop", "push", "window_shapes"]

Window = dict[str, np.ndarray]

# The output history tiers (model/output_history.py) and what their state holds: output (3),
# depth, normal (3), history length n (channel 7) in the top-level `accumulation` tensor.
OUTPUT_HISTORY = "output-history"
HISTORY_STATE, COUNT_CHANNEL = "accumulation", 7
# model/temporal.py's constants (the graphs hold them; the runtime never imports the model:
# tests/runtime/test_lookahead.py pins them to the model's)
MIN_CURRENT_WEIGHT = 0.2
ALIGNED_TOLERANCE = 1 / 64  # px: a fetch this close to whole pixels is exact
DEPTH_REL_TOLERANCE = 0.1
NORMAL_MIN_DOT = 0.9
EMPTY_NORMAL = 1e-3  # shorter 3×3-mean normals: no surface (Cycles writes 0 on the world)
CUBIC_A = -0.75  # Keys' cubic, PyTorch's bicubic: the tier's history fetch
INVERSION_STEPS = 4  # fixed-point steps of `invert` (a smooth field converges in one or two)
BAND_ROWS = 32  # the blend runs in bands of rows: its working set is a band's, not a frame's

# Pieces of one pending frame. INDEX, STARTS and COLOR always; the others where the frame can
# be blended (BLEND); FORWARD once known (rendered, or inverted when the next frame arrives).
INDEX, STARTS, COLOR = "index", "starts", "color"
ESTIMATED = "estimated"  # (1,) uint8: the frame's backward motion was estimated from the aux
INVERTED = "inverted"  # (1,) uint8: the frame's FORWARD is the next frame's backward inverted
FLAGS = (INDEX, STARTS, ESTIMATED, INVERTED)  # (1,) arrays
STAGE, WORTH, BACKWARD, ALBEDO, NORMAL, DEPTH = (
    "stage", "worth", "backward", "albedo", "normal", "depth")
# (3,) float32: the tier's w(spp) for this frame and its per-pixel trust bounds edge_depth,
# edge_motion (model/output_history.OutputHistoryConfig), which the blend applies as the
# tier's own history does.
LIMITS = "limits"
BLEND = (STAGE, WORTH, BACKWARD, ALBEDO, NORMAL, DEPTH, LIMITS)  # BACKWARD: where history went on
PLANES = {COLOR: 3, STAGE: 3, WORTH: 1, BACKWARD: 2, ALBEDO: 3, NORMAL: 3, DEPTH: 1, FORWARD: 2}
_KEY = re.compile(r"(\d+)\.(.+)")
DEPTH_RANGE = "depth_range"  # the blend's own: a later frame's 3×3 depth range
# Hops along motion estimated from the aux a frame may chain: none. Its forward-backward check
# is the estimate's own (the inversion holds to it by construction), so nothing refuses its
# 0.1-0.25 px errors: on the motion-blurred twin of the dolly one hop gained (+0.09..+0.14 dB)
# but on motion-blurred foliage under an orbit (garden-blur, validation) it lost 0.46 dB at
# 1 spp and 3.5 dB at 64, and on the blurred railing (test) 0.30 at 64 (docs/service.md,
# "Look-ahead"). Such frames keep their causal output.
ESTIMATED_HOPS = 0
# Above this current-frame weight w(spp) (the tier's: 0.575 at 8 spp, 0.65 at 16, 0.8 at 64) a
# resampled later frame is not blended: the cleaner the frames, the more the resampling's error
# and what the motion vectors do not follow (caustics and reflections moving over a still
# surface) outweigh the noise it averages. Validation (docs/service.md, "Look-ahead"): with a
# weight of 1 a fast pan lost 0.7-1.2 dB at 64 spp; with (1 - w) / w the dark studio's turning
# wireframe still lost 0.04/0.10 dB at 16 spp with k = 2/4 (worst frame -0.18/-0.26), while
# the pan and the dolly gained 0.06-0.31 there. Never below k = 0 comes first.
RESAMPLED_FLOOR_MAX = 0.6


# ---- what one frame leaves in the window ---------------------------------------------------

def current_weight_floor(architecture: Mapping, spp: float | None) -> float | None:
    """w(spp) of an output history tier (model/output_history.py): clamp(resampled_weight +
    resampled_weight_per_doubling · log2 spp, MIN_CURRENT_WEIGHT, resampled_weight_max), spp
    the frame's as the model was given it (else the card's default_spp); None for any other
    model (it keeps no output history to weigh)."""
    if architecture.get("family") != OUTPUT_HISTORY:
        return None
    try:
        spp = float(spp if spp is not None else architecture["default_spp"])
        floor = (float(architecture["resampled_weight"])
                 + float(architecture["resampled_weight_per_doubling"])
                 * np.log2(max(spp, 1.0)))
        return float(np.clip(floor, MIN_CURRENT_WEIGHT,
                             float(architecture["resampled_weight_max"])))
    except (KeyError, TypeError, ValueError):
        return None


def causal_worth(count: np.ndarray, motion: np.ndarray | None, floor: float) -> np.ndarray:
    """(1, H, W) n_t of the module docstring from the history length `count` (H, W), the
    backward `motion` (2, H, W) the model was given (None: zero) and w(spp) `floor`."""
    count = np.maximum(np.asarray(count, np.float32), 1.0)
    aligned = np.ones(count.shape, bool) if motion is None else pixel_aligned(motion)
    alpha = np.maximum(1 / count, np.where(aligned, MIN_CURRENT_WEIGHT, floor))
    return np.minimum(count, (2 - alpha) / alpha).astype(np.float32)[None]


def pixel_aligned(motion: np.ndarray) -> np.ndarray:
    """(H, W) model/temporal.pixel_aligned of (2, H, W) `motion`, in numpy: the pixel and its
    3×3 neighbours all move by the same whole number of pixels (where the graph's history is
    fetched exactly and weighs like a locked-off one)."""
    rows = slice(0, motion.shape[1])
    low, high = _range3(motion, rows)
    whole = ((np.abs(motion - np.rint(motion)).max(0) <= ALIGNED_TOLERANCE)
             & ((high - low).max(0) <= ALIGNED_TOLERANCE))
    return _range3(whole[None].astype(np.float32), rows)[0][0] > 0.5


def frame_pieces(step: Step, planes: Mapping[str, np.ndarray],
                 architecture: Mapping) -> dict[str, np.ndarray]:
    """What a finished causal step leaves in the window: its output, and where the model has an
    OIDN stage and an output history (and the frame its aux), what the blend reads. `planes`:
    the frame's (C, H, W) buffers as decoded (its FORWARD too, where the renderer wrote one);
    `architecture`: the model card's."""
    pieces = {COLOR: np.asarray(step.color, np.float32)}
    floor = current_weight_floor(architecture, step.spp)
    state = step.state.get(HISTORY_STATE)
    if (step.oidn is None or floor is None or state is None or state.ndim != 4
            or state.shape[1] <= COUNT_CHANNEL or not all(b in planes for b in
                                                          ("albedo", "normal", "depth"))):
        return pieces
    motion = None if step.motion is None else np.nan_to_num(np.asarray(step.motion, np.float32))
    depth = np.asarray(planes["depth"], np.float32)
    # No hit (0, ≥ 1e10, non-finite: every renderer's marker) is 0 alike, so the sky matches
    # the sky and no surface (sanitize's fill, the frame's farthest depth, changes per frame).
    hit = np.isfinite(depth) & (depth > 0) & (depth < DEPTH_NO_HIT)
    pieces |= {
        LIMITS: np.array([floor, float(architecture.get("edge_depth", 0.0)),
                          float(architecture.get("edge_motion", 0.0))], np.float32),
        STAGE: np.nan_to_num(np.asarray(step.oidn, np.float32)),
        WORTH: causal_worth(state[0, COUNT_CHANNEL], motion, floor),
        ALBEDO: sanitize_buffer("albedo", planes["albedo"])[0],
        NORMAL: box3(sanitize_buffer("normal", planes["normal"])[0]),
        DEPTH: np.where(hit, depth, np.float32(0)),
    }
    if step.history_used:  # the motion this frame's history followed: zero where none was given
        pieces[BACKWARD] = (motion if motion is not None
                            else np.zeros((2, *step.color.shape[-2:]), np.float32))
        if step.estimated is not None:
            pieces[ESTIMATED] = np.ones(1, np.uint8)
    if planes.get(FORWARD) is not None:
        pieces[FORWARD] = np.nan_to_num(np.asarray(planes[FORWARD], np.float32))
    return pieces


# ---- the window ----------------------------------------------------------------------------

def _slots(window: Mapping[str, np.ndarray]) -> list[dict[str, np.ndarray]]:
    """The window's pending frames' pieces, oldest first."""
    slots: dict[int, dict[str, np.ndarray]] = {}
    for key, value in window.items():
        match = _KEY.fullmatch(key)
        if match is None:
            raise ValueError(f"look-ahead window: {key!r} is not <slot>.<piece>")
        slots.setdefault(int(match[1]), {})[match[2]] = value
    if sorted(slots) != list(range(len(slots))):
        raise ValueError(f"look-ahead window: slots {sorted(slots)} are not 0..n-1")
    return [slots[i] for i in range(len(slots))]


def _window(slots: list[dict[str, np.ndarray]]) -> Window:
    return {f"{i}.{name}": value for i, pieces in enumerate(slots) for name, value in
            pieces.items()}


def pending(window: Mapping[str, np.ndarray] | None) -> list[int]:
    """The indices of the frames the window holds, oldest first."""
    return [int(s[INDEX][0]) for s in _slots(window or {})]


def push(window: Mapping[str, np.ndarray] | None, pieces: Mapping[str, np.ndarray], index: int,
         starts: bool) -> Window:
    """The window with frame `index` (frame_pieces, and any other pieces of the caller's, which
    travel with it) queued last. `starts`: its history did not continue (first frame, cut, gap,
    a dropped history): no earlier frame looks at it. Otherwise the previous frame's forward
    motion, where the renderer wrote none, is this frame's backward motion inverted."""
    slots = _slots(window or {})
    if slots and index <= int(slots[-1][INDEX][0]):
        raise ValueError(f"look-ahead: frame {index} after frame {int(slots[-1][INDEX][0])}")
    new = {**pieces, INDEX: np.array([index], np.int64), STARTS: np.array([starts], np.uint8)}
    if slots and _blends(slots[-1]) and _continues(new) and FORWARD not in slots[-1]:
        slots[-1] = {**slots[-1], FORWARD: invert(new[BACKWARD]),
                     INVERTED: np.ones(1, np.uint8)}
    return _window([*slots, new])


@dataclass(frozen=True)
class Popped:
    index: int
    color: np.ndarray  # (3, H, W) float32: the causal output, blended where it could be
    pieces: dict[str, np.ndarray]  # the frame's pieces as pushed (the caller's too)
    window: Window  # the frames still pending
    used: int  # later frames blended in
    trusted: float | None  # the share of their pixels trusted (mean over them); None: none


def pop(window: Mapping[str, np.ndarray]) -> Popped:
    """The oldest pending frame finished with the later frames of its run the window holds
    (module docstring), and the window without it. ValueError on an empty window."""
    slots = _slots(window)
    if not slots:
        raise ValueError("look-ahead: no frame is pending")
    run, estimated = [slots[0]], 0
    for later in slots[1:]:
        estimated += ESTIMATED in later and INVERTED in run[-1]  # a hop along the estimate
        if not _continues(later) or FORWARD not in run[-1] or estimated > ESTIMATED_HOPS:
            break
        run.append(later)
    me = slots[0]
    color, trusted = me[COLOR], None
    if len(run) > 1 and _blends(me):
        color, trusted = blend(run)
    return Popped(int(me[INDEX][0]), color, me, _window(slots[1:]), len(run) - 1, trusted)


def _blends(pieces: Mapping[str, np.ndarray]) -> bool:
    """Whether a frame has what the blend reads of it (BACKWARD aside)."""
    return all(name in pieces for name in BLEND if name != BACKWARD)


def _continues(pieces: Mapping[str, np.ndarray]) -> bool:
    """Whether a frame continues the run of the one before it and can be blended into it."""
    return not pieces[STARTS][0] and BACKWARD in pieces and _blends(pieces)


def window_shapes(lookahead: int, height: int, width: int) -> dict[str, tuple[int, ...]]:
    """The arrays a window of a session with look-ahead `lookahead` may hold, by name: its
    planes and FLAGS (a store checks a record against them: slots 0 … lookahead, one more than
    a stored window holds)."""
    shapes: dict[str, tuple[int, ...]] = {}
    for slot in range(lookahead + 1 if lookahead else 0):
        shapes |= {f"{slot}.{name}": (channels, height, width)
                   for name, channels in PLANES.items()}
        shapes |= {f"{slot}.{name}": (1,) for name in FLAGS}
        shapes[f"{slot}.{LIMITS}"] = (3,)
    return shapes


def frame_nbytes(height: int, width: int) -> int:
    """The most one pending frame's planes hold."""
    return 4 * sum(PLANES.values()) * height * width


def working_set_bytes(height: int, width: int) -> int:
    """About the most a push and a pop hold beside the window: `invert`'s fields (whole frame:
    ~40 B a pixel) or a band of the blend's temporaries (~600 B a pixel of BAND_ROWS rows)."""
    return 40 * height * width + 600 * min(BAND_ROWS, height) * width


# ---- motion --------------------------------------------------------------------------------

def invert(backward: np.ndarray) -> np.ndarray:
    """(2, H, W) forward motion of the previous frame from this frame's backward motion b: the
    fixed point f(p) = −b(p + f(p)) (nearest pixel, INVERSION_STEPS steps from f = −b(p)),
    which holds where the two frames see the same surface; elsewhere (a disocclusion, b
    pointing outside) the forward-backward check refuses it."""
    backward = np.nan_to_num(np.asarray(backward, np.float32))
    _, h, w = backward.shape
    flat = backward.reshape(2, -1)
    out = np.empty_like(backward)
    for top in range(0, h, BAND_ROWS):
        rows = slice(top, min(top + BAND_ROWS, h))
        ys, xs = np.mgrid[rows, 0:w].astype(np.float32)
        f = -backward[:, rows]
        for _ in range(INVERSION_STEPS):
            f = -flat[:, _nearest_index(xs + f[0], ys + f[1], h, w)]
        out[:, rows] = f
    return out


def _nearest_index(x: np.ndarray, y: np.ndarray, h: int, w: int) -> np.ndarray:
    """Flat indices of the nearest pixels to (x, y), clamped to the frame."""
    xi = np.clip(np.rint(x), 0, w - 1).astype(np.intp)
    yi = np.clip(np.rint(y), 0, h - 1).astype(np.intp)
    return yi * w + xi


# ---- the blend -----------------------------------------------------------------------------

def blend(run: list[dict[str, np.ndarray]]) -> tuple[np.ndarray, float]:
    """(out_t, the share of the later frames' pixels trusted) for run[0] and the later frames
    of its run (module docstring), band by band."""
    me = run[0]
    _, h, w = me[COLOR].shape
    out = np.empty((3, h, w), np.float32)
    trusted = np.zeros(len(run) - 1)
    flats = [{name: piece.reshape(piece.shape[0], -1) for name, piece in frame.items()
              if name in PLANES} for frame in run]
    for frame, flat in zip(run[1:], flats[1:], strict=True):  # the edge test where it lands
        low, high = _range3(frame[DEPTH], slice(0, h))
        flat[DEPTH_RANGE] = (high - low).reshape(1, -1)
    for top in range(0, h, BAND_ROWS):
        rows = slice(top, min(top + BAND_ROWS, h))
        out[:, rows], counts = _blend_band(run, flats, rows, h, w)
        trusted += counts
    return out, float(trusted.mean() / (h * w))


def _blend_band(run, flats, rows: slice, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    me = run[0]
    low, high = _range3(me[STAGE], rows)
    albedo_low, albedo_high = _range3(me[ALBEDO], rows)
    albedo_low -= TRUST_ERROR
    albedo_high += TRUST_ERROR
    here_normal, here_depth = me[NORMAL][:, rows], me[DEPTH][0, rows]
    worth = me[WORTH][:, rows]
    total = worth * me[COLOR][:, rows]
    weight = worth.copy()
    floor, edge_depth, edge_motion = (float(v) for v in me[LIMITS])
    # A later frame fetched at a sub-pixel position weighs what the tier lets its own
    # resampled history weigh against the current frame, (1 - w(spp)) / w(spp) (at most 1),
    # and nothing where w(spp) > RESAMPLED_FLOOR_MAX: the cleaner the frames, the more the
    # resampling's error outweighs the noise it averages. Whole-pixel hops fetch exactly and
    # weigh 1.
    resampled = (min(1.0, (1 - floor) / floor) if 0 < floor <= RESAMPLED_FLOOR_MAX
                 else 0.0 if floor > RESAMPLED_FLOOR_MAX else 1.0)
    smooth = _smooth_here(me, rows, edge_depth, edge_motion)
    y, x = np.mgrid[rows, 0:w].astype(np.float32)
    at = _nearest_index(x, y, h, w)
    ok = np.ones(x.shape, bool)
    exact = np.ones(x.shape, bool)
    counts = np.zeros(len(run) - 1)
    for j in range(1, len(run)):
        step = flats[j - 1][FORWARD][:, at].reshape(2, *x.shape)
        x, y = x + step[0], y + step[1]
        exact &= (np.abs(step - np.rint(step)) <= ALIGNED_TOLERANCE).all(0)
        ok &= (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        at = _nearest_index(x, y, h, w)
        later = flats[j]
        if edge_depth > 0:  # the fetch's footprint on one surface where it lands, too
            there = later[DEPTH][0, at].reshape(x.shape)
            smooth &= (later[DEPTH_RANGE][0, at].reshape(x.shape)
                       <= edge_depth * np.maximum(there, 1e-6))
        back = later[BACKWARD][:, at].reshape(2, *x.shape)
        ok &= np.hypot(step[0] + back[0], step[1] + back[1]) <= FB_PIXELS
        # the aux check (_aux_agree of experiments/lookahead.py, `range`)
        there_depth = later[DEPTH][0, at].reshape(x.shape)
        agree = ok & (np.abs(there_depth - here_depth)
                      <= DEPTH_REL_TOLERANCE * np.maximum(here_depth, 1e-6))
        taps = _bilinear_taps(x, y, h, w)
        albedo, normal = _bilinear(later[ALBEDO], taps), _bilinear(later[NORMAL], taps)
        agree &= ((albedo >= albedo_low) & (albedo <= albedo_high)).all(0)
        ln = np.sqrt((here_normal * here_normal).sum(0))
        lm = np.sqrt((normal * normal).sum(0))
        agree &= (((here_normal * normal).sum(0) > NORMAL_MIN_DOT * ln * lm)
                  | ((ln < EMPTY_NORMAL) & (lm < EMPTY_NORMAL)))
        fetched = np.maximum(bicubic(later[STAGE], x, y, h, w), 0)
        fetched = np.minimum(np.maximum(fetched, low), high)
        tau = agree * np.where(exact, 1.0, resampled * smooth).astype(np.float32)
        total += tau * fetched
        weight += tau
        counts[j - 1] = np.count_nonzero(tau)
    return total / weight, counts


def _smooth_here(me: Mapping[str, np.ndarray], rows: slice, edge_depth: float,
                 edge_motion: float) -> np.ndarray:
    """Where frame t's pixel may take a resampled fetch (the tier's own trust of a resampled
    history, model/output_history.trusted_resample): its 3×3 depth range within edge_depth of
    its depth (not a silhouette, thin geometry against a far background) and its neighbours
    moving alike (3×3 range of either forward-motion component within edge_motion px)."""
    depth = me[DEPTH][0, rows]
    smooth = np.ones(depth.shape, bool)
    if edge_depth > 0:
        low, high = _range3(me[DEPTH], rows)
        smooth &= (high - low)[0] <= edge_depth * np.maximum(depth, 1e-6)
    if edge_motion > 0:
        low, high = _range3(me[FORWARD], rows)
        smooth &= (high - low).max(0) <= edge_motion
    return smooth


def _range3(x: np.ndarray, rows: slice) -> tuple[np.ndarray, np.ndarray]:
    """Per channel, the min and max over each pixel's 3×3 neighbourhood (edges replicated) of
    rows `rows` of (C, H, W) `x`."""
    _, h, w = x.shape
    top, bottom = rows.start, rows.stop
    part = x[:, max(top - 1, 0):min(bottom + 1, h)]
    part = np.pad(part, ((0, 0), (int(top == 0), int(bottom >= h)), (1, 1)), mode="edge")
    n = bottom - top
    taps = [part[:, i:i + n, j:j + w] for i in range(3) for j in range(3)]
    low, high = taps[0].copy(), taps[0].copy()
    for tap in taps[1:]:
        np.minimum(low, tap, out=low)
        np.maximum(high, tap, out=high)
    return low, high


def box3(x: np.ndarray) -> np.ndarray:
    """The 3×3 box mean of (C, H, W) `x`, edges replicated."""
    _, h, w = x.shape
    padded = np.pad(x, ((0, 0), (1, 1), (1, 1)), mode="edge")
    out = np.zeros_like(x)
    for i in range(3):
        for j in range(3):
            out += padded[:, i:i + h, j:j + w]
    return out / np.float32(9)


def _bilinear_taps(x: np.ndarray, y: np.ndarray, h: int, w: int) -> tuple:
    """The flat indices of the four pixels around (x, y) and the fractions, clamped to the
    frame (as aux_motion.warp), for `_bilinear`."""
    x, y = np.clip(x, 0, w - 1), np.clip(y, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.intp), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.intp), max(h - 2, 0))
    fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    return y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1, fx, fy


def _bilinear(flat: np.ndarray, taps: tuple) -> np.ndarray:
    """(C, ...) of (C, H·W) `flat` fetched bilinearly at `_bilinear_taps`."""
    i00, i01, i10, i11, fx, fy = taps
    top = flat[:, i00] * (1 - fx) + flat[:, i01] * fx
    bottom = flat[:, i10] * (1 - fx) + flat[:, i11] * fx
    return top * (1 - fy) + bottom * fy


def _cubic_weights(f: np.ndarray) -> list[np.ndarray]:
    """Keys' cubic convolution weights of the taps at −1, 0, 1, 2 for fraction f."""
    a = CUBIC_A

    def near(d):
        return ((a + 2) * d - (a + 3)) * d * d + 1

    def far(d):
        return ((a * d - 5 * a) * d + 8 * a) * d - 4 * a

    return [far(1 + f), near(f), near(1 - f), far(2 - f)]


def bicubic(flat: np.ndarray, x: np.ndarray, y: np.ndarray, h: int, w: int) -> np.ndarray:
    """(C, *x.shape) of (C, H·W) `flat` fetched bicubically at (x, y), taps clamped to the
    frame (PyTorch's grid_sample bicubic with border padding, as the tier fetches its
    history)."""
    x, y = np.clip(x, 0, w - 1), np.clip(y, 0, h - 1)
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    wx = _cubic_weights((x - x0).astype(np.float32))
    wy = _cubic_weights((y - y0).astype(np.float32))
    cols = [np.clip(x0 + j - 1, 0, w - 1) for j in range(4)]
    out = np.zeros((flat.shape[0], *x.shape), np.float32)
    for i in range(4):
        row = np.clip(y0 + i - 1, 0, h - 1) * w
        line = np.zeros_like(out)
        for j in range(4):
            line += flat[:, row + cols[j]] * wx[j]
        out += line * wy[i]
    return out
