"""The one rule for bad input values, applied before a frame reaches a model; which rule a
buffer gets is part of the buffer vocabulary (buffers.py).

- RADIANCE (color, albedo): NaN, ±Inf and negative values become 0 (a failed or overflowed sample
  carries no usable estimate; radiance and albedo cannot be negative); values above 1e30 become
  1e30 (larger ones overflow the float32 grid sums; see docs/grid-math.md).
- DIRECTION (normal, motion): NaN and ±Inf become 0 (no orientation / no motion).
- DISTANCE (depth): NaN, ±Inf, negative values and the "no hit" markers of renderers (0:
  Blender's Denoising Depth and quietframe's own training data on the sky; ≥ 1e10: Blender's Depth
  pass) become the largest valid depth of the frame (the background is far away), or 0 if no
  depth is valid. Training reads depth through this same rule (model/data.py).
Every replaced value is counted per buffer so the service can report it.
"""

from __future__ import annotations

import numpy as np

from quietframe.runtime.buffers import BUFFERS, Rule

MAX_VALUE = np.float32(1e30)
DEPTH_NO_HIT = np.float32(1e10)  # a depth this far or farther marks a ray that hit nothing


def sanitize_buffer(name: str, values: np.ndarray) -> tuple[np.ndarray, int]:
    """Return (clean float32 array, number of replaced values); never modifies `values`."""
    rule = BUFFERS[name].rule
    values = np.asarray(values, dtype=np.float32)
    bad = ~np.isfinite(values)
    if rule in (Rule.RADIANCE, Rule.DISTANCE):
        bad |= values < 0  # NaN compares False, already in `bad`
    if rule is Rule.DISTANCE:
        bad |= (values == 0) | (values >= DEPTH_NO_HIT)
    huge = ((values > MAX_VALUE) & ~bad) if rule is Rule.RADIANCE else None
    count = int(np.count_nonzero(bad)) + (int(np.count_nonzero(huge)) if huge is not None else 0)
    if count == 0:
        return values, 0
    if huge is not None:
        values = np.minimum(values, MAX_VALUE)  # a copy: the caller's array is left alone
    fill = 0.0
    if rule is Rule.DISTANCE:
        finite = values[~bad]
        fill = float(finite.max()) if finite.size else 0.0
    return np.where(bad, np.float32(fill), values), count


def sanitize_output(values: np.ndarray) -> tuple[np.ndarray, int]:
    """Last guard: nothing non-finite leaves the runtime (should never trigger)."""
    bad = ~np.isfinite(values)
    count = int(np.count_nonzero(bad))
    return (np.where(bad, np.float32(0), values) if count else values), count
