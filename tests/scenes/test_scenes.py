"""Scene generator, renderer and on-disk format (Mitsuba `scalar_rgb`: no LLVM needed in CI)."""

from __future__ import annotations

import functools
import json
import os

import numpy as np
import pytest

from quietframe.scenes import architecture, exr_io, furniture, materials, meshes, textures
from quietframe.scenes.camera import Camera, project
from quietframe.scenes.environment import sun_enters
from quietframe.scenes.furnishing import camera_clear
from quietframe.scenes.generator import GENERATOR_VERSION, generate, summary

mi = pytest.importorskip("mitsuba")


def _mesh_ok(m: meshes.MeshData) -> None:
    assert np.allclose(np.linalg.norm(m.normals, axis=1), 1, atol=1e-5)
    p = m.positions[m.faces]
    geo = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = np.linalg.norm(geo, axis=1)
    agree = np.sum(geo * m.normals[m.faces].sum(1), 1)
    assert (agree[area > 1e-9] > 0).all(), "winding must agree with the normals"


def _area(m: meshes.MeshData) -> float:
    p = m.positions[m.faces]
    return float(np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum() / 2)


def test_meshes_are_consistent():
    assert np.isclose(_area(meshes.box((1, 2, 3))), 22.0)
    assert np.isclose(_area(meshes.uv_sphere(1.0, 48, 96)), 4 * np.pi, rtol=2e-3)
    sphere = meshes.uv_sphere(1.0)
    _mesh_ok(sphere)
    assert np.allclose(np.linalg.norm(sphere.positions, axis=1), 1, atol=1e-5)
    # An open cylinder as a lathe: area 2 pi r h, normals pointing away from the axis.
    tube = meshes.lathe([0.5, 0.5], [0.0, 2.0], cols=96)
    assert np.isclose(_area(tube), 2 * np.pi * 0.5 * 2.0, rtol=2e-3)
    assert (np.sum(tube.normals[:, [0, 2]] * tube.positions[:, [0, 2]], 1) > 0).all()
    for m in (
        meshes.box((0.3, 0.5, 0.7)),
        meshes.rounded_box((1, 2, 3), 0.3),
        meshes.cylinder(0.5, 1.0),
        meshes.torus(1.0, 0.3),
        meshes.heightfield(np.random.default_rng(0).random((9, 9))),
        meshes.slats(5, 2.0, 0.1, 0.02, 0.05),
        meshes.table(1.0, 0.6, 0.8, 0.04, 0.04),
        meshes.leaf(0.2, 0.05),
        tube,
    ):
        _mesh_ok(m)


def test_furniture_parts_are_valid_meshes_on_the_floor():
    rng = np.random.default_rng(3)
    for kind in furniture.KINDS:
        p = furniture.draw(kind, rng)
        parts = furniture.parts(kind, p)
        assert parts, kind
        for role, m in parts:
            assert role == "bulb" or role in materials.ROLES, (kind, role)
            _mesh_ok(m)
        lo = min(float(m.positions[:, 1].min()) for _, m in parts)
        if kind not in ("pendant", "picture"):  # these hang from the ceiling or a wall
            assert abs(lo) < 0.02, (kind, lo)  # stands on the floor, does not sink into it


def test_textures_deterministic_and_bounded():
    for kind in textures.PATTERNS:
        a, b = textures.make(kind, 7, 64), textures.make(kind, 7, 64)
        assert a.shape == (64, 64) and np.array_equal(a, b)
        assert a.min() >= 0 and a.max() <= 1 and a.std() > 0.01


def test_generator_reproducible_and_varied():
    a, b = generate(11, 8), generate(11, 8)
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    assert json.dumps(generate(12, 8)) != json.dumps(a)
    assert a["generator"] == GENERATOR_VERSION == "g2"


SEEDS = range(3_000_900, 3_000_912)


@pytest.fixture(scope="module")
def descs():
    return [generate(s, 8) for s in SEEDS]


def test_generated_scenes_keep_their_invariants(descs):
    """Cameras inside a space and clear of furniture; a sun that enters through a window;
    a light path into every scene; moving objects clear of the camera."""
    for d in descs:
        origins = np.array([c["origin"] for c in d["cameras"]])
        assert len(origins) == 8
        assert camera_clear(d, origins).all(), d["seed"]
        assert architecture.inside(d["layout"], origins, 0.3).all()
        targets = np.array([c["target"] for c in d["cameras"]])
        assert (np.linalg.norm(targets - origins, axis=1) > 0.5).all()
        env, layout = d["environment"], d["layout"]
        if layout["kind"] == "interior" and "sun" in env:
            assert sun_enters(d), d["seed"]
        daylight = env["scale"] > 0 and (
            layout["kind"] == "courtyard"
            or any(o["kind"] == "window" and o.get("space") == 0 for o in layout["openings"])
        )
        lamps = any(p.get("light", {}).get("on") for p in d["pieces"])
        assert daylight or lamps, d["seed"]
        if d["lighting"] in ("evening", "night"):
            assert any(p.get("light", {}).get("on") and p["kind"] != "led" for p in d["pieces"])
        for m in d["movers"]:
            pos = np.array([np.asarray(f)[:3, 3] for f in m["frames"]])
            assert np.linalg.norm((pos - origins)[:, [0, 2]], axis=1).min() > 0.5
        for p in d["pieces"]:  # everything stands inside the building
            c = np.asarray(p["transform"])[:3, 3]
            assert architecture.space_of(layout, c) >= 0, (d["seed"], p["kind"])
    summaries = [summary(d) for d in descs]
    assert {s["layout"] for s in summaries} == {"interior", "courtyard"}
    assert {s["lighting"] for s in summaries} == {"sun", "overcast", "evening", "night"}
    assert sum(bool(s["movers"]) for s in summaries) >= len(descs) // 4
    assert sum(s["blinds"] > 0 for s in summaries) >= 3
    kinds = {k for s in summaries for k in s["pieces"]}
    assert {"table", "chair", "bookcase", "plant", "pendant", "picture", "led"} <= kinds


@functools.cache
def _courtyard_seed() -> int:
    """A test seed whose scene is an open courtyard: bright sky light, so 128-spp references
    are clean enough to compare warped frames (indirectly lit rooms are far noisier)."""
    return next(
        s for s in range(3_000_000, 3_000_100) if generate(s, 2)["layout"]["kind"] == "courtyard"
    )


def _pinned_pan(seed: int, n_frames: int, attempt: int) -> dict:
    """A courtyard with the camera replaced by a fast pan (several pixels per frame)."""
    d = generate(_courtyard_seed(), n_frames, attempt)
    cam = Camera(**d["cameras"][0])
    o, t = np.asarray(cam.origin), np.asarray(cam.target)
    view = t - o
    frames = []
    for k in range(n_frames):
        a = np.radians(6.0) * k
        c, s = np.cos(a), np.sin(a)
        v = np.array([c * view[0] + s * view[2], view[1], -s * view[0] + c * view[2]])
        frames.append(Camera(o.tolist(), (o + v).tolist(), [0.0, 1.0, 0.0], 60.0).as_dict())
    d["cameras"], d["cuts"] = frames, []
    d["shots"] = [{"first_frame": 0, "move": "pan"}]
    return d


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from quietframe.scenes.mitsuba_scene import set_variant
    from quietframe.scenes.render import RenderConfig, render_sequence

    set_variant("scalar_rgb")
    cfg = RenderConfig(
        width=32,
        height=24,
        frames=(2, 2),
        spp_levels=(1, 2),
        reference_spp=128,
        variant="scalar_rgb",
    )
    out = tmp_path_factory.mktemp("seq") / "7"
    manifest = render_sequence(7, out, cfg, scene_fn=_pinned_pan)
    return out, cfg, manifest


def test_tiny_render_channels_shapes_finite(tiny):
    out, cfg, manifest = tiny
    assert [f["file"] for f in manifest["frames"]] == ["frame_0000.exr", "frame_0001.exr"]
    assert manifest["frames"][0]["reset"] and not manifest["frames"][1]["reset"]
    expected = {"pass0", "pass1", "color_1spp", "color_2spp", *exr_io.LAYERS}
    for f in manifest["frames"]:
        path = out / f["file"]
        assert set(exr_io.frame_layers(path)) == expected
        frame = exr_io.load_frame(path)
        for name, arr in frame.items():
            n = len(exr_io.layer_spec(name)[0])
            assert arr.shape == (24, 32, n) and arr.dtype == np.float32, name
            assert np.isfinite(arr).all(), name
        assert np.allclose(frame["color_1spp"], frame["pass0"])
        assert np.allclose(frame["color_2spp"], (frame["pass0"] + frame["pass1"]) / 2, rtol=1e-6)
        assert frame["reference"].mean() > 0 and (frame["reference"] >= 0).all()
        norms = np.linalg.norm(frame["normal"][frame["depth"][..., 0] > 0], axis=-1)
        assert np.median(norms) > 0.99 and norms.max() < 1.01  # means of unit normals
        meta = exr_io.read_meta(path)
        assert meta["frame"] == f["index"] and len(meta["world_to_pixel"]) == 3


def test_positions_project_to_their_pixels(tiny):
    """Our camera model is Mitsuba's: mean first-hit positions land in their own pixel."""
    out, _, manifest = tiny
    f = manifest["frames"][1]
    frame = exr_io.load_frame(out / f["file"], ["position", "depth"])
    x, y, _ = project(frame["position"], Camera(**f["camera"]), 32, 24)
    jj, ii = np.meshgrid(np.arange(32) + 0.5, np.arange(24) + 0.5)
    hit = frame["depth"][..., 0] > 0
    err = np.maximum(np.abs(x - jj), np.abs(y - ii))[hit]
    assert np.median(err) < 0.3


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    x, y = np.clip(x - 0.5, 0, w - 1), np.clip(y - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    return top * (1 - fy) + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy


def test_motion_vectors_warp_reference(tiny):
    """Warping frame t-1's reference by the motion reproduces frame t's far better than not
    warping, in pixels flagged visible."""
    out, _, manifest = tiny
    prev = exr_io.load_frame(out / "frame_0000.exr", ["reference"])["reference"]
    cur = exr_io.load_frame(out / "frame_0001.exr", ["reference", "motion", "motion_valid"])
    valid = cur["motion_valid"][..., 0] > 0.99
    assert valid.mean() > 0.5
    assert np.abs(cur["motion"][..., 0][valid]).mean() > 2.0  # the pan moves pixels
    jj, ii = np.meshgrid(np.arange(32) + 0.5, np.arange(24) + 0.5)
    warped = _bilinear(prev, jj + cur["motion"][..., 0], ii + cur["motion"][..., 1])

    def tm(x):
        return x / (1 + x)

    err_warp = np.abs(tm(warped) - tm(cur["reference"]))[valid].mean()
    err_none = np.abs(tm(prev) - tm(cur["reference"]))[valid].mean()
    assert err_warp < 0.5 * err_none, (err_warp, err_none)


def _moving_ball(seed: int, n_frames: int, attempt: int) -> dict:
    """A courtyard (bright sky) emptied of furniture; a static camera looks at a textured ball
    that rolls sideways 0.25 m per frame: all the motion in the image is object motion."""
    d = generate(_courtyard_seed(), n_frames, attempt)
    x0, z0, x1, z1 = d["layout"]["spaces"][0]["rect"]
    eye = np.array([(x0 + x1) / 2, 0.5, z1 - 1.0])
    ball = np.array([eye[0] - 0.25, 0.0, eye[2] - 2.0])
    d["pieces"], d["blockers"], d["cuts"] = [], [], []
    d["cameras"] = [
        Camera(eye.tolist(), (ball + [0, 0.3, 0]).tolist(), [0.0, 1.0, 0.0], 50.0).as_dict()
    ] * n_frames
    d["shots"] = [{"first_frame": 0, "move": "static"}]
    frames = []
    for k in range(n_frames):
        m = np.eye(4)
        c, sn = np.cos(0.8 * k), np.sin(0.8 * k)  # rolls about z while moving along x
        m[:3, :3] = [[c, -sn, 0], [sn, c, 0], [0, 0, 1]]
        m[:3, 3] = ball + [0.25 * k, 0.3, 0]
        back = np.eye(4)
        back[1, 3] = -0.3
        frames.append((m @ back).tolist())
    d["materials"].append(materials.role_material(np.random.default_rng(0), "paper"))
    mats = {"ceramic": len(d["materials"]) - 1}  # a printed texture shows the rolling
    d["movers"] = [
        {
            "kind": "ball",
            "params": {"r": 0.3, "role": "ceramic"},
            "frames": frames,
            "transform": frames[0],
            "materials": mats,
        }
    ]
    return d


def test_object_motion_vectors_warp_a_moving_ball(tmp_path):
    """With a static camera only the ball moves: its pixels get motion, the background none,
    and warping frame t-1 by the motion reproduces frame t better than not warping."""
    from quietframe.scenes.mitsuba_scene import set_variant
    from quietframe.scenes.render import RenderConfig, render_sequence

    set_variant("scalar_rgb")
    w, h = 40, 30
    cfg = RenderConfig(
        width=w, height=h, frames=(2, 2), spp_levels=(1, 2), reference_spp=64, variant="scalar_rgb"
    )
    render_sequence(5, tmp_path, cfg, scene_fn=_moving_ball)
    prev = exr_io.load_frame(tmp_path / "frame_0000.exr", ["reference"])["reference"]
    cur = exr_io.load_frame(tmp_path / "frame_0001.exr", ["reference", "motion", "motion_valid"])
    speed = np.linalg.norm(cur["motion"], axis=-1)
    moving = (speed > 1.0) & (cur["motion_valid"][..., 0] > 0.99)
    assert 10 < moving.sum() < 0.5 * w * h  # the ball, not the whole frame
    assert np.median(speed[speed > 0.01]) > 1.0 and (speed < 0.01).mean() > 0.5
    assert np.median(cur["motion"][..., 0][moving]) < -1.0  # moved right: came from the left
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    warped = _bilinear(prev, jj + cur["motion"][..., 0], ii + cur["motion"][..., 1])

    def tm(x):
        return x / (1 + x)

    err_warp = np.abs(tm(warped) - tm(cur["reference"]))[moving].mean()
    err_none = np.abs(tm(prev) - tm(cur["reference"]))[moving].mean()
    assert err_warp < 0.7 * err_none, (err_warp, err_none)


def test_resume_skips_and_reproduces(tiny):
    from quietframe.scenes.render import render_sequence

    out, cfg, manifest = tiny
    f1 = out / "frame_0001.exr"
    before = exr_io.load_frame(f1)
    stamp = os.path.getmtime(out / "frame_0000.exr")
    f1.unlink()
    again = render_sequence(7, out, cfg, scene_fn=_pinned_pan)
    assert os.path.getmtime(out / "frame_0000.exr") == stamp  # finished frame skipped
    after = exr_io.load_frame(f1)
    assert len(again["frames"]) == 2
    for name in before:  # same seeds -> the same frame, bit for bit
        assert np.array_equal(before[name], after[name]), name


def test_topup_adds_a_higher_spp_level_from_independent_passes(tiny, tmp_path):
    """`topup` (evaluation above the stored passes): the new level averages the stored passes
    with new, independent ones; every stored layer and the render config stay as they were;
    a second run writes nothing; a level the passes already give is refused."""
    import json
    import shutil

    from quietframe.scenes.mitsuba_scene import set_variant
    from quietframe.scenes.stored_sequence import TOPUP_KEY, topup_sequence

    out, cfg, _ = tiny
    seq = tmp_path / out.name
    shutil.copytree(out, seq)
    set_variant("scalar_rgb")
    before = {p.name: exr_io.load_frame(p) for p in sorted(seq.glob("frame_*.exr"))}
    assert topup_sequence(seq, 4) == 2
    for name, layers in before.items():
        after = exr_io.load_frame(seq / name)
        assert set(after) == set(layers) | {"color_4spp"}
        for layer, arr in layers.items():
            assert np.array_equal(arr, after[layer]), layer
        extra = 4 * after["color_4spp"] - 2 * layers["color_2spp"]  # the 2 new samples' sum
        assert np.isfinite(extra).all() and extra.min() > -1e-4
        assert not np.allclose(extra, 2 * layers["color_2spp"])  # new samples, not a copy
        assert 0.5 < extra.mean() / (2 * layers["color_2spp"].mean()) < 2  # same scene, exposure
        assert exr_io.read_meta(seq / name)[TOPUP_KEY] == [4]
    manifest = json.loads((seq / "manifest.json").read_text())
    assert manifest[TOPUP_KEY] == [4] and manifest["config"]["spp_levels"] == [1, 2]
    assert topup_sequence(seq, 4) == 0
    with pytest.raises(ValueError, match="stored already"):
        topup_sequence(seq, 2)


def test_reader_reads_rendered_sequence(tiny):
    torch = pytest.importorskip("torch")
    from quietframe.model.data import SequenceDataset

    out, _, _ = tiny
    ds = SequenceDataset(out.parent, spp=2)
    item = ds[0]
    assert item["color"].shape == (2, 3, 24, 32) and item["color"].dtype == torch.float32
    assert item["motion"].shape == (2, 2, 24, 32)
    assert item["reset"].tolist() == [1.0, 0.0]


@pytest.fixture(scope="module")
def locked(tmp_path_factory):
    """A tiny locked-off sequence of the fast pan: the camera must stay at frame 0's."""
    from quietframe.scenes.mitsuba_scene import set_variant
    from quietframe.scenes.render import RenderConfig, render_sequence

    set_variant("scalar_rgb")
    cfg = RenderConfig(width=32, height=32, frames=(3, 3), spp_levels=(1, 2), reference_spp=16,
                       variant="scalar_rgb", locked_off=True)
    out = tmp_path_factory.mktemp("locked") / "11"
    return out, cfg, render_sequence(11, out, cfg, scene_fn=_pinned_pan)


def test_locked_off_sequence_shares_camera_and_reference_with_fresh_noise(locked):
    out, cfg, manifest = locked
    assert manifest["locked_off"] and manifest["config"]["locked_off"] is True
    assert manifest["cuts"] == [] and len(manifest["scene"]["shots"]) == 1
    frames = [exr_io.load_frame(out / f["file"]) for f in manifest["frames"]]
    metas = [exr_io.read_meta(out / f["file"]) for f in manifest["frames"]]
    assert len(frames) == 3
    assert all(f["camera"] == manifest["frames"][0]["camera"] for f in manifest["frames"])
    assert all(m["to_world"] == metas[0]["to_world"] for m in metas)
    assert all(m["locked_off"] and m["reference_frame"] == 0 for m in metas)
    assert all(m["reference_spp"] == 4 * cfg.reference_spp for m in metas)  # one, at 4x
    for f in frames[1:]:
        assert np.array_equal(f["reference"], frames[0]["reference"])
        assert not np.array_equal(f["color_2spp"], frames[0]["color_2spp"])  # animated seed
        assert not np.array_equal(f["pass0"], frames[0]["pass0"])
    assert frames[0]["reference"].mean() > 0


def test_locked_off_resume_reuses_frame_0_reference(locked, tmp_path, monkeypatch):
    """Resuming after frame 0: the later frames take frame 0's stored reference (no new
    reference render) and come out as before, bit for bit."""
    import shutil

    from quietframe.scenes import render

    out, cfg, _ = locked
    seq = tmp_path / out.name
    shutil.copytree(out, seq)
    before = exr_io.load_frame(seq / "frame_0002.exr")
    for t in (1, 2):
        (seq / f"frame_{t:04d}.exr").unlink()

    def no_reference(*args, **kwargs):
        raise AssertionError("a locked-off resume must reuse frame 0's reference")

    monkeypatch.setattr(render, "render_reference", no_reference)
    again = render.render_sequence(11, seq, cfg, scene_fn=_pinned_pan)
    assert [f["index"] for f in again["frames"]] == [0, 1, 2]
    after = exr_io.load_frame(seq / "frame_0002.exr")
    for name in before:
        assert np.array_equal(before[name], after[name]), name


def test_render_config_key_resumes_old_manifests_and_splits_set_locked_off():
    import argparse

    from quietframe.scenes.cli import _config
    from quietframe.scenes.generator import locked_off
    from quietframe.scenes.render import RenderConfig

    key = RenderConfig().key()
    assert "locked_off" not in key  # key as before: sequences on disk still resume
    assert set(key) == {"width", "height", "frames", "spp_levels", "reference_spp", "max_depth"}
    assert RenderConfig(locked_off=True).key()["locked_off"] is True
    args = argparse.Namespace(size="32x32", frames="3", spp="1,2", reference_spp=16, max_depth=8,
                              variant="scalar_rgb")
    assert _config(argparse.Namespace(**vars(args), split="test-static")).locked_off
    assert not _config(argparse.Namespace(**vars(args), split="test")).locked_off
    assert not _config(args).locked_off  # bench: no split

    desc = generate(3_000_000, 4)
    still = locked_off(desc)
    assert still["cameras"] == [desc["cameras"][0]] * 4 and still["cuts"] == []
    assert all(m["frames"] == [m["frames"][0]] * 4 for m in still["movers"])
    assert desc == generate(3_000_000, 4)  # the input is left as it was


def test_static_seed_ranges_are_disjoint_from_every_other_split():
    from quietframe.scenes.layout import CYCLES_SPLIT_BASE, SPLIT_BASE, split_seeds

    assert {"test-static", "validation-static"} <= set(SPLIT_BASE) & set(CYCLES_SPLIT_BASE)
    bases = sorted([*SPLIT_BASE.values(), *CYCLES_SPLIT_BASE.values()])
    assert min(np.diff(bases)) >= 500_000  # room for far more sequences than any split has
    mitsuba = {s: set(split_seeds(s, 1000)) for s in SPLIT_BASE}
    cycles = {s: set(split_seeds(s, 1000, renderer="cycles")) for s in CYCLES_SPLIT_BASE}
    ranges = [*mitsuba.values(), *cycles.values()]
    assert sum(map(len, ranges)) == len(set().union(*ranges))
