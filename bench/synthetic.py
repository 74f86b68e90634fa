"""Torch-free inputs and machine facts shared by the benchmarks, model cards and tests."""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np

FMA_PIPES, FLOAT_LANES = 2, 8  # AVX2: two 256-bit FMA units per core


def cpu_peak_gflops(threads: int) -> tuple[float, str]:
    """AVX2-FMA peak (cores × clock × 2 FMA pipes × 8 float lanes × 2 FLOP) and a description."""
    text = Path("/proc/cpuinfo").read_text()
    mhz = float(re.search(r"cpu MHz\s*:\s*([\d.]+)", text).group(1))
    model = re.search(r"model name\s*:\s*(.+)", text).group(1).strip()
    peak = threads * mhz / 1e3 * FMA_PIPES * FLOAT_LANES * 2
    return peak, f"{model}, {mhz:.0f} MHz, {threads} threads"


def frame_buffers(height: int = 720, width: int = 1280, seed: int = 0) -> dict[str, np.ndarray]:
    """Plausible canonical buffers as the runtime takes them, (C, H, W) float32 planes: noisy
    colour, unit normals, motion."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(3, height, width)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=0, keepdims=True)
    return {
        "color": rng.exponential(0.5, (3, height, width)).astype(np.float32),
        "albedo": rng.uniform(0, 1, (3, height, width)).astype(np.float32),
        "normal": normal,
        "depth": rng.uniform(1, 5, (1, height, width)).astype(np.float32),
        "motion": rng.normal(0, 1, (2, height, width)).astype(np.float32),
    }


def synthetic_buffers(width: int, height: int, seed: int) -> dict[str, np.ndarray]:
    """Render-like (H, W, C) buffers of frame `seed` of a panning shot, so that EXR compression
    costs what it would on a real render: piecewise-constant albedo, smooth normals and depth,
    the camera panning 2 px a frame, colour = albedo × shading with 4-spp-like noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    x += 2.0 * seed  # the camera pans 2 px per frame
    tiles = ((x // 97).astype(int) * 7 + (y // 61).astype(int) * 13) % 17
    palette = np.random.default_rng(0).uniform(0.05, 0.9, size=(17, 3)).astype(np.float32)
    albedo = palette[tiles]
    normal = np.stack([np.sin(x / 300), np.cos(y / 200), np.ones_like(x)], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    depth = 4.0 + 2.0 * np.sin(x / 400) * np.cos(y / 300)
    shading = 0.3 + 0.7 * np.clip(normal[..., 2:3], 0, 1)
    noise = rng.gamma(4.0, 1 / 4.0, size=(height, width, 3))  # mean 1, like 4 spp
    color = albedo * shading * noise
    motion = np.stack([np.full_like(x, 2.0), np.zeros_like(x)], -1)  # to t-1: 2 px right
    return {"color": color, "albedo": albedo, "normal": normal, "depth": depth, "motion": motion}


def blender_exr(buffers: dict[str, np.ndarray], compression: str, half: bool,
                attributes: dict[str, str] | None = None) -> bytes:
    """`buffers` (synthetic_buffers') as Blender writes a multilayer EXR: its channel names,
    Cycles' Vector pass (y up), `compression` (zip, piz, none, ...), half or float.
    `attributes`: more header attributes (e.g. Cycles' `cycles.ViewLayer.samples`)."""
    import OpenEXR  # the serve and client extras: the service benchmarks' frames

    dtype = np.float16 if half else np.float32
    layer = "ViewLayer"
    channels = {}
    for name, pass_name, comps in (
        ("color", "Combined", "RGB"),
        ("albedo", "Denoising Albedo", "RGB"),
        ("normal", "Denoising Normal", "XYZ"),
    ):
        for i, c in enumerate(comps):
            channels[f"{layer}.{pass_name}.{c}"] = buffers[name][..., i]
    channels[f"{layer}.Combined.A"] = np.ones_like(buffers["depth"])
    channels[f"{layer}.Denoising Depth.Z"] = buffers["depth"]
    m = buffers["motion"]  # Cycles Vector: y up
    channels.update(
        {
            f"{layer}.Vector.X": m[..., 0],
            f"{layer}.Vector.Y": -m[..., 1],
            f"{layer}.Vector.Z": -m[..., 0],
            f"{layer}.Vector.W": m[..., 1],
        }
    )
    header = {
        "compression": getattr(OpenEXR, f"{compression.upper()}_COMPRESSION"),
        "type": OpenEXR.scanlineimage,
        **(attributes or {}),
    }
    arrays = {k: np.ascontiguousarray(v, dtype=dtype) for k, v in channels.items()}
    out = io.BytesIO()
    OpenEXR.File(header, arrays).write(out)
    return out.getvalue()
