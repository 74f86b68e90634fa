"""On-disk frame format: one multi-layer OpenEXR per frame. The channel table lives here only.

Layers (the canonical buffer names of runtime/buffers.py; `layer.channel` EXR naming):
- `pass<k>.R/G/B`      float  radiance of one-sample pass k (k = 0..S-1), independent seeds
- `color_<n>spp.R/G/B` float  mean of passes 0..n-1 (n in the stored spp levels)
- `reference.R/G/B`    float  clean target from an independent seed
- `albedo.R/G/B`       half   first-hit albedo, mean over the passes
- `normal.X/Y/Z`       half   world-space shading normal, mean over passes that hit geometry
- `depth.Z`            half   distance camera -> first hit, mean over hitting passes, 0 = none
- `position.X/Y/Z`     half   world position of the first hit, same averaging as depth
- `motion.X/Y`         half   backward motion in pixels (p of frame t was at p + motion in t-1)
- `motion_valid.V`     half   fraction of passes whose point was visible in frame t-1 (0..1)
`load_frame` is numpy-only (no torch, no mitsuba), for the evaluation harness and the reader.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import OpenEXR

# layer -> (channel suffixes, numpy dtype written to disk)
LAYERS: dict[str, tuple[str, type]] = {
    "reference": ("RGB", np.float32),
    "albedo": ("RGB", np.float16),
    "normal": ("XYZ", np.float16),
    "depth": ("Z", np.float16),
    "position": ("XYZ", np.float16),
    "motion": ("XY", np.float16),
    "motion_valid": ("V", np.float16),
}
RADIANCE_CHANNELS = "RGB"
HEADER_KEY = "quietframe"  # JSON string attribute: frame index, spp levels, camera, seeds


def pass_layer(k: int) -> str:
    return f"pass{k}"


def color_layer(spp: int) -> str:
    return f"color_{spp}spp"


def layer_spec(layer: str) -> tuple[str, type]:
    """Channel suffixes and on-disk dtype of any layer, including the numbered ones."""
    if layer in LAYERS:
        return LAYERS[layer]
    if layer.startswith("pass") or (layer.startswith("color_") and layer.endswith("spp")):
        return RADIANCE_CHANNELS, np.float32
    raise KeyError(f"unknown layer {layer!r}")


def write_frame(path: str | Path, layers: dict[str, np.ndarray], meta: dict) -> None:
    """Write (H, W, C) float arrays by layer name; atomic (temp file then rename), so an
    interrupted render never leaves a frame that looks finished."""
    channels = {}
    for layer, arr in layers.items():
        names, dtype = layer_spec(layer)
        arr = arr[..., None] if arr.ndim == 2 else arr
        if arr.shape[-1] != len(names):
            raise ValueError(f"layer {layer!r}: {arr.shape[-1]} channels, expected {len(names)}")
        for i, c in enumerate(names):
            channels[f"{layer}.{c}"] = np.ascontiguousarray(arr[..., i], dtype=dtype)
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,  # lossless
        "type": OpenEXR.scanlineimage,
        HEADER_KEY: json.dumps(meta),
    }
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with OpenEXR.File(header, channels) as f:
        f.write(str(tmp))
    os.replace(tmp, path)


def read_meta(path: str | Path) -> dict:
    with OpenEXR.File(str(path), header_only=True) as f:
        return json.loads(f.header()[HEADER_KEY])


def load_frame(path: str | Path, layers: list[str] | None = None) -> dict[str, np.ndarray]:
    """Read layers as float32 (H, W, C) arrays (all layers when `layers` is None)."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        chans = {name: ch.pixels for name, ch in f.channels().items()}
    found: dict[str, list[str]] = {}
    for name in chans:
        layer, _, _ = name.rpartition(".")
        found.setdefault(layer, []).append(name)
    wanted = list(found) if layers is None else layers
    out = {}
    for layer in wanted:
        if layer not in found:
            raise KeyError(f"{path}: no layer {layer!r} (has {sorted(found)})")
        names, _ = layer_spec(layer)
        out[layer] = np.stack([chans[f"{layer}.{c}"] for c in names], -1).astype(np.float32)
    return out


def frame_layers(path: str | Path) -> list[str]:
    with OpenEXR.File(str(path), header_only=True) as f:
        names = [c.name for c in f.header()["channels"]]
    return sorted({n.rpartition(".")[0] for n in names})
