"""Experiment: would a look-ahead of k future frames help the `oidn-history` tiers? Every
temporal tier is causal (frame t reads only its own history of earlier outputs), but a farm
has the whole shot on disk, and Cycles' `Vector` pass also holds the motion to the next frame.

    python -m quietframe.experiments.lookahead --zoo zoo3 --split validation \
        --shots study-dolly [--spp 1,4,16] [--k 1,2,4] [--model oidn-history-cleanaux] \
        [--time-720p] [--json out]

k = 0 is the shipped tier through the real per-sequence step, as bench/zoo_eval runs it
(RuntimeMethod from bench.evaluate.build_methods, the header's spp, scored by
harness.score_sequence: tone-mapped PSNR against the shot's reference, TRMAE). The look-ahead
is a blend on top of the causal output C_t, for frame t:

    out_t = (n_t · C_t + Σ_{j ≤ k} τ_j · F_{t+j}(p → t+j)) / (n_t + Σ_j τ_j)

- F_{t+j}: a later frame's image carried into frame t: by default the tier's per-frame stage
  S (`<tier>/frame`: OIDN on the frame alone); `oidn` the tier's own OIDN output D before its
  output history (free at run time: the tier computes it anyway); `causal` the later frames'
  causal outputs C (free too, but their histories overlap C_t's). Fetched where frame t's pixel
  lands in frame t + j along the rendered forward motion (Cycles' Vector.ZW, chained hop by hop
  through each frame's own field, nearest pixel per hop so no field is blended across a depth
  edge), bicubically (PyTorch's a = −0.75, as the tier fetches its history), clipped to the 3×3
  range of S_t (the tier's clamp_to_neighbourhood, on this frame's stage).
- τ_j ∈ {0, 1}: trusted where every hop lands inside the frame and passes a forward-backward
  check (t+i+1's rendered backward motion brings the hop back within FB_PIXELS, the threshold of
  runtime/aux_motion) and the aux of t + j at the landing point show frame t's surface
  (aux_agree: depth within 10% as the tier's surface test, normals of 3×3 box means within
  cos 0.9, the albedo within this frame's 3×3 albedo range ± aux_motion.TRUST_ERROR; the
  tier's own per-pixel normal test, `pixel aux`, rejects a bump-mapped fabric at sub-pixel
  offsets). The reference is never read.
- n_t: the causal output's worth in frames, per pixel, from the tier's own state (history
  length n, the current frame's weight α = max(1/n, w(spp)) where the motion is sub-pixel,
  0.2 where whole pixels): min(n, (2 − α)/α), the exponential history's noise reduction.
- `fill`: the first frames of a shot, whose history is empty, look further ahead, until their
  window holds as many frames as a middle frame's history (k + round((2 − w)/w) − (t + 1)).

Cycles' Vector convention, checked on the references (`convention` in the output, re-run with
every call): Vector.XY = position at t−1 minus position at t and Vector.ZW = position at t minus
position at t+1, both with raster y up. So the forward motion in quietframe's terms (x right,
y down; frame t+1 fetched at p + m) is (−Z, +W), and the backward one (X, −Y)
(runtime/exr_channels).

Result: experiments/README.md, "Look-ahead".
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from quietframe.bench import cli_args
from quietframe.bench.evaluate import _inputs, build_methods, give_header_spp
from quietframe.bench.harness import planar_frames, score_sequence
from quietframe.bench.synthetic import frame_buffers
from quietframe.bench.timing import time_ms
from quietframe.bench.zoo_eval import HISTORY_TIERS
from quietframe.experiments.history_trust import rendered_frames, stage_outputs
from quietframe.model import metrics
from quietframe.model.output_history import VARIANTS
from quietframe.model.temporal import (
    DEPTH_REL_TOLERANCE,
    MIN_CURRENT_WEIGHT,
    NORMAL_MIN_DOT,
    pixel_aligned,
)
from quietframe.runtime import Denoiser, find_model
from quietframe.runtime.aux_motion import FB_PIXELS, TRUST_ERROR, warp
from quietframe.runtime.exr_channels import Source
from quietframe.runtime.exr_codec import decode
from quietframe.runtime.lookahead import bicubic, box3
from quietframe.scenes import cycles_io
from quietframe.scenes.zoo_shots import zoo_dir

HISTORY_KEY = "accumulation"  # the output history's state: O (3), depth, normal (3), length
EMPTY_NORMAL = 1e-3  # shorter normals: no surface (the world background)
VECTOR = tuple(f"ViewLayer.Vector.{c}" for c in "XYZW")


@dataclass(frozen=True)
class Candidate:
    """One look-ahead rule (module docstring)."""

    source: str = "stage"  # stage (S), oidn (D) or causal (C) of the later frames
    fetch: str = "bicubic"  # or bilinear
    clamp: bool = True  # to the 3×3 range of this frame's stage
    aux_check: str = "range"  # range, box, pixel or "" (none): aux_agree
    fb_check: bool = True
    fill: bool = False  # the first frames look further ahead


CANDIDATES: dict[str, Candidate] = {
    "blend": Candidate(),
    "fill": Candidate(fill=True),
    "no clamp": Candidate(clamp=False),
    "bilinear": Candidate(fetch="bilinear"),
    "box aux": Candidate(aux_check="box"),
    "pixel aux": Candidate(aux_check="pixel"),
    "fb only": Candidate(aux_check=""),
    "no checks": Candidate(aux_check="", fb_check=False),
    "oidn": Candidate(source="oidn"),
    "causal": Candidate(source="causal"),
}


# --- Cycles' Vector pass --------------------------------------------------------------------

def vector_pass(folder: Path, t: int, spp: int) -> np.ndarray:
    """(4, H, W) Vector.XYZW of frame t as written (cycles_io keeps XY only, as `motion`)."""
    data = (folder / cycles_io.level_dir(spp) / cycles_io.frame_file(t)).read_bytes()
    return decode(data, {"vector": Source(VECTOR, "Cycles Vector, raw")}).buffers["vector"]


def forward_motion(vector: np.ndarray) -> np.ndarray:
    """(2, H, W) motion to frame t + 1 in quietframe's terms: t+1 holds p's surface at p + m."""
    return np.stack((-vector[2], vector[3])).astype(np.float32)


def backward_motion(vector: np.ndarray) -> np.ndarray:
    """(2, H, W) motion to frame t − 1 (runtime/exr_channels' Cycles alias)."""
    return np.stack((vector[0], -vector[1])).astype(np.float32)


def _masked_psnr(pred: np.ndarray, reference: np.ndarray, where: np.ndarray) -> float:
    return metrics.psnr((pred * where).transpose(1, 2, 0), (reference * where).transpose(1, 2, 0))


def check_convention(folder: Path, frames: int, spp: int) -> dict[str, float]:
    """Mean PSNR (inside the frame) of reference t against reference t + 1 fetched at
    p + (±Z, ±W) of frame t, and against reference t − 1 fetched at p + (±X, ±Y); `none`: t + 1
    unwarped. The right signs stand out by several dB."""
    refs = [cycles_io.load_reference(folder, t).transpose(2, 0, 1) for t in range(frames)]
    scores: dict[str, list[float]] = {}
    for t in range(frames):
        v = vector_pass(folder, t, spp)
        if t + 1 < frames:
            scores.setdefault("none", []).append(
                _masked_psnr(refs[t + 1], refs[t], np.ones(refs[t].shape[1:], bool)))
            for sx in (1, -1):
                for sy in (1, -1):
                    fetched, inside = warp(refs[t + 1], np.stack((sx * v[2], sy * v[3])))
                    scores.setdefault(f"t+1 at ({sx:+d}Z, {sy:+d}W)", []).append(
                        _masked_psnr(fetched, refs[t], inside))
        if t > 0:
            for sx in (1, -1):
                for sy in (1, -1):
                    fetched, inside = warp(refs[t - 1], np.stack((sx * v[0], sy * v[1])))
                    scores.setdefault(f"t-1 at ({sx:+d}X, {sy:+d}Y)", []).append(
                        _masked_psnr(fetched, refs[t], inside))
    return {name: round(float(np.mean(v)), 2) for name, v in scores.items()}


# --- fetching at positions ------------------------------------------------------------------

def sample_nearest(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    _, h, w = image.shape
    xi = np.clip(np.rint(x), 0, w - 1).astype(np.intp)
    yi = np.clip(np.rint(y), 0, h - 1).astype(np.intp)
    return image[:, yi, xi]


def sample_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    h, w = x.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    return warp(image, np.stack((x - xs, y - ys)))[0]


def sample_bicubic(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(C, H', W') bicubic fetch at float pixel positions, taps clamped to the frame (the
    runtime's: Keys, a = −0.75, the tier's history fetch)."""
    c, h, w = image.shape
    return bicubic(image.reshape(c, -1), x, y, h, w)


def _range3(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per channel, the min and max over each pixel's 3×3 neighbourhood (edges replicated)."""
    _, h, w = x.shape
    padded = np.pad(x, ((0, 0), (1, 1), (1, 1)), mode="edge")
    taps = [padded[:, i:i + h, j:j + w] for i in range(3) for j in range(3)]
    return np.min(taps, axis=0), np.max(taps, axis=0)


# --- the look-ahead -------------------------------------------------------------------------

@dataclass
class Frame:
    """What the blend reads of one frame (all (C, H, W) float32)."""

    planes: dict[str, np.ndarray]  # the runtime's input planes (albedo, normal, depth, motion)
    forward: np.ndarray  # (2, H, W) to t + 1
    backward: np.ndarray  # (2, H, W) to t − 1
    causal: np.ndarray  # C_t, the shipped tier's output
    worth: np.ndarray  # (H, W) n_t
    stage: np.ndarray  # S_t
    oidn: np.ndarray | None = None  # D_t


def causal_worth(count: np.ndarray, motion: np.ndarray, spp: float,
                 model: str = "oidn-history-cleanaux") -> np.ndarray:
    """(H, W) n_t of the module docstring from the history length the tier's state holds."""
    config = VARIANTS[model]
    floor = np.clip(config.resampled_weight
                    + config.resampled_weight_per_doubling * np.log2(max(spp, 1.0)),
                    MIN_CURRENT_WEIGHT, config.resampled_weight_max)
    aligned = pixel_aligned(torch.from_numpy(np.ascontiguousarray(motion))[None])[0, 0].numpy()
    count = np.maximum(count, 1.0)
    alpha = np.maximum(1 / count, np.where(aligned, MIN_CURRENT_WEIGHT, floor))
    return np.minimum(count, (2 - alpha) / alpha).astype(np.float32)


def steady_worth(spp: float, model: str = "oidn-history-cleanaux") -> float:
    """n of a middle frame's history where the motion is sub-pixel."""
    return float(causal_worth(np.full((1, 1), 1e3, np.float32), np.full((2, 1, 1), 0.5), spp,
                              model)[0, 0])


def carry(frames: list[Frame], t: int, k: int, fb_check: bool = True):
    """Per j = 1 … k: (x, y) where frame t's pixels land in frame t + j, and whether every hop
    so far stayed in the frame (and passed the forward-backward check)."""
    _, h, w = frames[t].forward.shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    ok = np.ones((h, w), bool)
    for j in range(1, k + 1):
        step = sample_nearest(frames[t + j - 1].forward, x, y)
        x, y = x + step[0], y + step[1]
        ok &= (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        if fb_check:
            back = sample_nearest(frames[t + j].backward, x, y)
            ok &= np.hypot(*(step + back)) <= FB_PIXELS
        yield x, y, ok.copy()


def aux_agree(here: dict[str, np.ndarray], there: dict[str, np.ndarray], x: np.ndarray,
              y: np.ndarray, mode: str = "range") -> np.ndarray:
    """(H, W) bool: the later frame's aux at (x, y) show the surface frame t shows. Always the
    depth of the nearest pixel within 10%. `pixel`: the tier's own surface test (normals within
    cos 0.9 at the nearest pixel), and the albedo's |difference| over a 3×3 window within
    TRUST_ERROR; a bump-mapped fabric fails it at sub-pixel offsets. `box`: normals and albedo
    of the 3×3 box means. `range` (default): box normals, and the later albedo (bilinear)
    within this frame's 3×3 albedo range ± TRUST_ERROR, which a sub-pixel shift of printed text
    at 1 spp passes and another material does not. Where both normals are empty (the world
    background: Cycles writes zeros) they agree."""
    depth = here["depth"][0]
    fetched_depth = sample_nearest(there["depth"], x, y)[0]
    ok = np.abs(fetched_depth - depth) <= DEPTH_REL_TOLERANCE * np.maximum(depth, 1e-6)
    if mode == "pixel":
        n, m = here["normal"], sample_nearest(there["normal"], x, y)
        a = np.abs(sample_bilinear(there["albedo"], x, y) - here["albedo"]).mean(0)
        ok &= box3(a[None])[0] <= TRUST_ERROR
    else:
        n, m = box3(here["normal"]), sample_bilinear(box3(there["normal"]), x, y)
    if mode == "box":
        a, b = box3(here["albedo"]), sample_bilinear(box3(there["albedo"]), x, y)
        ok &= np.abs(a - b).mean(0) <= TRUST_ERROR
    elif mode == "range":
        low, high = _range3(here["albedo"])
        b = sample_bilinear(there["albedo"], x, y)
        ok &= ((b >= low - TRUST_ERROR) & (b <= high + TRUST_ERROR)).all(0)
    ln, lm = np.linalg.norm(n, axis=0), np.linalg.norm(m, axis=0)
    empty = (ln < EMPTY_NORMAL) & (lm < EMPTY_NORMAL)
    return ok & (((n * m).sum(0) > NORMAL_MIN_DOT * ln * lm) | empty)


def look_ahead(frames: list[Frame], t: int, k: int, candidate: Candidate,
               steady: float = 0.0) -> tuple[np.ndarray, float]:
    """(out_t, the share of the later frames' pixels trusted) for frame t; `steady`: a middle
    frame's history in frames, for `fill`."""
    me = frames[t]
    if candidate.fill:
        k += max(0, round(steady) - (t + 1))
    k = min(k, len(frames) - 1 - t)
    if k <= 0:
        return me.causal, float("nan")
    low, high = _range3(me.stage) if candidate.clamp else (None, None)
    total = me.worth * me.causal
    weight = me.worth.copy()
    shares = []
    for j, (x, y, ok) in enumerate(carry(frames, t, k, candidate.fb_check), start=1):
        later = frames[t + j]
        if candidate.aux_check:
            ok = ok & aux_agree(me.planes, later.planes, x, y, candidate.aux_check)
        image = {"stage": later.stage, "oidn": later.oidn, "causal": later.causal}[
            candidate.source]
        sample = sample_bicubic if candidate.fetch == "bicubic" else sample_bilinear
        fetched = np.maximum(sample(image, x, y), 0)
        if low is not None:
            fetched = np.minimum(np.maximum(fetched, low), high)
        total += ok * fetched
        weight += ok
        shares.append(float(ok.mean()))
    return (total / weight).astype(np.float32), float(np.mean(shares))


# --- scoring --------------------------------------------------------------------------------

class _Recorded:
    """A method run as it is (the zoo evaluation's), keeping the history length its state
    holds after every frame."""

    def __init__(self, method) -> None:
        self.method, self.counts = method, []

    def reset(self) -> None:
        self.method.reset()

    def __call__(self, planes):
        out = self.method(planes)
        state = self.method.state
        self.counts.append(state[HISTORY_KEY][0, 7].copy())
        assert np.allclose(state[HISTORY_KEY][0, :3], out, atol=1e-5), "not the history state"
        return out


class _Replay:
    """Outputs made beforehand, one per frame, given to the one scoring loop."""

    def __init__(self, outputs: list[np.ndarray]) -> None:
        self.outputs, self.i = outputs, 0

    def reset(self) -> None:
        pass

    def __call__(self, planes):
        self.i += 1
        return self.outputs[self.i - 1]


def _run(method, frames) -> tuple[list[float], float, list[np.ndarray]]:
    """(PSNR per frame, TRMAE, planar outputs) of `method` as run_sequence scores it."""
    s = score_sequence(method, frames, ("psnr",), inputs=_inputs)
    return s.per_frame["psnr"], s.trmae, [o.transpose(2, 0, 1) for o in s.outputs]


def prepare(folder: Path, model: str, spp: int, threads: int):
    """The shot's frames as the evaluation scores them, its Frames, the k = 0 and stage rows."""
    frames = planar_frames(rendered_frames(folder, spp))
    frames = [(p, r, i == 0) for i, (p, r, _) in enumerate(frames)]  # zoo_eval: no cut flags
    methods = build_methods(threads, single_frame=(model,), renderer="cycles")
    tier, stage_method = methods[model](), methods[f"{model}/frame"]()
    for method in (tier, stage_method):
        give_header_spp(method, "cycles", spp)
    recorded = _Recorded(tier)
    base, base_trmae, causal = _run(recorded, frames)
    stage_psnr, stage_trmae, stage = _run(stage_method, frames)
    oidn, _ = stage_outputs(Denoiser(find_model(model)), frames, spp)
    data = []
    for t, (planes, _, _) in enumerate(frames):
        vector = vector_pass(folder, t, spp)
        data.append(Frame(_inputs(planes), forward_motion(vector), backward_motion(vector),
                          causal[t], causal_worth(recorded.counts[t], planes["motion"], spp,
                                                  model), stage[t], oidn[t]))
    rows = [{"variant": "shipped", "k": 0, "per_frame": base, "trmae": base_trmae},
            {"variant": f"{model}/frame", "k": 0, "per_frame": stage_psnr,
             "trmae": stage_trmae}]
    return frames, data, rows


def run_shot(folder: Path, model: str, spps: list[int], ks: list[int], threads: int,
             candidates: dict[str, Candidate]) -> list[dict]:
    rows = []
    for spp in spps:
        frames, data, mine = prepare(folder, model, spp, threads)
        steady = steady_worth(spp, model)
        for name, candidate in candidates.items():
            for k in ([0] if candidate.fill else []) + ks:
                made = [look_ahead(data, t, k, candidate, steady) for t in range(len(data))]
                psnr, trmae, _ = _run(_Replay([m[0] for m in made]), frames)
                shares = [s for _, s in made if np.isfinite(s)]
                mine.append({"variant": name, "k": k, "per_frame": psnr, "trmae": trmae,
                             "trusted": float(np.mean(shares)) if shares else float("nan")})
        for row in mine:
            row |= {"shot": folder.name, "spp": spp, "psnr": float(np.mean(row["per_frame"]))}
        print_table(mine, max(ks))
        rows += mine
    return rows


def middle_frames(n: int, k_max: int) -> range:
    """Frames past the first two with every k's full look-ahead (all past the first two where
    the shot is too short)."""
    return range(2, n - k_max) if n - k_max > 2 else range(2, n)


def summary(row: dict, base: list[float], stage: list[float], middle: range) -> dict:
    """Against k = 0 per frame: the mean and the worst difference over the frames that look
    ahead (all but the last), the first two frames' mean; the first two frames against the
    middle ones, as PSNR and as the gain over the per-frame stage (frame 0's content may be
    harder: the stage itself differs)."""
    pf = np.asarray(row["per_frame"])
    gaps = pf - np.asarray(base)
    gain = pf - np.asarray(stage)
    return {"d_mean": float(gaps.mean()), "d_worst": float(gaps[:-1].min()),
            "d_first2": float(gaps[:2].mean()),
            "first2_mid": float(pf[:2].mean() - pf[list(middle)].mean()),
            "gain_first2_mid": float(gain[:2].mean() - gain[list(middle)].mean())}


def print_table(rows: list[dict], k_max: int) -> None:
    base = next(r for r in rows if r["variant"] == "shipped")["per_frame"]
    stage = rows[1]["per_frame"]
    n = len(base)
    middle = middle_frames(n, k_max)
    r0 = rows[0]
    print(f"\n{r0['shot']}, {r0['spp']} spp, {n} frames (middle: {middle.start}–"
          f"{middle.stop - 1}); Δ to k = 0 (shipped, {np.mean(base):.2f} dB)", flush=True)
    print(f"{'variant':<28} {'k':>2} {'PSNR':>6} {'Δmean':>6} {'worst':>6} {'Δ0-1':>6} "
          f"{'f2-mid':>6} {'gain f2-mid':>11} {'TRMAE':>6} {'trusted':>7}")
    for r in rows:
        r |= summary(r, base, stage, middle)
        print(f"{r['variant']:<28} {r['k']:>2} {r['psnr']:6.2f} {r['d_mean']:+6.2f} "
              f"{r['d_worst']:+6.2f} {r['d_first2']:+6.2f} {r['first2_mid']:+6.2f} "
              f"{r['gain_first2_mid']:+11.2f} {r['trmae']:6.3f} "
              f"{r.get('trusted', float('nan')):7.0%}")


def time_blend(ks: list[int], height: int = 720, width: int = 1280) -> dict[int, str]:
    """The blend's cost per frame (the default candidate) at `height`×`width` on synthetic
    buffers: every later frame is carried, checked and fetched, whatever its trust."""
    rng = np.random.default_rng(0)
    frames = []
    for t in range(max(ks) + 1):
        planes = frame_buffers(height, width, seed=t)
        field = np.full((2, height, width), 1.2, np.float32) + rng.normal(0, 0.05, (2, height,
                                                                                 width))
        colour = rng.uniform(0, 1, (3, height, width)).astype(np.float32)
        frames.append(Frame(planes, field.astype(np.float32), -field.astype(np.float32), colour,
                            np.full((height, width), 3.0, np.float32), colour))
    out = {}
    for k in ks:
        timing = time_ms(lambda k=k: look_ahead(frames, 0, k, Candidate()), warmup=1,
                         repeats=3)
        out[k] = str(timing)
        print(f"blend at {width}×{height}, k = {k}: {timing}", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_zoo_shots(p, zoo="zoo3")
    p.add_argument("--spp", type=cli_args.spp_levels, default="1,4,16")
    p.add_argument("--k", type=cli_args.spp_levels, default="1,2,4",
                   help="look-ahead depths (comma list; k = 0 is always scored)")
    p.add_argument("--model", default="oidn-history-cleanaux", choices=HISTORY_TIERS)
    p.add_argument("--variants", default=",".join(CANDIDATES),
                   help=f"comma list of {', '.join(CANDIDATES)}")
    p.add_argument("--time-720p", action="store_true", help="also time the blend at 1280×720")
    cli_args.add_threads(p)
    cli_args.add_json(p)
    args = p.parse_args(argv)
    candidates = {name: CANDIDATES[name] for name in args.variants.split(",")}
    root = zoo_dir(args.data, args.split, args.zoo)
    folders = sorted(f.parent for f in root.glob("*/manifest.json")
                     if not args.shots or f.parent.name in args.shots)
    result: dict = {"command": " ".join(["python -m quietframe.experiments.lookahead",
                                         *(sys.argv[1:] if argv is None else argv)]),
                    "convention": {}, "rows": []}
    for folder in folders:
        if json.loads((folder / "manifest.json").read_text())["zoo"].get("motion_blur"):
            print(f"{folder.name}: motion blur on, its Vector is zero: skipped")
            continue
        n = len(rendered_frames(folder, args.spp[-1]))
        result["convention"][folder.name] = check_convention(folder, n, args.spp[-1])
        print(f"{folder.name}: reference t against its neighbour fetched along Vector "
              f"(PSNR): {result['convention'][folder.name]}", flush=True)
        result["rows"] += run_shot(folder, args.model, list(args.spp), list(args.k),
                                   args.threads, candidates)
    if args.time_720p:
        result["ms_720p"] = time_blend(list(args.k))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
