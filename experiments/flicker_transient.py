"""How much of a locked-off shot's flicker is the history's start-up (the flicker target: at
most 0.5× per-frame OIDN's).

    python -m quietframe.experiments.flicker_transient --split validation-static
        [--renderer mitsuba] [--spp 4,16,64] [--methods oidn-history,oidn-acc] [--settle 3]
        [--json out.json]

A history starts empty at a shot's first frame, so there every temporal tier returns what
per-frame OIDN does, and its output then moves towards the converged image over the frames the
history takes to fill (1/n weights up to n = 5, model/temporal.history_weights). The flicker
metric (model/metrics.flicker: the temporal standard deviation of τ(output) over the whole shot)
counts that settling as flicker, and on the splits' 8-frame shots it weighs as much as the
steady state a long shot would show. This prints per spp, as ratios to the base method's
(`oidn-frame`) over the same frames:

- `all`: the flicker the evaluation scores (every frame);
- `settled`: over frames `--settle` onwards, once the history holds several frames;
- `one history, iid`: what one history with the shipped weights leaves of frames with
  independent errors over the whole shot (the ratio for a denoiser whose output error were
  independent per frame and unbiased: the floor the settling adds nothing to).

No reference is needed: on a locked-off shot the true image is constant.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch

from quietframe.bench import cli_args
from quietframe.bench.evaluate import (
    _inputs,
    build_methods,
    give_header_spp,
    load_sequence,
    sequence_dirs,
)
from quietframe.bench.harness import planar_frames, score_sequence
from quietframe.model import metrics
from quietframe.model.temporal import history_weights

BASE = "oidn-frame"


def one_history_ratio(frames: int) -> float:
    """sqrt(E[temporal variance] of one history of iid unit frames ÷ that of the frames): the
    history's output o_t = Σ_s W[t, s] x_s, and a sample variance about the shot's mean is
    x^T M^T C M x / T with C = I - 11^T/T, so its expectation is trace(M^T C M) / T."""
    weights = np.zeros((frames, frames))
    count = torch.zeros(1)
    for t in range(frames):
        alpha, count = history_weights(torch.ones(1) if t else torch.zeros(1), count)
        a = float(alpha)
        if t:
            weights[t] = (1 - a) * weights[t - 1]
        weights[t, t] = a
    centre = np.eye(frames) - 1.0 / frames
    return float(np.sqrt(np.trace(weights.T @ centre @ weights) / (frames - 1)))


def flicker_ratio(outputs: dict[str, list[np.ndarray]], name: str, first: int) -> float:
    """`name`'s mean flicker over its shots from frame `first` on, ÷ the base method's."""
    def mean_flicker(shots: list[np.ndarray]) -> float:
        return float(np.mean([metrics.flicker(o[first:]) for o in shots]))
    return mean_flicker(outputs[name]) / mean_flicker(outputs[BASE])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    cli_args.add_sequences(p, spp="4,16,64")
    p.add_argument("--methods", default="oidn-history,oidn-fast-history,oidn-acc")
    p.add_argument("--settle", type=int, default=3, help="first frame of the settled figure")
    cli_args.add_threads(p)
    cli_args.add_json(p)
    args = p.parse_args(argv)
    names = [BASE, *args.methods.split(",")]
    factories = build_methods(args.threads, renderer=args.renderer)
    unknown = [n for n in names if n not in factories]
    if unknown:
        print(f"unknown methods {unknown}; known: {sorted(factories)}", file=sys.stderr)
        return 2
    folders = sequence_dirs(args.data, args.split, args.renderer, args.spp)
    if not folders:
        print(f"no sequences in {args.split} ({args.renderer}) under {args.data}", file=sys.stderr)
        return 1
    rows = []
    for spp in args.spp:
        outputs: dict[str, list[np.ndarray]] = {n: [] for n in names}
        for folder in folders:
            frames = planar_frames(load_sequence(folder, spp))
            for name in names:
                method = factories[name]()
                give_header_spp(method, args.renderer, spp)
                score = score_sequence(method, frames, (), inputs=_inputs)
                outputs[name].append(np.stack(score.outputs))
        frames_per_shot = outputs[BASE][0].shape[0]

        rows.append({"spp": spp, "frames": frames_per_shot,
                     "one_history_iid": one_history_ratio(frames_per_shot),
                     **{name: {"all": flicker_ratio(outputs, name, 0),
                               "settled": flicker_ratio(outputs, name, args.settle)}
                        for name in names[1:]}})
    print(f"{args.renderer} {args.split}: {len(folders)} locked-off shot(s); flicker ÷ {BASE}'s "
          f"over all frames / from frame {args.settle} on\n")
    print("| spp | " + " | ".join(names[1:]) + " | one history, iid (all) |")
    print("|---" * (len(names) + 1) + "|")
    for r in rows:
        cells = [f"{r[n]['all']:.2f} / {r[n]['settled']:.2f}" for n in names[1:]]
        print(f"| {r['spp']} | " + " | ".join(cells) + f" | {r['one_history_iid']:.2f} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
