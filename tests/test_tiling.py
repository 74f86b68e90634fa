"""Large frames run in overlapping tiles (runtime/tiling.py): tiled and untiled runs of the same
sequence agree, so tiles join without seams. 512x384 frames cut into 200x200-pixel padded tiles
(24 tiles, 192 with the larger motion's wider overlap), history carried over three frames, depth
that differs 50-fold between the halves of the frame (the GuideNet's depth scale is frame-wide).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_buffers

from quietframe.runtime import Denoiser, default_model_path
from quietframe.runtime.buffers import planes_from_hwc
from quietframe.runtime.tiling import model_geometry, plan_tiles

TILE_PIXELS = 200 * 200


@pytest.fixture(scope="module")
def pair():
    path = default_model_path()
    return Denoiser(path, threads=1, tile_pixels=None), Denoiser(path, 1, TILE_PIXELS)


def frames(motion: tuple[float, float], count: int = 3):
    for f in range(count):
        b = make_buffers(384, 512, seed=1, noise=10 + f)
        yy, xx = np.mgrid[0:384, 0:512]
        b["depth"] = (1 + 50 * (xx > 256) + 0.01 * yy).astype(np.float32)
        b["motion"][..., 0], b["motion"][..., 1] = motion
        yield planes_from_hwc(b)


@pytest.mark.parametrize("motion", [(1.3, -0.7), (-37.2, 21.6)])
def test_tiled_run_matches_untiled(pair, motion):
    whole, tiled = pair
    geometry = tiled.geometry
    assert geometry is not None and geometry.depth_mean
    tiles = plan_tiles(384, 512, 64, geometry.align, TILE_PIXELS)
    assert len(tiles) > 1
    assert all(t.y0 % geometry.align == 0 == t.x0 % geometry.align for t in tiles)
    state_whole = state_tiled = None
    for planes in frames(motion):
        a, b = whole.denoise(planes, state_whole), tiled.denoise(planes, state_tiled)
        state_whole, state_tiled = a.state, b.state
        scale = np.abs(a.color).max()
        assert np.abs(a.color - b.color).max() <= 1e-4 * scale  # float rounding only
        for name in a.state:  # the history is exact
            np.testing.assert_array_equal(a.state[name], b.state[name])


def test_geometry_from_the_model_card():
    meta = Denoiser(default_model_path(), threads=1).info.metadata
    geometry = model_geometry(meta)
    assert geometry is not None and geometry.radius >= 2 * geometry.align
    assert model_geometry({}) is None  # unknown models are not tiled


def test_tiles_cover_the_frame_once():
    tiles = plan_tiles(1000, 1700, 80, 16, 512 * 512)
    covered = np.zeros((1000, 1700), np.int32)
    for t in tiles:
        covered[t.y0 : t.y1, t.x0 : t.x1] += 1
        assert (t.py1 - t.py0) * (t.px1 - t.px0) <= 512 * 512
    assert (covered == 1).all()
