"""`quietframe denoise --dry-run` refuses what the run refuses (same exit code, same words)
without sending a frame; Blender's `A..B` frame ranges; no abbreviated options; `quietframe
models` with the renderer's tables, Blender's denoise beside them and a description that sets
each model apart; time figures measured on this server or said for what they are; and what
--force redoes, named in the refusal and counted in the progress."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import httpx
import pytest
from conftest import read_exr, shot, write_exr

from quietframe.client.choice_text import describe_choice
from quietframe.client.cli import main
from quietframe.client.model_table import describe

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "blender"


def write_shot(folder: Path, n: int, start: int = 1001) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i, data in enumerate(shot(n, "blender")):
        (folder / f"shot.{start + i:04d}.exr").write_bytes(data)


def events(out: str) -> list[dict]:
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def denoise(server_url: str, source: Path, out: Path, *flags: str) -> list[str]:
    return ["denoise", "--server", server_url, str(source), "--out", str(out), "--quiet",
            *flags]


def sessions_created(server) -> float:
    text = httpx.get(f"{server.url}/metrics").text
    return float(re.search(r"^quietframe_sessions_created_total (\S+)", text, re.M).group(1))


def run_and_dry_run(capsys, args: list[str]) -> tuple[tuple[int, str], tuple[int, str]]:
    """(exit code, stderr) of the run, then of the same command with --dry-run."""
    code = main(args)
    run = (code, capsys.readouterr().err)
    code = main([*args, "--dry-run"])
    return run, (code, capsys.readouterr().err)


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if "error:" in line or "--" in line]


@pytest.mark.parametrize("flags, code", [
    (("--model", "no-such-model"), 2),
    (("--model", "affinity-h16-k5gc", "--model-option", "kernel_size=6"), 2),
    (("--model", "nbg-2l-3g", "--model-option", "kernel_size=5"), 2),
])
def test_dry_run_refuses_a_model_or_option_as_the_run_does(tmp_path, live_server, capsys,
                                                           flags, code):
    write_shot(tmp_path / "in", 2)
    before = sessions_created(live_server)
    (run_code, run_err), (dry_code, dry_err) = run_and_dry_run(
        capsys, denoise(live_server.url, tmp_path / "in", tmp_path / "out", *flags))
    assert run_code == dry_code == code
    assert error_lines(dry_err) == error_lines(run_err)  # the same message and advice
    assert sessions_created(live_server) == before  # refused at creation; the dry run made none


def test_dry_run_refuses_view_layers_as_the_run_does(tmp_path, live_server, capsys):
    src = tmp_path / "in"
    src.mkdir()
    shutil.copy(FIXTURES / "two_view_layers.0002.exr", src / "v.0002.exr")
    args = denoise(live_server.url, src, tmp_path / "out")
    (run_code, run_err), (dry_code, dry_err) = run_and_dry_run(capsys, args)
    assert run_code == dry_code == 3
    assert "--layer NAME, or --layer all" in run_err and "--layer NAME, or --layer all" in dry_err
    (run_code, run_err), (dry_code, dry_err) = run_and_dry_run(capsys, [*args, "--layer", "Nope"])
    assert run_code == dry_code == 2
    assert error_lines(dry_err) == error_lines(run_err)
    assert main([*args, "--layer", "Objects", "--dry-run"]) == 0


def test_dry_run_checks_the_server_and_its_token(tmp_path, live_server, capsys, monkeypatch):
    from pydantic import SecretStr

    write_shot(tmp_path / "in", 2)
    down = ["denoise", "--server", "http://127.0.0.1:9", str(tmp_path / "in"), "--out",
            str(tmp_path / "out"), "--quiet", "--retries", "0"]
    (run_code, run_err), (dry_code, dry_err) = run_and_dry_run(capsys, down)
    assert run_code == dry_code == 75
    assert "cannot reach the quietframe server at http://127.0.0.1:9" in dry_err
    assert error_lines(dry_err) == error_lines(run_err)
    monkeypatch.setattr(live_server.app.state.settings, "auth_token", SecretStr("s3cret"))
    args = denoise(live_server.url, tmp_path / "in", tmp_path / "out")
    (run_code, run_err), (dry_code, dry_err) = run_and_dry_run(capsys, args)
    assert run_code == dry_code == 2 and "--token" in dry_err
    assert error_lines(dry_err) == error_lines(run_err)
    assert main([*args, "--dry-run", "--token", "s3cret"]) == 0
    assert not list((tmp_path / "out").glob("*.exr"))


def test_dry_run_refuses_files_in_the_way_and_says_what_is_to_do(tmp_path, live_server,
                                                                 capsys):
    write_shot(tmp_path / "in", 3)
    out = tmp_path / "out"
    out.mkdir()
    (out / "shot.1002.exr").write_bytes(b"someone else's file")
    args = denoise(live_server.url, tmp_path / "in", out)
    assert main([*args, "--dry-run"]) == 3
    assert "were not written by quietframe" in capsys.readouterr().err
    assert main([*args, "--dry-run", "--force", "--json"]) == 0
    (dry,) = [e for e in events(capsys.readouterr().out) if e["event"] == "dry-run"]
    assert dry["to_denoise"] == 3 and (out / "shot.1002.exr").read_bytes().startswith(b"some")


@pytest.mark.parametrize("frames, expected", [
    ("1002..1004", [1002, 1003, 1004]),
    ("1001,1003..1004", [1001, 1003, 1004]),
])
def test_frames_take_blenders_range_notation(tmp_path, live_server, capsys, frames, expected):
    write_shot(tmp_path / "in", 4)
    args = denoise(live_server.url, tmp_path / "in", tmp_path / "out", "--frames", frames,
                   "--model", "nbg-2l-3g", "--json")
    args.remove("--quiet")
    assert main(args) == 0
    written = [e["frame"] for e in events(capsys.readouterr().out) if e["event"] == "frame"]
    assert written == expected


@pytest.mark.parametrize("argv", [
    ["denoise", "in", "--out", "out", "--pre-rol", "2"],
    ["denoise", "in", "--ou", "out"],
    ["models", "--jso"],
])
def test_options_are_never_abbreviated(argv, capsys):
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    assert stopped.value.code == 2 and "error:" in capsys.readouterr().err  # not taken


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


def test_force_names_and_counts_every_frame_it_redoes(tmp_path, live_server, capsys):
    """Frame 1003 of six re-rendered: frames 1003-1006 are redone (their history runs through
    1003), so the refusal names all four and --force's progress goes on from [3/6]."""
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 6)
    args = denoise(live_server.url, src, out, "--model", "nbg-2l-3g")
    assert main(args) == 0
    _, rerendered = read_exr(shot(4, "blender")[3])  # new noise: a re-render
    (src / "shot.1003.exr").write_bytes(write_exr(rerendered))
    assert main(args) == 3
    err = capsys.readouterr().err
    assert "shot.1003.exr" in err and "--force redoes 4 output(s), frame(s) 1003-1006" in err
    forced = [*args, "--force", "--json"]
    forced.remove("--quiet")
    assert main(forced) == 0
    seen = events(capsys.readouterr().out)
    frames = [(e["frame"], e["done"], e["total"]) for e in seen if e["event"] == "frame"]
    assert frames == [(1003, 3, 6), (1004, 4, 6), (1005, 5, 6), (1006, 6, 6)]
    (note,) = [e["message"] for e in seen if e["event"] == "note"]
    assert "redoing 4 output(s), frame(s) 1003-1006" in note
