"""Can OIDN's aux prefilters be spared on still pixels: the aux accumulated through a history
where nothing moved, the prefiltered aux reused there, or both? An ablation of the quality
tier's OIDN stage (`oidn-history-cleanaux`), measured through the runtime:

    python -m quietframe.experiments.aux_history --split test [--shots a,b] [--spp 1,4,16,64]
        [--policies ...] [--timing-only | --quality-only] [--json out.json]

Policies (what the main filter gets as its clean aux; `per-frame` is the shipped stage):
- per-frame: the frame's raw aux, prefiltered every frame;
- accumulate: the raw aux accumulated where the pixel is still (no motion) and shows the same
  surface (depth within 10%, isolated failures ignored: a 1-spp edge's depth jumps between its
  two surfaces), with the colour's weights (1/n, then 0.2), prefiltered every frame;
- reuse: the raw aux prefiltered once per surface (where it is new) and reused while it stays;
- accumulate+reuse: the accumulated aux prefiltered when the surface is new and as its history
  reaches 2, 4 and 6 frames (then its weight is fixed), reused in between;
- halves: the raw aux prefiltered on one half of the frame each frame (top, bottom, in turn, with
  a margin), reused on the other.
A tile whose raw aux left its history by more than noise (an animated texture) starts again.
Prefilters run on crops (the tiles that need one, with MARGIN px of context), the whole frame
once the crops would cover 80% of it.

Quality: the zoo's shots per spp, mean tone-mapped PSNR and locked-off flicker beside Blender's
denoise. Speed: CPU seconds per 1280x720 frame on a locked-off synthetic sequence (colour noise
new every frame) and a moving one, frame by frame, beside the runtime's plain OIDN-high on the
same frames: ratios measured in the same run.
Result (docs/evaluation/oidn-floor/README.md, "Aux across frames"): rejected.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.evaluate import build_methods
from quietframe.bench.harness import RuntimeMethod
from quietframe.bench.synthetic import frame_buffers
from quietframe.bench.zoo_eval import evaluate, shot_folders
from quietframe.model.temporal import DEPTH_REL_TOLERANCE, MIN_CURRENT_WEIGHT
from quietframe.runtime.card import OIDNStage
from quietframe.runtime.denoiser import Denoiser
from quietframe.runtime.oidn_prepass import OIDNFilters, OIDNPrepass
from quietframe.runtime.registry import find_model
from quietframe.scenes.zoo_shots import ZOO_SPLITS

MODEL = "oidn-history-cleanaux"
AUX_NAMES = ("albedo", "normal")
RAW, CLEAN, DEPTH, COUNT = slice(0, 6), slice(6, 12), 12, 13  # the history's planes
COUNT_CAP = round(1 / MIN_CURRENT_WEIGHT) + 1  # its weight stops changing at this length
STILL_TOLERANCE = 0.01  # px of motion that counts as none
TILE = 32  # px: the unit of the staleness test and of the crops
MARGIN = 32  # px of context around a crop
WHOLE_FRAME_SHARE = 0.8  # crops covering more than this: prefilter the whole frame
# Tile-mean change of the raw aux beyond which a tile's history is dropped: ±0.3 of noise at a
# 1-spp edge averages to ~0.01 over a 32x32 tile.
STALE_LIMIT = 0.03

Prefilter = Callable[[Mapping[str, np.ndarray]], dict[str, np.ndarray]]


@dataclass(frozen=True)
class Policy:
    accumulate: bool  # the raw aux accumulated where still
    refresh: str  # "always", "new" (once per surface), "schedule" (new, 2, 4, 6), "halves"


POLICIES = {
    "accumulate": Policy(True, "always"),
    "reuse": Policy(False, "new"),
    "accumulate+reuse": Policy(True, "schedule"),
    "halves": Policy(False, "halves"),
}


@dataclass
class AuxStep:
    clean: dict[str, np.ndarray]  # (3, H, W) albedo and normal for the main filter
    state: np.ndarray  # (14, H, W): raw or accumulated aux 6, prefiltered aux 6, depth, length
    prefiltered: float  # share of the frame prefiltered


def step(policy: Policy, aux: Mapping[str, np.ndarray], motion: np.ndarray, depth: np.ndarray,
         previous: np.ndarray | None, frame: int, prefilter: Prefilter) -> AuxStep:
    """One frame of `policy`: `aux` the sanitised albedo and normal (3, H, W), `motion`
    (2, H, W), `depth` (H, W), `previous` the last AuxStep.state (None after a reset), `frame`
    the frame's index in the shot (for "halves")."""
    _, height, width = aux["albedo"].shape
    raw = np.concatenate([aux[name] for name in AUX_NAMES])
    still = np.abs(motion).max(axis=0) <= STILL_TOLERANCE
    if previous is None or not still.any():
        clean = np.concatenate(list(prefilter(_named(raw)).values()))
        return AuxStep(_named(clean), _state(raw, clean, depth, np.ones_like(depth)), 1.0)
    moved_surface = np.abs(depth - previous[DEPTH]) > DEPTH_REL_TOLERANCE * np.abs(depth)
    keep = still & (previous[COUNT] >= 1) & ~_opened(moved_surface)
    keep &= ~_stale_tiles(raw, previous[RAW], keep)
    count = np.where(keep, np.minimum(previous[COUNT], COUNT_CAP - 1) + 1, 1).astype(np.float32)
    accumulated = raw
    if policy.accumulate:
        alpha = np.maximum(1 / count, MIN_CURRENT_WEIGHT)
        accumulated = np.where(keep, alpha * raw + (1 - alpha) * previous[RAW], raw)
        accumulated = accumulated.astype(np.float32)
    refresh = ~keep
    if policy.refresh == "always":
        refresh = np.ones_like(keep)
    elif policy.refresh == "schedule":
        refresh |= (np.isin(count, (2, 4))
                    | ((count == COUNT_CAP) & (previous[COUNT] == COUNT_CAP - 1)))
    elif policy.refresh == "halves":
        half = np.arange(height)[:, None] < height // 2
        refresh |= np.broadcast_to(half if frame % 2 else ~half, keep.shape)
    clean = np.where(keep, previous[CLEAN], 0).astype(np.float32)
    share = _prefilter_dirty(accumulated, clean, refresh, prefilter)
    return AuxStep(_named(clean), _state(accumulated, clean, depth, count), share)


def _opened(mask: np.ndarray) -> np.ndarray:
    """`mask` less what a 3×3 square does not fit in (a morphological opening): isolated
    pixels and one- or two-pixel lines go, blobs stay."""
    return _spread(~_spread(~mask))


def _spread(mask: np.ndarray) -> np.ndarray:
    """3×3 dilation (the frame's border counts as unset)."""
    padded = np.pad(mask, 1)
    height, width = mask.shape
    out = np.zeros_like(mask)
    for dy in range(3):
        for dx in range(3):
            out |= padded[dy:dy + height, dx:dx + width]
    return out


def _named(planes: np.ndarray) -> dict[str, np.ndarray]:
    return {"albedo": planes[0:3], "normal": planes[3:6]}


def _state(raw: np.ndarray, clean: np.ndarray, depth: np.ndarray,
           count: np.ndarray) -> np.ndarray:
    return np.concatenate((raw, clean, depth[None], count[None])).astype(np.float32, copy=False)


def _tile_sums(x: np.ndarray, height: int, width: int) -> np.ndarray:
    """(C, ⌈H/TILE⌉, ⌈W/TILE⌉) sums over each tile of (C, H, W) `x` (edge tiles padded with 0)."""
    th, tw = -(-height // TILE), -(-width // TILE)
    padded = np.zeros((x.shape[0], th * TILE, tw * TILE), np.float32)
    padded[:, :height, :width] = x
    return padded.reshape(x.shape[0], th, TILE, tw, TILE).sum(axis=(2, 4))


def _stale_tiles(raw: np.ndarray, accumulated: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels of tiles whose kept pixels' raw aux left the accumulation on average
    by more than STALE_LIMIT in some channel."""
    _, height, width = raw.shape
    diff = np.where(keep, raw - accumulated, 0)
    sums = _tile_sums(diff, height, width)
    counts = _tile_sums(keep[None].astype(np.float32), height, width)[0]
    stale = (np.abs(sums).max(axis=0) > STALE_LIMIT * np.maximum(counts, 1))
    return np.repeat(np.repeat(stale, TILE, 0), TILE, 1)[:height, :width]


def _prefilter_dirty(accumulated: np.ndarray, clean: np.ndarray, refresh: np.ndarray,
                     prefilter: Prefilter) -> float:
    """Prefilter the accumulated aux where `refresh` into `clean` (in place): the tiles that
    hold such a pixel, in crops with MARGIN px of context, or the whole frame once the crops
    would cover WHOLE_FRAME_SHARE of it. Returns the share of the frame prefiltered."""
    _, height, width = accumulated.shape
    dirty = _tile_sums(refresh[None].astype(np.float32), height, width)[0] > 0
    if not dirty.any():
        return 0.0
    boxes = ([] if dirty.mean() >= WHOLE_FRAME_SHARE  # the crops' margins only add to it
             else [_crop(box, height, width) for box in _components(dirty)])
    area = sum((c[1] - c[0]) * (c[3] - c[2]) for _, c in boxes)
    if not boxes or area >= WHOLE_FRAME_SHARE * height * width:
        clean[:] = np.concatenate(list(prefilter(_named(accumulated)).values()))
        return 1.0
    for (y0, y1, x0, x1), (cy0, cy1, cx0, cx1) in boxes:
        out = prefilter(_named(np.ascontiguousarray(accumulated[:, cy0:cy1, cx0:cx1])))
        crop = np.concatenate([out[name] for name in AUX_NAMES])
        clean[:, y0:y1, x0:x1] = crop[:, y0 - cy0:y1 - cy0, x0 - cx0:x1 - cx0]
    return area / (height * width)


def _crop(box: tuple[int, int, int, int], height: int, width: int
          ) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]]:
    """(the pixels a tile box covers, that region with MARGIN px of context), clipped."""
    ty0, ty1, tx0, tx1 = box
    region = (ty0 * TILE, min(ty1 * TILE, height), tx0 * TILE, min(tx1 * TILE, width))
    y0, y1, x0, x1 = region
    return region, (max(y0 - MARGIN, 0), min(y1 + MARGIN, height),
                    max(x0 - MARGIN, 0), min(x1 + MARGIN, width))


def _components(dirty: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Bounding boxes (tile rows y0:y1, columns x0:x1) of groups of dirty tiles; tiles closer
    than two margins are grouped (their crops would overlap)."""
    reach = -(-2 * MARGIN // TILE)
    th, tw = dirty.shape
    seen = np.zeros_like(dirty)
    boxes = []
    for start in zip(*np.nonzero(dirty), strict=True):
        if seen[start]:
            continue
        seen[start] = True
        stack, box = [start], [start[0], start[0] + 1, start[1], start[1] + 1]
        while stack:
            y, x = stack.pop()
            box = [min(box[0], y), max(box[1], y + 1), min(box[2], x), max(box[3], x + 1)]
            near = dirty[max(y - reach, 0):y + reach + 1, max(x - reach, 0):x + reach + 1]
            for dy, dx in zip(*np.nonzero(near), strict=True):
                ny, nx = max(y - reach, 0) + dy, max(x - reach, 0) + dx
                if not seen[ny, nx]:
                    seen[ny, nx] = True
                    stack.append((ny, nx))
        boxes.append(tuple(box))
    return boxes


class PolicyPrepass:
    """Stands in for a Denoiser's OIDN stage: the main filter gets the aux `policy` gives.
    `frame` (the frame's planes) is set before each call; `state` None restarts the history."""

    def __init__(self, prepass: OIDNPrepass, policy: Policy) -> None:
        self.prepass, self.policy = prepass, policy
        self.frame: Mapping[str, np.ndarray] = {}
        self.state: np.ndarray | None = None
        self.index = 0
        self.shares: list[float] = []

    def __call__(self, planes: Mapping[str, np.ndarray], renderer: str | None = None,
                 filters: OIDNFilters | None = None) -> np.ndarray:
        self.index = 0 if self.state is None else self.index + 1
        result = step(self.policy, planes, self.frame["motion"], self.frame["depth"][0],
                      self.state, self.index,
                      # crops of any size: built per call (kept filters hold one frame size)
                      lambda aux: self.prepass.prefilter(aux, renderer))
        self.state = result.state
        self.shares.append(result.prefiltered)
        return self.prepass({"color": planes["color"], **result.clean}, renderer,
                            clean_aux=True, filters=filters)


class PolicyMethod(RuntimeMethod):
    """The quality tier through the runtime, its OIDN stage following `policy`."""

    def __init__(self, path: Path, threads: int, policy: Policy) -> None:
        super().__init__(Denoiser(path, threads=threads), renderer="cycles")
        self.stage = PolicyPrepass(self.denoiser.prepass, policy)
        self.denoiser.prepass = self.stage

    def __call__(self, planes):
        if self.state is None:  # a first frame, a cut, or history dropped without vectors
            self.stage.state = None
        self.stage.frame = planes
        return super().__call__(planes)


def synthetic_sequence(frames: int, locked: bool) -> list[dict[str, np.ndarray]]:
    """720p frames of a fixed random scene whose colour noise is new every frame; locked-off
    (no motion) or moving by half a pixel (every pixel new)."""
    base = frame_buffers(720, 1280, seed=0)
    rng = np.random.default_rng(1)
    motion = np.zeros_like(base["motion"]) if locked else np.full_like(base["motion"], 0.5)
    return [{**base, "motion": motion,
             "color": (base["color"] * rng.gamma(4.0, 0.25, base["color"].shape)
                       ).astype(np.float32)} for _ in range(frames)]


def timing(model: Path, policies: dict[str, Policy], threads: int, frames: int) -> dict:
    """CPU seconds per frame of the shipped stage and each policy on both synthetic sequences
    and of plain OIDN-high on the same frames, interleaved frame by frame."""
    plain = OIDNPrepass(OIDNStage(quality="high"), num_threads=threads)
    out: dict = {}
    for shot, locked in (("locked-off", True), ("moving", False)):
        methods = {"per-frame": RuntimeMethod(Denoiser(model, threads=threads),
                                              renderer="cycles"),
                   **{k: PolicyMethod(model, threads, p) for k, p in policies.items()}}
        for method in methods.values():
            method.header_spp = 4.0
        rows: dict[str, list[float]] = {k: [] for k in (*methods, "oidn-high")}
        for planes in synthetic_sequence(frames, locked):
            start = time.process_time()
            plain({k: planes[k] for k in ("color", *AUX_NAMES)}, "cycles")
            rows["oidn-high"].append(time.process_time() - start)
            for name, method in methods.items():
                start = time.process_time()
                method(planes)
                rows[name].append(time.process_time() - start)
        base = float(np.median(rows["oidn-high"]))
        out[shot] = {"oidn_high_cpu_s": base, **{
            k: {"cpu_s": v, "ratio_mean": float(np.mean(v)) / base,
                "ratio_last": v[-1] / base,
                "prefiltered": getattr(methods[k], "stage", None) and methods[k].stage.shares}
            for k, v in rows.items() if k != "oidn-high"}}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_split(p, ZOO_SPLITS)
    cli_args.add_data(p)
    p.add_argument("--spp", default="1,4,16,64")
    p.add_argument("--shots", default="", help="comma list (default: every finished shot)")
    p.add_argument("--policies", default=",".join(POLICIES))
    p.add_argument("--frames", type=int, default=8, help="frames of each timing sequence")
    cli_args.add_threads(p)
    p.add_argument("--timing-only", action="store_true")
    p.add_argument("--quality-only", action="store_true")
    cli_args.add_json(p)
    args = p.parse_args(argv)
    policies = {k: POLICIES[k] for k in args.policies.split(",")}
    model = find_model(MODEL)
    result: dict = {"threads": args.threads, "command": "python -m quietframe.experiments."
                    "aux_history " + " ".join(sys.argv[1:] if argv is None else argv)}
    if not args.quality_only:
        result["timing_720p"] = t = timing(model, policies, args.threads, args.frames)
        print("| sequence | policy | × plain OIDN-high, mean over frames | last frame | "
              "share prefiltered per frame |")
        print("|---|---|---|---|---|")
        for shot, row in t.items():
            for name in ("per-frame", *policies):
                r = row[name]
                shares = " ".join(f"{s:.2f}" for s in r["prefiltered"] or [])
                print(f"| {shot} | {name} | {r['ratio_mean']:.2f} | {r['ratio_last']:.2f} | "
                      f"{shares} |", flush=True)
    if not args.timing_only:
        spp_levels = tuple(int(s) for s in args.spp.split(","))
        folders = [f for f in shot_folders(args.data, args.split, spp_levels)
                   if not args.shots or f.name in args.shots.split(",")]
        methods = {"blender-denoise": build_methods(args.threads,
                                                    renderer="cycles")["blender-denoise"],
                   "per-frame": lambda: RuntimeMethod(model, args.threads, renderer="cycles"),
                   **{k: (lambda q=q: PolicyMethod(model, args.threads, q))
                      for k, q in policies.items()}}
        rows = evaluate(folders, spp_levels, methods, flag_cuts=True, log=lambda _: None)
        result["quality"] = rows
        report(rows, list(policies))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


def report(rows: list[dict], policies: list[str]) -> None:
    by = {(r["shot"], r["spp"], r["method"]): r for r in rows}
    print("\n| shot | spp | Blender dB | per-frame − Blender | "
          + " | ".join(f"{k} − per-frame" for k in policies) + " | flicker per-frame / "
          + " / ".join(policies) + " |")
    print("|---|---|---|---|" + "---|" * (len(policies) + 1))
    for shot, spp in dict.fromkeys((r["shot"], r["spp"]) for r in rows):
        b, a = by[(shot, spp, "blender-denoise")], by[(shot, spp, "per-frame")]
        others = [by[(shot, spp, k)] for k in policies]
        flicker = (" / ".join(f"{r['flicker']:.5f}" for r in (a, *others))
                   if a["flicker"] == a["flicker"] else "")
        print(f"| {shot} | {spp} | {b['psnr']:.2f} | {a['psnr'] - b['psnr']:+.3f} | "
              + " | ".join(f"{r['psnr'] - a['psnr']:+.3f}" for r in others)
              + f" | {flicker} |", flush=True)
    for spp in sorted({r["spp"] for r in rows}):
        shots = [shot for shot, q in dict.fromkeys((r["shot"], r["spp"]) for r in rows)
                 if q == spp]
        gains = {k: [by[(s, spp, k)]["psnr"] - by[(s, spp, "per-frame")]["psnr"] for s in shots]
                 for k in policies}
        print(f"spp {spp}: " + ", ".join(f"{k} − per-frame mean {np.mean(g):+.3f} worst "
                                         f"{min(g):+.3f}" for k, g in gains.items()))

if __name__ == "__main__":
    sys.exit(main())
