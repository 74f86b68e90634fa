"""`bench.model_card --input-margin` (bench/input_margin_stamp.py): validation zoo runs with the
`noisy` method become each model's `input_margin` (joined by shot, the zoo rows untouched),
then the markdown card's line on where the model is worse than its own input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from quietframe.bench import model_card
from quietframe.bench.model_metrics import card_of
from quietframe.runtime.card import worse_than_input_from
from quietframe.runtime.registry import installed_models

MODEL = "nbg-2l-3g"


def run(tmp_path: Path, name: str, margins: dict[str, dict[int, float]],
        split: str = "validation", noisy: bool = True) -> Path:
    """A zoo.json whose model rows are `margins` (shot -> spp -> dB) above the noisy input."""
    rows = []
    for shot, by_spp in margins.items():
        for spp, margin in by_spp.items():
            base = 10.0 + spp
            if noisy:
                rows.append({"shot": shot, "spp": spp, "method": "noisy", "psnr": base})
            rows.append({"shot": shot, "spp": spp, "method": MODEL, "psnr": base + margin})
            rows.append({"shot": shot, "spp": spp, "method": "other", "psnr": base + 50})
    path = tmp_path / f"{name}.json"
    meta = {"split": split, "zoo": name, "shots": list(margins), "command": f"zoo_eval {name}"}
    path.write_text(json.dumps({"meta": meta, "rows": rows}))
    return path


@pytest.fixture
def model(tmp_path) -> Path:
    installed = {p.stem: p for p in installed_models()}
    if MODEL not in installed:
        pytest.skip(f"needs {MODEL} installed")
    path = tmp_path / "models" / f"{MODEL}.onnx"
    path.parent.mkdir()
    shutil.copy(installed[MODEL], path)
    return path


def test_runs_are_joined_by_shot_into_the_cycles_table_and_the_card_says_where(tmp_path, model):
    zoo_before = card_of(model).measured("cycles").zoo
    first = run(tmp_path, "zoo1", {"pan": {1: 15.0, 4: 8.0, 16: 6.0},
                                   "blur": {1: 5.0, 4: 1.0, 16: -5.0}})
    # the second round: other shots, and "blur" again, measured later: it counts as given here
    second = run(tmp_path, "zoo3", {"dolly": {1: 12.0, 4: 6.0, 16: 1.5},
                                    "blur": {1: 5.0, 4: 2.0, 16: -4.0}})
    assert model_card.main([str(model), "--no-card", "--input-margin", str(first),
                            str(second)]) == 0
    table = card_of(model).measured("cycles")
    assert table.zoo == zoo_before  # the zoo rows are another section
    rows = {r.spp: r for r in table.input_margin}
    assert sorted(rows) == [1.0, 4.0, 16.0]
    assert rows[16].worst_db == pytest.approx(-4.0) and rows[16].worst_shot == "blur"
    assert rows[16].mean_db == pytest.approx((6.0 + 1.5 - 4.0) / 3, abs=1e-3)
    assert rows[16].shots == 3
    assert rows[4].worst_db == pytest.approx(2.0)
    assert table.input_margin_measured["shots"] == ["blur", "dolly", "pan"]
    assert table.input_margin_measured["commands"] == ["zoo_eval zoo1", "zoo_eval zoo3"]
    worse = worse_than_input_from(table.input_margin)
    assert 4 < worse < 16
    # the markdown, re-written from the card without measuring anything
    assert model_card.main([str(model)]) == 0
    card = model.with_suffix(".md").read_text()
    assert (f"worse than its noisy input from {worse:g} spp on the validation zoo's worst shot"
            in card)
    assert "16 spp -4.00 dB (worst shot blur; mean +1.17)" in card
    assert "through quietframe.runtime: the card's figure" in card  # quoted, not timed


def test_a_model_never_below_its_input_says_so(tmp_path, model):
    clean = run(tmp_path, "zoo1", {"pan": {1: 15.0, 4: 8.0}})
    assert model_card.main([str(model), "--input-margin", str(clean)]) == 0
    card = model.with_suffix(".md").read_text()
    assert "never worse than its noisy input on the validation zoo's worst shot over 1-4 spp" \
        in card


@pytest.mark.parametrize("kind, message", [
    ("test", "a test run"),
    ("no-noisy", "no 'noisy' rows"),
])
def test_runs_that_cannot_measure_the_margin_are_refused_before_anything_is_written(
        tmp_path, model, capsys, kind, message):
    before = model.read_bytes()
    good = run(tmp_path, "good", {"pan": {1: 3.0}})
    bad = run(tmp_path, "bad", {"pan": {1: 3.0}}, split="test" if kind == "test" else
              "validation", noisy=kind != "no-noisy")
    with pytest.raises(SystemExit, match=message):
        model_card.main([str(model), "--no-card", "--input-margin", str(good), str(bad)])
    assert model.read_bytes() == before


def test_models_given_after_the_flag_are_a_usage_error(tmp_path, model, capsys):
    good = run(tmp_path, "good", {"pan": {1: 3.0}})
    with pytest.raises(SystemExit) as exit_:
        model_card.main(["--no-card", str(model), "--input-margin", str(good), str(model)])
    assert exit_.value.code == 2
    assert "give the models before --input-margin" in capsys.readouterr().err
