"""Large frames in overlapping tiles, so a model's working set stays bounded (NBG needs about
0.7 KiB per pixel untiled, which an 8K frame would multiply by 33 Mpx; docs/reliability.md).

Why the tiles join without seams: an NBG output pixel depends only on inputs within a finite
radius (its receptive field) and on the history at those pixels' motion targets. With
- every tile read with `overlap` extra pixels on each side, overlap >= receptive radius + the
  frame's largest motion (+1 for the nearest-pixel fetch), so every input and history pixel an
  interior pixel depends on is in its tile, and a motion target that is inside the frame is
  inside the tile (the warp's in-frame test agrees with the untiled run);
- every tile's origin a multiple of the coarsest grid cell (sigma_s * 2^(grids-1)), so the
  bilateral grids' cells lie where they lie in the untiled frame;
- only each tile's interior kept, for the output and for the new state;
each interior pixel is computed from the same values as untiled. One frame-wide quantity is not
local: the GuideNet feature depth / mean(depth) (model/nbg.py guide_features). Each tile gets a
ballast band appended on a side that is not the frame's edge (so at least `overlap` away from
its interior, which it cannot reach): zero buffers and one depth value chosen so that the tile's
mean depth is the frame's. The interior then sees the frame's depth scale. What remains is float
rounding (the mean is summed in another order), and nearest-pixel warps whose source falls on an
exact .5 tie, where the warp's normalised-coordinate arithmetic rounds by the tile's width.
tests/test_tiling.py compares tiled and untiled runs.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np

# Pixels of one padded tile: 1080p (2.07 Mpx) still runs whole (tiles cost their overlap);
# NBG's working set is ~0.7 KiB/px, so a tile in flight holds ~1.4 GiB whatever the frame size.
DEFAULT_TILE_PIXELS = 1 << 21


@dataclass(frozen=True)
class Geometry:
    """What tiling needs to know about a model."""

    radius: int  # receptive radius in pixels (without motion)
    align: int  # tile origins are multiples of this
    depth_mean: bool  # the graph divides depth by its frame mean (GuideNet features)


def model_geometry(metadata: Mapping[str, str]) -> Geometry | None:
    """From the model card's architecture (docs/model-interface.md); None: unknown model, not
    tiled. Radius: 2 cells of the coarsest grid (splat then slice reach one cell each way, a
    cell is sigma pixels) + 2 px per 5x5 GuideNet layer + 2 px of outlier suppression (5x5)."""
    try:
        arch = json.loads(metadata["quietframe.architecture"])
        grids, layers, sigma = int(arch["grids"]), int(arch["layers"]), int(arch["sigma_s"])
    except (KeyError, TypeError, ValueError):
        return None
    coarsest = sigma * 2 ** max(grids - 1, 0) if grids else 1
    return Geometry(
        radius=2 * coarsest * (grids > 0) + 2 * layers + 2,
        align=max(coarsest, 1),
        depth_mean=layers > 0,
    )


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


def overlap_for(geometry: Geometry, motion: np.ndarray | None) -> int:
    reach = 0
    if motion is not None and motion.size:
        reach = int(math.ceil(float(np.abs(motion).max()))) + 1
    return _round_up(geometry.radius + reach, geometry.align)


def plan_tiles(height: int, width: int, overlap: int, align: int, tile_pixels: int) -> list[Tile]:
    """Interior tiles (multiples of `align`, about square) whose padded size fits in
    `tile_pixels` where the overlap allows it; one tile when the frame fits."""
    if height * width <= tile_pixels:
        return [Tile(0, height, 0, width, 0, height, 0, width)]
    side = max((int(math.sqrt(tile_pixels)) - 2 * overlap) // align * align, align)
    return [
        Tile(
            y0, min(y0 + side, height), x0, min(x0 + side, width),
            max(y0 - overlap, 0), min(y0 + side + overlap, height),
            max(x0 - overlap, 0), min(x0 + side + overlap, width),
        )
        for y0 in range(0, height, side)
        for x0 in range(0, width, side)
    ]


def crop(array: np.ndarray, tile: Tile) -> np.ndarray:
    """The padded region of an (N, C, H, W) array, contiguous (what onnxruntime reads)."""
    return np.ascontiguousarray(array[..., tile.py0 : tile.py1, tile.px0 : tile.px1])


def add_ballast(
    feeds: dict[str, np.ndarray], tile: Tile, height: int, width: int, mean_depth: float,
    align: int,
) -> tuple[dict[str, np.ndarray], int, int]:
    """Append a band of `align` rows (or columns) beyond a padded edge that is not the frame's:
    zeros, and depth v with mean(tile + band) = `mean_depth`. Returns the feeds and the rows and
    columns put before the tile (the interior's shift)."""
    depth = feeds["depth"]  # (1, 1, h, w)
    h, w = depth.shape[2:]
    if tile.py1 < height or tile.py0 > 0:
        axis, count, before = 2, align * w, tile.py1 >= height
    else:
        axis, count, before = 3, align * h, tile.px1 >= width
    value = mean_depth + (mean_depth * h * w - float(depth.sum(dtype=np.float64))) / count
    out = {}
    for name, array in feeds.items():
        if array.ndim != 4:
            out[name] = array
            continue
        shape = list(array.shape)
        shape[axis] = align
        band = np.full(shape, value if name == "depth" else 0.0, array.dtype)
        parts = (band, array) if before else (array, band)
        out[name] = np.ascontiguousarray(np.concatenate(parts, axis=axis))
    shift = align if before else 0
    return out, shift * (axis == 2), shift * (axis == 3)


def place(target: np.ndarray, tile: Tile, result: np.ndarray, dy: int = 0, dx: int = 0) -> None:
    """Put the interior of a padded tile's (N, C, h, w) result (shifted by a leading ballast
    band of dy rows / dx columns) in place."""
    oy, ox = tile.y0 - tile.py0 + dy, tile.x0 - tile.px0 + dx
    interior = result[..., oy : oy + tile.y1 - tile.y0, ox : ox + tile.x1 - tile.x0]
    target[..., tile.y0 : tile.y1, tile.x0 : tile.x1] = interior


def tiles_of(
    height: int, width: int, geometry: Geometry, motion: np.ndarray | None, tile_pixels: int
) -> Iterator[Tile]:
    yield from plan_tiles(
        height, width, overlap_for(geometry, motion), geometry.align, tile_pixels
    )


def _round_up(value: int, multiple: int) -> int:
    return -(-value // multiple) * multiple
