"""`quietframe models`: the renderer's tables with Blender's denoise beside them, and a
description that sets each model apart; time per frame measured on this server or said to be
the tables' figure."""

from __future__ import annotations

import re

import httpx
from farm_cli_support import denoise, events, write_shot

from quietframe.client.choice_text import describe_choice
from quietframe.client.cli import main
from quietframe.client.model_table import describe


def listing(server) -> dict:
    return httpx.get(f"{server.url}/v1/models").json()


def table_row(text: str, name: str) -> str:
    return next(line for line in text.splitlines() if line.startswith(f"{name} "))


def test_models_shows_the_renderers_tables_beside_blenders_denoise(live_server, capsys):
    models = {m["name"]: m for m in listing(live_server)["models"]}
    assert main(["models", "--server", live_server.url]) == 0
    text = capsys.readouterr().out
    assert text.startswith("MODEL") and "Cycles frames (--renderer cycles, the default" in text
    cycles = {r["spp"]: r for r in models["oidn-history"]["metrics"]["by_renderer"]["cycles"][
        "by_spp"]}
    row = table_row(text, "oidn-history")
    assert f"{cycles[1]['psnr']:.1f}/{cycles[4]['psnr']:.1f}/{cycles[8]['psnr']:.1f}" in row
    gap = cycles[1]["psnr"] - cycles[1]["renderer_denoise"]
    assert f"{gap:+.1f}/" in row  # beside Blender's denoise of the same frames
    blender = re.search(r"(\d+\.\d)/", table_row(text, "Blender's denoise")).group(1)
    assert abs(float(blender) - cycles[1]["renderer_denoise"]) < 0.06
    assert "not this server's time" in text
    # final frames or preview, from the same gaps: the learned preview tiers trail by > 1 dB
    gaps = [cycles[n]["psnr"] - cycles[n]["renderer_denoise"] for n in (1, 4, 8)]
    assert (" final " in row) == (min(gaps) >= -0.1) and " preview " in table_row(text, "nbg-2l-3g")
    assert "x oidn-frame" in table_row(text, "Blender's denoise")  # its cost, measured
    assert main(["models", "--server", live_server.url, "--renderer", "mitsuba"]) == 0
    mitsuba = {r["spp"]: r for r in models["oidn-history"]["metrics"]["by_spp"]}
    assert f"{mitsuba[1]['psnr']:.1f}/" in table_row(capsys.readouterr().out, "oidn-history")


def test_each_model_says_what_sets_it_apart(live_server):
    models = listing(live_server)["models"]
    descriptions = {m["name"]: describe(m) for m in models}
    assert len(set(descriptions.values())) == len(models), descriptions
    assert "prefiltered" in descriptions["oidn-history-cleanaux"]
    assert "plain aux" in descriptions["oidn-history"]
    assert "fast" in descriptions["oidn-fast-history"]
    assert "learned preview" in descriptions["nbg-2l-3g"]
    assert "pass-through" in descriptions["nbg-2l-3g"]  # version 6 (docs/training.md)
    assert "pass-through" not in descriptions["nbg-7l-3g"]


def test_time_per_frame_is_measured_here_or_said_to_be_a_table_figure(tmp_path, live_server,
                                                                      capsys):
    choice = {"model": "oidn-history", "reason": "balanced: the best expected", "spp": 4,
              "noise_source": "header", "buffers": ["albedo", "normal", "depth", "motion"],
              "expected_psnr": 30.3, "expected_ms": 231.0}
    table = describe_choice(choice)
    assert "231 ms per frame by the tables" in table and "not measured here" in table
    measured = describe_choice(choice, measured_ms=1312.0)
    assert "1312 ms per frame measured on this server" in measured and "231" not in measured
    write_shot(tmp_path / "in", 3)
    args = denoise(live_server.url, tmp_path / "in", tmp_path / "out", "--model", "nbg-2l-3g",
                   "--json")
    args.remove("--quiet")
    assert main(args) == 0
    summary = events(capsys.readouterr().out)[-1]
    assert summary["event"] == "summary" and summary["server_ms_median"] > 0
