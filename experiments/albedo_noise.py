"""How much of the learned tiers' error is the noise of the aux buffers they are given, and how
much of it does a blurred albedo win back?

    python -m quietframe.experiments.albedo_noise --zoo corpus --split validation
        [--shots A,B] [--spp 1,4,16,64] [--models nbg-2l-3g,affinity-h16-k5gc]
        [--variants clean-aux,clean-albedo,...] [--json F]

Each shipped model runs every shot as the service runs it (bench/harness.RuntimeMethod, the
header's spp), once on the input render's own buffers and once per variant, where one or more
aux buffers are replaced:

- `clean-aux`, `clean-albedo`, `clean-normal`, `clean-depth`: that buffer (or all three) from
  the reference's first half (reference_a, hundreds of samples: an upper bound no renderer
  sends);
- `aux64`: albedo, normal and depth from the 64-spp render of the same frame;
- `blur:<σ₁>:<exponent>`: the albedo blurred by a Gaussian of σ₁ · spp^(-exponent) px, by
  model/albedo_prefilter.albedo_blur (what the tiers do with NBGConfig /
  AffinityConfig.albedo_prefilter on); a model that blurs already gets it on top.

Prints each (shot, spp, model) row's PSNR per variant, then per model and spp the mean and worst
change against the input's buffers. The finding behind the albedo prefilter: docs/training.md,
"The albedo's own noise".
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from quietframe.bench import cli_args
from quietframe.bench.evaluate import Scores, give_header_spp, load_sequence, run_sequence
from quietframe.bench.harness import RuntimeMethod, planar_frames
from quietframe.bench.zoo_eval import CORPUS, shot_folders
from quietframe.model.albedo_prefilter import RADIUS, albedo_blur
from quietframe.scenes import cycles_io

CLEAN = {"clean-aux": ("albedo", "normal", "depth"), "clean-albedo": ("albedo",),
         "clean-normal": ("normal",), "clean-depth": ("depth",)}
DEFAULT_VARIANTS = "clean-aux,clean-albedo,clean-normal,clean-depth,aux64"

Buffers = dict[str, np.ndarray]


def blurred(sigma: float, exponent: float) -> Callable[[np.ndarray, int], np.ndarray]:
    """The albedo ((H, W, 3)) blurred as the tiers' prefilter does at `spp`."""

    def blur(albedo: np.ndarray, spp: int) -> np.ndarray:
        planar = torch.from_numpy(np.ascontiguousarray(albedo.transpose(2, 0, 1)))[None]
        out = albedo_blur(planar, torch.tensor([float(spp)]), sigma, exponent, RADIUS)
        return out[0].numpy().transpose(1, 2, 0)

    return blur


def variant_frames(name: str, frames: list, clean: list[Buffers], aux64: list | None,
                   spp: int) -> list:
    """The sequence's (buffers, reference, reset) frames with the variant's buffers replaced."""
    out = []
    for t, (buffers, reference, reset) in enumerate(frames):
        changed = dict(buffers)
        if name in CLEAN:
            changed |= {k: clean[t][k] for k in CLEAN[name] if k in clean[t]}
        elif name == "aux64":
            changed |= {k: aux64[t][0][k] for k in ("albedo", "normal", "depth")}
        else:
            _, sigma, exponent = name.split(":")
            changed["albedo"] = blurred(float(sigma), float(exponent))(buffers["albedo"], spp)
        out.append((changed, reference, reset))
    return out


def score(model: Path, frames: list, spp: int, threads: int) -> float:
    """Mean PSNR of the model over the sequence, its history restarting at the first frame."""
    planar = [(p, r, i == 0) for i, (p, r, _) in enumerate(planar_frames(frames))]
    method = RuntimeMethod(model, threads=threads, renderer="cycles")
    give_header_spp(method, "cycles", spp)
    scores = Scores()
    run_sequence(method, planar, scores, None, False)
    return scores.summary()["psnr"]


def run_shot(folder: Path, spp_levels: tuple[int, ...], models: list[str], variants: list[str],
             threads: int, log=print) -> list[dict]:
    count = len(cycles_io.frame_resets(folder))
    clean = [cycles_io.load_reference_aux(folder, t) for t in range(count)]
    aux64 = load_sequence(folder, 64) if "aux64" in variants else None
    rows = []
    for spp in spp_levels:
        frames = load_sequence(folder, spp)
        for model in models:
            path = Path("models") / f"{model}.onnx" if "/" not in model else Path(model)
            row = {"shot": folder.name, "spp": spp, "model": path.stem,
                   "input": round(score(path, frames, spp, threads), 3)}
            for name in variants:
                row[name] = round(score(path, variant_frames(name, frames, clean, aux64, spp),
                                        spp, threads), 3)
            rows.append(row)
            log(json.dumps(row))
    return rows


def summary(rows: list[dict], variants: list[str]) -> list[str]:
    lines = []
    for model in dict.fromkeys(r["model"] for r in rows):
        for spp in dict.fromkeys(r["spp"] for r in rows):
            mine = [r for r in rows if r["model"] == model and r["spp"] == spp]
            cells = []
            for name in variants:
                change = [r[name] - r["input"] for r in mine]
                cells.append(f"{name} {np.mean(change):+.2f} (worst {min(change):+.2f})")
            lines.append(f"{model} {spp:>3} spp over {len(mine)} shots: " + ", ".join(cells))
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    cli_args.add_zoo_shots(p, also=(CORPUS,))
    p.add_argument("--spp", type=cli_args.spp_levels, default="1,4,16,64")
    p.add_argument("--models", default="nbg-2l-3g,affinity-h16-k5gc",
                   help="shipped model names or .onnx paths")
    p.add_argument("--variants", default=DEFAULT_VARIANTS,
                   help="clean-aux, clean-albedo, clean-normal, clean-depth, aux64, "
                        "blur:<sigma at 1 spp>:<exponent>")
    cli_args.add_threads(p)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    variants = args.variants.split(",")
    folders = [f for f in shot_folders(args.data, args.split, args.spp, args.zoo)
               if not args.shots or f.name in args.shots]
    if not folders:
        raise SystemExit(f"no finished {args.zoo} {args.split} shots under {args.data}")
    rows = []
    for folder in folders:
        rows += run_shot(folder, args.spp, args.models.split(","), variants, args.threads)
    lines = summary(rows, variants)
    print("\n".join(lines))
    if args.json:
        args.json.write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows,
                                         "summary": lines}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
