"""quietframe-eval end to end on a tiny on-disk dataset: shipped models through the runtime,
an extra --model file, the report files; and the metrics order a denoiser must produce."""

from __future__ import annotations

import json
import shutil

import pytest
from dataset_support import write_sequence

pytest.importorskip("matplotlib", reason="the evaluation plots need the train extra")

from quietframe.bench import evaluate  # noqa: E402
from quietframe.runtime import find_model  # noqa: E402
from quietframe.scenes.generator import GENERATOR_VERSION  # noqa: E402


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    for seed in (31, 32):
        write_sequence(root / GENERATOR_VERSION / "validation", seed, frames=4, noise=1.0)
    return root


def test_eval_writes_table_plot_and_crops(data, tmp_path):
    extra = tmp_path / "my-run.onnx"
    shutil.copy(find_model("nbg-2l-3g"), extra)
    out = tmp_path / "report"
    evaluate.main(["--data", str(data), "--spp", "1,4", "--threads", "1",
                   "--methods", "noisy,accumulation,nbg-2l-3g,my-run",
                   "--model", str(extra), "--out", str(out)])
    report = json.loads((out / "benchmarks.json").read_text())
    rows = {(r["method"], r["spp"]): r for r in report["rows"]}
    assert set(rows) == {(m, s) for m in ("noisy", "accumulation", "nbg-2l-3g", "my-run")
                         for s in (1, 4)}
    assert report["meta"]["sequences"] == 2 and report["meta"]["frames"] == 8
    for spp in (1, 4):
        # the same file under two names gives the same scores: one pipeline, no hidden state
        assert rows[("my-run", spp)]["psnr"] == pytest.approx(rows[("nbg-2l-3g", spp)]["psnr"])
    # reference + strong white noise, exact integer motion: averaging 4 frames must help
    assert rows[("accumulation", 1)]["psnr"] > rows[("noisy", 1)]["psnr"] + 1
    assert rows[("nbg-2l-3g", 1)]["psnr"] > rows[("noisy", 1)]["psnr"] + 5
    assert rows[("noisy", 4)]["psnr"] > rows[("noisy", 1)]["psnr"]
    assert all(r["ms_720p"] > 0 for r in report["rows"] if r["method"] != "noisy")
    table = (out / "benchmarks.md").read_text()
    assert "| my-run | 4 |" in table
    for image in ("psnr_vs_ms.png", "crops.png"):
        assert (out / image).stat().st_size > 1000


def test_eval_rejects_a_missing_model_file(data, tmp_path):
    with pytest.raises(SystemExit, match="no such file"):
        evaluate.main(["--data", str(data), "--model", str(tmp_path / "nope.onnx")])


def test_eval_rows_per_kernel_size_and_single_frame(data, tmp_path):
    """--kernel-sizes adds a row per run-time kernel size of a model that has one (and none for
    models without); --single-frame adds the model with its history cleared every frame."""
    torch = pytest.importorskip("torch")
    from quietframe.export.affinity_export import export_affinity
    from quietframe.model import affinity

    torch.manual_seed(0)
    model = affinity.AffinityDenoiser(affinity.VARIANTS["affinity-h8"]).eval()
    extra = export_affinity(model, tmp_path / "aff.onnx")  # default kernel size 13
    out = tmp_path / "report"
    evaluate.main(["--data", str(data), "--spp", "1", "--threads", "1", "--methods",
                   "noisy,accumulation,nbg-2l-3g,aff", "--model", str(extra), "--kernel-sizes",
                   "5,13,6", "--single-frame", "accumulation", "--no-timing", "--out", str(out)])
    rows = {r["method"]: r for r in json.loads((out / "benchmarks.json").read_text())["rows"]}
    # 13 is the default (the plain row), 6 is not an allowed size; NBG has no kernel size
    assert set(rows) == {"noisy", "accumulation", "accumulation/frame", "nbg-2l-3g", "aff",
                         "aff@k5"}
    assert rows["aff@k5"]["psnr"] != pytest.approx(rows["aff"]["psnr"], abs=1e-6)
    # the accumulation without its history is the noisy input again, several dB below itself
    assert rows["accumulation/frame"]["psnr"] == pytest.approx(rows["noisy"]["psnr"], abs=0.5)
    assert rows["accumulation/frame"]["psnr"] < rows["accumulation"]["psnr"] - 1


def test_auto_is_the_services_choice_made_once_per_shot(data, tmp_path):
    """The `auto` row: at each sequence's first frame the service's choice among the installed
    models, then that model's figures on the shot (not a blend, not re-chosen per frame)."""
    out = tmp_path / "auto"
    evaluate.main(["--data", str(data), "--spp", "1", "--threads", "1", "--methods", "auto",
                   "--out", str(out)])
    auto = json.loads((out / "benchmarks.json").read_text())["rows"][0]
    assert auto["method"] == "auto" and sum(auto["chosen"].values()) == 2  # 2 shots, no cut
    assert auto["ms_720p"] != auto["ms_720p"]  # nan: its time is its choice's
    chosen = sorted(auto["chosen"])
    out = tmp_path / "fixed"
    evaluate.main(["--data", str(data), "--spp", "1", "--threads", "1", "--methods",
                   ",".join(chosen), "--no-timing", "--out", str(out)])
    fixed = {r["method"]: r for r in json.loads((out / "benchmarks.json").read_text())["rows"]}
    if len(chosen) == 1:  # both shots went to one model: auto's figures are that model's
        assert auto["psnr"] == pytest.approx(fixed[chosen[0]]["psnr"], abs=1e-6)
        assert auto["trmae"] == pytest.approx(fixed[chosen[0]]["trmae"], abs=1e-6)
    else:
        assert min(r["psnr"] for r in fixed.values()) - 1e-6 <= auto["psnr"] <= max(
            r["psnr"] for r in fixed.values()) + 1e-6


def test_normal_absence_scores_a_model_with_and_without_normals(data, capsys):
    from quietframe.experiments import normal_absence

    normal_absence.main(["--data", str(data), "--renderer", "mitsuba", "--split", "validation",
                         "--sequences", "1", "--spp", "1", "nbg-2l-3g"])
    row = next(r for r in capsys.readouterr().out.splitlines() if r.startswith("| nbg-2l-3g"))
    given, no_normal, no_aux = (float(c) for c in row.strip("| ").split(" | ")[2:])
    assert all(10 < v < 60 for v in (given, no_normal, no_aux))
    assert given != no_normal  # the model reads the normals it is given
