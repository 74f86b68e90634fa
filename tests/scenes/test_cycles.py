"""The Cycles back end (scenes/cycles_scene.py, cycles_render.py) and its split reader
(scenes/cycles_io.py): a tiny g2 sequence rendered by Blender itself, read the way the
service reads a farm's upload, sent through the service, and scored with Blender's own denoise
as a method. Skipped without a Cycles venv (tests/cycles_support.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cycles_support import require_cycles, run_blender

SEED = 7_000_000  # the first Cycles test sequence (a moving camera)
LEVELS = (1, 2)


@pytest.fixture(scope="module")
def tiny_split(tmp_path_factory):
    """One 2-frame 48x40 sequence at 1 and 2 spp with a 16-spp reference in two halves."""
    require_cycles()
    data = tmp_path_factory.mktemp("cycles")
    run_blender(["-m", "quietframe.scenes.cycles_render", "--split", "test", "--sequences", "1",
                 "--frames", "2", "--size", "48x40", "--spp", ",".join(map(str, LEVELS)),
                 "--reference-spp", "16", "--reference-min-spp", "8", "--threads", "2",
                 "--out", str(data)])
    return data


def sequence(data):
    from quietframe.scenes.layout import split_dir

    return split_dir(data, "test", renderer="cycles") / str(SEED)


def test_cycles_writes_what_a_blender_farm_writes(tiny_split):
    import OpenEXR

    seq = sequence(tiny_split)
    manifest = json.loads((seq / "manifest.json").read_text())
    assert manifest["renderer"] == "cycles" and manifest["blender"].startswith("4.5")
    assert [f["index"] for f in manifest["frames"]] == [0, 1]
    with OpenEXR.File(str(seq / "spp0002" / "frame_0002.exr"), separate_channels=True) as f:
        header = dict(f.header())
        names = set(f.channels())
    passes = {n.split(".")[1] for n in names}
    assert passes == {"Combined", "Noisy Image", "Denoising Albedo", "Denoising Normal",
                      "Denoising Depth", "Depth", "Vector"}
    assert header["BlenderMultiChannel"].startswith("Blender")
    assert str(header["cycles.ViewLayer.samples"]) == "2"
    for half in ("reference_a", "reference_b"):
        assert (seq / half / "frame_0001.exr").exists() and (seq / half / "frame_0002.exr").exists()
    split = json.loads((seq.parent / "split.json").read_text())
    assert split["frames_done"] == 2 and split["cpu_s"] > 0
    noise = split["reference_noise"]
    assert 0 < noise["median_relative_difference"] < 2 and noise["psnr_ceiling_db_median"] > 10


def test_each_spp_level_is_its_own_render_with_noise_that_changes_per_frame(tiny_split):
    from quietframe.scenes import cycles_io

    seq = sequence(tiny_split)
    one = [cycles_io.load_frame(seq, t, 1) for t in (0, 1)]
    two = cycles_io.load_frame(seq, 0, 2)
    # Not the mean of the 1-spp render and another: a separate render, other samples.
    assert not np.allclose(one[0]["color"], two["color"])
    assert one[0]["color"].shape == (40, 48, 3)
    for frame in (*one, two):
        for name in ("color", "albedo", "normal", "depth", "motion", "blender_denoise",
                     "reference"):
            assert np.isfinite(frame[name]).all(), name
    # Blender's denoise is its own output, not the noisy input.
    assert np.abs(one[0]["blender_denoise"] - one[0]["color"]).mean() > 1e-3
    # The camera moves in this shot: backward motion on frame 1 (frame 0 has no history).
    assert np.abs(one[1]["motion"]).mean() > 0.05


def test_reference_is_the_mean_of_its_independent_halves(tiny_split):
    from quietframe.scenes import cycles_io

    seq = sequence(tiny_split)
    a, b = (cycles_io._decode(seq / h / "frame_0001.exr", {"color": "ViewLayer.Combined"})
            ["color"] for h in cycles_io.REFERENCE_HALVES)
    assert not np.array_equal(a, b)  # independent seeds
    np.testing.assert_allclose(cycles_io.load_reference(seq, 0), (a + b) / 2, rtol=1e-6)


def test_a_cycles_split_frame_round_trips_through_the_service(tiny_split, live_server):
    import httpx
    from conftest import read_exr

    body = (sequence(tiny_split) / "spp0001" / "frame_0001.exr").read_bytes()
    with httpx.Client(base_url=live_server.url, timeout=120) as client:
        session = client.post("/v1/sessions", json={"width": 48, "height": 40}).json()
        reply = client.post(f"/v1/sessions/{session['id']}/frames/1", content=body,
                            headers={"content-type": "image/x-exr"})
    assert reply.status_code == 200, reply.text
    _, channels = read_exr(reply.content)
    given = {n.split(".")[1] for n in channels}
    assert {"Combined", "Noisy Image", "Denoising Albedo", "Vector", "Depth"} <= given
    combined = np.stack([channels[f"ViewLayer.Combined.{c}"] for c in "RGB"])
    assert np.isfinite(combined).all() and combined.mean() > 0


def test_evaluation_scores_blender_denoise_as_a_method(tiny_split, tmp_path):
    from quietframe.bench import evaluate

    evaluate.main(["--data", str(tiny_split), "--renderer", "cycles", "--split", "test",
                   "--spp", "1,2", "--methods", "noisy,blender-denoise,auto", "--threads",
                   "1", "--no-timing", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "benchmarks.json").read_text())["rows"]
    by = {(r["method"], r["spp"]): r for r in rows}
    assert set(by) == {(m, s) for m in ("noisy", "blender-denoise", "auto") for s in LEVELS}
    # auto chose once per shot, with the spp a Cycles header states
    assert all(sum(by[("auto", s)]["chosen"].values()) == 1 for s in LEVELS)
    for spp in LEVELS:
        assert by[("blender-denoise", spp)]["psnr"] > by[("noisy", spp)]["psnr"] + 3
    assert "blender-denoise" in (tmp_path / "benchmarks.md").read_text()
