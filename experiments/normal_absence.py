"""Whether a model gains or loses from a split's normals: its PSNR with the normal buffer as the
renderer wrote it, without it (as the runtime feeds an absent optional buffer), and without
normal and albedo, per spp. A diagnostic of the normal space (Blender's camera-space normals
for models trained on Mitsuba's world-space ones, docs/data.md), not a reported quality figure:
any split may be read, including train.

    python -m quietframe.experiments.normal_absence --renderer cycles --split train
        --sequences 12 --spp 4,64 nbg-2l-3g oidn-frame
"""

from __future__ import annotations

import argparse

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.evaluate import load_sequence, sequence_dirs
from quietframe.bench.harness import Planes, RuntimeMethod, planar_frames, score_sequence
from quietframe.runtime import find_model

WITHOUT = {"as written": (), "no normal": ("normal",), "no normal, albedo": ("normal", "albedo")}


def without(names: tuple[str, ...]):
    def inputs(planes: Planes) -> Planes:
        return {k: v for k, v in planes.items() if k not in names}
    return inputs


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("models", nargs="+", help="installed model names (optional normal buffer)")
    cli_args.add_sequences(p, spp="4,64")
    p.add_argument("--sequences", type=int, default=12)
    cli_args.add_threads(p)
    args = p.parse_args(argv)
    folders = sequence_dirs(args.data, args.split, args.renderer, args.spp)[: args.sequences]
    print(f"{len(folders)} {args.renderer} {args.split} sequences; mean PSNR (dB)\n")
    print("| model | spp | " + " | ".join(WITHOUT) + " |")
    print("|---|---|" + "---|" * len(WITHOUT))
    for name in args.models:
        method = RuntimeMethod(find_model(name), threads=args.threads)
        for spp in args.spp:
            scores = {k: [] for k in WITHOUT}
            for folder in folders:
                frames = planar_frames(load_sequence(folder, spp))
                for k, names in WITHOUT.items():
                    scores[k].append(score_sequence(method, frames, inputs=without(names))
                                     .mean("psnr"))
            print(f"| {name} | {spp} | "
                  + " | ".join(f"{np.mean(v):.2f}" for v in scores.values()) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
