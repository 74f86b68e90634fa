"""OIDN on the frame vs OIDN on the reprojected accumulation of the noisy colour (the input
oidn-temporal-acc's prepass gets), per spp: PSNR / TRMAE against the references.

    python -m quietframe.experiments.oidn_accumulated [--split validation] [--spp 1,2,4,8]
        [--accumulation models/accumulation.onnx] [--quality high] [--threads 2]

Both through the shipped code: the accumulation model through the runtime (`Denoiser`, state
carried, reset at cuts), OIDN through the runtime's prepass (`bench.baselines.OIDNDenoiser`).
`--accumulation` takes another export (e.g. `git show a52faac:models/accumulation.onnx`, the
version with the firefly clamp) to compare.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.baselines import OIDNDenoiser
from quietframe.bench.evaluate import load_sequence, sequence_dirs
from quietframe.bench.harness import ImageMethod, RuntimeMethod, planar_frames, score_sequence
from quietframe.models import MODELS_DIR


class OIDNOnAccumulation:
    """OIDN given the accumulation's output as its colour (what oidn-temporal's prepass sees)."""

    def __init__(self, accumulation: RuntimeMethod, oidn: ImageMethod) -> None:
        self.accumulation, self.oidn = accumulation, oidn

    def reset(self) -> None:
        self.accumulation.reset()

    def __call__(self, planes: dict[str, np.ndarray]) -> np.ndarray:
        return self.oidn({**planes, "color": self.accumulation(planes)})


def compare(folders: list[Path], spp: int, accumulation: Path, oidn: OIDNDenoiser,
            threads: int) -> dict[str, tuple[float, float]]:
    """Method -> (mean PSNR over frames, mean TRMAE over sequences), each method scored by the
    harness's one loop."""
    methods = {
        "oidn": lambda: ImageMethod(oidn),
        "accumulation": lambda: RuntimeMethod(accumulation, threads),
        "oidn(accumulation)": lambda: OIDNOnAccumulation(RuntimeMethod(accumulation, threads),
                                                         ImageMethod(oidn)),
    }
    psnr: dict[str, list[float]] = {k: [] for k in methods}
    trmae: dict[str, list[float]] = {k: [] for k in methods}
    for folder in folders:
        frames = planar_frames(load_sequence(folder, spp))
        for name, make in methods.items():
            score = score_sequence(make(), frames)
            psnr[name] += score.per_frame["psnr"]
            trmae[name].append(score.trmae)
    return {k: (float(np.mean(psnr[k])), float(np.mean(trmae[k]))) for k in psnr}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    cli_args.add_data(parser)
    cli_args.add_split(parser)
    parser.add_argument("--spp", default="1,2,4,8")
    parser.add_argument("--accumulation", type=Path, default=MODELS_DIR / "accumulation.onnx")
    parser.add_argument("--quality", default="high")
    cli_args.add_threads(parser)
    args = parser.parse_args(argv)
    folders = sequence_dirs(args.data.expanduser(), args.split)
    if not folders:
        raise SystemExit(f"no {args.split} sequences under {args.data}")
    oidn = OIDNDenoiser(args.quality, num_threads=args.threads)
    print(f"{len(folders)} {args.split} sequences; accumulation: {args.accumulation}; "
          f"OIDN {args.quality}; PSNR / TRMAE\n")
    print("| spp | OIDN on the frame | accumulation alone | OIDN on the accumulation |")
    print("|---|---|---|---|")
    for spp in (int(s) for s in args.spp.split(",")):
        r = compare(folders, spp, args.accumulation, oidn, args.threads)
        cells = [f"{r[k][0]:.2f} / {r[k][1]:.3f}"
                 for k in ("oidn", "accumulation", "oidn(accumulation)")]
        print(f"| {spp} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
