"""Torch-free inputs and machine facts shared by the benchmarks, model cards and tests."""

from __future__ import annotations

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
