"""The one rule for bad input values, applied before a frame reaches a model; which rule a
buffer gets is part of the buffer vocabulary (buffers.py).

- RADIANCE (color, albedo): NaN, ±Inf and negative values become 0 (a failed or overflowed sample
  carries no usable estimate; radiance and albedo cannot be negative); values above MAX_VALUE =
  65504, the largest half float, become 65504. The ceiling is what a half-float render can hold
  at all, far above any display-referred or exposed scene value, and it bounds what enters the
  temporal history: the history is a weighted average of inputs, so one bad sample (1e30 from a
  divergent path) no longer keeps thousands of pixels at 1e28..1e29 for a dozen frames; it can
  at most be as bright as a half-float firefly and fades at the history's rate.
- DIRECTION (normal, motion): NaN and ±Inf become 0 (no orientation / no motion).
- DISTANCE (depth): NaN, ±Inf, negative values and the "no hit" markers of renderers (0:
  Blender's Denoising Depth and quietframe's own training data on the sky; ≥ 1e10: Blender's Depth
  pass) become the largest valid depth of the frame (the background is far away), or 1 if no
  depth is valid (a frame without geometry). Training reads depth through this same rule
  (model/data.py).
Every replaced value is counted per buffer so the service can report it.
"""

from __future__ import annotations

import numpy as np

from quietframe.runtime.buffers import BUFFERS, Rule

MAX_VALUE = np.float32(65504.0)  # np.finfo(np.float16).max
HALF_MAX = np.float32(np.finfo(np.float16).max)
DEPTH_NO_HIT = np.float32(1e10)  # a depth this far or farther marks a ray that hit nothing
NO_GEOMETRY_DEPTH = 1.0  # the depth of a frame in which no ray hit anything


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
        # A frame with no valid depth shows no geometry: any one distance will do, and 0 would
        # itself read as "no hit" next time.
        fill = float(finite.max()) if finite.size else NO_GEOMETRY_DEPTH
    return np.where(bad, np.float32(fill), values), count


def sanitize_output(values: np.ndarray) -> tuple[np.ndarray, int]:
    """Last guard: nothing non-finite leaves the runtime (should never trigger)."""
    bad = ~np.isfinite(values)
    count = int(np.count_nonzero(bad))
    return (np.where(bad, np.float32(0), values) if count else values), count


def clamp_to_half(values: np.ndarray) -> tuple[np.ndarray, int]:
    """float32 -> the range a float16 can hold (±65504): a plain cast turns 65520 and above into
    ±Inf. Returns (values, number clamped); a copy only when something was clamped."""
    over = np.abs(values) > HALF_MAX
    count = int(np.count_nonzero(over))
    return (np.clip(values, -HALF_MAX, HALF_MAX) if count else values), count
