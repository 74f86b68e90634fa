"""Buffers a frame carries that hold nothing a model can use, so a choice treats them as absent.

A renderer sometimes writes a pass it could not fill: Cycles writes an all-zero `Vector` when
motion blur is on, and a frame of sky (or a pass left unconnected) writes one depth everywhere.
Such a buffer is in the header but not in the pixels: a model that needs it (reprojection needs
motion, edge stops need depth) would run on nothing, so `model=auto` must decide as if it were
missing (docs/service.md: no motion vectors -> a per-frame model, no accumulation ghosts).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from quietframe.runtime.sanitize import DEPTH_NO_HIT

# Relative depth range below which a depth pass is called constant (float32 rounding of one
# distance written everywhere stays far below this).
CONSTANT_DEPTH_RELATIVE = 1e-6


def unusable_buffers(buffers: Mapping[str, np.ndarray]) -> tuple[str, ...]:
    """Names among `buffers` ((C, H, W) planes as decoded) that carry no information:
    motion without one finite nonzero vector; depth whose valid (hit) values, after leaving
    out the renderers' no-hit markers (0, >= 1e10, non-finite, negative), are absent or one
    value."""
    unusable = []
    motion = buffers.get("motion")
    if motion is not None and not _any_motion(motion):
        unusable.append("motion")
    depth = buffers.get("depth")
    if depth is not None and _constant_depth(depth):
        unusable.append("depth")
    return tuple(unusable)


def _any_motion(motion: np.ndarray) -> bool:
    values = np.asarray(motion)
    return bool(np.any((values != 0) & np.isfinite(values)))


def _constant_depth(depth: np.ndarray) -> bool:
    values = np.asarray(depth, np.float32)
    hits = values[np.isfinite(values) & (values > 0) & (values < DEPTH_NO_HIT)]
    if hits.size == 0:
        return True
    low, high = float(hits.min()), float(hits.max())
    return high - low <= CONSTANT_DEPTH_RELATIVE * max(abs(high), 1e-30)
