"""Does a renderer sample the same point of a still pixel in every frame, and what does the mean
of such frames converge to?

    python -m quietframe.experiments.repeated_samples --zoo zoo2 --split validation
        --shots fence-locked,studio-locked [--spp 1,4,16,64] [--frames 24] [--json F]

For each locked-off shot and spp: the share of surface pixels (normal not 0) whose depth and
normal equal the previous frame's to the last bit (the property model/temporal.repeated_sample
tests in the aligned accumulation, there to 1e-6; its surface test never keeps the background),
and the PSNR (tone-mapped, model/metrics) against the reference of the mean colour of the first
1, 4 and `frames` frames. Frames with independent samples converge towards the reference as
their count grows; frames that repeat their one sample a pixel converge to that point sample,
an aliased image of thin geometry and fine texture. Cycles 4.5 repeats at 1 spp (the seed is
animated, yet every frame's one sample of a still pixel lands on the same point): the finding
behind version 3 of the aligned accumulation (docs/zoo.md "Repeated samples").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.model import metrics
from quietframe.scenes import cycles_io
from quietframe.scenes.zoo_shots import zoo_dir


def repeated_share(previous: dict, frame: dict) -> float:
    """Share of the surface pixels (normal not 0) whose depth and normal equal `previous`'s to
    the last bit ((H, W, C) planes as cycles_io loads them)."""
    surface = np.abs(frame["normal"]).max(axis=-1) > 0
    same = ((previous["depth"][..., 0] == frame["depth"][..., 0])
            & (previous["normal"] == frame["normal"]).all(axis=-1))
    return float(same[surface].mean()) if surface.any() else float("nan")


def mean_psnr(colours: list[np.ndarray], reference: np.ndarray, counts: tuple[int, ...]
              ) -> dict[int, float]:
    """PSNR of the mean of the first n colours against `reference`, for each n of `counts`."""
    return {n: metrics.psnr(np.mean(colours[:n], axis=0), reference)
            for n in counts if n <= len(colours)}


def run_shot(folder: Path, spp: int, frames: int) -> dict:
    loaded = [cycles_io.load_frame(folder, t, spp) for t in range(frames)]
    shares = [repeated_share(a, b) for a, b in zip(loaded, loaded[1:], strict=False)]
    psnr = mean_psnr([f["color"] for f in loaded], loaded[0]["reference"], (1, 4, frames))
    return {"shot": folder.name, "spp": spp, "repeated_share": float(np.mean(shares)),
            "mean_psnr": {str(n): round(v, 2) for n, v in psnr.items()}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default="~/.cache/quietframe/data")
    p.add_argument("--zoo", default="zoo2")
    p.add_argument("--split", default="validation")
    p.add_argument("--shots", required=True, help="comma-separated locked-off shots")
    p.add_argument("--spp", type=cli_args.spp_levels, default="1,4,16,64")
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    root = zoo_dir(args.data, args.split, args.zoo)
    rows = []
    for shot in args.shots.split(","):
        for spp in args.spp:
            row = run_shot(root / shot.strip(), spp, args.frames)
            rows.append(row)
            means = ", ".join(f"{n} frames {v:.2f} dB" for n, v in row["mean_psnr"].items())
            print(f"{row['shot']} {spp:>3} spp: aux repeated at {row['repeated_share']:.1%} "
                  f"of the surface pixels; mean colour of {means}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows},
                                        indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
