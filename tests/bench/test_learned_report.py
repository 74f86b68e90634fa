"""bench/learned_report: the learned tiers' figures in the terms of their quality targets."""

from __future__ import annotations

import json

import pytest

from quietframe.bench import learned_report as lr


def write_run(path, psnr: dict[tuple[str, int], dict[str, float]]) -> None:
    rows = [{"shot": shot, "spp": spp, "method": m, "psnr": v}
            for (shot, spp), methods in psnr.items() for m, v in methods.items()]
    meta = {"zoo": "zoo2", "split": "test", "command": "zoo_eval ..."}
    path.write_text(json.dumps({"meta": meta, "rows": rows}))


def cell(noisy, tier, fast, blender):
    return {"noisy": noisy, "nbg-2l-3g-corpus": tier, "oidn-fast-history/frame": fast,
            "oidn-high": fast + 0.3, "blender-denoise": blender}


def test_figures_are_the_targets_terms_and_say_which_are_missed(tmp_path):
    run = tmp_path / "zoo.json"
    write_run(run, {("a", 1): cell(20.0, 28.0, 29.0, 30.0), ("a", 4): cell(25.0, 30.0, 31.5, 32.0),
                    ("b", 1): cell(18.0, 25.0, 27.5, 27.0), ("b", 64): cell(38.0, 36.0, 39, 40)})
    table, commands = lr.read_rows([run])
    s = lr.summary(table, "nbg-2l-3g-corpus")
    assert s["input_margin_worst"] == {1.0: 7.0, 4.0: 5.0, 64.0: -2.0}
    assert s["vs_blender_low"] == pytest.approx(-2.0)  # (-2, -2, -2): 64 spp is out of range
    assert s["vs_oidn_fast_low"] == pytest.approx((-1.0 - 1.5 - 2.5) / 3)
    assert s["vs_oidn_fast_low_worst"] == pytest.approx(-2.5)
    assert s["target_vs_blender"] == -2.5  # an nbg candidate takes nbg's target
    text = lr.report(table, ["nbg-2l-3g-corpus"], commands)
    assert "-2.00 (met)" in text and "-2.50 (missed by 1.00)" in text
    assert "| b | 64 | 40.00 | -2.00 | -4.00 |" in text
    times = {"nbg-2l-3g-corpus": 0.12, "oidn-high": 1.0, "oidn-fast": 0.55}
    assert lr.plot(table, ["nbg-2l-3g-corpus"], times, tmp_path).stat().st_size > 1000
