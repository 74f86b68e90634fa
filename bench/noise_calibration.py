"""Fit the reference-free noise estimate of `model=auto` to spp (service/noise_calibration.json).

    python -m quietframe.bench.noise_calibration [--data ~/.cache/quietframe/data] [--synthetic]

Every rendered frame under <data>/*/validation/*/frame_*.exr (finished sequences or not)
at each of its spp levels gives a point (log2 σ, log2 spp), σ = noise_estimate.noise_statistic
(a relative variance) of the noisy colour with its albedo; a least-squares line through them
is the mapping. Without rendered frames (or with --synthetic) the points come from synthetic
frames whose per-pixel noise has variance ∝ 1/spp: that proves the fit, not the figures (the
file says which).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.scenes.exr_io import color_layer, frame_layers, load_frame
from quietframe.service.noise_estimate import CALIBRATION_FILE, noise_statistic

SPLITS = ("validation",)  # model selection data; the test split only reports


def rendered_points(data: Path, max_frames: int) -> tuple[list[tuple[float, float]], list[str]]:
    points, used = [], []
    files = sorted(p for s in SPLITS for p in data.glob(f"*/{s}/*/frame_*.exr"))[:max_frames]
    for path in files:
        levels = sorted(int(n[6:-3]) for n in frame_layers(path) if n.startswith("color_"))
        layers = load_frame(path, ["albedo", *(color_layer(s) for s in levels)])
        albedo = layers["albedo"].transpose(2, 0, 1)
        for spp in levels:
            sigma = noise_statistic(layers[color_layer(spp)].transpose(2, 0, 1), albedo)
            if sigma > 0:
                points.append((float(np.log2(sigma)), float(np.log2(spp))))
        used.append(str(path.relative_to(data)))
    return points, used


def synthetic_points(frames: int = 6, size: int = 128) -> list[tuple[float, float]]:
    """Smooth radiance times a textured albedo, Monte Carlo-like noise (gamma, mean 1, variance
    2/spp per pixel) on the shading: the statistic's slope must come out near -1."""
    rng = np.random.default_rng(0)
    points = []
    yy, xx = np.mgrid[0:size, 0:size] / size
    for f in range(frames):
        shading = 0.2 + np.exp(-((xx - rng.uniform()) ** 2 + (yy - rng.uniform()) ** 2) * 8)
        albedo = rng.uniform(0.2, 0.9, (3, size, size))
        for spp in (1, 2, 4, 8, 16, 32):
            noise = rng.gamma(spp / 2, 2 / spp, (size, size))
            color = albedo * (shading * noise)[None]
            points.append((float(np.log2(noise_statistic(color, albedo))), float(np.log2(spp))))
        del f
    return points


def fit(points: list[tuple[float, float]]) -> tuple[float, float, float]:
    """(slope, intercept, rms error in log2 spp) of log2 spp = intercept + slope·log2 σ."""
    x, y = np.array(points).T
    slope, intercept = np.polyfit(x, y, 1)
    rms = float(np.sqrt(np.mean((intercept + slope * x - y) ** 2)))
    return float(slope), float(intercept), rms


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="noise_calibration", description=__doc__.split("\n")[0])
    cli_args.add_data(parser)
    parser.add_argument("--synthetic", action="store_true", help="ignore rendered frames")
    parser.add_argument("--max-frames", type=int, default=64)
    parser.add_argument("--out", type=Path, default=CALIBRATION_FILE)
    args = parser.parse_args(argv)
    data = args.data.expanduser()
    points, used = ([], []) if args.synthetic else rendered_points(data, args.max_frames)
    sequences = sorted({path.split("/")[-2] for path in used})
    source = (f"rendered: {len(used)} frames of {len(sequences)} validation sequences under "
              f"{args.data} ({', '.join(sequences)})")
    if len(points) < 4:
        points = synthetic_points()
        source = "synthetic (no rendered frames): figures not meaningful"
    slope, intercept, rms = fit(points)
    spps = [2**y for _, y in points]
    result = {
        "slope": round(slope, 4), "intercept": round(intercept, 4),
        "rms_log2_spp": round(rms, 3), "points": len(points),
        "min_spp": 0.25, "max_spp": 4 * max(spps), "demodulated": True, "source": source,
        "command": "python -m quietframe.bench.noise_calibration",
    }
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
