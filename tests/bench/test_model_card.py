"""Model cards are written from the graph's metadata, the data manifests and a measurement."""

from __future__ import annotations

import json
import re

import pytest
from dataset_support import write_sequence

torch = pytest.importorskip("torch")

from quietframe.bench.model_card import write_model_card  # noqa: E402
from quietframe.export.onnx_export import export_nbg  # noqa: E402
from quietframe.model.nbg import VARIANTS, NBGDenoiser  # noqa: E402
from quietframe.scenes.generator import GENERATOR_VERSION  # noqa: E402


def test_card_reports_architecture_data_speed_and_metrics(tmp_path):
    data = tmp_path / "data"
    for split, seeds in (("train", (3, 4)), ("validation", (9,))):
        for seed in seeds:
            write_sequence(data / GENERATOR_VERSION / split, seed, frames=3, levels=(1, 2))
    torch.manual_seed(0)
    path = export_nbg(NBGDenoiser(VARIANTS["nbg-2l-1g"]), tmp_path / "nbg-2l-1g.onnx",
                      version="7", training={"variant": "nbg-2l-1g", "data": str(data),
                                             "steps_done": 12}, metrics={"val": 1.0})
    rows = [{"spp": 1, "psnr": 21.5, "ssim": 0.5, "smape": 0.2, "relmse": 0.3, "trmae": 1.25}]
    card = write_model_card(path, rows, threads=2).read_text()
    assert card.startswith("# nbg-2l-1g (version 7)")
    assert '"grids": 1' in card and '"steps_done": 12' in card
    # from the ModelCard: composition and tiling (radius 2 cells of 4 px + 2 x 2 layers + 2)
    assert "Stages: this file's graph." in card
    assert "Tiles: receptive radius 14 px, origins on multiples of 4 px" in card
    assert "saw fewer): 2 sequences (seeds 3–4, generator" in card
    assert "6 frames, 48×40, inputs at [1, 2] spp" in card
    assert "- validation (never trained on; picks `best.pt`): 1 sequences (seeds 9–9" in card
    speed = re.search(r"(\d+) ms per 1280×720 frame", card)
    assert speed and int(speed.group(1)) > 0
    assert "| 1 | 21.50 | 0.5000 | 0.2000 | 0.3000 | 1.2500 |" in card


def test_card_says_when_the_data_is_absent(tmp_path):
    # a measured 720p time in the card: quoted, not timed again (timing: the test above)
    path = export_nbg(NBGDenoiser(VARIANTS["nbg-2l-1g"]), tmp_path / "m.onnx",
                      training={"data": str(tmp_path / "nowhere")}, metrics={"ms_720p": 5.0})
    card = write_model_card(path, threads=1).read_text()
    assert "5 ms per 1280×720 frame through quietframe.runtime: the card's figure" in card
    assert "not present on the machine that wrote this card" in card
    assert "no evaluation run given" in card


def test_stamp_writes_the_evaluation_into_the_metadata_then_the_card(tmp_path):
    """`bench.model_card --stamp` (what `quietframe-export --card` did, export no longer
    importing bench): the rows become the measured table `auto` reads, then the card."""
    import json

    import onnx

    from quietframe.bench import model_card
    from quietframe.runtime.card import ModelCard

    path = export_nbg(NBGDenoiser(VARIANTS["nbg-2l-1g"]), tmp_path / "m.onnx")
    row = {"method": "m", "spp": 2, "psnr": 24.25, "ssim": 0.6, "smape": 0.1, "relmse": 0.2,
           "trmae": 0.75, "ms_720p": 7.0}
    evaluation = tmp_path / "benchmarks.json"
    evaluation.write_text(json.dumps({"rows": [row], "meta": {"split": "validation"}}))
    assert model_card.main(["--stamp", "--evaluation", str(evaluation), str(path)]) == 0
    props = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    table = ModelCard.from_props(props, "m").measured(None)
    assert [(r.spp, r.psnr, r.trmae) for r in table.by_spp] == [(2, 24.25, 0.75)]
    assert table.ms_720p == 7.0
    card = path.with_suffix(".md").read_text()
    assert "| 2 | 24.25 | 0.6000 | 0.1000 | 0.2000 | 0.7500 |" in card
    assert "7 ms per 1280×720 frame through quietframe.runtime: the card's figure" in card
    # a Cycles run becomes the Cycles table; a test-split run is never stamped
    evaluation.write_text(json.dumps({"rows": [{**row, "psnr": 21.5}], "meta": {
        "split": "validation", "renderer": "cycles"}}))
    assert model_card.main(["--stamp", "--evaluation", str(evaluation), str(path)]) == 0
    props = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    stamped = ModelCard.from_props(props, "m")
    assert stamped.measured("cycles").by_spp[0].psnr == 21.5
    assert stamped.measured("mitsuba").by_spp[0].psnr == 24.25
    # re-written without a run (after bench/model_metrics stamped it): the quality table stays
    assert model_card.main([str(path)]) == 0
    card = path.with_suffix(".md").read_text()
    assert "| 2 | 21.50 | 0.6000 |" in card and "no evaluation run given" not in card
    assert "Measured on cycles frames (what `auto` reads): 2 spp 21.50 dB" in card
    evaluation.write_text(json.dumps({"rows": [row], "meta": {"split": "test"}}))
    with pytest.raises(SystemExit):
        model_card.main(["--stamp", "--evaluation", str(evaluation), str(path)])


def test_card_of_a_candidate_measured_under_its_own_name(tmp_path):
    """A retrained candidate scored as `<name>-mix` beside the shipped models, then installed as
    `<name>`: `--measured-as` takes its rows, and only for one model."""
    import json
    import shutil

    from quietframe.bench import model_card
    from quietframe.runtime import find_model

    path = tmp_path / "oidn-frame.onnx"  # a shipped file: its card quotes its measured time
    shutil.copy(find_model("oidn-frame"), path)
    rows = [{"method": name, "spp": 1, "psnr": psnr, "ssim": 0.5, "smape": 0.1, "relmse": 0.2,
             "trmae": 0.75} for name, psnr in (("oidn-frame", 20.0), ("oidn-frame-mix", 23.0))]
    evaluation = tmp_path / "benchmarks.json"
    evaluation.write_text(json.dumps({"rows": rows, "meta": {"split": "validation"}}))
    assert model_card.main(["--evaluation", str(evaluation), "--measured-as", "oidn-frame-mix",
                            str(path)]) == 0
    assert "| 1 | 23.00 | 0.5000 |" in path.with_suffix(".md").read_text()
    with pytest.raises(SystemExit):
        model_card.main(["--evaluation", str(evaluation), "--measured-as", "oidn-frame-mix",
                         str(path), str(path)])


def test_card_lists_each_renderers_split_and_an_unvalidated_run(tmp_path):
    """A fine-tune on both renderers' train splits without a validation split (the Cycles
    fine-tune's candidates): one train line per renderer, and no validation split claimed to
    pick best.pt."""
    data = tmp_path / "data"
    write_sequence(data / GENERATOR_VERSION / "train", 3, frames=2, levels=(1,))
    write_sequence(data / f"{GENERATOR_VERSION}-cycles" / "train", 5, frames=2, levels=(1,))
    write_sequence(data / GENERATOR_VERSION / "validation", 9, frames=2, levels=(1,))
    path = export_nbg(NBGDenoiser(VARIANTS["nbg-2l-1g"]), tmp_path / "m.onnx",
                      training={"data": str(data), "renderers": "mitsuba,cycles"},
                      metrics={"val_sequences": 0, "ms_720p": 5.0})
    card = write_model_card(path, threads=1).read_text()
    assert re.search(r"- train, mitsuba \(as on disk.*\): 1 sequences \(seeds 3–3", card)
    assert re.search(r"- train, cycles \(as on disk.*\): 1 sequences \(seeds 5–5", card)
    assert "- validation: none on the machine during the run" in card
    assert "picks `best.pt`" not in card


def test_data_section_names_the_corpus_and_the_shots_that_picked_best(tmp_path):
    from quietframe.bench.model_card import data_lines
    from quietframe.scenes.corpus_shots import corpus_dir

    shot = corpus_dir(tmp_path, "train") / "9000000-exterior-pan"
    shot.mkdir(parents=True)
    config = {"width": 160, "height": 160, "spp_levels": [1, 4, 16, 64], "reference_spp": 96}
    (shot / "manifest.json").write_text(json.dumps(
        {"generator": "corpus1", "seed": 9_000_000, "frame_count": 4, "config": config}))
    training = {"data": str(tmp_path), "renderers": "cycles", "corpus": 1}
    metrics = {"selected_on": "corpus", "step": 750, "zoo_psnr": 28.6, "zoo_sequences": 48,
               "val_sequences": 12}
    text = "\n".join(data_lines(training, [], metrics))
    assert ("- train, corpus (as on disk when this card was written; a run started while the "
            "split was still rendering saw fewer): 1 sequences (seeds 9000000–9000000, "
            "generator corpus1), 4 frames, 160×160") in text
    assert "- train, cycles" in text and "picks `best.pt`" not in text
    assert "step 750) was picked on the corpus validation shots" in text and "48 (shot" in text
