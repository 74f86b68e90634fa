"""Non-network denoisers the evaluation compares against.

Each is a stateful per-sequence object: `reset()` at a first frame or camera cut, then
`__call__(buffers) -> (H, W, 3)` once per frame with the canonical buffers
(docs/architecture.md): `color`, `albedo`, `normal` (H, W, 3), `depth` (H, W, 1) or (H, W),
`motion` (H, W, 2) backward in pixels (pixel p of frame t was at p + motion in frame t-1; a
missing motion is a static camera).

The temporal rule (`nearest_warp`, `history_valid`, the accumulation weights, demodulation) is
a numpy twin of the NBG pre-stage in `model/temporal.py` and `model/nbg.py`: same names, same
constants, same formulas (tests/bench/test_baselines.py holds them equal), without torch.

The evaluation times the ones it runs (svgf, oidn-*) per 1280×720 frame in `quietframe-eval`'s
`ms/frame 720p` column, so this module has no command of its own.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import Literal, NamedTuple

import numpy as np

from quietframe.runtime.buffers import BUFFER_CHANNELS, BUFFER_NAMES, planes_from_hwc
from quietframe.runtime.oidn_prepass import QUALITIES, OIDNPrepass, OIDNSettings

# --- shared temporal rule (NBG §4.6; equal to model/temporal.py and model/nbg.py) -------------
DEPTH_REL_TOLERANCE = 0.1  # history kept where |d_prev - d| <= 0.1 d ...
NORMAL_MIN_DOT = 0.9  # ... and n_prev · n > 0.9 (warped normal as is, not renormalised)
# Current-frame weight max(1/n, 0.2): the paper's fixed 0.2 (previous 0.8) once the history
# holds >= 5 frames, a plain mean of the frames seen before that (after a reset/disocclusion).
MIN_CURRENT_WEIGHT = 0.2
ALBEDO_EPSILON = 1e-2  # demodulation divides by (max(albedo, 0) + ε); remodulation multiplies
ALBEDO_DEMODULATION_FLOOR = 5e-2  # below this max-channel albedo the divisor fades to 1 (sky)
# State planes, as the model's state tensor: radiance (3), depth, normal (3), history length.
STATE_CHANNELS = 8


def _luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of planar (3, ...) radiance. Written out: np.dot/tensordot would go
    through OpenBLAS, whose spinning worker threads steal the cores the filter runs on."""
    return 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]


def _canonical(buffers: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
    """color, albedo, normal (H, W, 3), depth (H, W, 1), motion (H, W, 2) as float32."""
    try:
        color, albedo, normal, depth = (
            np.asarray(buffers[k], np.float32) for k in ("color", "albedo", "normal", "depth")
        )
    except KeyError as exc:
        raise ValueError(f"baseline: missing buffer {exc.args[0]!r}") from None
    h, w = color.shape[:2]
    if depth.ndim == 2:
        depth = depth[..., None]
    motion = buffers.get("motion")
    motion = np.zeros((h, w, 2), np.float32) if motion is None else np.asarray(motion, np.float32)
    for name, arr in zip(BUFFER_NAMES, (color, albedo, normal, depth, motion), strict=True):
        if arr.shape != (h, w, BUFFER_CHANNELS[name]):
            want = (h, w, BUFFER_CHANNELS[name])
            raise ValueError(f"baseline: {name} has shape {arr.shape}, want {want}")
    if h < 2 or w < 2:
        raise ValueError(f"baseline: frames must be at least 2×2, got {(h, w)}")
    return color, albedo, normal, depth, motion


def _planar(x: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.moveaxis(x, -1, 0))  # (H, W, C) → (C, H, W)


def _demodulated(buffers: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
    """What the temporal baselines filter: radiance (3, H, W) demodulated by the safe albedo
    (3, H, W), normal (3, H, W), depth (H, W) and motion (H, W, 2)."""
    color, albedo, normal, depth, motion = _canonical(buffers)
    albedo_p = _planar(safe_albedo(albedo))
    return _planar(color) / albedo_p, albedo_p, _planar(normal), depth[..., 0], motion


def safe_albedo(albedo: np.ndarray) -> np.ndarray:
    albedo = np.maximum(albedo, 0)
    ramp = np.minimum(albedo.max(axis=-1, keepdims=True) / ALBEDO_DEMODULATION_FLOOR, 1)
    return (1 + ramp * (albedo + ALBEDO_EPSILON - 1)).astype(np.float32)


def nearest_warp(image: np.ndarray, motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planar (C, H, W) image(t-1) at the pixel nearest to p + motion(p), clamped to the frame
    (grid_sample nearest with border padding: round half to even, as np.rint), and `inside`
    (H, W): the source lies within half a pixel of the frame (as ai.quietframe::BackwardWarp)."""
    h, w = motion.shape[:2]
    mx, my = _planar(motion)  # contiguous planes: ops on strided (..., 0) views are slow
    src_x = np.arange(w, dtype=np.float32)[None, :] + mx  # (H, W) position in frame t-1
    src_y = np.arange(h, dtype=np.float32)[:, None] + my
    # NaN compares False: non-finite motion is outside
    inside = (src_x > -0.5) & (src_x < w - 0.5) & (src_y > -0.5) & (src_y < h - 0.5)
    qx = np.clip(np.rint(np.nan_to_num(src_x)), 0, w - 1)
    qy = np.clip(np.rint(np.nan_to_num(src_y)), 0, h - 1)
    index = (qy * w + qx).astype(np.intp)
    # 1-D takes per plane: several times faster than gathering (C,)-rows of an (H·W, C) array
    warped = np.stack([plane.take(index) for plane in image.reshape(len(image), -1)])
    return warped, inside


def history_valid(
    warped_depth: np.ndarray, warped_normal: np.ndarray, depth: np.ndarray, normal: np.ndarray
) -> np.ndarray:
    """Disocclusion test on depth (H, W) and normals (3, H, W): True where the reprojected
    surface is the current one."""
    depth_ok = np.abs(warped_depth - depth) <= DEPTH_REL_TOLERANCE * np.maximum(depth, 1e-6)
    dot = warped_normal[0] * normal[0] + warped_normal[1] * normal[1] + warped_normal[2] * normal[2]
    lengths = np.sqrt(np.sum(warped_normal**2, axis=0) * np.sum(normal**2, axis=0))
    return depth_ok & (dot > NORMAL_MIN_DOT * lengths)  # cosine test, as model/temporal


def _reproject(
    state: np.ndarray | None, motion: np.ndarray, depth: np.ndarray, normal: np.ndarray,
    max_count: float,
) -> tuple[np.ndarray | None, np.ndarray]:
    """Warp a state laid out as STATE_CHANNELS (+ extras); return it (None without a state) and
    the new history length n: 1 where history is dropped, else min(n_prev, max_count) + 1."""
    if state is None or state.shape[1:] != depth.shape:
        return None, np.ones(depth.shape, np.float32)
    # nearest pixel, as model/temporal: the surface test checks the very pixel that is reused
    warped, inside = nearest_warp(state, motion)
    keep = inside & history_valid(warped[3], warped[4:7], depth, normal)
    return warped, keep * np.clip(warped[7], 0, max_count) + 1


def _blend(current: np.ndarray, previous: np.ndarray, weight: np.ndarray) -> np.ndarray:
    # weight·current + (1 - weight)·previous, as model/temporal.accumulate (weight 1: no history)
    return weight * current + (1 - weight) * previous


class TemporalAccumulation:
    """The NBG §4.6 pre-stage alone: demodulate, reproject, accumulate, remodulate."""

    def __init__(self) -> None:
        self._state: np.ndarray | None = None  # (8, H, W), as the model's state
        self.valid_fraction = 0.0  # share of pixels that reused history in the last frame

    def reset(self) -> None:
        self._state = None

    def __call__(self, buffers: dict[str, np.ndarray]) -> np.ndarray:
        radiance, albedo_p, normal_p, depth_p, motion = _demodulated(buffers)
        warped, count = _reproject(self._state, motion, depth_p, normal_p, 1 / MIN_CURRENT_WEIGHT)
        if warped is not None:
            radiance = _blend(radiance, warped[:3], np.maximum(1 / count, MIN_CURRENT_WEIGHT))
        self.valid_fraction = float(np.mean(count > 1))
        self._state = np.concatenate([radiance, depth_p[None], normal_p, count[None]])
        return np.ascontiguousarray(np.moveaxis(radiance * albedo_p, 0, -1))


# --- SVGF (Schied et al. 2017) --------------------------------------------------------------
_B3 = (1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16)  # B3-spline taps
_B3_3X3 = (0.25, 0.5, 0.25)  # binomial 3-tap, the variance prefilter
_MAX_HISTORY = 32  # history length cap (SVGF: only used for the 1/n blend early on)
_MIN_TEMPORAL_SAMPLES = 4  # below this, variance is estimated spatially (SVGF §4.2)
_VARIANCE_RADIUS = 3  # 7×7 spatial variance estimate
_BAND_ROWS = 48  # filters run on row bands so that their temporaries stay in cache
_GATHER_FRACTION = 0.25  # spatial variance by gathering below this share of young pixels
_TINY = 1e-30  # ln(max(n·n_q, tiny)) · σn: exp gives exactly 0 for back-facing neighbours


class _PaddedFrame:
    """Per-resolution workspace: planes zero-padded by `reach` on all sides and flattened, so
    that the neighbour at offset (dy, dx) of a run of pixels is the same run shifted by
    dy·Wp + dx. Every numpy op of the filter loops then works on contiguous memory (3× faster
    than 2-D views), and the buffers are reused across frames (fresh large arrays cost page
    faults: ~25% of the time here). The padding stays 0: its zero normal gives every weight
    towards it 0, and a padding pixel filtered in a band keeps its value (its own weight only).
    """

    def __init__(self, shape: tuple[int, int], reach: int) -> None:
        self.shape, self.reach = shape, reach
        self.row = shape[1] + 2 * reach  # Wp
        n = (shape[0] + 2 * reach) * self.row
        self.guides = np.zeros((5, n), np.float32)  # depth, 1 / (σz |∇z|), normal×3
        self.depth, self.inv_phi_z, self.normal = self.guides[0], self.guides[1], self.guides[2:]
        self.src = np.zeros((5, n), np.float32)  # radiance×3, luminance, variance
        self.spare = np.zeros((5, n), np.float32)  # à-trous passes ping-pong src ↔ spare
        self.moments = np.zeros((2, n), np.float32)
        self.moments_out = np.zeros((2, n), np.float32)
        self.inv_phi_l = np.zeros(n, np.float32)  # 1 / (σl √(3×3 blur of variance))
        self.scratch = np.zeros(n, np.float32)

    def interior(self, flat: np.ndarray) -> np.ndarray:
        """(C, Hp·Wp) → writable (C, H, W) view of the unpadded pixels."""
        (h, w), r = self.shape, self.reach
        return flat.reshape(len(flat), h + 2 * r, self.row)[:, r : r + h, r : r + w]

    def bands(self) -> list[tuple[int, int]]:
        """Flat [start, stop) runs covering the frame by row bands (the padding columns between
        rows are filtered too; a run starts and ends inside the frame so that every shifted run
        stays inside the array)."""
        (h, w), r = self.shape, self.reach
        rows = range(0, h, _BAND_ROWS)
        return [((r + y) * self.row + r, (r + min(y + _BAND_ROWS, h) - 1) * self.row + r + w)
                for y in rows]

    def flat_index(self, mask: np.ndarray) -> np.ndarray:
        """Flat padded indices of the True pixels of an (H, W) mask."""
        y, x = np.nonzero(mask)
        return (y + self.reach) * self.row + (x + self.reach)

    def offset(self, dy: int, dx: int) -> int:
        return dy * self.row + dx


class _Taps(NamedTuple):
    """One cross-bilateral pass: centre kernel weight and (flat offset, kernel weight, 1/dist)."""

    center: float
    taps: list[tuple[int, float, float]]


def _depth_gradient(depth: np.ndarray) -> np.ndarray:
    """Screen-space depth slope per pixel: max over axes of the smaller one-sided difference.

    The smaller side keeps a pixel next to a depth edge from taking the edge as its slope.
    """
    z = np.pad(depth, 1, mode="edge")
    dx = np.minimum(np.abs(z[1:-1, 2:] - z[1:-1, 1:-1]), np.abs(z[1:-1, 1:-1] - z[1:-1, :-2]))
    dy = np.minimum(np.abs(z[2:, 1:-1] - z[1:-1, 1:-1]), np.abs(z[1:-1, 1:-1] - z[:-2, 1:-1]))
    return np.maximum(dx, dy)


class SVGFStyleFilter:
    """Edge-avoiding à-trous wavelet filter with temporal accumulation, after SVGF.

    Temporal stage: demodulated radiance and luminance moments blended with weight
    max(α, 1/n) (n = history length), same reprojection rule as `TemporalAccumulation`.
    Variance: temporal moments, or a 7×7 normal/depth-weighted spatial estimate while n < 4.
    Spatial stage: `iterations` à-trous passes (5×5 B3 kernel, step 2^i) with edge-stopping
    weights w = max(0, n·n_q)^σn · exp(-|z - z_q| / (σz |∇z| step |o|) - |l - l_q| / (σl √var)),
    var = 3×3 Gaussian of the variance; variance propagated with w². The first pass's output is
    the next frame's radiance history. `num_threads` > 1 filters row bands in parallel (numpy
    releases the GIL inside its loops).
    """

    def __init__(
        self,
        iterations: int = 5,
        sigma_normal: float = 128.0,
        sigma_depth: float = 1.0,
        sigma_luminance: float = 4.0,
        alpha_color: float = 0.2,
        alpha_moments: float = 0.2,
        num_threads: int = 1,
    ) -> None:
        if iterations < 1:
            raise ValueError(f"SVGFStyleFilter: iterations must be >= 1, got {iterations}")
        self.iterations = iterations
        self.sigma_normal = sigma_normal
        self.sigma_depth = sigma_depth
        self.sigma_luminance = sigma_luminance
        self.alpha_color = alpha_color
        self.alpha_moments = alpha_moments
        self._pool = ThreadPoolExecutor(num_threads) if num_threads > 1 else None
        self._scratch = threading.local()  # per-thread band buffers
        self._frame: _PaddedFrame | None = None
        # (10, H, W): the accumulation state layout (radiance, depth, normal, n), then m1, m2
        self._state: np.ndarray | None = None

    def reset(self) -> None:
        self._state = None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __call__(self, buffers: dict[str, np.ndarray]) -> np.ndarray:
        radiance, albedo_p, normal_p, depth_p, motion = _demodulated(buffers)
        lum = _luminance(radiance)
        moments = np.stack([lum, lum * lum])  # (2, H, W)
        warped, count = _reproject(self._state, motion, depth_p, normal_p, _MAX_HISTORY)
        if warped is not None:
            radiance = _blend(radiance, warped[:3], np.maximum(1 / count, self.alpha_color))
            moments = _blend(moments, warped[8:10], np.maximum(1 / count, self.alpha_moments))

        frame = self._prepare(depth_p, normal_p)
        frame.interior(frame.src)[:3] = radiance
        frame.interior(frame.src)[4] = self._variance(frame, moments, count)
        src, spare = frame.src, frame.spare
        feedback = radiance
        for i in range(self.iterations):
            src[3] = _luminance(src[:3])  # (N,) luminance of this pass's input
            src, spare = self._atrous(frame, src, 1 << i, spare, i == self.iterations - 1), src
            if i == 0:
                feedback = frame.interior(src[:3]).copy()
        state = [feedback, depth_p[None], normal_p, count[None], moments]
        self._state = np.concatenate(state).astype(np.float32)
        return np.ascontiguousarray(np.moveaxis(frame.interior(src[:3]) * albedo_p, 0, -1))

    def _prepare(self, depth: np.ndarray, normal: np.ndarray) -> _PaddedFrame:
        """The workspace for this resolution, with this frame's edge-stopping guides."""
        reach = max(2 << (self.iterations - 1), _VARIANCE_RADIUS)
        if self._frame is None or self._frame.shape != depth.shape:
            self._frame = _PaddedFrame(depth.shape, reach)
        frame = self._frame
        guides = frame.interior(frame.guides)
        guides[0], guides[2:] = depth, normal
        guides[1] = 1 / (self.sigma_depth * np.maximum(_depth_gradient(depth), 1e-8))
        return frame

    def _variance(
        self, frame: _PaddedFrame, moments: np.ndarray, count: np.ndarray
    ) -> np.ndarray:
        """(H, W) luminance variance: temporal where n >= 4, else a spatial 7×7 estimate."""
        variance = np.maximum(moments[1] - moments[0] ** 2, 0)
        young = count < _MIN_TEMPORAL_SAMPLES
        if not young.any():
            return variance
        # Moments averaged over 7×7 with normal and depth edge-stopping (no luminance term: the
        # variance is what is being estimated).
        reach = range(-_VARIANCE_RADIUS, _VARIANCE_RADIUS + 1)
        taps = [(frame.offset(dy, dx), 1.0, 1 / float(np.hypot(dx, dy)))
                for dy in reach for dx in reach if (dy, dx) != (0, 0)]
        frame.interior(frame.moments)[...] = moments
        # only young pixels need it: gather them when few (disocclusions), else whole bands
        pixels = frame.flat_index(young) if young.mean() < _GATHER_FRACTION else None
        self._run(frame, frame.moments, _Taps(1.0, taps), None, 2, None, frame.moments_out, pixels)
        spatial = frame.interior(frame.moments_out)
        spatial = np.maximum(spatial[1] - spatial[0] ** 2, 0)
        spatial *= _MIN_TEMPORAL_SAMPLES / count  # few samples underestimate it: SVGF's 4/n boost
        return np.where(young, spatial, variance)

    def _atrous(
        self, frame: _PaddedFrame, src: np.ndarray, step: int, out: np.ndarray, last: bool
    ) -> np.ndarray:
        """One à-trous pass over padded (5, N) [radiance×3, luminance, variance] into `out`
        (the last pass skips the variance: nothing reads it)."""
        taps = [(frame.offset((j - 2) * step, (i - 2) * step), _B3[i] * _B3[j],
                 1 / (step * float(np.hypot(i - 2, j - 2)))) for j in range(5) for i in range(5)
                if (i, j) != (2, 2)]
        # 1 / (σl √(3×3 binomial blur of the variance)), on the flat layout
        var, inv_l, tmp = src[4], frame.inv_phi_l, frame.scratch
        lo, hi = frame.offset(1, 1), len(var) - frame.offset(1, 1)
        inv_l[lo:hi] = 0
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                off, k = frame.offset(dy, dx), _B3_3X3[dy + 1] * _B3_3X3[dx + 1]
                inv_l[lo:hi] += np.multiply(var[lo + off : hi + off], k, out=tmp[lo:hi])
        np.sqrt(inv_l, out=inv_l)
        inv_l *= self.sigma_luminance
        inv_l += 1e-10
        np.reciprocal(inv_l, out=inv_l)
        var_row = None if last else 4
        return self._run(frame, src, _Taps(_B3[2] ** 2, taps), inv_l, 3, var_row, out)

    def _run(
        self,
        frame: _PaddedFrame,
        src: np.ndarray,
        taps: _Taps,
        inv_phi_l: np.ndarray | None,
        n_filtered: int,
        var_row: int | None,
        out: np.ndarray,
        pixels: np.ndarray | None = None,
    ) -> np.ndarray:
        """A cross-bilateral pass into `out` over all bands, or over the given flat pixel indices
        only (rows not filtered, and pixels not computed, are left as they are)."""
        job = partial(self._band, frame, src, out, taps, inv_phi_l, n_filtered, var_row)
        if pixels is None:
            bands: list = frame.bands()
        else:
            chunk = _BAND_ROWS * frame.shape[1]
            bands = [pixels[i : i + chunk] for i in range(0, len(pixels), chunk)]
        if self._pool is None:
            for band in bands:
                job(band)
        else:
            list(self._pool.map(job, bands))
        return out

    def _band(
        self,
        frame: _PaddedFrame,
        src: np.ndarray,
        out: np.ndarray,
        taps: _Taps,
        inv_phi_l: np.ndarray | None,
        n_filtered: int,
        var_row: int | None,
        band: tuple[int, int] | np.ndarray,
    ) -> None:
        """One run [start, stop) of the flat layout, or gathered pixels (the same code on index
        arrays). Temporaries are band-sized, contiguous, and reused (per thread)."""
        if isinstance(band, tuple):
            start, stop = band
            here, size = slice(start, stop), stop - start
            shifted = lambda off: slice(start + off, stop + off)  # noqa: E731
        else:
            here, size = band, len(band)
            shifted = band.__add__
        scratch = getattr(self._scratch, "buffers", None)
        if scratch is None or scratch.shape[1] < size:
            scratch = self._scratch.buffers = np.empty((8, size), np.float32)
        dot, e, tmp, wsum, vacc = scratch[:5, :size]
        acc = scratch[5 : 5 + n_filtered, :size]
        n_c, z_c, inv_z = frame.normal[:, here], frame.depth[here], frame.inv_phi_z[here]
        wsum.fill(taps.center)
        np.multiply(src[:n_filtered, here], taps.center, out=acc)
        if var_row is not None:
            np.multiply(src[var_row, here], taps.center**2, out=vacc)
        if inv_phi_l is not None:
            l_c, inv_l = src[3, here], inv_phi_l[here]
        for off, k, inv_dist in taps.taps:
            there = shifted(off)
            n_q = frame.normal[:, there]
            # all three edge-stopping terms in one exp: max(0, n·n_q)^σn = exp(σn ln(n·n_q))
            np.multiply(n_c[0], n_q[0], out=dot)
            dot += np.multiply(n_c[1], n_q[1], out=tmp)
            dot += np.multiply(n_c[2], n_q[2], out=tmp)
            np.maximum(dot, _TINY, out=dot)
            np.log(dot, out=dot)
            np.subtract(z_c, frame.depth[there], out=e)
            np.abs(e, out=e)
            e *= inv_z
            e *= -inv_dist
            dot *= self.sigma_normal
            e += dot
            if inv_phi_l is not None:
                np.subtract(l_c, src[3, there], out=tmp)
                np.abs(tmp, out=tmp)
                tmp *= inv_l
                e -= tmp
            np.exp(e, out=e)
            e *= k
            wsum += e
            for c in range(n_filtered):
                acc[c] += np.multiply(e, src[c, there], out=tmp)
            if var_row is not None:
                np.square(e, out=e)
                vacc += np.multiply(e, src[var_row, there], out=tmp)
        # (assignment, not out=: with gathered pixels out[:, here] would be a copy)
        out[:n_filtered, here] = np.divide(acc, wsum, out=acc)
        if var_row is not None:
            out[var_row, here] = np.divide(vacc, np.square(wsum, out=wsum), out=vacc)


# --- Open Image Denoise ----------------------------------------------------------------------
Quality = Literal["fast", "balanced", "high"]


class OIDNDenoiser:
    """Intel Open Image Denoise alone (RT filter, hdr, albedo + normal), single-frame, on
    (H, W, C) images. It is the runtime's OIDN prepass (runtime/oidn_prepass.py), so this
    baseline and the oidn-temporal tier run the same OIDN code with the same settings.

    With `prefilter_aux`, albedo and normal are first denoised by their own RT filters (at
    `aux_quality`, default the main filter's) and the main filter is told `cleanAux` (OIDN's
    documented workflow for noisy auxiliary buffers; Blender's Accurate prefilter). `aux`
    chooses what OIDN is given besides the colour (a normal only together with an albedo).
    `renderer`: the frames' renderer (OIDN sees the rows in its order, as the runtime's stage
    does: runtime/oidn_prepass.py rows_bottom_up).
    """

    def __init__(
        self,
        quality: Quality = "high",
        prefilter_aux: bool = False,
        num_threads: int = 0,
        aux: tuple[str, ...] = ("albedo", "normal"),
        aux_quality: str = "",
        renderer: str | None = None,
    ) -> None:
        if quality not in QUALITIES:
            raise ValueError(f"OIDNDenoiser: quality must be fast, balanced or high: {quality!r}")
        self.quality, self.prefilter_aux = quality, prefilter_aux
        settings = OIDNSettings(quality, prefilter_aux, aux=aux, aux_quality=aux_quality)
        self._prepass = OIDNPrepass(settings, num_threads)
        self.renderer = renderer

    def reset(self) -> None:
        """Single-frame: nothing to forget (resources are kept for the next frame)."""

    def __call__(self, buffers: dict[str, np.ndarray]) -> np.ndarray:
        color, albedo, normal, _, _ = _canonical(buffers)
        planes = planes_from_hwc({"color": color, "albedo": albedo, "normal": normal})
        return self._prepass(planes, self.renderer)[0].transpose(1, 2, 0)

    def close(self) -> None:
        """Release filters, then the device, then the memory they were bound to."""
        self._prepass.close()

