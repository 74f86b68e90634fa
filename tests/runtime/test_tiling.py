"""Large frames run in overlapping tiles (runtime/tiling.py): tiled and untiled runs of the same
sequence agree for every shipped model, so tiles join without seams. Each model's tiles are
sized from its card (overlap = radius + motion, 64-px interiors), history is carried over three
frames, and depth differs 50-fold between the halves of the frame (NBG's GuideNet and the
affinity guide scale depth by its frame mean, which tiles are fed from the whole frame).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import make_buffers

from quietframe.runtime import Denoiser, default_model_path, installed_models
from quietframe.runtime.buffers import planes_from_hwc
from quietframe.runtime.card import ModelCard
from quietframe.runtime.oidn_prepass import PrepassUnavailable
from quietframe.runtime.tiling import (
    DEFAULT_MAX_MEMORY_MB,
    overlap_for,
    plan_tiles,
    tile_bytes_per_pixel,
    tile_pixels_for,
)

HEIGHT, WIDTH, INTERIOR = 320, 384, 64  # multiples of every shipped model's alignment
TOLERANCE = 1e-5  # of the peak: float rounding (measured: <= 3e-7; affinity and OIDN-only 0)


def frames(motion: tuple[float, float], height: int = HEIGHT, width: int = WIDTH,
           count: int = 2):  # the second reads the first's history
    for f in range(count):
        b = make_buffers(height, width, seed=1, noise=10 + f)
        yy, xx = np.mgrid[0:height, 0:width]
        b["depth"] = (1 + 50 * (xx > width // 2) + 0.01 * yy).astype(np.float32)
        b["motion"][..., 0], b["motion"][..., 1] = motion
        yield planes_from_hwc(b)


def tile_pixels(denoiser: Denoiser, motion: tuple[float, float]) -> int:
    """Padded tiles of INTERIOR-pixel interiors for the widest-reaching graph of the model."""
    overlaps = [overlap_for(stage.card.tiling, defaults(stage.card), np.array(motion))
                for stage in denoiser.stages if hasattr(stage, "card")]
    return (2 * max(overlaps) + INTERIOR) ** 2


def defaults(card: ModelCard) -> dict[str, float | int]:
    return {spec.name: spec.default for spec in card.inputs}


def load(path, tiles):
    try:
        return Denoiser(path, threads=2, tile_pixels=tiles)
    except PrepassUnavailable:
        pytest.skip("pyoidn not installed")


def assert_runs_agree(path, motion, height=HEIGHT, width=WIDTH):
    whole = load(path, None)
    tiles = tile_pixels(whole, motion)
    tiled = load(path, tiles)
    tiling = tiled.graph.card.tiling
    overlap = overlap_for(tiling, defaults(tiled.graph.card), np.array(motion))
    plan = plan_tiles(height, width, overlap, tiling.align, tiles, tiling.size_ratios)
    assert len(plan) > 1 or not tiling.radius  # the pass-through graph of OIDN-only models
    state_whole = state_tiled = None
    for planes in frames(motion, height, width):
        a, b = whole.denoise(planes, state_whole), tiled.denoise(planes, state_tiled)
        state_whole, state_tiled = a.state, b.state
        scale = np.abs(a.color).max()
        assert np.abs(a.color - b.color).max() <= TOLERANCE * scale
        for name in a.state:  # the history agrees to the same rounding
            peak = max(np.abs(a.state[name]).max(), 1e-6)
            assert np.abs(a.state[name] - b.state[name]).max() <= TOLERANCE * peak, name


@pytest.mark.parametrize("path", installed_models(), ids=lambda p: p.stem)
def test_every_shipped_model_tiles_seamlessly(path):
    assert ModelCard.from_props({}, "x").tiling is None  # a model no rule knows runs whole
    assert_runs_agree(path, (1.3, -0.7))


def test_large_motion_widens_the_overlap():
    """The default model with motion of (-37.2, 21.6) px: the overlap covers the warp's reach."""
    assert_runs_agree(default_model_path(), (-37.2, 21.6))


def test_affinity_tiles_a_side_that_is_not_aligned_in_strips():
    """322 rows are no multiple of the U-Net's 8: tiles span all rows (its upsampling ratios
    are then the frame's), columns are cut."""
    path = next(p for p in installed_models() if p.stem.startswith("affinity"))
    assert_runs_agree(path, (1.3, -0.7), 322, 384)


def test_one_memory_setting_chooses_the_tile_size():
    nbg = Denoiser(default_model_path(), threads=1)
    assert nbg.max_memory_mb == DEFAULT_MAX_MEMORY_MB
    assert nbg.tile_pixels > 1920 * 1080  # 1080p still runs whole through NBG-2l
    path = next(p for p in installed_models() if p.stem.startswith("affinity"))
    small = Denoiser(path, threads=1, max_memory_mb=256)
    card = small.card
    # the graph's 768 B/px + 4 B x (12 buffer + 2 x (18 + 32/4) state + 3 output) channels
    assert tile_bytes_per_pixel(card.tiling, card.state) == 768 + 4 * (12 + 2 * 26 + 3)
    assert small.tile_pixels == tile_pixels_for(card.tiling, card.state, 256)
    # what a memory guard can reserve: bounded by the setting at any frame size
    assert small.working_set_bytes(4320, 7680) <= 256 * 2**20
    assert small.working_set_bytes(64, 64) == 64 * 64 * tile_bytes_per_pixel(card.tiling,
                                                                              card.state)
    side = math.isqrt(small.tile_pixels)
    tiles = plan_tiles(2160, 3840, overlap_for(card.tiling, {"kernel_size": 5}, None),
                       card.tiling.align, small.tile_pixels)
    assert all((t.py1 - t.py0) * (t.px1 - t.px0) <= side * side for t in tiles)


def test_a_composition_shares_the_bound_with_oidn():
    """The bound is shared: half for OIDN's scratch, half for the graphs' tiles. OIDN's images
    (colour, aux, output: 4 × 12 B/px here) are whole-frame, like the frame's own buffers."""
    composed = load(next(p for p in installed_models() if p.stem == "oidn-temporal-acc"),
                    "by_memory")
    composed = Denoiser(composed.info.path, threads=1, max_memory_mb=512)
    assert composed.prepass.max_memory_mb == 256
    for stage in (composed.color_stage, composed.graph):
        assert stage.tile_pixels == tile_pixels_for(stage.card.tiling, stage.card.state, 256)
    oidn_images = 4 * 12 * 4320 * 7680
    assert composed.prepass.working_set_bytes(4320, 7680) == oidn_images + 256 * 2**20
    assert composed.working_set_bytes(4320, 7680) <= oidn_images + 512 * 2**20


def test_kernel_size_sets_the_affinity_reach():
    path = next(p for p in installed_models() if p.stem.startswith("affinity"))
    tiling = Denoiser(path, threads=1).card.tiling
    arch_kernels = 5  # affinity-h16-k5gc: K = 5 kernels, dilations 1..16
    for k in (5, 13):
        assert tiling.radius_for({"kernel_size": k}) == tiling.radius + (k // 2) * (
            2**arch_kernels - 1)
    assert tiling.align == 8 and tiling.statistic("mean_depth").how == "frame"


def test_tiles_cover_the_frame_once():
    tiles = plan_tiles(1000, 1700, 80, 16, 512 * 512)
    covered = np.zeros((1000, 1700), np.int32)
    for t in tiles:
        covered[t.y0 : t.y1, t.x0 : t.x1] += 1
        assert (t.py1 - t.py0) * (t.px1 - t.px0) <= 512 * 512
    assert (covered == 1).all()
