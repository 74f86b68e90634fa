"""bench/model_metrics.py (`bench.model_card --stamp`): what a validation run writes into a model's
card for `auto`, per renderer, with flicker from locked-off shots and the time from a quiet run."""

from __future__ import annotations

import json
import shutil

import onnx
import pytest

from quietframe.bench import model_card
from quietframe.runtime import find_model
from quietframe.runtime.card import ModelCard


def _run(path, split, rows, renderer="cycles"):
    path.write_text(json.dumps({"meta": {"split": split, "renderer": renderer,
                                         "command": f"quietframe-eval --split {split}"},
                                "rows": rows}))
    return path


def stamp(argv: list[str]) -> int:
    """The stamp alone, as the ship pipelines run it (no markdown card)."""
    return model_card.main(["--stamp", "--no-card", *argv])


def _card(path):
    model = onnx.load(str(path), load_external_data=False)
    return ModelCard.from_props({p.key: p.value for p in model.metadata_props}, path.stem)


def test_cycles_table_with_locked_off_flicker_and_quiet_timing(tmp_path):
    model = tmp_path / "oidn-frame.onnx"
    shutil.copy(find_model("oidn-frame"), model)
    mitsuba_before = _card(model).measured("mitsuba")
    moving = _run(tmp_path / "moving.json", "validation", [
        {"method": "oidn-frame", "spp": s, "psnr": 30.0 + s / 64, "trmae": 0.5,
         "ms_720p": 2000.0} for s in (1, 64)] + [{"method": "other", "spp": 1, "psnr": 1.0,
                                                   "trmae": 1.0, "ms_720p": 1.0}])
    static = _run(tmp_path / "static.json", "validation-static", [
        {"method": "oidn-frame", "spp": 1, "psnr": 35.0, "trmae": 0.3, "flicker": 0.012,
         "ms_720p": float("nan")}])
    timing = _run(tmp_path / "timing.json", "test", [
        {"method": "oidn-frame", "spp": 1, "psnr": 0.0, "trmae": 0.0, "ms_720p": 1017.0}])
    assert stamp([str(model), "--evaluation", str(moving), "--renderer", "cycles",
                 "--static-evaluation", str(static), "--timing", str(timing)]) == 0
    card = _card(model)
    cycles = card.measured("cycles")
    assert [(r.spp, r.psnr, r.flicker) for r in cycles.by_spp] == [
        (1, 30.016, 0.012), (64, 31.0, None)]  # flicker only where a locked-off run measured it
    assert cycles.ms_720p == 1017.0  # the quiet run's, not the evaluation's 2000
    assert cycles.measured["flicker"]["split"] == "validation-static"
    assert card.measured("mitsuba") == mitsuba_before  # the other renderer's table untouched


def test_tables_never_come_from_the_test_split_or_another_renderer(tmp_path):
    model = tmp_path / "oidn-frame.onnx"
    shutil.copy(find_model("oidn-frame"), model)
    before = _card(model).measurements
    row = [{"method": "oidn-frame", "spp": 1, "psnr": 30.0, "trmae": 0.5, "ms_720p": 9.0}]
    test_run = _run(tmp_path / "test.json", "test", row)
    with pytest.raises(SystemExit):
        stamp([str(model), "--evaluation", str(test_run), "--renderer", "cycles"])
    validation = _run(tmp_path / "val.json", "validation", row)
    static_test = _run(tmp_path / "st.json", "test-static", row)
    with pytest.raises(SystemExit):
        stamp([str(model), "--evaluation", str(validation), "--renderer",
              "cycles", "--static-evaluation", str(static_test)])
    mitsuba = _run(tmp_path / "mi.json", "validation-static", row, renderer="mitsuba")
    with pytest.raises(SystemExit):
        stamp([str(model), "--evaluation", str(validation), "--renderer",
              "cycles", "--static-evaluation", str(mitsuba)])
    with pytest.raises(SystemExit):  # a Cycles run stamped as the Mitsuba table
        stamp([str(model), "--evaluation", str(validation), "--renderer", "mitsuba"])
    assert _card(model).measurements == before  # nothing was written


def test_a_candidate_measured_under_its_own_name_is_stamped_under_the_shipped_one(tmp_path):
    model = tmp_path / "oidn-frame.onnx"
    shutil.copy(find_model("oidn-frame"), model)
    run = _run(tmp_path / "val.json", "validation", [
        {"method": m, "spp": 1, "psnr": psnr, "trmae": 0.5, "ms_720p": 900.0}
        for m, psnr in (("oidn-frame", 30.0), ("oidn-frame-mix", 31.5))])
    assert stamp([str(model), "--evaluation", str(run), "--renderer", "cycles",
                 "--measured-as", "oidn-frame-mix"]) == 0
    assert [r.psnr for r in _card(model).measured("cycles").by_spp] == [31.5]
    with pytest.raises(SystemExit):  # one method's rows cannot stand for two models
        stamp([str(model), str(model), "--evaluation", str(run), "--renderer",
              "cycles", "--measured-as", "oidn-frame-mix"])


def test_the_runs_of_a_table_only_with_stamp(tmp_path):
    """A run file given without --stamp would be silently ignored: refused instead."""
    model = tmp_path / "oidn-frame.onnx"
    shutil.copy(find_model("oidn-frame"), model)
    run = _run(tmp_path / "val.json", "validation", [])
    for flags in (["--timing", str(run)], ["--renderer", "cycles"], ["--no-card"],
                  ["--stamp"]):
        with pytest.raises(SystemExit):  # refused before anything is written
            model_card.main([str(model), *flags])
