"""Dataset reader: windows, crops, spp choice, and augmentation consistency (synthetic frames in
the real on-disk format; no rendering)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from dataset_support import H, W
from dataset_support import write_sequence as _write_sequence

from quietframe.model.data import FrameCache, _to_camera, augment, list_sequences, load_window
from quietframe.scenes import exr_io

torch = pytest.importorskip("torch")



@pytest.fixture(scope="module")
def root(tmp_path_factory):
    r = tmp_path_factory.mktemp("split")
    _write_sequence(r, 1)
    _write_sequence(r, 2)
    (r / "3").mkdir()  # unfinished sequence: manifest lists a missing frame
    (r / "3" / "manifest.json").write_text(
        json.dumps({"seed": 3, "frame_count": 2, "frames": [], "config": {"spp_levels": [1]}})
    )
    return r


def _warp_nearest(img: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """prev sampled at p + motion (integer motion: exact), (H, W, C)."""
    h, w = img.shape[:2]
    ii, jj = np.mgrid[0:h, 0:w]
    y = np.clip(ii + np.rint(motion[..., 1]).astype(int), 0, h - 1)
    x = np.clip(jj + np.rint(motion[..., 0]).astype(int), 0, w - 1)
    return img[y, x]


def test_lists_only_finished_sequences(root):
    seqs = list_sequences(root)
    assert [s.seed for s in seqs] == [1, 2]
    assert seqs[0].resets == [True, False, False] and seqs[0].spp_levels == [1, 2, 4]


def test_window_matches_disk(root):
    seq = list_sequences(root)[0]
    win = load_window(seq, 1, history=2, spp=2)
    assert win["color"].shape == (3, H, W, 3)
    frame1 = exr_io.load_frame(seq.path / seq.files[1], ["color_2spp", "depth"])
    # Model inputs are read through the serving rule (here: negative noisy radiance -> 0).
    assert (frame1["color_2spp"] < 0).any()
    assert np.array_equal(win["color"][2], np.maximum(frame1["color_2spp"], 0))
    # t=1 with history 2: the missing frame -1 repeats frame 0 and is flagged as a reset.
    assert win["reset"].tolist() == [1.0, 1.0, 0.0]


def test_window_reads_no_hit_depth_as_serving_does(root):
    from quietframe.runtime.sanitize import sanitize_buffer

    seq = list_sequences(root)[0]
    path = seq.path / seq.files[0]
    depth = exr_io.load_frame(path, ["depth"])["depth"]
    win = load_window(seq, 0, history=0, spp=1)
    np.testing.assert_array_equal(win["depth"][0], sanitize_buffer("depth", depth)[0])
    hole = depth.copy()
    hole[:4] = 0  # rays that hit nothing, as the renderer writes them
    assert (sanitize_buffer("depth", hole)[0][:4] == hole[4:].max()).all()


@pytest.mark.parametrize("flip", [False, True])
@pytest.mark.parametrize("rot", [0, 1, 2, 3])
def test_augmentation_keeps_motion_consistent(root, flip, rot):
    seq = list_sequences(root)[0]
    win = load_window(seq, 2, history=1, spp=4)
    warped = _warp_nearest(win["reference"][0], win["motion"][1])
    inner = np.s_[4:-4, 4:-4]
    assert np.allclose(warped[inner], win["reference"][1][inner])  # the synthetic truth
    aug = augment(win, flip, rot)
    warped = _warp_nearest(aug["reference"][0], aug["motion"][1])
    assert np.allclose(warped[inner], aug["reference"][1][inner])


def test_camera_normals_turn_with_the_image():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(1, 4, 4, 3)).astype(np.float32)
    # A camera-space normal (x right, y up) and an image-space vector (x right, y down)
    # describe the same in-plane direction; both must rotate the same way.
    window = {"normal": v.copy(), "motion": np.stack([v[..., 0], -v[..., 1]], -1)}
    for flip in (False, True):
        for rot in range(4):
            out = augment(window, flip, rot, normal_space="camera")
            assert np.allclose(out["motion"][..., 0], out["normal"][..., 0])
            assert np.allclose(out["motion"][..., 1], -out["normal"][..., 1])
    # World-space: rotations leave normals alone, flips reflect world X.
    out = augment({"normal": v.copy()}, True, 1, normal_space="world")
    assert np.allclose(np.rot90(np.flip(v, 2), 1, axes=(1, 2))[..., 1:], out["normal"][..., 1:])
    assert np.allclose(np.rot90(np.flip(v, 2), 1, axes=(1, 2))[..., 0], -out["normal"][..., 0])


def test_to_camera_frame():
    to_world = np.eye(4)  # left = +X, up = +Y, forward = +Z
    n = np.array([[[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]]])  # facing the camera; pointing right
    assert np.allclose(_to_camera(n, to_world), [[[0, 0, 1], [1, 0, 0]]])


def test_crop_dataset_items(root):
    from quietframe.model.data import CropDataset

    torch.manual_seed(0)
    ds = CropDataset(root, crop=32, history=2, with_passes=True)
    assert len(ds) == 6
    seen_spp = set()
    for i in range(len(ds)):
        item = ds[i]
        assert item["color"].shape == (3, 3, 32, 32) and item["color"].dtype == torch.float32
        assert item["motion"].shape == (3, 2, 32, 32)
        assert item["passes"].shape == (3, 4, 3, 32, 32)
        assert item["reset"].shape == (3,)
        spp = int(item["spp"])
        seen_spp.add(spp)
        # `color` is the mean of the first `spp` passes (through the serving rule: >= 0), after
        # the same crop and augmentation.
        mean = item["passes"][:, :spp].mean(1).clamp_min(0)
        assert torch.allclose(item["color"], mean, atol=1e-5)
    assert seen_spp <= {1, 2, 4} and len(seen_spp) > 1
    loader = torch.utils.data.DataLoader(ds, batch_size=2, num_workers=0)
    batch = next(iter(loader))
    assert batch["reference"].shape == (2, 3, 3, 32, 32)


def test_cache_is_bounded(root):
    seq = list_sequences(root)[0]
    cache = FrameCache(max_frames=2)
    for t in range(3):
        cache.get(seq.path / seq.files[t], ("reference",))
    assert len(cache._items) == 2
