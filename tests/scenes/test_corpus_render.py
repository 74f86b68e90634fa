"""The Cycles training corpus rendered by Blender itself (scenes/corpus_scene.py,
corpus_render.py): a tiny corpus shot is written in the zoo's layout with a manifest that says
what it is and what it cost, a re-run renders nothing again, the training reader reads it as it
reads the Cycles splits, and every shot of the corpus builds in Blender. Skipped without a
Cycles venv (tests/cycles_support.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cycles_support import blender_json, require_cycles, run_blender

from quietframe.scenes.corpus_shots import corpus_dir, corpus_shots, describe

# a moving camera without motion blur, so its Vector pass carries the motion
SHOT = next(s for s in corpus_shots("validation") if not s.locked_off and not s.motion_blur)
ARGS = ["-m", "quietframe.scenes.corpus_render", "--split", "validation", "--shots", SHOT.name,
        "--frames", "2", "--size", "48x48", "--spp", "1,4", "--reference-spp", "16"]


@pytest.fixture(scope="module")
def tiny_corpus(tmp_path_factory):
    """SHOT's scene: 2 frames at 48x48, inputs at 1 and 4 spp, a 16-spp reference in halves."""
    require_cycles()
    data = tmp_path_factory.mktemp("corpus")
    log = run_blender([*ARGS, "--out", str(data)])
    return data, log


def _folder(data):
    return corpus_dir(data, "validation") / SHOT.name


def test_a_corpus_shot_is_written_in_the_zoo_layout_with_what_it_is_and_cost(tiny_corpus):
    data, _ = tiny_corpus
    folder = _folder(data)
    for level in ("spp0001", "spp0004", "reference_a", "reference_b"):
        assert sorted(p.name for p in (folder / level).iterdir()) == ["frame_0001.exr",
                                                                     "frame_0002.exr"]
    m = json.loads((folder / "manifest.json").read_text())
    assert m["renderer"] == "cycles" and m["generator"] == "corpus1"
    assert m["seed"] == SHOT.seed and m["shot"]["name"] == SHOT.name
    assert m["config"]["spp_levels"] == [1, 4] and m["config"]["reference_spp"] == 16
    assert m["scene"] == describe(SHOT, m["attempt"])  # the parts it was built from
    assert m["exposure"] > 0 and m["tags"] == m["scene"]["tags"]
    by_kind = m["cpu_s_by_kind"]
    assert by_kind["inputs"] > 0 and by_kind["reference"] > 0
    assert m["cpu_s"] == pytest.approx(sum(by_kind.values()), abs=0.2)
    ref = m["reference"]
    assert ref["spp"] == 16 and ref["halves"] == 2 and set(ref["per_frame"]) == {"0", "1"}
    assert 0 < ref["noise_median"] < 2 and ref["psnr_ceiling_db_median"] > 5
    split = json.loads((folder.parent / "split.json").read_text())
    assert split["shots_done"] == 1 and split["frames_done"] == 2
    assert split["projected_cpu_hours"] > 0


def test_a_rerun_renders_nothing_again(tiny_corpus):
    data, _ = tiny_corpus
    files = sorted(_folder(data).glob("*/*.exr"))
    before = {p: p.stat().st_mtime_ns for p in files}
    manifest = (_folder(data) / "manifest.json").read_text()
    log = run_blender([*ARGS, "--out", str(data)])
    assert "frame 0" not in log and "frame 1" not in log
    assert {p: p.stat().st_mtime_ns for p in files} == before
    assert (_folder(data) / "manifest.json").read_text() == manifest


def test_the_training_reader_reads_a_corpus_shot_as_a_cycles_sequence(tiny_corpus):
    torch = pytest.importorskip("torch")
    from quietframe.model.data import CropDataset, SequenceDataset, list_sequences
    from quietframe.scenes import cycles_io

    data, _ = tiny_corpus
    root = corpus_dir(data, "validation")
    (seq,) = list_sequences(root)
    assert seq.renderer == "cycles" and seq.seed == SHOT.seed and seq.size == (48, 48)
    torch.manual_seed(0)
    item = CropDataset(root, crop=32, history=1)[1]  # frames 0 and 1
    assert item["color"].shape == (2, 3, 32, 32) and item["normal"].shape == (2, 3, 32, 32)
    assert item["motion"].shape == (2, 2, 32, 32) and item["reference"].shape == (2, 3, 32, 32)
    assert item["reset"].tolist() == [1.0, 0.0] and int(item["spp"]) in (1, 4)
    whole = SequenceDataset(root, spp=4)[0]
    reference = cycles_io.load_reference(_folder(data), 1)
    np.testing.assert_allclose(whole["reference"][1].numpy(), reference.transpose(2, 0, 1))
    assert float(whole["motion"][1].abs().mean()) > 0  # the camera moved between the frames
    assert all(bool(torch.isfinite(v).all()) for v in whole.values())


CODE = """
import json, sys
import bpy
from quietframe.scenes import corpus_scene
from quietframe.scenes.corpus_shots import corpus_shots, describe
out = {}
for shot in corpus_shots():
    scene = corpus_scene.build(shot, describe(shot), 1.0)
    out[shot.name] = [len(bpy.data.objects), len([o for o in bpy.data.objects
                                                   if o.type == "CAMERA"]),
                      len(scene.timeline_markers), scene.render.use_motion_blur]
print("@@" + json.dumps(out))
"""


@pytest.mark.slow  # ~16 s: 132 scenes
def test_every_corpus_shot_builds_in_blender():
    built = blender_json(CODE, timeout=600)
    for shot in corpus_shots():
        objects, cameras, markers, blur = built[shot.name]
        d = describe(shot)
        assert objects >= len(d["shell"]) + len(d["props"]), shot.name
        assert cameras == (2 if shot.cut_at is not None else 1), shot.name
        assert markers == (2 if shot.cut_at is not None else 0), shot.name
        assert blur == shot.motion_blur, shot.name


def test_a_bad_size_is_refused_with_what_to_give():
    import subprocess

    result = subprocess.run([require_cycles(), "-m", "quietframe.scenes.corpus_render",
                             "--split", "train", "--size", "160"], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 2 and "give WxH" in result.stderr
