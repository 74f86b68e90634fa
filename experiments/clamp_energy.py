"""How much energy the NBG pre-stage's firefly clamp takes from rendered frames, per floor.

    python -m quietframe.experiments.clamp_energy [--split validation] [--frames 24] [--spp 1,4]
        [--floors 0,16,32,64,128,256]

For the first `--frames` frames of the split (sorted by sequence and frame), the noisy colour
at each spp is demodulated as the pre-stage does (`nbg.demodulation_divisor`), clamped by
`nbg.suppress_outliers` (3σ of the 5×5 neighbourhood, bound never below floor × the frame's mean
luminance; floor 0 = the plain 3σ clamp) and remodulated. Printed per spp and floor, means over
the frames: `energy kept` = mean of the clamped frame / mean of the reference (1.0 = unbiased),
and `box error` = mean |box(clamped) − box(reference)| / mean |box(reference)| with a 9×9 box
filter, a proxy for what a spatial filter after the clamp can reach (bias and variance both).
The row `none` is the unclamped frame. This is the probe behind `NBGConfig.outlier_floor`
(docs/training.md).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
import torch.nn.functional as F

from quietframe.bench import cli_args
from quietframe.model.nbg import OUTLIER_SIGMAS, demodulation_divisor, suppress_outliers
from quietframe.scenes.exr_io import color_layer, load_frame
from quietframe.scenes.layout import split_dir

BOX = 9


def _planes(arr: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(arr).permute(2, 0, 1)[None]  # (1, C, H, W)


def clamped(color: torch.Tensor, albedo: torch.Tensor, floor: float | None) -> torch.Tensor:
    """The colour after the pre-stage's clamp with `floor` (None: no clamp), remodulated."""
    if floor is None:
        return color
    divisor = demodulation_divisor(albedo)
    return suppress_outliers(color / divisor, sigmas=OUTLIER_SIGMAS, floor=floor) * divisor


def figures(out: torch.Tensor, reference: torch.Tensor) -> tuple[float, float]:
    """(energy kept, box error) of one frame, as the module docstring defines them."""
    box = lambda x: F.avg_pool2d(x, BOX, 1, BOX // 2, count_include_pad=False)  # noqa: E731
    error = (box(out) - box(reference)).abs().mean() / box(reference).abs().mean()
    return float(out.mean() / reference.mean()), float(error)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="clamp_energy", description=__doc__.split("\n")[0])
    cli_args.add_data(parser)
    cli_args.add_split(parser)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--spp", default="1,4")
    parser.add_argument("--floors", default="0,16,32,64,128,256")
    args = parser.parse_args(argv)
    files = sorted(split_dir(args.data, args.split).glob("*/frame_*.exr"))[:args.frames]
    if not files:
        raise SystemExit(f"no frames in {split_dir(args.data, args.split)}")
    floors: list[float | None] = [float(f) for f in args.floors.split(",")] + [None]
    print(f"{len(files)} frames of {args.split}; 3σ clamp with a floor (× frame mean luminance)")
    print("| spp | floor | energy kept | box error |\n|---|---|---|---|")
    for spp in (int(s) for s in args.spp.split(",")):
        rows: dict[float | None, list[tuple[float, float]]] = {f: [] for f in floors}
        for path in files:
            layers = load_frame(path, [color_layer(spp), "albedo", "reference"])
            color, albedo = _planes(layers[color_layer(spp)]), _planes(layers["albedo"])
            reference = _planes(layers["reference"])
            for floor in floors:
                rows[floor].append(figures(clamped(color, albedo, floor), reference))
        for floor, values in rows.items():
            kept, error = np.mean(values, axis=0)
            label = "none" if floor is None else f"{floor:g}"
            print(f"| {spp} | {label} | {kept:.3f} | {error:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
