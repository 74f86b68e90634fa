"""Large frames in overlapping tiles, so a graph's working set stays bounded by one setting,
`max_memory_mb` (like OIDN's `maxMemoryMB`): a tile holds at most max_memory_mb / the card's
`bytes_per_pixel` padded pixels (NBG ~0.75 KiB/px, the affinity model ~1 KiB/px untiled, which
an 8K frame would multiply by 33 Mpx; docs/reliability.md). What tiles need to know about a
graph is its card's `Tiling` (runtime/card.py; the rules per family: runtime/receptive.py).

Why the tiles join without seams: an output pixel depends only on inputs within a finite
radius (its receptive field) and on the history at those pixels' motion targets. With
- every tile read with `overlap` extra pixels on each side, overlap >= receptive radius + the
  frame's largest motion (+1 for the nearest-pixel fetch), so every input and history pixel an
  interior pixel depends on is in its tile, and a motion target that is inside the frame is
  inside the tile (the warp's in-frame test agrees with the untiled run);
- every tile's origin a multiple of the card's `align` (NBG: the coarsest grid cell; affinity:
  the U-Net's coarsest cell), so grid cells, pooling blocks and resampling grids lie where they
  lie in the untiled frame (a state at 1/s resolution is cut at origin / s);
- only each tile's interior kept, for the output and for the new state;
each interior pixel is computed from the same values as untiled. Frame-wide quantities are not
local (the card lists them: mean depth, which NBG's GuideNet and the affinity guide divide depth
by, and the mean luminance under NBG's firefly floor): the graph's own reductions over the image
run on the whole frame and every tile is fed their values (runtime/statistics.py). What remains
is float rounding (convolutions of another size may sum in another order), and nearest-pixel
warps whose source falls on an exact .5 tie, where the warp's normalised-coordinate arithmetic
rounds by the tile's width.
The affinity model's U-Net resamples by the ratio of its level sizes, which tiles and frame
share only along sides that are multiples of `align` (card: `size_ratios`): a side that is not
is not cut (strips across it); a frame with neither side a multiple tiles with a small
parameter shift (~1.5% of the peak at 322×390). A first frame's zero state is made per tile.
tests/runtime/test_tiling.py compares tiled and untiled runs of every shipped model.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from quietframe.runtime.card import StateSpec
from quietframe.runtime.receptive import Tiling

# Re-exported: the Denoiser's docs and tests know the default as tiling.DEFAULT_MAX_MEMORY_MB.
from quietframe.runtime.settings import DEFAULT_MAX_MEMORY_MB as DEFAULT_MAX_MEMORY_MB
from quietframe.runtime.settings import runtime_settings

# A graph without tiling in its card runs whole: its working set is budgeted like the largest
# tiled ones per pixel (the affinity model, ~1 KiB/px untiled; docs/reliability.md).
UNTILED_BYTES_PER_PIXEL = 1024


def max_memory_mb_default() -> float:
    """The working set one tile may hold, in MiB: QUIETFRAME_MAX_MEMORY_MB, else
    DEFAULT_MAX_MEMORY_MB (runtime/settings.py, where the default is argued)."""
    return runtime_settings().max_memory_mb


def tile_bytes_per_pixel(tiling: Tiling, state: Sequence[StateSpec]) -> int:
    """A tile's memory per padded pixel: the graph's working set (the card's bytes_per_pixel)
    and the tile's own float32 inputs (at most the five buffers, 12 channels), state in and out
    and output (3 channels)."""
    state_channels = sum(s.channels / s.scale**2 for s in state)
    return tiling.bytes_per_pixel + int(4 * (12 + 2 * state_channels + 3))


def tile_pixels_for(tiling: Tiling, state: Sequence[StateSpec], max_memory_mb: float) -> int:
    """Padded pixels of one tile whose memory fits in `max_memory_mb`."""
    return max(int(max_memory_mb * 2**20) // tile_bytes_per_pixel(tiling, state), 1)


@dataclass(frozen=True)
class Tile:
    y0: int  # interior rows [y0, y1), columns [x0, x1)
    y1: int
    x0: int
    x1: int
    py0: int  # padded (read) region
    py1: int
    px0: int
    px1: int


def overlap_for(tiling: Tiling, values: Mapping[str, float | int],
                motion: np.ndarray | None) -> int:
    """Radius (at the run-time inputs' `values`) + the frame's largest motion + 1 (the nearest
    fetch), rounded up to the alignment."""
    reach = 0
    if tiling.motion and motion is not None and motion.size:
        reach = int(math.ceil(float(np.abs(motion).max()))) + 1
    return _round_up(tiling.radius_for(values) + reach, tiling.align)


def plan_tiles(height: int, width: int, overlap: int, align: int, tile_pixels: int,
               size_ratios: bool = False) -> list[Tile]:
    """Interior tiles (multiples of `align`, about square) whose padded size fits in
    `tile_pixels` where the overlap allows it; one tile when the frame fits. With
    `size_ratios` (the graph resamples by the ratio of its levels' sizes, runtime/card.py) a
    side that is not a multiple of `align` is not cut: the tiles are strips across it, so they
    resample by the frame's ratios."""
    if height * width <= tile_pixels:
        return [Tile(0, height, 0, width, 0, height, 0, width)]
    side_y = side_x = _side(math.isqrt(tile_pixels), overlap, align)
    if size_ratios and height % align and not width % align:
        side_y, side_x = height, _side(tile_pixels // height, overlap, align)
    elif size_ratios and width % align and not height % align:
        side_y, side_x = _side(tile_pixels // width, overlap, align), width
    return [
        Tile(
            y0, min(y0 + side_y, height), x0, min(x0 + side_x, width),
            max(y0 - overlap, 0), min(y0 + side_y + overlap, height),
            max(x0 - overlap, 0), min(x0 + side_x + overlap, width),
        )
        for y0 in range(0, height, side_y)
        for x0 in range(0, width, side_x)
    ]


def _side(extent: int, overlap: int, align: int) -> int:
    """The interior side of tiles `extent` pixels across with `overlap` on both sides."""
    return max((extent - 2 * overlap) // align * align, align)


def crop(array: np.ndarray, tile: Tile, scale: int = 1) -> np.ndarray:
    """The padded region of an (N, C, H, W) array at 1/scale resolution, contiguous (what
    onnxruntime reads)."""
    return np.ascontiguousarray(array[..., tile.py0 // scale : -(-tile.py1 // scale),
                                      tile.px0 // scale : -(-tile.px1 // scale)])


def place(target: np.ndarray, tile: Tile, result: np.ndarray, scale: int = 1) -> None:
    """Put the interior of a padded tile's (N, C, h, w) result at 1/scale resolution in
    place."""
    y0, x0 = tile.y0 // scale, tile.x0 // scale
    y1, x1 = -(-tile.y1 // scale), -(-tile.x1 // scale)
    oy, ox = (tile.y0 - tile.py0) // scale, (tile.x0 - tile.px0) // scale
    target[..., y0:y1, x0:x1] = result[..., oy : oy + y1 - y0, ox : ox + x1 - x0]


def run_tiled(
    run: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]],
    feeds: Mapping[str, np.ndarray], height: int, width: int, tiling: Tiling,
    values: Mapping[str, float | int], tile_pixels: int, scales: Mapping[str, int],
    zero_state: Mapping[str, StateSpec] = {},  # noqa: B006 (read only)
) -> dict[str, np.ndarray]:
    """`run` (one graph run on feeds -> outputs) over tiles of the frame, each tile's interior
    put in place. `scales`: input and output names at 1/scale resolution; `zero_state`: state
    inputs not in `feeds` that are zeros (a first frame), made per tile."""
    tiles = plan_tiles(height, width, overlap_for(tiling, values, feeds.get("motion")),
                       tiling.align, tile_pixels, tiling.size_ratios)
    outputs: dict[str, np.ndarray] = {}
    for tile in tiles:
        th, tw = tile.py1 - tile.py0, tile.px1 - tile.px0
        part = {k: crop(v, tile, scales.get(k, 1)) if v.ndim == 4 else v
                for k, v in feeds.items()}
        part |= {k: np.zeros(spec.shape(th, tw), np.float32) for k, spec in zero_state.items()}
        for name, result in run(part).items():
            scale = scales.get(name, 1)
            if name not in outputs:  # (N, C, H, W) of the whole frame
                shape = (*result.shape[:2], -(-height // scale), -(-width // scale))
                outputs[name] = np.empty(shape, result.dtype)
            place(outputs[name], tile, result, scale=scale)
    return outputs


def _round_up(value: int, multiple: int) -> int:
    return -(-value // multiple) * multiple
