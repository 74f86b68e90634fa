"""How far an output pixel of each model family reaches into its inputs: the tiling of a card.

One rule per family, derived from the architecture the exporter records, so a card written
before tilings were recorded (every model shipped so far) gets the same tiling as a new export.
Radii are upper bounds in full-resolution pixels, without motion (the warp's reach is added per
frame from the motion buffer, runtime/tiling.py). `align`: tile origins are multiples of it, so
every grid cell, pooling block and resampling grid lies where it lies in the untiled frame.
`bytes_per_pixel`: the graph's transient working set per pixel in onnxruntime without memory
patterns (how tiles run), measured on a 1024² frame as peak RSS added by one run less its
outputs, rounded up by ~25%: accumulation 64, nbg-2l-1g 313, nbg-2l-3g 251, nbg-7l-3g 919,
affinity-h16-k5gc 571, oidn-temporal-acc's graph 240 B/px (this machine, onnxruntime 1.32);
runtime/tiling.py adds the tile's own inputs, state and outputs, which the card's state gives.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from quietframe.runtime.scalar_inputs import InputSpec

# px each way: the learned tiers' albedo prefilter (model/albedo_prefilter), a separable Gaussian
# that every later stage reads through, where the architecture has it on
ALBEDO_PREFILTER_RADIUS = 3

# px: the output history's still test reads the motion's range per block of this size
# (model/temporal.still_pixels), so a tiled frame's tiles align to it
STILL_BLOCK = 8


@dataclass(frozen=True)
class FrameStatistic:
    """A frame-wide quantity a graph computes (not local to a pixel), and how a tile gets it:
    "frame" = the graph's own reduction runs on the whole frame and its value is fed to every
    tile (runtime/statistics.py); "tile" = the tile's own (parity then holds only where the
    statistic does not decide)."""

    name: str  # e.g. "mean_depth"
    buffer: str  # the buffer it is computed from
    how: str  # "frame" | "tile"


@dataclass(frozen=True)
class Tiling:
    """What cutting a frame into tiles needs to know about one graph (runtime/tiling.py)."""

    radius: int  # receptive radius in pixels, without motion and without `reach`
    align: int  # tile origins are multiples of this
    # Extra radius per value of a run-time input (e.g. the affinity kernels' reach by
    # kernel_size); a value not listed counts as the largest listed.
    reach: Mapping[str, Mapping[int, int]] = field(default_factory=dict)
    motion: bool = True  # the graph warps its history: overlap grows with max |motion| + 1
    statistics: tuple[FrameStatistic, ...] = ()
    bytes_per_pixel: int = 1024  # the graph's working set per padded-tile pixel
    # The graph resamples by the ratio of its levels' sizes (bilinear upsampling to a skip's
    # size): a side that is not a multiple of `align` is not cut (runtime/tiling.py).
    size_ratios: bool = False

    def radius_for(self, values: Mapping[str, float | int]) -> int:
        """The radius when the run-time inputs have `values` (name -> value)."""
        extra = 0
        for name, table in self.reach.items():
            value = values.get(name)
            extra += table.get(int(value), max(table.values())) if value is not None \
                else max(table.values())
        return self.radius + extra

    def statistic(self, name: str) -> FrameStatistic | None:
        return next((s for s in self.statistics if s.name == name), None)

    def to_dict(self) -> dict:
        return {"radius": self.radius, "align": self.align,
                "reach": {k: {str(v): r for v, r in t.items()} for k, t in self.reach.items()},
                "motion": self.motion,
                "statistics": [[s.name, s.buffer, s.how] for s in self.statistics],
                "bytes_per_pixel": self.bytes_per_pixel, "size_ratios": self.size_ratios}

    @classmethod
    def from_dict(cls, d: Mapping) -> Tiling:
        return cls(int(d["radius"]), int(d["align"]),
                   {k: {int(v): int(r) for v, r in t.items()} for k, t in d.get("reach",
                                                                               {}).items()},
                   bool(d.get("motion", True)),
                   tuple(FrameStatistic(*s) for s in d.get("statistics", [])),
                   int(d.get("bytes_per_pixel", 1024)), bool(d.get("size_ratios", False)))


# GuideNet's relative depth is depth / mean(depth) over the frame (model/nbg.py guide_features;
# model/affinity.py guide_inputs, at full and at U-Net resolution), and NBG's firefly floor is
# `outlier_floor` × the frame's mean luminance (model/nbg.py suppress_outliers): computed on the
# whole frame by the graph's own reductions and fed to every tile (runtime/statistics.py).
MEAN_DEPTH = FrameStatistic("mean_depth", "depth", "frame")
MEAN_LUMINANCE = FrameStatistic("mean_luminance", "color", "frame")

NBG_BYTES_PER_PIXEL_PER_LAYER = 128  # per GuideNet layer + 1 (the prestage and the grids)
AFFINITY_BYTES_PER_PIXEL = 768
OIDN_TEMPORAL_BYTES_PER_PIXEL = 320
IDENTITY_BYTES_PER_PIXEL = 16
OUTPUT_HISTORY_BYTES_PER_PIXEL = 160


def firefly_clamp(arch: Mapping) -> tuple[int, tuple[FrameStatistic, ...]]:
    """The firefly clamp's reach (model/nbg.suppress_outliers, 5x5: 2 px) and, with a floor,
    its frame-wide statistic; (0, ()) where the architecture has no clamp."""
    if not float(arch.get("outlier_sigmas", 0) or 0) > 0:
        return 0, ()
    return 2, (MEAN_LUMINANCE,) if float(arch.get("outlier_floor", 0) or 0) > 0 else ()


def albedo_prefilter_radius(arch: Mapping) -> int:
    """What the albedo's prefilter adds to a learned tier's radius (0 where it is off)."""
    return ALBEDO_PREFILTER_RADIUS if float(arch.get("albedo_prefilter", 0) or 0) > 0 else 0


def nbg_tiling(arch: Mapping) -> Tiling:
    """2 cells of the coarsest grid (splat then slice reach one cell each way, a cell is sigma
    pixels) + 2 px per 5x5 GuideNet layer + 2 px of outlier suppression (5x5; counted whether
    or not the clamp is on, as every NBG card so far says) + the albedo's prefilter."""
    grids, layers, sigma = int(arch["grids"]), int(arch["layers"]), int(arch["sigma_s"])
    coarsest = sigma * 2 ** max(grids - 1, 0) if grids else 1
    statistics = ((MEAN_DEPTH,) if layers > 0 else ()) + firefly_clamp(arch)[1]
    radius = 2 * coarsest * (grids > 0) + 2 * layers + 2 + albedo_prefilter_radius(arch)
    return Tiling(radius=radius, align=max(coarsest, 1),
                  statistics=statistics,
                  bytes_per_pixel=NBG_BYTES_PER_PIXEL_PER_LAYER * (layers + 1))


def unet_radius(levels: int) -> int:
    """Receptive radius of model/affinity.UNet in its own pixels: two 3x3 convolutions per level
    at stride 2^level down and up, a 2x2 max-pool between levels, bilinear upsampling (one
    coarse pixel) on the way up."""
    down = sum(2 * 2**level for level in range(levels))
    pools = sum(2**level for level in range(levels - 1))
    up = sum(2 * 2**level + 2**(level + 1) for level in range(levels - 1))
    return down + pools + up


def affinity_tiling(arch: Mapping, inputs: Sequence[InputSpec]) -> Tiling:
    """K dilated k×k kernels in sequence (dilations 2^0..2^(K-1), either order) reach
    (k // 2)·(2^K - 1) px, at the `kernel_size` input's value; the kernel parameters come from
    the U-Net at 1/s resolution on s×s block means, upsampled bilinearly (one block each way);
    the temporal kernel gathers the warped history within temporal_kernel_size // 2; the
    albedo's prefilter reaches before all of it. Tile origins are multiples of s·2^(levels-1),
    so blocks and U-Net pooling cells keep their places."""
    scale, levels = int(arch.get("unet_scale", 1)), len(arch["widths"])
    kernels = int(arch.get("kernels", 3))
    dilation_sum = 2**kernels - 1
    params = scale * (unet_radius(levels) + 2)
    temporal = int(arch.get("temporal_kernel_size", 5)) // 2 if arch.get("temporal") else 0
    sizes = next((spec.allowed for spec in inputs if spec.name == "kernel_size"), None)
    sizes = sizes or (int(arch["kernel_size"]),)
    clamp, statistics = firefly_clamp(arch)
    return Tiling(radius=params + temporal + scale + clamp + albedo_prefilter_radius(arch),
                  align=scale * 2 ** (levels - 1),
                  reach={"kernel_size": {int(k): (int(k) // 2) * dilation_sum for k in sizes}},
                  statistics=(MEAN_DEPTH, *statistics),
                  bytes_per_pixel=AFFINITY_BYTES_PER_PIXEL,
                  size_ratios=scale > 1 or levels > 1)


def oidn_temporal_tiling(arch: Mapping) -> Tiling:
    """model/oidn_temporal: (layers - 1) 3x3 convolutions (at 1/net_scale with block means and
    bilinear upsampling), then one spatial kernel and one temporal window at dilation 1."""
    scale = int(arch.get("net_scale", 1))
    net = scale * (int(arch["layers"]) - 1 + (2 if scale > 1 else 0))
    kernels = int(arch["kernel_size"]) // 2 + int(arch["temporal_kernel_size"]) // 2
    return Tiling(radius=net + kernels, align=scale,
                  bytes_per_pixel=OIDN_TEMPORAL_BYTES_PER_PIXEL, size_ratios=scale > 1)


def output_history_tiling(arch: Mapping) -> Tiling:
    """model/output_history: the bicubic fetch reads 2 px beyond the motion target's pixel and
    the clip the 3×3 neighbourhood of OIDN's output: 3 px with the warp's motion on top; the
    detail test (`resampling_detail`) shifts OIDN's output by under half a pixel and back, two
    bicubic fetches: 4 px; the still test reads the motion's range per 8×8 block over
    ⌈still_radius / 8⌉ blocks each way (model/temporal.still_pixels): tiles then align to
    the blocks and reach that many blocks and one more."""
    radius, align = (4 if float(arch.get("resampling_detail", 0) or 0) > 0 else 3), 1
    if (still := int(arch.get("still_radius", 0) or 0)) > 0:
        blocks = -(-still // STILL_BLOCK)
        radius, align = max(radius, STILL_BLOCK * (blocks + 1)), STILL_BLOCK
    return Tiling(radius=radius, align=align, bytes_per_pixel=OUTPUT_HISTORY_BYTES_PER_PIXEL)


def identity_tiling() -> Tiling:
    """A graph that passes a prepass result through (the OIDN-only compositions)."""
    return Tiling(radius=0, align=1, motion=False, bytes_per_pixel=IDENTITY_BYTES_PER_PIXEL)


def tiling_for(arch: Mapping, inputs: Sequence[InputSpec], has_prepass: bool) -> Tiling | None:
    """The family rule for an architecture; None when no rule knows it (the model then runs
    whole, and says so)."""
    try:
        if arch.get("family") == "affinity":
            return affinity_tiling(arch, inputs)
        if arch.get("family") == "output-history":
            return output_history_tiling(arch)
        if "grids" in arch and "layers" in arch:
            return nbg_tiling(arch)
        if has_prepass and "layers" in arch and "kernel_size" in arch:
            return oidn_temporal_tiling(arch)
        if has_prepass:
            return identity_tiling()
    except (KeyError, TypeError, ValueError):
        return None
    return None
