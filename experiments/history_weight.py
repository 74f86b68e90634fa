"""Ablation for oidn-history v2: where the output history is resampled, how much of
it to keep. The shipped rule is a weight floor from the frame's spp (model/output_history.py,
w(spp)); this bench scores it against the alternatives that need no spp, in one run:

    python -m quietframe.experiments.history_weight --renderer cycles [--spp 1,2,4,8,16,64]
        [--json rows.json]

Rows (each over the same cached per-frame base: the pixel-aligned accumulation then OIDN-high,
what `oidn-history` composes, so only the history rule differs):
- `w0.5`: the constant floor v1 shipped;
- `w(spp)`: the shipped schedule, given the spp the Cycles header states;
- `w(frame noise)`: the floor from a statistic of the frame itself, g = log2(mean |C - D| /
  mean D) (C the noisy colour, D OIDN's output), mapped linearly so that the validation
  median of g at 1 and 64 spp gives the schedule's weights there (fit below, FRAME_NOISE_FIT);
- `w(local noise)`: the same statistic in 9×9 windows, per pixel;
- `varclip γ`: the schedule, with the fetched history clipped to mean ± γ·σ of the frame's
  3×3 neighbourhood of D instead of its min/max.
Every row is scored against the references like quietframe-eval (PSNR, TRMAE).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch
import torch.nn.functional as F

from quietframe.bench import cli_args
from quietframe.bench.evaluate import (
    Scores,
    give_header_spp,
    load_sequence,
    run_sequence,
    sequence_dirs,
)
from quietframe.bench.harness import planar_frames
from quietframe.experiments.output_history import RUNTIME_BUFFERS, PreStage
from quietframe.model.output_history import OutputHistoryConfig, clamp_to_neighbourhood
from quietframe.model.temporal import (
    HISTORY_LENGTH,
    MIN_CURRENT_WEIGHT,
    RADIANCE,
    backward_warp,
    history_weights,
    pixel_aligned,
    reproject_history,
)
from quietframe.runtime.oidn_prepass import OIDNPrepass, OIDNSettings
from quietframe.runtime.sanitize import sanitize_buffer

# (a, b) of floor = a + b·g: the median g on the Cycles validation split is +0.56 at 1 spp and
# -2.10 at 64 spp, where the schedule gives 0.35 and 0.80.
FRAME_NOISE_FIT = (0.445, -0.17)
LOCAL_WINDOW = 9


def frame_key(planes: dict) -> int:
    return planes["color"].ctypes.data  # the same frame arrays for every row of one spp


def base_outputs(sequences, oidn) -> tuple[dict, dict, dict]:
    """Per frame of the sequences (by frame_key): OIDN on the pixel-aligned accumulation (the
    history tiers' base, what `oidn-history` composes), OIDN on the frame alone (oidn-frame),
    and the sanitised noisy colour. One OIDN pass per frame, shared by every row."""
    base, frame, noisy = {}, {}, {}
    for frames in sequences:
        pre = PreStage(aligned_only=True)
        for planes, _, reset in frames:
            if reset:
                pre.reset()
            clean = {k: sanitize_buffer(k, planes[k])[0] for k in RUNTIME_BUFFERS}
            accumulated = np.ascontiguousarray(pre(clean), np.float32)
            base[frame_key(planes)] = oidn({**clean, "color": accumulated})[0]
            frame[frame_key(planes)] = oidn(clean)[0]
            noisy[frame_key(planes)] = clean["color"]
    return base, frame, noisy


class Cached:
    """A per-frame 'method' returning the cached base output of the frame."""

    def __init__(self, table: dict) -> None:
        self.table = table

    def reset(self) -> None:
        pass

    def __call__(self, planes: dict) -> np.ndarray:
        return self.table[frame_key(planes)]


def noise_log2(colour: torch.Tensor, denoised: torch.Tensor, local: bool) -> torch.Tensor:
    """log2 of |C - D| over D: frame-wide (a scalar) or per pixel in LOCAL_WINDOW windows."""
    if not local:
        return torch.log2((colour - denoised).abs().mean() / (denoised.mean() + 1e-3))
    k = LOCAL_WINDOW
    num = F.avg_pool2d((colour - denoised).abs().mean(1, keepdim=True), k, 1, k // 2,
                       count_include_pad=False)
    den = F.avg_pool2d(denoised.mean(1, keepdim=True), k, 1, k // 2, count_include_pad=False)
    return torch.log2(num / (den + 1e-3))


def variance_clip(previous: torch.Tensor, current: torch.Tensor, gamma: float) -> torch.Tensor:
    mean = F.avg_pool2d(current, 3, 1, 1, count_include_pad=False)
    square = F.avg_pool2d(current * current, 3, 1, 1, count_include_pad=False)
    sigma = (square - mean * mean).clamp_min(0).sqrt()
    return torch.minimum(torch.maximum(previous, mean - gamma * sigma), mean + gamma * sigma)


class HistoryRule:
    """The output-history stage over the cached base with one floor rule (module docstring):
    `floor` is "constant", "spp", "frame" or "local"; `gamma` > 0 clips by variance."""

    def __init__(self, base: dict, noisy: dict, floor: str, weight: float = 0.5,
                 gamma: float = 0.0) -> None:
        self.base, self.noisy, self.floor = base, noisy, floor
        self.weight, self.gamma = weight, gamma
        self.config = OutputHistoryConfig()
        self.header_spp: float | None = None
        self.state: torch.Tensor | None = None

    def reset(self) -> None:
        self.state = None

    def _floor(self, current: torch.Tensor, planes: dict) -> torch.Tensor | float:
        if self.floor == "constant":
            return self.weight
        if self.floor == "spp":
            spp = self.header_spp if self.header_spp is not None else self.config.default_spp
            return self.config.resampled_floor(torch.tensor([float(spp)]))
        colour = torch.from_numpy(self.noisy[frame_key(planes)])[None]
        a, b = FRAME_NOISE_FIT
        return (a + b * noise_log2(colour, current, self.floor == "local")).clamp(
            self.config.resampled_weight, self.config.resampled_weight_max)

    def __call__(self, planes: dict) -> np.ndarray:
        current = torch.from_numpy(self.base[frame_key(planes)])[None]
        depth = torch.from_numpy(planes["depth"])[None]
        normal = torch.from_numpy(planes["normal"])[None]
        motion = torch.from_numpy(planes["motion"])[None]
        if self.state is None:
            out, count = current, torch.ones_like(depth)
        else:
            warped, keep = reproject_history(self.state, motion, depth, normal, torch.zeros(1))
            fetched = backward_warp(self.state[:, RADIANCE], motion, mode="bicubic")[0].clamp_min(0)
            fetched = (variance_clip(fetched, current, self.gamma) if self.gamma
                       else clamp_to_neighbourhood(fetched, current))
            exact = pixel_aligned(motion).to(current.dtype)
            previous = fetched + exact * (warped[:, RADIANCE] - fetched)
            alpha, count = history_weights(keep, warped[:, HISTORY_LENGTH])
            alpha = torch.maximum(alpha, exact * MIN_CURRENT_WEIGHT)
            alpha = torch.maximum(alpha, (1 - exact) * self._floor(current, planes))
            out = current + (1 - alpha) * (previous - current)
        self.state = torch.cat((out, depth, normal, count), 1)
        return out[0].numpy()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    cli_args.add_sequences(p, spp="1,2,4,8,16,64")
    cli_args.add_threads(p)
    cli_args.add_json(p)
    args = p.parse_args(argv)
    folders = sequence_dirs(args.data.expanduser(), args.split, args.renderer, args.spp)
    if not folders:
        print(f"no finished {args.renderer} {args.split} sequences", file=sys.stderr)
        return 1
    oidn = OIDNPrepass(OIDNSettings("high", False), args.threads)
    rows = []
    for spp in args.spp:
        sequences = [planar_frames(load_sequence(f, spp)) for f in folders]
        base, frame, noisy = base_outputs(sequences, oidn)
        methods = {
            "oidn-frame": Cached(frame),
            "w0.5": HistoryRule(base, noisy, "constant", 0.5),
            "w(spp)": HistoryRule(base, noisy, "spp"),
            "w(frame noise)": HistoryRule(base, noisy, "frame"),
            "w(local noise)": HistoryRule(base, noisy, "local"),
            "w(spp)+varclip 1.0": HistoryRule(base, noisy, "spp", gamma=1.0),
            "w(spp)+varclip 1.5": HistoryRule(base, noisy, "spp", gamma=1.5),
        }
        for name, method in methods.items():  # reset() by every sequence's scoring
            scores = Scores()
            give_header_spp(method, args.renderer, spp)
            for frames in sequences:
                run_sequence(method, frames, scores)
            rows.append({"method": name, "spp": spp, **scores.summary()})
    base_rows = {r["spp"]: r for r in rows if r["method"] == "oidn-frame"}
    print(f"{args.renderer} {args.split}: {len(folders)} sequence(s); Δ PSNR to oidn-frame\n")
    print("| row | " + " | ".join(f"{s}" for s in args.spp) + " spp | worst |")
    print("|---" * (len(args.spp) + 2) + "|")
    for name in dict.fromkeys(r["method"] for r in rows):
        delta = [r["psnr"] - base_rows[r["spp"]]["psnr"] for r in rows if r["method"] == name]
        print(f"| {name} | " + " | ".join(f"{d:+.2f}" for d in delta) + f" | {min(delta):+.2f} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
