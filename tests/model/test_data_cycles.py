"""Dataset reader on Cycles sequences (scenes/cycles_io.py) and training on a renderer mix:
tiny synthetic sequences in Blender's on-disk layout (per-spp folders of multilayer EXRs named
as Blender names them, two reference halves), written without bpy."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import layout_blender, write_exr
from dataset_support import write_generator_splits, write_sequence

from quietframe.model.data import (
    CropDataset,
    SequenceDataset,
    augment,
    list_sequences,
    load_window,
    window_normal_space,
)
from quietframe.scenes import cycles_io
from quietframe.scenes.generator import GENERATOR_VERSION
from quietframe.scenes.layout import split_dir

torch = pytest.importorskip("torch")

from quietframe.model import train as qt  # noqa: E402

H = W = 20  # square: every quarter turn is drawn
LEVELS = (1, 2, 8)  # 8 is not a Mitsuba level of dataset_support: per-sequence draws show
FRAMES = 4
HEADER = {"BlenderMultiChannel": "Blender V2.55.1 and newer"}


def truth(seed: int, t: int, spp: int | None = None, half: int | None = None) -> dict:
    """What a file holds, in quietframe's conventions: geometry per frame; colour per frame and
    spp level (or per reference half). Normals are camera space, in-plane part parallel to the
    motion (y up versus y down), so a transform that treats them differently shows."""
    rng = np.random.default_rng([seed, t])
    motion = rng.uniform(-3, 3, (H, W, 2)).astype(np.float32)
    normal = np.concatenate([motion[..., :1], -motion[..., 1:], -np.ones((H, W, 1))], -1)
    depth = rng.uniform(2, 9, (H, W)).astype(np.float32)
    depth[0, :3] = 0  # rays that hit nothing
    b = {
        "albedo": rng.uniform(0.1, 0.9, (H, W, 3)).astype(np.float32),
        "normal": (normal / np.linalg.norm(normal, axis=-1, keepdims=True)).astype(np.float32),
        "depth": depth,
        "motion": motion,
    }
    which = [seed, t, 1000 + spp] if spp is not None else [seed, t, 2000 + (half or 0)]
    b["color"] = np.random.default_rng(which).uniform(0, 2, (H, W, 3)).astype(np.float32)
    if spp is not None:
        b["color"][1, 1] = -0.5  # a negative noisy sample: the serving rule makes it 0
    return b


def write_cycles_sequence(root, seed: int, cuts=(), levels=LEVELS, skip: str | None = None):
    """A finished sequence under root/<seed>/ (or one lacking the file `skip` names)."""
    d = root / str(seed)
    for t in range(FRAMES):
        files = {cycles_io.level_dir(s): layout_blender(truth(seed, t, spp=s), noisy=True)
                 for s in levels}
        for i, half in enumerate(cycles_io.REFERENCE_HALVES):
            files[half] = layout_blender(truth(seed, t, half=i))  # Combined, no denoise
        for folder, channels in files.items():
            path = d / folder / cycles_io.frame_file(t)
            if f"{folder}/{path.name}" != skip:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(write_exr(channels, HEADER))
    resets = [t == 0 or t in cuts for t in range(FRAMES)]
    manifest = {
        "generator": GENERATOR_VERSION, "renderer": "cycles", "blender": "4.5.4 LTS",
        "seed": seed, "attempt": 0, "frame_count": FRAMES, "cuts": list(cuts),
        "config": {"width": W, "height": H, "frames": [FRAMES, FRAMES],
                   "spp_levels": list(levels), "reference_spp": 64, "locked_off": False},
        "frames": [{"index": t, "file": cycles_io.frame_file(t), "reset": r, "seconds": {},
                    "cpu_s": {}} for t, r in enumerate(resets)],
    }
    (d / cycles_io.MANIFEST).write_text(json.dumps(manifest))
    return d


@pytest.fixture(scope="module")
def cycles_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("cycles")
    write_cycles_sequence(root, 5_000_001, cuts=(2,))
    write_cycles_sequence(root, 5_000_002)
    write_cycles_sequence(root, 5_000_003, skip="reference_b/frame_0003.exr")
    write_cycles_sequence(root, 5_000_004, skip="spp0008/frame_0004.exr")
    return root


@pytest.fixture(scope="module")
def mitsuba_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("mitsuba")
    write_sequence(root, 1)
    write_sequence(root, 2)
    return root


def test_lists_finished_cycles_sequences_only(cycles_root):
    seqs = list_sequences(cycles_root)
    assert [s.seed for s in seqs] == [5_000_001, 5_000_002]  # 3 and 4 are still rendering
    seq = seqs[0]
    assert seq.renderer == "cycles" and seq.normal_space == "camera"
    assert seq.spp_levels == list(LEVELS) and seq.size == (H, W)
    assert seq.resets == [True, False, True, False]  # the cut at frame 2
    assert seq.files == [f"frame_{t + 1:04d}.exr" for t in range(FRAMES)]


def test_window_has_the_keys_shapes_and_dtypes_of_a_mitsuba_window(cycles_root, mitsuba_root):
    mitsuba = load_window(list_sequences(mitsuba_root)[0], 2, history=2, spp=2)
    cycles = load_window(list_sequences(cycles_root)[0], 2, history=2, spp=2)
    assert cycles.keys() == mitsuba.keys()
    for name, a in mitsuba.items():
        b = cycles[name]
        assert b.dtype == a.dtype == np.float32, name
        assert b.ndim == a.ndim and b.shape[0] == a.shape[0] and b.shape[-1] == a.shape[-1], name
        if b.ndim == 4:
            assert b.shape[1:3] == (H, W), name


def test_inputs_are_the_spp_files_as_the_service_decodes_them(cycles_root):
    from quietframe.runtime.sanitize import sanitize_buffer

    seq = list_sequences(cycles_root)[0]
    for spp in LEVELS:
        win = load_window(seq, 1, history=1, spp=spp)
        for j, t in enumerate((0, 1)):
            want = truth(seq.seed, t, spp=spp)
            # Noisy Image, not Blender's denoised Combined (7 everywhere), through the serving
            # rule: the negative sample becomes 0.
            assert np.array_equal(win["color"][j], np.maximum(want["color"], 0))
            assert win["color"][j][1, 1].tolist() == [0, 0, 0]
            assert np.array_equal(win["albedo"][j], want["albedo"])
            assert np.array_equal(win["normal"][j], want["normal"])
            # Vector converted back to backward motion in pixels, y down.
            assert np.allclose(win["motion"][j], want["motion"])
            # Denoising Depth (not the plain Depth pass, +100), no-hit 0 as serving reads it.
            depth = sanitize_buffer("depth", want["depth"][..., None])[0]
            assert np.array_equal(win["depth"][j], depth)
            assert (win["depth"][j][0, :3] == want["depth"].max()).all()


def test_reference_is_the_mean_of_the_two_halves(cycles_root):
    seq = list_sequences(cycles_root)[1]
    win = load_window(seq, 3, history=3, spp=1)
    for t in range(FRAMES):
        a, b = (truth(seq.seed, t, half=i)["color"] for i in (0, 1))
        np.testing.assert_allclose(win["reference"][t], (a + b) / 2, rtol=1e-6)


def test_a_cut_resets_history_and_motion_valid(cycles_root):
    seq = list_sequences(cycles_root)[0]  # cut at frame 2
    win = load_window(seq, 3, history=2, spp=1)
    assert win["reset"].tolist() == [0.0, 1.0, 0.0]
    # No visibility pass in Cycles: 0 on reset frames (as Mitsuba's), 1 elsewhere.
    assert [float(v.min()) for v in win["motion_valid"]] == [1.0, 0.0, 1.0]
    assert [float(v.max()) for v in win["motion_valid"]] == [1.0, 0.0, 1.0]
    start = load_window(seq, 0, history=1, spp=1)  # before the start: frame 0 repeated
    assert start["reset"].tolist() == [1.0, 1.0] and not start["motion_valid"].any()


def _by_hand(win: dict, flip: bool, rot: int) -> dict:
    """A mirror then `rot` CCW quarter turns, worked out per vector: image motion (x right, y
    down): mirror x -> -x, turn (x, y) -> (y, -x); camera normals (x right, y up): mirror
    x -> -x, turn (x, y) -> (-y, x); z untouched."""
    out = {}
    for name, a in win.items():
        if a.ndim == 4:
            a = np.rot90(a[:, :, ::-1] if flip else a, rot, axes=(1, 2)).copy()
        out[name] = a
    m, n = out["motion"], out["normal"]
    sign = -1.0 if flip else 1.0
    mx, my, nx, ny = sign * m[..., 0], m[..., 1], sign * n[..., 0], n[..., 1]
    for _ in range(rot):
        mx, my, nx, ny = my, -mx, -ny, nx
    out["motion"] = np.stack([mx, my], -1)
    out["normal"] = np.stack([nx, ny, n[..., 2]], -1)
    return out


@pytest.mark.parametrize("flip", [False, True])
@pytest.mark.parametrize("rot", [0, 1, 2, 3])
def test_augmenting_cycles_normals_and_motion_matches_doing_it_by_hand(cycles_root, flip, rot):
    seq = list_sequences(cycles_root)[0]
    win = load_window(seq, 2, history=1, spp=2)
    aug = augment(win, flip, rot, window_normal_space(seq))
    hand = _by_hand(win, flip, rot)
    for name in ("color", "motion", "normal", "reference"):
        assert np.allclose(aug[name], hand[name]), name
    # The in-plane normal still points along the motion (y up versus y down).
    n, m = aug["normal"], aug["motion"]
    assert np.allclose(n[..., 0] * -m[..., 1], n[..., 1] * m[..., 0], atol=1e-5)
    assert (n[..., 0] * m[..., 0] - n[..., 1] * m[..., 1] > 0).all()


def test_crop_dataset_augments_cycles_normals_in_camera_space(cycles_root):
    torch.manual_seed(0)
    ds = CropDataset(cycles_root, crop=H, history=1, spp=2)  # whole frames: no crop offset
    seen = set()
    for i in range(len(ds)):
        item = {k: v.numpy() for k, v in ds[i].items()}
        s, t = ds.items[i]
        plain = load_window(ds.sequences[s], t, history=1, spp=2)
        img = {k: np.moveaxis(v, -3, -1) if v.ndim == 4 else v for k, v in item.items()}
        match = [(f, r) for f in (False, True) for r in range(4)
                 if np.array_equal(_by_hand(plain, f, r)["color"], img["color"])]
        assert len(match) == 1
        hand = _by_hand(plain, *match[0])
        assert np.allclose(img["normal"], hand["normal"]) and np.allclose(img["motion"],
                                                                          hand["motion"])
        seen.add(match[0])
    assert any(r % 2 for _, r in seen)  # a quarter turn, where world space would differ


def test_unsupported_options_raise(cycles_root):
    seq = list_sequences(cycles_root)[0]
    oidn = qt.oidn_settings(qt.TrainConfig(variant="oidn-temporal-fast"))
    with pytest.raises(ValueError, match="with_passes"):
        load_window(seq, 1, 1, 1, with_passes=True)
    with pytest.raises(ValueError, match="oidn"):
        load_window(seq, 1, 1, 1, oidn=oidn)
    with pytest.raises(ValueError, match="normal_space"):
        load_window(seq, 1, 1, 1, normal_space="camera")
    with pytest.raises(ValueError, match="with_passes"):
        CropDataset(cycles_root, with_passes=True)
    with pytest.raises(ValueError, match="oidn"):
        SequenceDataset(cycles_root, oidn=oidn)


def test_mixed_crop_dataset_draws_from_both_renderers(mitsuba_root, cycles_root):
    from torch.utils.data import default_collate

    torch.manual_seed(1)
    ds = CropDataset([mitsuba_root, cycles_root], crop=16, history=1)
    assert [s.renderer for s in ds.sequences] == ["mitsuba"] * 2 + ["cycles"] * 2
    assert len(ds) == 2 * 3 + 2 * FRAMES
    spp = {"mitsuba": set(), "cycles": set()}
    for _ in range(3):
        for i in range(len(ds)):
            item = ds[i]
            assert item["color"].shape == (2, 3, 16, 16) and item["normal"].shape == (2, 3, 16, 16)
            spp[ds.sequences[ds.items[i][0]].renderer].add(int(item["spp"]))
    assert spp["mitsuba"] <= {1, 2, 4} and 4 in spp["mitsuba"]  # each from its own levels
    assert spp["cycles"] <= set(LEVELS) and 8 in spp["cycles"]
    batch = default_collate([ds[0], ds[len(ds) - 1]])  # one of each in a batch
    assert batch["motion_valid"].shape == (2, 2, 1, 16, 16)
    with pytest.raises(FileNotFoundError, match="no finished sequences"):
        CropDataset([mitsuba_root, cycles_root / "missing"])


# ---- training on a renderer mix ------------------------------------------------------------


def _data(root, cycles: bool):
    write_generator_splits(root)
    if cycles:
        for split, base in (("train", 5_000_000), ("validation", 6_000_000)):
            for i in range(2):
                write_cycles_sequence(split_dir(root, split, "cycles"), base + i, cuts=(2,))
    return root


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return _data(tmp_path_factory.mktemp("both"), cycles=True)


def config(data, **kw) -> qt.TrainConfig:
    base = dict(variant="nbg-2l-1g", width=4, data=str(data), crop=16, frames=2, batch=2,
                steps=2, eval_every=2, log_every=1, threads=1, seed=5)
    return qt.TrainConfig(**{**base, **kw})


def test_default_config_is_mitsuba_only_and_unchanged_by_cycles_data(data, tmp_path):
    assert qt.TrainConfig().renderers == "mitsuba"
    alone = _data(tmp_path / "mitsuba", cycles=False)
    a, b = qt.TrainingBatches(config(data)), qt.TrainingBatches(config(alone))
    assert {s.renderer for s in a.dataset.sequences} == {"mitsuba"}
    for step in range(4):
        x, y = a(step), b(step)
        assert all(torch.equal(x[k], y[k]) for k in x), step
    assert len(qt.validation_batches(config(data))) == 1


def test_renderers_name_the_union_of_their_splits(data):
    mixed = qt.TrainingBatches(config(data, renderers="mitsuba,cycles"))
    assert [s.seed for s in mixed.dataset.sequences] == [11, 12, 5_000_000, 5_000_001]
    only = qt.TrainingBatches(config(data, renderers="cycles"))
    assert {s.renderer for s in only.dataset.sequences} == {"cycles"}
    assert only(0)["color"].shape == (2, 2, 3, 16, 16)
    val = qt.validation_batches(config(data, renderers="mitsuba,cycles"))
    assert [v["seed"].item() for v in val] == [21, 6_000_000, 6_000_001]
    assert val[-1]["color"].shape == (1, FRAMES, 3, H, W)
    with pytest.raises(ValueError, match="renderers"):
        qt.split_roots(config(data, renderers="mitsuba,blender"), "train")


def test_the_corpus_joins_the_splits_when_the_run_takes_it(data):
    from quietframe.scenes.corpus_shots import corpus_dir

    write_cycles_sequence(corpus_dir(data, "train"), 9_500_001)
    without = qt.TrainingBatches(config(data, renderers="cycles"))
    assert 9_500_001 not in [s.seed for s in without.dataset.sequences]
    taken = qt.TrainingBatches(config(data, renderers="cycles", corpus=1))
    assert [s.seed for s in taken.dataset.sequences][-1] == 9_500_001
    assert taken(0)["color"].shape == (2, 2, 3, 16, 16)


def test_a_renderer_without_a_split_is_refused_for_training_not_validation(tmp_path):
    data = tmp_path / "data"
    write_cycles_sequence(split_dir(data, "train", "cycles"), 5_000_000)
    assert qt.validation_batches(config(data, renderers="mitsuba,cycles")) == []
    with pytest.raises(FileNotFoundError, match="no finished sequences"):
        qt.TrainingBatches(config(data, renderers="mitsuba,cycles"))


def test_crops_that_cannot_share_a_batch_and_oidn_variants_are_refused(data):
    with pytest.raises(ValueError, match="cannot share a batch"):
        qt.TrainingBatches(config(data, renderers="mitsuba,cycles", crop=32))
    assert qt.TrainingBatches(config(data, renderers="mitsuba,cycles", crop=32, batch=1))
    with pytest.raises(ValueError, match="oidn"):
        qt.TrainingBatches(config(data, renderers="cycles", variant="oidn-temporal-fast"))


def test_training_runs_on_a_mix_and_validates_on_both(data, tmp_path):
    run = tmp_path / "run"
    qt.train(config(data, renderers="mitsuba,cycles"), run)
    lines = [json.loads(x) for x in (run / "log.txt").read_text().splitlines()]
    evals = [r for r in lines if "val_psnr" in r]
    assert [r["val_sequences"] for r in evals] == [3] and np.isfinite(evals[0]["val_psnr"])
    saved = torch.load(run / "checkpoint.pt", weights_only=False)["training"]
    assert saved["renderers"] == "mitsuba,cycles"
    with pytest.raises(SystemExit):
        qt.main(["--renderers", "blender", "--run", str(tmp_path / "bad")])
