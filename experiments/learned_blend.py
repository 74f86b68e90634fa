"""Ablation: a learned per-pixel blend (model/learned_blend.py, Işık et al. eq. 5's
λ) against the shipped hand rule of `oidn-history`, trained on both renderers' train splits and
scored on their test splits beside per-frame OIDN, in one run:

    python -m quietframe.experiments.learned_blend [--steps 1500]
        [--out docs/evaluation/learned-blend]

Every row shares one cached base per frame, as experiments/history_weight.py's: the pixel-aligned
accumulation then OIDN-high (what `oidn-history` composes), so only the blend differs:
- `oidn-frame`: OIDN-high on the frame alone (the temporal tiers' floor);
- `rule`: the shipped stage (model/output_history.OutputHistory; the untrained blend, whose
  correction is zero, computes exactly it);
- `learned`: the trained blend.
The spp the blend sees is what the service gives it: the header's on Cycles, the default on
Mitsuba (bench/evaluate.HEADER_STATES_SPP), in training as in scoring. Training data: the Cycles
train split (1-64 spp) and the Mitsuba train slice (1-8 spp), 4-frame windows, random crops;
the final step is kept (no test-split selection). A result here is an ablation row; shipping a
learned blend would need its validation tables like any model.
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from quietframe.bench import cli_args
from quietframe.bench.evaluate import (
    HEADER_STATES_SPP,
    Scores,
    load_sequence,
    run_sequence,
    sequence_dirs,
)
from quietframe.bench.harness import planar_frames
from quietframe.experiments.history_weight import Cached, base_outputs, frame_key
from quietframe.experiments.output_history import ShippedStage
from quietframe.model.learned_blend import LearnedBlendHistory
from quietframe.model.losses import tonemap_tau
from quietframe.runtime.oidn_prepass import OIDNPrepass, OIDNSettings

WINDOW = 4  # frames unrolled per training item (the Cycles train split's sequence length)
TEMPORAL_WEIGHT = 0.25  # of the τ-MSE of frame differences (steadiness; Işık et al. eq. 13)


@dataclass
class Item:
    """One sequence at one spp: per-frame tensors (T, C, H, W) and the spp the blend is given."""

    base: torch.Tensor  # OIDN on the pixel-aligned accumulation
    albedo: torch.Tensor
    normal: torch.Tensor
    depth: torch.Tensor
    motion: torch.Tensor
    reference: torch.Tensor
    resets: list[bool]
    spp: float | None


def gather(folders: list[Path], levels: tuple[int, ...], header_spp: bool, oidn) -> list[Item]:
    """Training items of a split: every sequence at every spp level."""
    items = []
    for folder in folders:
        for spp in levels:
            frames = planar_frames(load_sequence(folder, spp))
            base, _, _ = base_outputs([frames], oidn)
            planes = [p for p, _, _ in frames]
            stack = {k: torch.from_numpy(np.stack([p[k] for p in planes]))
                     for k in ("albedo", "normal", "depth", "motion")}
            items.append(Item(
                torch.from_numpy(np.stack([base[frame_key(p)] for p in planes])),
                stack["albedo"], stack["normal"], stack["depth"], stack["motion"],
                torch.from_numpy(np.stack([r.transpose(2, 0, 1) for _, r, _ in frames])),
                [r for _, _, r in frames], float(spp) if header_spp else None))
    return items


def batch(items: list[Item], size: int, crop: int, rng: random.Random) -> list[dict]:
    """`size` random 4-frame windows, each cropped to `crop`² at a random place, stacked per
    frame: [{name: (B, C, crop, crop)}] × WINDOW, `reset` (B,) 1 on each window's first frame
    and at a cut inside it."""
    picked = []
    for item in rng.choices(items, k=size):
        t0 = rng.randrange(len(item.resets) - WINDOW + 1)
        h, w = item.base.shape[-2:]
        y, x = rng.randrange(h - crop + 1), rng.randrange(w - crop + 1)
        window = slice(t0, t0 + WINDOW)
        resets = [t == 0 or item.resets[t0 + t] for t in range(WINDOW)]  # a cut inside too
        picked.append({k: getattr(item, k)[window, :, y:y + crop, x:x + crop]
                       for k in ("base", "albedo", "normal", "depth", "motion", "reference")}
                      | {"spp": item.spp, "reset": resets})
    frames = []
    for t in range(WINDOW):
        frames.append({k: torch.stack([p[k][t] for p in picked])
                       for k in ("base", "albedo", "normal", "depth", "motion", "reference")}
                      | {"spp": torch.tensor([p["spp"] or 0.0 for p in picked]),
                         "reset": torch.tensor([float(p["reset"][t]) for p in picked])})
    return frames


def unrolled_loss(model: LearnedBlendHistory, frames: list[dict]) -> torch.Tensor:
    """τ-MSE of every frame after the first (which has no history to blend) plus the weighted
    τ-MSE of consecutive frames' differences (not across a cut), through the unrolled
    history."""
    first = frames[0]
    state = model.initial_state(*first["base"].shape[:1], *first["base"].shape[-2:])
    outputs = []
    for f in frames:
        # spp 0 marks "not given" (Mitsuba): the default, as the service runs the tier there
        spp = torch.where(f["spp"] > 0, f["spp"], model.rule.config.default_spp)
        out, state = model(f["base"], f["albedo"], f["normal"], f["depth"], f["motion"],
                           f["reset"], state, spp)
        outputs.append(out)
    loss, previous = 0.0, None
    for t, (out, f) in enumerate(zip(outputs, frames, strict=True)):
        tau_out, tau_ref = tonemap_tau(out), tonemap_tau(f["reference"])
        if t > 0:
            loss = loss + (tau_out - tau_ref).square().mean()
            continuing = (1 - f["reset"]).view(-1, 1, 1, 1)  # no frame difference across a cut
            change = (tau_out - previous[0]) - (tau_ref - previous[1])
            loss = loss + TEMPORAL_WEIGHT * (continuing * change.square()).mean()
        previous = (tau_out, tau_ref)
    return loss / (len(frames) - 1)


def train(model: LearnedBlendHistory, items: list[Item], steps: int, seed: int, lr: float,
          size: int, crop: int, log: list[dict]) -> None:
    rng = random.Random(seed)
    torch.manual_seed(seed)
    optimizer = torch.optim.Adam(model.net.parameters(), lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps, eta_min=lr * 0.05)
    start = time.time()
    for step in range(1, steps + 1):
        loss = unrolled_loss(model, batch(items, size, crop, rng))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
        if step % 50 == 0 or step == steps:
            log.append({"step": step, "loss": loss.item(), "s": round(time.time() - start, 1)})
            print(f"step {step}: loss {loss.item():.6f} ({log[-1]['s']} s)", flush=True)


def score(models: dict[str, LearnedBlendHistory], folders: list[Path], levels, header_spp,
          oidn, renderer: str) -> list[dict]:
    """Rows (method, spp, PSNR, SSIM, TRMAE, ...) of oidn-frame and each blend on a split."""
    rows = []
    for spp in levels:
        sequences = [planar_frames(load_sequence(f, spp)) for f in folders]
        base, frame, _ = base_outputs(sequences, oidn)
        methods = {"oidn-frame": Cached(frame)}
        for name, model in models.items():
            methods[name] = ShippedStage(Cached(base), stage=model)
            methods[name].header_spp = float(spp) if header_spp else None
        for name, method in methods.items():
            scores = Scores()
            for frames in sequences:
                run_sequence(method, frames, scores)
            rows.append({"renderer": renderer, "method": name, "spp": spp,
                         **scores.summary()})
    return rows


def table(rows: list[dict], renderer: str) -> str:
    """Markdown: per method, PSNR and its difference to oidn-frame, then TRMAE ÷ oidn-frame's."""
    rows = [r for r in rows if r["renderer"] == renderer]
    levels = sorted({r["spp"] for r in rows})
    by = {(r["method"], r["spp"]): r for r in rows}
    lines = ["| method | " + " | ".join(f"{s} spp" for s in levels) + " | TRMAE ÷ oidn-frame |",
             "|---" * (len(levels) + 2) + "|"]
    for name in dict.fromkeys(r["method"] for r in rows):
        cells = []
        for s in levels:
            r, b = by[(name, s)], by[("oidn-frame", s)]
            cells.append(f"{r['psnr']:.2f} ({r['psnr'] - b['psnr']:+.2f})")
        ratios = [by[(name, s)]["trmae"] / by[("oidn-frame", s)]["trmae"] for s in levels]
        lines.append(f"| {name} | " + " | ".join(cells)
                     + f" | {min(ratios):.2f}–{max(ratios):.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    cli_args.add_data(p)
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--crop", type=int, default=80)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--width", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    cli_args.add_threads(p)
    p.add_argument("--train-sequences", type=int, default=0,
                   help="per renderer, the first N train sequences only (0: all)")
    p.add_argument("--test-sequences", type=int, default=0,
                   help="per renderer, the first N test sequences only (0: all)")
    p.add_argument("--out", type=Path, default=Path("docs/evaluation/learned-blend"))
    args = p.parse_args(argv)
    data = args.data.expanduser()
    torch.set_num_threads(args.threads)
    oidn = OIDNPrepass(OIDNSettings("high", False), args.threads)
    splits = {  # renderer: (train spp levels, test spp levels)
        "cycles": ((1, 2, 4, 8, 16, 64), (1, 2, 4, 8, 16, 64)),
        "mitsuba": ((1, 2, 4, 8), (1, 2, 4, 8, 16)),
    }
    items = []
    for renderer, (levels, _) in splits.items():
        folders = sequence_dirs(data, "train", renderer, levels)
        folders = folders[:args.train_sequences or None]
        if not folders:
            print(f"no {renderer} train sequences under {data}", file=sys.stderr)
            return 1
        items += gather(folders, levels, renderer in HEADER_STATES_SPP, oidn)
        print(f"{renderer} train: {len(folders)} sequences", flush=True)
    model = LearnedBlendHistory(width=args.width)
    log: list[dict] = []
    train(model, items, args.steps, args.seed, args.lr, args.batch, args.crop, log)
    args.out.mkdir(parents=True, exist_ok=True)
    torch.save(model.net.state_dict(), args.out / "blend_net.pt")
    rule = LearnedBlendHistory(width=args.width)  # untrained: the shipped rule
    rows = []
    for renderer, (_, levels) in splits.items():
        folders = sequence_dirs(data, "test", renderer, levels)[:args.test_sequences or None]
        rows += score({"rule": rule, "learned": model}, folders, levels,
                      renderer in HEADER_STATES_SPP, oidn, renderer)
        print(f"\n{renderer} test ({len(folders)} sequences), PSNR (Δ to oidn-frame):\n")
        print(table(rows, renderer), flush=True)
    meta = {"command": "python -m quietframe.experiments.learned_blend "
                       + " ".join(sys.argv[1:] if argv is None else argv),
            "train_items": len(items), "args": {k: str(v) for k, v in vars(args).items()}}
    (args.out / "rows.json").write_text(json.dumps({"meta": meta, "log": log, "rows": rows},
                                                   indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
