"""bench/compare_table (`quietframe-eval --compare`): differences and ratios against the run's
baselines, misses stated."""

from __future__ import annotations

import json

import pytest

from quietframe.bench.evaluate import main


def write(path, rows):
    path.write_text(json.dumps({"meta": {}, "rows": rows}))
    return path


def row(method, spp, psnr, trmae=1.0, flicker=float("nan"), ms=100.0):
    return {"method": method, "spp": spp, "psnr": psnr, "ssim": 0.5, "trmae": trmae,
            "flicker": flicker,
            "ms_720p": ms}


def test_targets_met_and_missed_with_their_amounts(tmp_path, capsys):
    run = write(tmp_path / "run.json", [
        row("base", 1, 30.0), row("base", 4, 33.0), row("ref", 1, 30.5), row("ref", 4, 32.0),
        row("good", 1, 30.6, 0.6, ms=110), row("good", 4, 33.1, 0.65, ms=110),
        row("bad", 1, 29.8, 0.9), row("bad", 4, 33.5, 0.5)])
    static = write(tmp_path / "static.json", [
        row("base", 1, 0, flicker=0.02), row("base", 4, 0, flicker=0.02),
        row("good", 1, 0, flicker=0.008), row("good", 4, 0, flicker=0.009),
        row("bad", 1, 0, flicker=0.016), row("bad", 4, 0, flicker=0.004)])
    assert main(["--compare", str(run), "--static", str(static), "--methods", "good,bad",
                 "--against", "base,ref"]) == 0
    out = capsys.readouterr().out
    assert "| good | 1 | 30.60 | 0.5000 | +0.60 | +0.10 | 0.60 | 0.40 | 110 | 1.10 |" in out
    assert "| good | +0.10 | +0.10 | 0.65 | 0.45 | none |" in out
    assert ("| bad | -0.20 | -0.70 | 0.90 | 0.80 | PSNR 0.20 dB below base; PSNR 0.70 dB "
            "below ref; TRMAE 0.90× (target ≤ 0.7×); flicker 0.80× (target ≤ 0.5×) |") in out


def test_wide_table_has_one_row_per_method(tmp_path, capsys):
    run = write(tmp_path / "run.json", [row("base", 1, 30.0), row("base", 4, 33.0),
                                        row("good", 1, 30.6, ms=110), row("good", 4, 33.1)])
    assert main(["--compare", str(run), "--against", "base", "--methods", "good", "--wide"]) == 0
    assert "| good | 30.60 (+0.60) | 33.10 (+0.10) | 110 |" in capsys.readouterr().out


def test_a_run_without_the_baselines_or_flags_without_a_run_are_refused(tmp_path):
    run = write(tmp_path / "run.json", [row("good", 1, 30.6)])
    with pytest.raises(SystemExit):
        main(["--compare", str(run), "--against", "base"])
    with pytest.raises(SystemExit):  # nothing evaluated: --wide reads an earlier run
        main(["--wide"])
