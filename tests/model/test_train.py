"""quietframe-train on a tiny dataset in the real on-disk format: batches are a function of
(seed, step), a paused-and-resumed run equals an uninterrupted one, and the run directory holds
what the docs promise."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest
from dataset_support import write_generator_splits

torch = pytest.importorskip("torch", reason="training needs torch")

from quietframe.model import train as qt  # noqa: E402
from quietframe.model.families import load_checkpoint  # noqa: E402


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    write_generator_splits(root, train_seeds=(11, 12, 13))
    return root


def config(data, **kw) -> qt.TrainConfig:
    base = dict(variant="nbg-2l-1g", width=4, data=str(data), crop=24, frames=2, batch=2,
                steps=6, eval_every=3, log_every=1, threads=1, seed=5)
    return qt.TrainConfig(**{**base, **kw})


def test_batches_depend_only_on_seed_and_step(data):
    a, b = qt.TrainingBatches(config(data)), qt.TrainingBatches(config(data))
    for step in (4, 0, 4, 9):  # any order, across epoch boundaries (4 items / batch 2)
        x, y = a(step), b(step)
        assert all(torch.equal(x[k], y[k]) for k in x)
    assert not torch.equal(a(0)["color"], a(1)["color"])
    other = qt.TrainingBatches(config(data, seed=6))(0)
    assert not torch.equal(other["color"], a(0)["color"])
    assert a(0)["color"].shape == (2, 2, 3, 24, 24)  # (batch, frames, C, crop, crop)


@pytest.mark.parametrize("loss", ["smape+temporal", "l1", "relmse+temporal", "tau+temporal"])
def test_resumed_run_equals_uninterrupted_run(data, tmp_path, loss):
    cfg = config(data, loss=loss)
    qt.train(cfg, tmp_path / "straight")
    qt.train(cfg, tmp_path / "paused", stop_at=4)
    paused = torch.load(tmp_path / "paused" / "checkpoint.pt", weights_only=False)
    assert paused["step"] == 4
    qt.train(cfg, tmp_path / "paused")  # resume to the end
    a = torch.load(tmp_path / "straight" / "checkpoint.pt", weights_only=False)
    b = torch.load(tmp_path / "paused" / "checkpoint.pt", weights_only=False)
    assert a["step"] == b["step"] == 6
    for name, value in a["model"].items():
        assert torch.equal(value, b["model"][name]), name
    assert not torch.equal(a["model"]["guide_net.last.weight"],
                           paused["model"]["guide_net.last.weight"])
    assert all(torch.isfinite(v).all() for v in a["model"].values())


def test_run_directory_contents(data, tmp_path):
    run = tmp_path / "run"
    best = qt.train(config(data), run)
    assert best == run / "best.pt" and best.exists()
    assert json.loads((run / "config.json").read_text())["variant"] == "nbg-2l-1g"
    lines = [json.loads(line) for line in (run / "log.txt").read_text().splitlines()]
    losses = [r for r in lines if "loss" in r]
    evals = [r for r in lines if "val_psnr" in r]
    assert [r["step"] for r in losses] == [1, 2, 3, 4, 5, 6]
    assert [r["step"] for r in evals] == [3, 6]
    assert all(r["val_sequences"] == 1 and math.isfinite(r["val_psnr"]) for r in evals)
    ckpt = torch.load(best, weights_only=False)
    assert ckpt["metrics"]["val_psnr_1spp_last_frame"] == pytest.approx(
        max(r["val_psnr"] for r in evals), abs=1e-3)
    model, _ = load_checkpoint(str(best))
    assert model.config.width == 4


def test_buffer_dropout_zeroes_whole_sequences_deterministically(data):
    cfg = config(data, batch=4, dropout=0.5)
    batch = qt.TrainingBatches(cfg)(0)
    seen = set()
    for step in range(12):
        dropped = qt.drop_buffers(cfg, batch, step)
        assert torch.equal(dropped["color"], batch["color"])  # colour is never dropped
        for name in ("albedo", "normal", "depth", "motion"):
            zero = dropped[name].flatten(1).abs().amax(1) == 0  # per sequence, all frames
            kept = (dropped[name] == batch[name]).flatten(1).all(1)
            assert bool((zero | kept).all()), name
            seen.update((name, bool(z)) for z in zero)
        again = qt.drop_buffers(cfg, batch, step)
        assert all(torch.equal(again[k], dropped[k]) for k in dropped)
    assert {(n, z) for n in ("albedo", "normal", "depth", "motion") for z in (0, 1)} <= seen
    assert qt.drop_buffers(config(data), batch, 0) is batch  # off by default
    with pytest.raises(ValueError, match="color"):
        qt.dropped_buffers(config(data, dropout=0.5, dropout_buffers="color"))


def test_training_with_dropout_runs_and_records_it(data, tmp_path):
    cfg = config(data, dropout=0.5, steps=3)
    qt.train(cfg, tmp_path / "run")
    saved = torch.load(tmp_path / "run" / "best.pt", weights_only=False)["training"]
    assert saved["dropout"] == 0.5 and saved["dropout_buffers"] == "albedo,normal,depth,motion"


def test_learning_rate_decays_to_the_final_fraction():
    cfg = qt.TrainConfig(lr=1e-3, lr_final=0.05, steps=100)
    assert qt.learning_rate(cfg, 0) == pytest.approx(1e-3)
    assert qt.learning_rate(cfg, 50) == pytest.approx(1e-3 * (0.05 + 0.95 * 0.5))
    assert qt.learning_rate(cfg, 100) == pytest.approx(5e-5)
    rates = [qt.learning_rate(cfg, s) for s in range(101)]
    assert all(a >= b for a, b in zip(rates, rates[1:], strict=False))


def test_training_report_summarises_the_log(data, tmp_path, capsys, monkeypatch):
    pytest.importorskip("matplotlib")
    # a repository tool, not part of the package: loaded from its file (registered first, as
    # its dataclasses look their module up)
    path = Path(__file__).resolve().parents[2] / "tools" / "training_report.py"
    spec = importlib.util.spec_from_file_location("training_report", path)
    training_report = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "training_report", training_report)
    spec.loader.exec_module(training_report)

    run = tmp_path / "tiny-run"
    qt.train(config(data), run)
    log = training_report.read_run(run)
    assert [s for s, _ in log.validations] == [3, 6]
    assert log.best[1] == max(v for _, v in log.validations)
    training_report.main([str(run), "--out", str(tmp_path / "docs")])
    assert (tmp_path / "docs" / "training_curves.png").stat().st_size > 1000
    row = next(line for line in capsys.readouterr().out.splitlines() if "tiny-run" in line)
    assert f"| {log.best[1]:.2f} | {log.best[0]} |" in row and "| 6 |" in row


def test_resumed_run_is_rebuilt_from_its_checkpoint_not_the_flags(data, tmp_path):
    run = tmp_path / "run"
    qt.train(config(data), run, stop_at=2)
    # Flags that would build another model are refused; other settings come from the run.
    with pytest.raises(ValueError, match="cannot change a checkpoint's model"):
        qt.resume_config(run, {"width": 8})
    cfg = qt.resume_config(run, {"steps": 9})
    assert (cfg.variant, cfg.width, cfg.steps, cfg.batch) == ("nbg-2l-1g", 4, 9, 2)
    assert qt.resume_config(tmp_path / "new", {"width": 8}).width == 8
    with pytest.raises(SystemExit):  # the CLI says so instead of training a different model
        qt.main(["--run", str(run), "--variant", "nbg-7l-3g"])


def test_outlier_sigmas_reaches_the_nbg_model_and_is_fixed_per_run(data, tmp_path):
    cfg = config(data, outlier_sigmas=0.0, steps=2, eval_every=2)
    assert qt.build_model(cfg).config.outlier_sigmas == 0.0
    assert qt.build_model(config(data)).config.outlier_sigmas == 3.0  # the variant's own
    qt.train(cfg, tmp_path / "run")
    with pytest.raises(ValueError, match="outlier_sigmas"):
        qt.resume_config(tmp_path / "run", {"outlier_sigmas": 3.0})


def test_fine_tuning_starts_from_the_init_checkpoints_weights_with_a_fresh_schedule(data, tmp_path):
    qt.train(config(data, steps=3), tmp_path / "base")
    init = str(tmp_path / "base" / "checkpoint.pt")
    base = torch.load(init, weights_only=False)
    flags = {"init": init, "data": str(data), "crop": 24, "frames": 2, "batch": 2, "steps": 2,
             "eval_every": 2, "threads": 1}
    # The architecture comes from the init checkpoint (no --variant/--width given).
    cfg = qt.resume_config(tmp_path / "tuned", {**flags, "lr": 1e-3})
    assert (cfg.variant, cfg.width) == ("nbg-2l-1g", 4)
    # At lr 0 the run's weights are the init's, weight for weight: the weights were loaded.
    frozen = qt.resume_config(tmp_path / "frozen", {**flags, "lr": 0.0})
    qt.train(frozen, tmp_path / "frozen")
    kept = torch.load(tmp_path / "frozen" / "checkpoint.pt", weights_only=False)
    assert all(torch.equal(v, base["model"][n]) for n, v in kept["model"].items())
    qt.train(cfg, tmp_path / "tuned")
    tuned = torch.load(tmp_path / "tuned" / "checkpoint.pt", weights_only=False)
    assert tuned["step"] == 2  # its own schedule, not the base's 3 steps continued
    assert tuned["training"]["init"] == init
    assert any(not torch.equal(v, base["model"][n]) for n, v in tuned["model"].items())
    with pytest.raises(ValueError, match="drop the flag"):
        qt.resume_config(tmp_path / "other", {"init": init, "width": 8})
    with pytest.raises(SystemExit):  # a missing init checkpoint is a usage error
        qt.main(["--run", str(tmp_path / "x"), "--init", str(tmp_path / "nope.pt")])


def test_a_fine_tune_scores_its_starting_model_first_and_keeps_it_if_nothing_beats_it(
        data, tmp_path, monkeypatch):
    qt.train(config(data, steps=2), tmp_path / "base")
    init = str(tmp_path / "base" / "checkpoint.pt")
    scores = iter([30.0, 29.0, 28.5])  # steps 0, 2, 4: training only made it worse
    monkeypatch.setattr(qt, "validate", lambda model, batches: next(scores))
    cfg = qt.resume_config(tmp_path / "tuned", {"init": init, "data": str(data), "crop": 24,
                                                "frames": 2, "batch": 2, "steps": 4,
                                                "eval_every": 2, "threads": 1})
    best = torch.load(qt.train(cfg, tmp_path / "tuned"), weights_only=False)
    assert best["step"] == 0 and best["best_psnr"] == 30.0
    start = torch.load(init, weights_only=False)
    assert all(torch.equal(v, start["model"][n]) for n, v in best["model"].items())
    evals = [json.loads(x) for x in (tmp_path / "tuned" / "log.txt").read_text().splitlines()]
    assert [(r["step"], r["kept"]) for r in evals if "val_psnr" in r] == [
        (0, True), (2, False), (4, False)]
