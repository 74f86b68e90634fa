"""bench/auto_choice.py: the summary's target arithmetic, and a tiny synthetic run end to end."""

from __future__ import annotations

import json

import pytest

from quietframe.bench import auto_choice


def row(fixed: dict[str, tuple[float, float]], auto: str | None):
    out = {"fixed": {m: {"psnr": p, "ms": ms} for m, (p, ms) in fixed.items()}}
    for mode in ("header", "estimate"):
        chosen = fixed.get(auto) if auto else None
        out[f"auto_{mode}"] = {"model": auto, "psnr": chosen[0] if chosen else None,
                               "ms": chosen[1] if chosen else None}
    return out


def test_summary_checks_quality_on_every_sequence_and_speed_against_the_best_model():
    rows = [row({"slow": (30.0, 100.0), "fast": (29.8, 20.0)}, "fast"),
            row({"slow": (28.0, 100.0), "fast": (27.9, 20.0)}, "fast")]
    summary = auto_choice.summarise(rows, ["slow", "fast"])
    assert summary["best_model"] == "slow" and summary["best_model_ms"] == 100
    assert summary["header"]["worst_gap_db"] == pytest.approx(0.2)
    assert summary["header"]["ms_share_of_best"] == 0.2 and summary["header"]["meets_target"]
    rows.append(row({"slow": (25.0, 100.0), "fast": (24.0, 20.0)}, "fast"))  # 1 dB behind
    summary = auto_choice.summarise(rows, ["slow", "fast"])
    assert summary["header"]["sequences_within_tolerance"] == 2
    assert not summary["header"]["meets_target"]
    rows = [row({"slow": (30.0, 100.0), "fast": (29.8, 20.0)}, "slow")]  # right but not cheap
    summary = auto_choice.summarise(rows, ["slow", "fast"])
    assert not summary["header"]["meets_target"]
    assert summary["oracle"] == {"ms": 20.0, "ms_share_of_best": 0.2}  # fast was good enough


def test_oracle_takes_the_cheapest_model_within_tolerance_per_sequence():
    rows = [row({"slow": (30.0, 100.0), "mid": (29.9, 60.0), "fast": (29.0, 20.0)}, "slow"),
            row({"slow": (25.0, 100.0), "mid": (24.0, 60.0), "fast": (24.9, 20.0)}, "slow")]
    oracle = auto_choice.summarise(rows, ["slow", "mid", "fast"])["oracle"]
    assert oracle == {"ms": 40.0, "ms_share_of_best": 0.4}


def test_synthetic_run_lists_choices_per_sequence(tmp_path):
    assert auto_choice.main(["--synthetic", "--no-absence", "--threads", "1",
                             "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "auto_choice.json").read_text())
    assert "no more" in result["meta"]["data"]
    assert {r["buffers"] for r in result["rows"]} == set(auto_choice.BUFFER_SETS)
    runnable = [r for r in result["rows"] if r["fixed"]]
    assert runnable and all(r["auto_header"]["model"] in r["fixed"] for r in runnable)
    assert "auto (estimate)" in (tmp_path / "auto_choice.md").read_text()
    assert all(r["noise"]["log2_sigma"] is not None for r in result["rows"])
    assert not (tmp_path / "benchmarks.md").exists()  # only a test-split run reports


def test_validation_rows_become_by_noise_points(tmp_path):
    from quietframe.bench.model_metrics import noise_points

    assert auto_choice.main(["--synthetic", "--no-absence", "--threads", "1", "--buffer-sets",
                             "all", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "auto_choice.json").read_text())
    model = next(iter(result["rows"][0]["fixed"]))
    points = noise_points(result, model)["points"]
    assert len(points) == len(result["rows"])  # one per (sequence, spp)
    assert [p[2] for p in points] == [round(r["fixed"][model]["psnr"], 3)
                                      for r in result["rows"]]


def test_benchmarks_section_is_replaced_not_repeated(tmp_path):
    path = tmp_path / "benchmarks.md"
    path.write_text("# quietframe evaluation\n\n| table |\n")
    auto_choice.update_section(path, "first\n")
    auto_choice.update_section(path, "second\n")
    text = path.read_text()
    assert text.startswith("# quietframe evaluation\n\n| table |\n")
    assert "second" in text and "first" not in text and text.count(auto_choice.MARK_BEGIN) == 1


def test_only_runs_the_named_models(tmp_path):
    assert auto_choice.main(["--synthetic", "--no-absence", "--threads", "1", "--buffer-sets",
                             "all", "--only", "accumulation,nbg-2l-1g", "--out",
                             str(tmp_path)]) == 0
    result = json.loads((tmp_path / "auto_choice.json").read_text())
    assert all(set(r["fixed"]) == {"accumulation", "nbg-2l-1g"} for r in result["rows"])
    with pytest.raises(SystemExit):
        auto_choice.main(["--synthetic", "--only", "no-such-model", "--out", str(tmp_path)])
