"""The Super Image Denoiser add-on's temporal mode ("SID Temporal") as an evaluation baseline.

What the add-on does (read in github.com/PidgeonTools/SuperImageDenoiser at b418638, SID 4.0.0
for Blender 3.6; no code is taken from it, this is our own numpy rendering of its node graph):

- Step 1 renders the animation with Blender's render motion blur switched off and the Vector
  pass on, through SID's per-frame compositor denoiser (Cycles/SID_Create_Passes_Cycles.py,
  `create_cycles_passes`), and writes per frame a multilayer EXR holding SID's denoised image,
  the Vector pass, the Denoising Depth and a "Temporal Albedo" (diffuse + transmission colour,
  emission and environment: Cycles/SID_Create_Group_Cycles.py). The default quality, High,
  denoises each light path (direct + indirect, times its colour) with a Denoise node on the
  Accurate prefilter, sums them and runs a final Denoise node over the sum
  (Cycles/SID_Create_Links_Cycles.py, Cycles/SID_QualityHigh_Cycles.py, create_denoiser.py).
  The frames are rendered with 5 % overscan (Temporal/SID_Render_Denoise_Temporal_BG.py).
- Step 2 (Temporal/SID_Create_Temporal_Groups.py, `create_temporal_setup` and
  `create_temporal_align`) is a compositor graph over three consecutive frames t-1, t, t+1:
  frame t-1 is moved with a Displace node by its *own* Vector pass at scale -1, frame t+1 by
  its own Vector pass at scale +1; the per-channel median of the current frame and the two
  moved ones is taken with min/max math nodes (`create_temporal_median`). A "TED filter" then
  decides where to trust it: the same median is formed of a filter source (default "Image",
  the denoised image itself; else the temporal albedo or the depth), its absolute difference
  to the current frame's source (clamped to [0, 1]) is turned into a value (the compositor's
  colour-to-value: the mean of R, G, B), multiplied by the threshold (default 3) and clamped,
  feathered by a Dilate/Erode node (Feather, distance 3, Sphere falloff), and used to mix from
  the median back to the current frame. Last, a Vector Blur node (on by default: "fake motion
  blur", 32 samples, shutter 0.5, no speed limits, linear) blurs the result along the current
  frame's vectors, and the overscan is cropped away. Defaults: SID_Settings.py (`SIDT_*`).
  Outputs are numbered from 1 whatever the render's first frame s (output f is centred on
  input s + f), the first and the last two frames of a render get no output, and renders of
  four or fewer frames are skipped. (SID_Temporal.py is the other temporal mode, Blender's
  own OptiX/NLM `denoise_animation`; it is not this baseline.)

The Blender behaviour this relies on (Blender 3.6 sources read: compositor
COM_DisplaceOperation, COM_ConvertOperation, COM_DilateErodeNode with
COM_GaussianAlpha{X,Y}BlurOperation and COM_BlurBaseOperation, COM_VectorBlurOperation; Cycles
kernel `primitive_motion_vector`): Displace outputs in(p - scale·v(p)), reading the vector at
the output pixel; Cycles' Vector.XY is the position in t-1 minus the position in t and ZW the
position in t minus the position in t+1. In quietframe's convention `motion` is Vector.XY with
y flipped to image rows (pixel p of frame t was at p + motion_t(p) in t-1;
runtime/exr_channels.py, bench/baselines.py `nearest_warp`), so the add-on's alignment reads,
per pixel p:

    frame t-1 aligned:  D[t-1](p + motion[t-1](p))     (its own vectors, towards t-2)
    frame t+1 aligned:  D[t+1](p - motion[t+1](p))     (its vectors the other way)

The second is the first-order inverse of frame t+1's backward vectors: a surface at q in t+1
was at q + motion[t+1](q) in t, so the one at p in t is at q ≈ p - motion[t+1](p). The first
is exact only for constant velocity (frame t's own backward vectors would be the exact gather:
`previous_vectors="current"`). Both are exact for uniform motion and go wrong at motion edges,
where the TED filter is meant to take over. Where frame t-1 opened its shot its own vectors
point out of the shot (quietframe's renders store none there), so frame t's are used.

Here: the per-frame stage is OIDN as Blender's Denoise node runs it (high quality, albedo +
normal, prefiltered aux: baselines.OIDNDenoiser("high", prefilter_aux=True)) on the combined
colour; our frames carry no light-path splits, so SID High's per-pass denoise is not
reproduced. Then the median, the TED filter and (by default) the vector blur as above, with
these approximations: bilinear sampling with positions clamped to the frame stands in for the
Displace node's EWA filtering and for the overscan; frames are opaque, so the Alpha Over of the
median on the current frame is the median; the Vector Blur is a point-splat rendering of
Blender 3.6's z-buffered quad rasteriser (same steps, shutter offsets, per-step weights, depth
test against the static pixels and final blend; per-pixel instead of per-vertex speeds, no
antialiased motion mask, our own sub-pixel jitter), with frame t's ZW taken from frame t+1's
backward vectors at p (from frame t's when there is no next frame); the result is linear
radiance (the add-on's default file output is an 8-bit PNG through the view transform).

Look-ahead: the median needs frame t+1 to produce frame t, and the harness is causal (one call
per frame, the output scored at once against that frame's reference). Delaying the output by a
frame would score output t-1 against reference t, so instead frame t+1's buffers ride with
frame t: `with_next_frame` (the method's `look_ahead`, which evaluate.run_sequence applies)
adds them to frame t's planes under NEXT-prefixed names, never across a cut. Output t is then
returned by call t and scored against reference t; each call runs the per-frame stage once (on
frame t+1; frame t's was kept from the previous call). Where a neighbour is missing (the first
frame of a shot or after a cut, the last one before a cut or at the end, where the add-on
writes no frame) the current frame stands in for it: the median is then the per-frame output
and the TED filter leaves it as is. Called without look-ahead (a plain causal loop, or the
720p timing) every frame gets the per-frame output (plus the blur), with a warning once.

Variants (evaluate.build_methods): `sid-temporal-default`, the add-on's defaults including the
fake motion blur (which a reference rendered without motion blur penalises), and
`sid-temporal`, the same without the blur: the add-on's denoising alone.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from quietframe.bench import baselines
from quietframe.bench.harness import Frames, ImageMethod, Planes
from quietframe.runtime.buffers import BUFFER_NAMES

NEXT = "next:"  # planes key prefix: frame t+1's buffers riding with frame t
# The add-on's defaults (SID_Settings.py)
TED_THRESHOLD = 3.0  # SIDT_TED_Filter_Threshold: gain on the source difference (0: no filter)
TED_RADIUS = 3  # SIDT_TED_Filter_Distance: Dilate/Erode feather distance in pixels
MB_SAMPLES = 32  # SIDT_MB_Samples
MB_SHUTTER = 0.5  # SIDT_MB_Shutter, in frames
# Blender's Gaussian filter (RE_filter_value, gaussfac 1.6) at x = i / radius: exp(-4.5 x²)
_FEATHER_GAUSS = 4.5

FilterSource = Literal["image", "albedo", "depth"]


def with_next_frame(frames: Frames) -> Frames:
    """The frames with frame t+1's input buffers added to frame t's planes (NEXT + name), where
    t+1 is in the same shot; references and reset flags as they were."""
    out = []
    for t, (planes, reference, reset) in enumerate(frames):
        if t + 1 < len(frames) and not frames[t + 1][2]:
            upcoming = frames[t + 1][0]  # input buffers only: no stored output rides along
            planes = {**planes, **{NEXT + k: v for k, v in upcoming.items() if k in BUFFER_NAMES}}
        out.append((planes, reference, reset))
    return out


def warp(image: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Planar (C, H, W) image sampled bilinearly at p + offset(p), offset (2, H, W) as (x, y)
    in pixels; positions are clamped to the frame (the overscan's stand-in)."""
    _, h, w = image.shape
    x = np.clip(np.arange(w, dtype=np.float32)[None, :] + offset[0], 0, w - 1)
    y = np.clip(np.arange(h, dtype=np.float32)[:, None] + offset[1], 0, h - 1)
    x0 = np.minimum(np.floor(x), w - 2).astype(np.intp)  # x0 + 1 stays inside; fx reaches 1
    y0 = np.minimum(np.floor(y), h - 2).astype(np.intp)
    fx, fy = x - x0, y - y0
    i00 = y0 * w + x0
    out = np.empty(image.shape, np.float32)
    for c, plane in enumerate(image.reshape(len(image), -1)):  # 1-D takes: fast gathers
        top = plane.take(i00) * (1 - fx) + plane.take(i00 + 1) * fx
        bottom = plane.take(i00 + w) * (1 - fx) + plane.take(i00 + w + 1) * fx
        out[c] = top * (1 - fy) + bottom * fy
    return out


def median3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Per-element median of three (the add-on's min/max network)."""
    return np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))


def feather(mask: np.ndarray, radius: int) -> np.ndarray:
    """Blender's Dilate/Erode node in Feather mode with a positive distance and Sphere falloff
    on an (H, W) mask: a pass along x, then one along y."""
    if radius <= 0:
        return mask
    i = np.arange(-radius, radius + 1, dtype=np.float32)
    gauss = np.exp(-_FEATHER_GAUSS * (i / radius) ** 2)
    near = 1 - np.abs(i) / radius
    falloff = np.sqrt(2 * near - near * near)  # Sphere
    return _feather_pass(_feather_pass(mask, gauss, falloff, 1), gauss, falloff, 0)


def _feather_pass(x: np.ndarray, gauss: np.ndarray, falloff: np.ndarray,
                  axis: int) -> np.ndarray:
    """One 1-D pass: the largest neighbour scaled by its falloff f (the pixel itself has f = 1
    and wins ties; a later tap must be strictly larger), output as that value times f plus the
    Gaussian blur times (1 - f); taps outside the frame are skipped (as Blender does)."""
    r = len(gauss) // 2
    xt = np.moveaxis(x, axis, -1)
    n = xt.shape[-1]
    padded = np.pad(xt, [(0, 0)] * (xt.ndim - 1) + [(r, r)])
    valid = np.pad(np.ones(n, bool), r)
    num, den = np.zeros_like(xt), np.zeros(n, np.float32)
    best, best_f = xt.copy(), np.ones_like(xt)
    for k in range(2 * r + 1):  # Blender's scan order, -r .. r
        tap, ok = padded[..., k : k + n], valid[k : k + n]
        num += gauss[k] * tap  # padding is 0
        den += gauss[k] * ok
        candidate = np.where(ok, tap * falloff[k], -np.inf)
        better = candidate > best
        best = np.where(better, candidate, best)
        best_f = np.where(better, falloff[k], best_f)
    out = best * best_f + num / den * (1 - best_f)
    return np.moveaxis(out, -1, axis)


def _jitter(step: int) -> tuple[float, float]:
    """A deterministic sub-pixel offset in [-0.5, 0.5)² per blur step (R2 sequence), so that
    sub-pixel path offsets are dithered between pixels instead of rounded away."""
    return ((0.5 + step * 0.7548777) % 1 - 0.5, (0.5 + step * 0.5698403) % 1 - 0.5)


def vector_blur(image: np.ndarray, depth: np.ndarray, past: np.ndarray, future: np.ndarray,
                samples: int = MB_SAMPLES, shutter: float = MB_SHUTTER) -> np.ndarray:
    """The Vector Blur node's accumulation as point splats: (3, H, W) image, (H, W) depth,
    past = frame t's backward vectors (Vector.XY), future = Vector.ZW (position in t minus in
    t+1), both (2, H, W). Moving pixels (any non-zero vector) are splatted samples//2 times
    each way, at fractions 0.5·shutter·k/(samples//2 + 1) of their path, the nearest one winning
    a pixel, never over a nearer static pixel; step k weighs smoothstep(1 - k/(samples//2)).
    Each pixel ends as the weighted mean of what landed on it, blended with its own value by
    the largest weight that landed (1 - that weight stays its own)."""
    c, h, w = image.shape
    moving = ((past != 0) | (future != 0)).any(axis=0).ravel()
    if not moving.any():
        return image.copy()
    z = depth.ravel()
    order = np.flatnonzero(moving)
    order = order[np.argsort(z[order], kind="stable")]  # nearest first, ties in scan order
    ys, xs = np.divmod(order, w)
    static_z = np.where(moving, np.inf, z)  # moving pixels never occlude a splat
    flat = image.reshape(c, -1)
    acc = np.zeros_like(flat)
    weight = np.zeros(h * w, np.float32)
    peak = np.zeros(h * w, np.float32)
    rank = np.arange(len(order))
    owner = np.empty(h * w, np.intp)  # per target: the depth rank of its nearest splat
    steps = samples // 2
    for k in range(1, steps + 1):
        frac = 0.5 * shutter * k / (steps + 1)
        t = (steps - k) / steps
        blend = 3 * t * t - 2 * t * t * t
        jx, jy = _jitter(k)
        for vectors, sign in ((past, frac), (future, -frac)):  # towards t-1, towards t+1
            tx = np.rint(xs + sign * vectors[0].ravel()[order] + jx).astype(np.intp)
            ty = np.rint(ys + sign * vectors[1].ravel()[order] + jy).astype(np.intp)
            inside = (tx >= 0) & (tx < w) & (ty >= 0) & (ty < h)
            owner.fill(len(order))
            np.minimum.at(owner, (ty * w + tx)[inside], rank[inside])  # the nearest wins
            target = np.flatnonzero(owner < len(order))
            source = order[owner[target]]
            shown = z[source] < static_z[target]
            target, source = target[shown], source[shown]
            acc[:, target] += blend * flat[:, source]
            weight[target] += blend
            peak[target] = np.maximum(peak[target], blend)
    hit = weight > 0
    out = flat.copy()
    out[:, hit] = (peak[hit] / weight[hit]) * acc[:, hit] + (1 - peak[hit]) * flat[:, hit]
    return out.reshape(c, h, w)


@dataclass
class _Frame:
    denoised: np.ndarray  # (3, H, W): the per-frame stage's output
    source: np.ndarray | None  # the TED filter's source planes (None: the denoised image)
    motion: np.ndarray  # (2, H, W) backward vectors
    depth: np.ndarray  # (H, W)
    had_next: bool = False  # frame t+1 rode with this frame
    opens_shot: bool = False  # the first frame after a reset


def oidn_per_frame(num_threads: int = 0, renderer: str | None = None) -> ImageMethod:
    """OIDN as Blender's Denoise node runs it (high, albedo + normal, prefiltered aux, rows in
    the renderer's order); raises PrepassUnavailable without pyoidn."""
    return ImageMethod(baselines.OIDNDenoiser("high", prefilter_aux=True,
                                              num_threads=num_threads, renderer=renderer))


class SIDTemporal:
    """SID Temporal (module docstring): a Method of bench/harness.py that needs its frames
    through `look_ahead` (evaluate.run_sequence applies it). Defaults are the add-on's;
    `motion_blur=False` leaves out the fake motion blur; `previous_vectors="current"` aligns
    frame t-1 with frame t's vectors (exact) instead of its own (the add-on's);
    `filter_source="albedo"` reads the albedo buffer where the add-on reads its Temporal
    Albedo; `per_frame` replaces the OIDN stage ((C, H, W) planes -> (3, H, W))."""

    look_ahead = staticmethod(with_next_frame)

    def __init__(self, motion_blur: bool = True, threshold: float = TED_THRESHOLD,
                 radius: int = TED_RADIUS, filter_source: FilterSource = "image",
                 samples: int = MB_SAMPLES, shutter: float = MB_SHUTTER,
                 previous_vectors: Literal["previous", "current"] = "previous",
                 num_threads: int = 0,
                 per_frame: Callable[[Planes], np.ndarray] | None = None,
                 renderer: str | None = None) -> None:
        if filter_source not in ("image", "albedo", "depth"):
            raise ValueError(f"SIDTemporal: filter_source must be image, albedo or depth: "
                             f"{filter_source!r}")
        if previous_vectors not in ("previous", "current"):
            raise ValueError(f"SIDTemporal: previous_vectors must be previous or current: "
                             f"{previous_vectors!r}")
        self.motion_blur, self.threshold, self.radius = motion_blur, threshold, radius
        self.filter_source, self.samples, self.shutter = filter_source, samples, shutter
        self.previous_vectors = previous_vectors
        self.per_frame = (per_frame if per_frame is not None
                          else oidn_per_frame(num_threads, renderer))
        self._prev: _Frame | None = None
        self._ahead: tuple[np.ndarray, _Frame] | None = None  # (frame t+1's colour, its stage)
        self._warned = False

    def reset(self) -> None:
        self._prev = self._ahead = None

    def close(self) -> None:
        close = getattr(getattr(self.per_frame, "method", None), "close", None)
        if close is not None:
            close()

    def __call__(self, planes: Planes) -> np.ndarray:
        current = {k: v for k, v in planes.items() if not k.startswith(NEXT)}
        upcoming = {k[len(NEXT):]: v for k, v in planes.items() if k.startswith(NEXT)}
        cur = self._stage(current)
        nxt = self._stage(upcoming) if "color" in upcoming else None
        cur.had_next, cur.opens_shot = nxt is not None, self._prev is None
        self._ahead = (upcoming["color"], nxt) if nxt is not None else None
        prev = self._prev
        if nxt is None and prev is not None and not prev.had_next and not self._warned:
            self._warned = True  # two frames of one shot without frame t+1: a causal caller
            warnings.warn("SIDTemporal called without look-ahead: frames get the per-frame "
                          "output (run the frames through its look_ahead)", stacklevel=2)
        # the missing neighbour is the current frame itself: the median is then the current
        if prev is None:
            d_prev, s_prev = cur.denoised, cur.source
        else:
            # a shot's first frame has no vectors into its shot (quietframe's renders store
            # none there): frame t's stand in for them
            own = self.previous_vectors == "previous" and not prev.opens_shot
            vectors = prev.motion if own else cur.motion
            d_prev, s_prev = self._aligned(prev, vectors)
        if nxt is None:
            d_next, s_next = cur.denoised, cur.source
        else:
            d_next, s_next = self._aligned(nxt, -nxt.motion)
        out = median3(cur.denoised, d_prev, d_next)
        if self.threshold > 0:
            if cur.source is None:
                source, source_median = cur.denoised, out
            else:
                source, source_median = cur.source, median3(cur.source, s_prev, s_next)
            diff = np.clip(np.abs(source_median - source), 0, 1).mean(axis=0)
            mask = feather(np.clip(diff * self.threshold, 0, 1), self.radius)
            out = out + mask * (cur.denoised - out)  # mask 1: the current frame
        if self.motion_blur:
            future = nxt.motion if nxt is not None else cur.motion
            out = vector_blur(out, cur.depth, cur.motion, future, self.samples, self.shutter)
        self._prev = cur
        return np.asarray(out, np.float32)

    def _stage(self, planes: Planes) -> _Frame:
        """The frame's per-frame output and the planes the filter reads; frame t's output was
        made by the previous call when it rode there as frame t+1."""
        color = planes["color"]
        if self._ahead is not None and self._ahead[0] is color:
            return self._ahead[1]
        _, h, w = color.shape
        zeros = np.zeros((2, h, w), np.float32)
        motion = np.nan_to_num(np.asarray(planes.get("motion", zeros), np.float32))
        depth = np.asarray(planes.get("depth", zeros[:1]), np.float32)[0]
        source = {"image": None, "albedo": planes["albedo"] if self.filter_source == "albedo"
                  else None, "depth": depth[None]}[self.filter_source]
        denoised = np.asarray(self.per_frame(planes), np.float32)
        return _Frame(denoised, None if source is None else np.asarray(source, np.float32),
                      motion, depth)

    def _aligned(self, frame: _Frame, offset: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        """A neighbour's output and filter source read at p + offset(p)."""
        source = None if frame.source is None else warp(frame.source, offset)
        return warp(frame.denoised, offset), source
