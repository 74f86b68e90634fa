"""quietframe-train --select-on zoo|corpus|zoo+corpus: best.pt is picked on the zoo's or the
training corpus's validation shots. Tiny shots in Blender's on-disk layout (per-spp folders of
multilayer EXRs, two reference halves, the zoo's folder names), written without bpy; the
generator's splits from dataset_support."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from conftest import layout_blender, write_exr
from dataset_support import write_generator_splits, write_sequence

torch = pytest.importorskip("torch", reason="training needs torch")

from quietframe.model import train as qt  # noqa: E402
from quietframe.model import zoo_selection as zs  # noqa: E402
from quietframe.model.metrics import psnr  # noqa: E402
from quietframe.runtime.buffers import BUFFER_NAMES  # noqa: E402
from quietframe.scenes import cycles_io  # noqa: E402
from quietframe.scenes.corpus_shots import corpus_dir, corpus_shots  # noqa: E402
from quietframe.scenes.generator import GENERATOR_VERSION  # noqa: E402
from quietframe.scenes.zoo_shots import zoo_dir  # noqa: E402

H, W = 24, 40  # a 32 px crop takes the whole height and the centre 32 columns
CROP = 32
SHIFT = (2, 1)  # frame t at pixel p shows frame t-1 at p + SHIFT: backward motion, x right y down
LEVELS = (1, 4)
HEADER = {"BlenderMultiChannel": "Blender V2.55.1 and newer"}


def scene(seed: int, frames: int) -> list[dict[str, np.ndarray]]:
    """A camera sliding over one smooth image: per frame the clean buffers (reference colour,
    albedo, normal, depth) and the exact backward motion."""
    rng = np.random.default_rng(seed)
    size = (H + 16, W + 24)  # room for 8 frames, whatever the count (a partial render's too)

    def smooth(c: int) -> np.ndarray:
        x = rng.random((*size, c)).astype(np.float32)
        return (x + np.roll(x, 1, 0) + np.roll(x, 1, 1)) / 3

    normal = smooth(3) - 0.5
    normal[..., 2] = -1  # Cycles camera space: z away from the viewer
    big = {"reference": 2 * smooth(3), "albedo": 0.2 + 0.6 * smooth(3),
           "normal": normal / np.linalg.norm(normal, axis=-1, keepdims=True),
           "depth": 3 + smooth(1)[..., 0]}
    out = []
    for t in range(frames):
        x0, y0 = 1 + SHIFT[0] * t, 1 + SHIFT[1] * t
        frame = {k: np.ascontiguousarray(v[y0 : y0 + H, x0 : x0 + W]) for k, v in big.items()}
        frame["motion"] = np.broadcast_to(np.float32(SHIFT), (H, W, 2)).copy()
        out.append(frame)
    return out


def noisy(frame: dict, seed: int, t: int, spp: int) -> np.ndarray:
    noise = np.random.default_rng([seed, t, spp]).normal(0, 1.5 / np.sqrt(spp), (H, W, 3))
    return np.maximum(frame["reference"] + noise, 0).astype(np.float32)


def halves(frame: dict, seed: int, t: int) -> tuple[np.ndarray, np.ndarray]:
    d = np.random.default_rng([seed, t, 99]).normal(0, 0.02, (H, W, 3)).astype(np.float32)
    return frame["reference"] + d, frame["reference"] - d


def write_shot(data, zoo: str, name: str, seed: int, frames: int = 4, rendered: int | None = None,
               cuts=(), levels=LEVELS):
    """A zoo validation shot as scenes/zoo_render.py leaves it (zoo "corpus": a corpus
    validation shot, the same layout): `rendered` of its `frames` done (a render in progress),
    each with every spp level and both reference halves."""
    folder = (corpus_dir(data, "validation") if zoo == "corpus"
              else zoo_dir(data, "validation", zoo)) / name
    done = frames if rendered is None else rendered
    truth = scene(seed, frames)
    for t in range(done):
        files = {cycles_io.level_dir(s): layout_blender(
            {**truth[t], "color": noisy(truth[t], seed, t, s)}, noisy=True) for s in levels}
        for half, colour in zip(cycles_io.REFERENCE_HALVES, halves(truth[t], seed, t),
                                strict=True):
            files[half] = layout_blender({**truth[t], "color": colour})
        for sub, channels in files.items():
            path = folder / sub / cycles_io.frame_file(t)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(write_exr(channels, HEADER))
    manifest = {
        "generator": zoo, "renderer": "cycles", "seed": seed, "frame_count": frames,
        "cuts": list(cuts),
        "config": {"width": W, "height": H, "spp_levels": list(levels), "locked_off": False},
        "frames": [{"index": t, "file": cycles_io.frame_file(t), "reset": t == 0 or t in cuts}
                   for t in range(done)],
    }
    (folder / cycles_io.MANIFEST).write_text(json.dumps(manifest))
    return folder


def tiny_model(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return qt.build_model(qt.TrainConfig(variant="nbg-2l-1g", width=4))


def expected_psnr(model, seed: int, frames: int, spp: int, resets) -> float:
    """Mean per-frame PSNR of the model unrolled by hand on the truth written to disk
    (centre crop, the history restarted where `resets` says)."""
    crop = slice(0, H), slice((W - CROP) // 2, (W - CROP) // 2 + CROP)
    truth = scene(seed, frames)
    buffers = {name: [] for name in BUFFER_NAMES}
    for t, frame in enumerate(truth):
        planes = {**frame, "color": noisy(frame, seed, t, spp)}
        for name in BUFFER_NAMES:
            a = planes[name] if planes[name].ndim == 3 else planes[name][..., None]
            buffers[name].append(torch.from_numpy(a[crop].transpose(2, 0, 1).copy()))
    batch = {k: torch.stack(v)[None] for k, v in buffers.items()}
    batch["reset"] = torch.tensor([[float(r) for r in resets]])
    with torch.no_grad():
        outputs = qt.unroll(model, batch)
    scores = []
    for t, out in enumerate(outputs):
        a, b = halves(truth[t], seed, t)
        scores.append(psnr(out[0].numpy().transpose(1, 2, 0), ((a + b) / 2)[crop]))
    return float(np.mean(scores))


def zoo_config(data, **kw) -> qt.TrainConfig:
    base = dict(variant="nbg-2l-1g", width=4, data=str(data), crop=24, frames=2, batch=2,
                steps=6, eval_every=2, log_every=1, threads=1, seed=5, select_on="zoo",
                select_spp="1,4", select_frames=4, select_crop=CROP)
    return qt.TrainConfig(**{**base, **kw})


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    write_generator_splits(root)
    write_shot(root, "zoo1", "gallery-pan", seed=1, frames=4, cuts=(2,))
    write_shot(root, "zoo2", "fence-truck", seed=2, frames=6, rendered=3)  # still rendering
    write_shot(root, "zoo3", "study-dolly", seed=3, frames=4, levels=(1,))  # no 4 spp level
    return root


def test_sequences_are_the_rendered_shots_and_say_what_they_skip(data):
    notes: list[str] = []
    seqs = zs.zoo_sequences(zoo_config(data), notes)
    assert [(s.zoo, s.shot, s.spp, s.frames) for s in seqs] == [
        ("zoo1", "gallery-pan", 1, 4), ("zoo1", "gallery-pan", 4, 4),
        ("zoo2", "fence-truck", 1, 3), ("zoo2", "fence-truck", 4, 3),
        ("zoo3", "study-dolly", 1, 4)]
    assert "zoo1/study-locked not rendered, skipped" in " ".join(notes)
    assert "zoo3/study-dolly has no frame at 4 spp, skipped" in " ".join(notes)
    capped = zs.zoo_sequences(zoo_config(data, select_frames=2, select_spp="4"))
    assert [(s.shot, s.frames) for s in capped] == [("gallery-pan", 2), ("fence-truck", 2)]


def test_the_score_is_each_shots_frames_with_the_state_carried_through_a_runtime_stream(data):
    model = tiny_model()
    lines: list[str] = []
    seqs = [s for s in zs.zoo_sequences(zoo_config(data)) if s.zoo != "zoo3"]
    result = zs.score(model, seqs, CROP, lines.append)
    carried = {"gallery-pan": expected_psnr(model, 1, 4, 1, [1, 0, 1, 0]),  # the cut at 2
               "fence-truck": expected_psnr(model, 2, 3, 1, [1, 0, 0])}
    for shot, want in carried.items():
        assert result.per_shot[shot]["psnr"]["1"] == pytest.approx(want, abs=2e-3), shot
        fresh = expected_psnr(model, {"gallery-pan": 1, "fence-truck": 2}[shot],
                              result.per_shot[shot]["frames"], 1, [1] * 4)
        assert abs(fresh - want) > 0.05, shot  # the history matters: a dropped one would show
    assert result.per_shot["fence-truck"]["frames"] == 3
    four = expected_psnr(model, 1, 4, 4, [1, 0, 1, 0])
    assert result.per_shot["gallery-pan"]["psnr"]["4"] == pytest.approx(four, abs=2e-3)
    means = [v for s in result.per_shot.values() for v in s["psnr"].values()]
    assert result.psnr == pytest.approx(np.mean(means), abs=2e-3)
    assert lines[0].startswith("zoo gallery-pan (4 frames): 1 spp ")
    assert lines[-1] == f"zoo mean {result.psnr:.3f} dB"
    assert model.training  # left in training mode


def test_a_zoo_run_keeps_the_zoo_best_when_the_generator_disagrees(data, tmp_path, monkeypatch):
    real = zs.score
    # Evaluations at steps 2, 4, 6: the generator's split prefers step 2, the zoo step 4.
    generator, zoo = iter([30.0, 20.0, 10.0]), iter([20.0, 25.0, 22.0])
    monkeypatch.setattr(qt, "validate", lambda model, batches: next(generator))
    monkeypatch.setattr(zs, "score", lambda *a, **k: dataclasses.replace(real(*a, **k),
                                                                         psnr=next(zoo)))
    run = tmp_path / "zoo"
    best = qt.train(zoo_config(data), run)
    saved = torch.load(best, weights_only=False)
    assert saved["step"] == 4 and saved["best_psnr"] == 25.0
    m = saved["metrics"]
    assert m["selected_on"] == "zoo" and m["zoo_psnr"] == 25.0 and m["step"] == 4
    assert m["val_psnr_1spp_last_frame"] == 20.0  # the generator's score of that checkpoint
    assert set(m["zoo_per_shot"]) == {"gallery-pan", "fence-truck", "study-dolly"}
    assert m["zoo_sequences"] == 5
    evals = [json.loads(x) for x in (run / "log.txt").read_text().splitlines()]
    evals = [r for r in evals if "zoo_psnr" in r]
    assert [(r["step"], r["kept"]) for r in evals] == [(2, True), (4, True), (6, False)]
    assert [r["val_psnr"] for r in evals] == [30.0, 20.0, 10.0]
    latest = torch.load(run / "checkpoint.pt", weights_only=False)
    assert latest["step"] == 6 and latest["metrics"]["step"] == 4
    assert any(not torch.equal(v, latest["model"][k]) for k, v in saved["model"].items())
    # The same run selecting on the generator's split keeps its step 2.
    generator = iter([30.0, 20.0, 10.0])
    plain = torch.load(qt.train(zoo_config(data, select_on="validation"), tmp_path / "val"),
                       weights_only=False)
    assert plain["step"] == 2 and "selected_on" not in plain["metrics"]


def test_the_flags_come_from_the_config_and_a_resumed_run_keeps_them(data, tmp_path):
    run = tmp_path / "run"
    args = ["--variant", "nbg-2l-1g", "--width", "4", "--data", str(data), "--crop", "24",
            "--frames", "2", "--batch", "2", "--steps", "4", "--eval-every", "2",
            "--threads", "1", "--run", str(run)]
    assert qt.main([*args, "--select-on", "zoo", "--select-spp", "1", "--select-frames", "2",
                    "--select-crop", "16", "--stop-at", "2"]) == 0
    resumed = qt.resume_config(run, {"steps": 4})
    assert (resumed.select_on, resumed.select_spp, resumed.select_frames,
            resumed.select_crop) == ("zoo", "1", 2, 16)
    assert qt.main(args) == 0  # resumed without the flags: still selected on the zoo
    saved = torch.load(run / "best.pt", weights_only=False)
    assert saved["training"]["select_on"] == "zoo" and saved["metrics"]["selected_on"] == "zoo"
    assert {s["frames"] for s in saved["metrics"]["zoo_per_shot"].values()} == {2}


def test_no_rendered_zoo_shot_is_an_error_before_any_step(data, tmp_path, capsys):
    empty = tmp_path / "data"
    for split in ("train", "validation"):
        write_sequence(empty / GENERATOR_VERSION / split, 31, frames=3)
    with pytest.raises(FileNotFoundError, match="no validation shot is rendered"):
        qt.train(zoo_config(empty), tmp_path / "run")
    assert not (tmp_path / "run").exists()
    with pytest.raises(SystemExit) as exit_:
        qt.main(["--select-on", "zoo", "--data", str(empty), "--run", str(tmp_path / "cli")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "no validation shot is rendered" in err and "--select-on validation" in err
    assert "docs/zoo.md" in err
    with pytest.raises(SystemExit):  # a shot lacking every level asked for counts as none
        qt.main(["--select-on", "zoo", "--select-spp", "64", "--data", str(data),
                 "--run", str(tmp_path / "cli")])
    for bad, match in ((dict(select_on="test"), "select_on"), (dict(select_spp="1,x"), "spp"),
                       (dict(variant="oidn-temporal-fast"), "OIDN")):
        with pytest.raises(ValueError, match=match):
            zs.check(zoo_config(data, **bad))


def test_corpus_selection_reads_the_corpus_validation_shots_and_not_the_zoos(data, tmp_path):
    root = tmp_path / "data"
    write_generator_splits(root)
    first, second = (s.name for s in corpus_shots("validation")[:2])
    write_shot(root, "corpus", first, seed=4, frames=3)
    write_shot(root, "zoo1", "gallery-pan", seed=1, frames=4)
    notes: list[str] = []
    seqs = zs.zoo_sequences(zoo_config(root, select_on="corpus"), notes)
    assert [(s.zoo, s.shot, s.spp, s.frames) for s in seqs] == [
        ("corpus", first, 1, 3), ("corpus", first, 4, 3)]
    assert f"corpus/{second} not rendered, skipped" in " ".join(notes)
    both = zs.zoo_sequences(zoo_config(root, select_on="zoo+corpus"))
    assert {(s.zoo, s.shot) for s in both} == {("zoo1", "gallery-pan"), ("corpus", first)}
    best = torch.load(qt.train(zoo_config(root, select_on="corpus", steps=2), tmp_path / "run"),
                      weights_only=False)
    assert best["metrics"]["selected_on"] == "corpus"
    assert set(best["metrics"]["zoo_per_shot"]) == {first}
    with pytest.raises(FileNotFoundError, match="corpus-cycles/validation"):
        zs.zoo_sequences(zoo_config(data, select_on="corpus"))  # zoo shots only there
