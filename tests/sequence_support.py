"""A small moving sequence for the export parity tests (NBG, affinity): torch tensors."""

from __future__ import annotations

import torch

from quietframe.export.onnx_export import example_inputs


def moving_frame(index: int, height: int, width: int) -> tuple:
    """Frame `index`: the same scene content shifted one pixel per frame (colour with noise of
    its own per frame), with sub-pixel motion
    (pixel p came from about p - 1 in the previous frame; -1.3 and 0.4 keep nearest-warp ties
    away from .5, and a bilinear and a nearest reprojection give different histories, so a
    stale export cannot pass)."""
    color, albedo, normal, depth, motion, _, _ = example_inputs(height, width, seed=7)
    # Monte Carlo-like noise of its own in every frame, so that history changes the output.
    gen = torch.Generator().manual_seed(1000 + index)
    color = color * (1 + 0.5 * (torch.rand(color.shape, generator=gen) - 0.5))
    shift = lambda t: torch.roll(t, shifts=index, dims=3)  # noqa: E731
    motion = torch.zeros_like(motion)
    motion[:, 0] = -1.3 if index else 0.0
    motion[:, 1] = 0.4 if index else 0.0
    return shift(color), shift(albedo), shift(normal), shift(depth), motion
