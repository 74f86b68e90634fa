"""Scene generator, renderer and on-disk format (Mitsuba `scalar_rgb`: no LLVM needed in CI)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from quietframe.scenes import exr_io, meshes, textures
from quietframe.scenes.camera import Camera, project
from quietframe.scenes.generator import generate

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
    for m in (
        meshes.box((0.3, 0.5, 0.7)),
        meshes.rounded_box((1, 2, 3), 0.3),
        meshes.cylinder(0.5, 1.0),
        meshes.torus(1.0, 0.3),
        meshes.heightfield(np.random.default_rng(0).random((9, 9))),
        meshes.slats(5, 2.0, 0.1, 0.02, 0.05),
        meshes.table(1.0, 0.6, 0.8, 0.04, 0.04),
    ):
        _mesh_ok(m)


def test_textures_deterministic_and_bounded():
    for kind in textures.PATTERNS:
        a, b = textures.make(kind, 7, 64), textures.make(kind, 7, 64)
        assert a.shape == (64, 64) and np.array_equal(a, b)
        assert a.min() >= 0 and a.max() <= 1 and a.std() > 0.01


def test_generator_reproducible_and_varied():
    a, b = generate(11, 8), generate(11, 8)
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    assert json.dumps(generate(12, 8)) != json.dumps(a)
    descs = [generate(s, 8) for s in range(20, 26)]
    for d in descs:
        assert 10 <= len(d["objects"]) <= 40
        assert len(d["cameras"]) == 8
        assert d["lights"] or d["environment"]["kind"] != "closed"  # closed rooms are lit
        # No object sphere swallows a camera position (camera is not blocked).
        origins = np.array([c["origin"] for c in d["cameras"]])
        for o in d["objects"]:
            centre = np.asarray(o["transform"])[:3, 3]
            assert np.linalg.norm(origins - centre, axis=1).min() > o["radius"]
    kinds = {o["material"]["kind"] for d in descs for o in d["objects"]}
    assert {"diffuse", "roughconductor", "dielectric", "roughplastic"} <= kinds


def _pinned_pan(seed: int, n_frames: int, attempt: int) -> dict:
    """Generator output with the camera replaced by a fast pan (several pixels per frame)."""
    d = generate(seed, n_frames, attempt)
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
    from quietframe.scenes.render import RenderConfig, render_sequence, set_variant

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


def test_reader_reads_rendered_sequence(tiny):
    torch = pytest.importorskip("torch")
    from quietframe.model.data import SequenceDataset

    out, _, _ = tiny
    ds = SequenceDataset(out.parent, spp=2)
    item = ds[0]
    assert item["color"].shape == (2, 3, 24, 32) and item["color"].dtype == torch.float32
    assert item["motion"].shape == (2, 2, 24, 32)
    assert item["reset"].tolist() == [1.0, 0.0]
