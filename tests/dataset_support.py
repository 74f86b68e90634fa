"""A tiny dataset in the real on-disk format (docs/data.md), written without rendering."""

from __future__ import annotations

import json

import numpy as np

from quietframe.scenes import exr_io
from quietframe.scenes.generator import GENERATOR_VERSION

H, W = 40, 48
SHIFT = (3, -2)  # frame t shows frame t-1 moved by this many pixels (x, y)


def _smooth(rng: np.random.Generator, c: int) -> np.ndarray:
    """Random image with detail at several scales (integer shifts keep it exact)."""
    img = rng.random((H + 8, W + 8, c)).astype(np.float32)
    return img + np.roll(img, 1, 0) + np.roll(img, 1, 1)


def write_sequence(
    root, seed: int, frames: int = 3, levels=(1, 2, 4), noise: float = 0.1
) -> None:
    """A camera that slides: frame t at pixel p equals frame t-1 at p + SHIFT (backward
    motion = SHIFT everywhere). Frames are crops of one big image."""
    rng = np.random.default_rng(seed)
    big = {"reference": _smooth(rng, 3), "albedo": _smooth(rng, 3), "normal": _smooth(rng, 3)}
    big_w = W + 8 + abs(SHIFT[0]) * frames
    big = {k: np.tile(v, (2, 3, 1))[: H + 30, :big_w] for k, v in big.items()}
    d = root / str(seed)
    d.mkdir(parents=True)
    recs = []
    for t in range(frames):
        x0, y0 = 2 + SHIFT[0] * t, 12 + SHIFT[1] * t
        layers = {k: v[y0 : y0 + H, x0 : x0 + W] for k, v in big.items()}
        passes = [layers["reference"] + rng.normal(0, noise, (H, W, 3)) for _ in range(max(levels))]
        for k, p in enumerate(passes):
            layers[exr_io.pass_layer(k)] = p
        for n in levels:
            layers[exr_io.color_layer(n)] = np.mean(passes[:n], 0)
        layers["depth"] = np.ones((H, W, 1))
        layers["position"] = np.zeros((H, W, 3))
        layers["motion"] = np.tile(np.array(SHIFT, np.float32), (H, W, 1)) * (t > 0)
        layers["motion_valid"] = np.full((H, W, 1), float(t > 0))
        exr_io.write_frame(d / f"frame_{t:04d}.exr", layers, {"frame": t})
        recs.append(
            {
                "index": t,
                "file": f"frame_{t:04d}.exr",
                "reset": t == 0,
                "to_world": np.eye(4).tolist(),
            }
        )
    manifest = {
        "seed": seed,
        "frame_count": frames,
        "frames": recs,
        "generator": GENERATOR_VERSION,
        "config": {"width": W, "height": H, "frames": [frames, frames],
                   "spp_levels": list(levels), "reference_spp": 64},
    }
    (d / "manifest.json").write_text(json.dumps(manifest))


def write_generator_splits(root, train_seeds=(11, 12), validation_seeds=(21,)):
    """The generator's train and validation splits as `quietframe-train` reads them
    (<root>/<GENERATOR_VERSION>/<split>), one 3-frame sequence per seed; returns `root`."""
    for split, seeds in (("train", train_seeds), ("validation", validation_seeds)):
        for seed in seeds:
            write_sequence(root / GENERATOR_VERSION / split, seed, frames=3)
    return root
