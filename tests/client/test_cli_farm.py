"""Farm features of `quietframe denoise` through the real CLI against a real server: frame
patterns and ranges, pre-roll (and the pop it removes), cuts, JSON events, the per-frame log,
the pre-flight, missing frames, exit codes and the advice that comes with them."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import LAYOUTS, make_buffers, read_exr, shot, write_exr

from quietframe.client.cli import main

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "blender"
CLI = [sys.executable, "-m", "quietframe.client.cli"]


def write_shot(folder: Path, n: int, start: int = 1001, name: str = "shot.{:04d}.exr"):
    folder.mkdir(parents=True, exist_ok=True)
    for i, data in enumerate(shot(n, "blender")):
        (folder / name.format(start + i)).write_bytes(data)


def events(out: str) -> list[dict]:
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def denoise(server, source, out, *flags) -> list[str]:
    return ["denoise", "--server", server.url, str(source), "--out", str(out), *flags]


def test_pattern_range_and_pre_roll_write_only_the_chunk(tmp_path, live_server, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 6)
    args = denoise(live_server, src / "shot.####.exr", out, "--frames", "1004-1005",
                   "--pre-roll", "2", "--json", "--model", "nbg-2l-3g")
    assert main(args) == 0
    seen = events(capsys.readouterr().out)
    assert [e["frame"] for e in seen if e["event"] == "warmup"] == [1002, 1003]
    frames = [e for e in seen if e["event"] == "frame"]
    assert [e["frame"] for e in frames] == [1004, 1005] and frames[0]["reset"] == "none"
    assert sorted(p.name for p in out.glob("*.exr")) == ["shot.1004.exr", "shot.1005.exr"]
    assert seen[-1]["event"] == "summary" and seen[-1]["written"] == 2
    shot_events = [e for e in seen if e["event"] == "shot"]
    assert len(shot_events) == 1 and "nbg-2l-3g" in shot_events[0]["text"]
    # printf-style pattern, the next chunk in parallel: its own job file, no conflict
    assert main(denoise(live_server, src / "shot.%04d.exr", out, "--frames", "1006",
                        "--pre-roll", "2", "--quiet", "--model", "nbg-2l-3g")) == 0
    assert (out / "shot.1006.exr").exists() and not (out / "shot.1003.exr").exists()


def test_pre_roll_removes_the_pop_at_a_chunk_boundary(tmp_path, live_server, capsys):
    """A locked-off shot in two chunks: the second chunk's first frame without pre-roll is
    denoised from an empty history, so it differs from the same frame of one unchunked run
    (a visible pop); with pre-roll it matches. Prints the measured figures."""
    src = tmp_path / "in"
    write_shot(src, 8)
    flags = ("--quiet", "--model", "nbg-2l-3g")
    main(denoise(live_server, src, tmp_path / "whole", *flags))
    main(denoise(live_server, src, tmp_path / "cold", "--frames", "1005-1008", *flags))
    main(denoise(live_server, src, tmp_path / "warm", "--frames", "1005-1008", "--pre-roll",
                 "4", *flags))

    def colour(folder: str, frame: int) -> np.ndarray:
        _, ch = read_exr((tmp_path / folder / f"shot.{frame:04d}.exr").read_bytes())
        return np.stack([ch[f"ViewLayer.Combined.{c}"] for c in "RGB"]).astype(np.float64)

    whole_step = np.abs(colour("whole", 1005) - colour("whole", 1004)).mean()
    figures = {}
    for kind in ("cold", "warm"):
        pop = np.abs(colour(kind, 1005) - colour("whole", 1004)).mean()  # the step at the cut
        off = np.abs(colour(kind, 1005) - colour("whole", 1005)).mean()  # vs. unchunked
        figures[kind] = (pop, off)
    with capsys.disabled():
        print(f"\npre-roll pop (mean |diff| per pixel, 64x48, nbg-2l-3g): unchunked step "
              f"1004->1005 {whole_step:.4f}; without pre-roll step {figures['cold'][0]:.4f}, "
              f"off the unchunked frame {figures['cold'][1]:.4f}; with --pre-roll 4 step "
              f"{figures['warm'][0]:.4f}, off {figures['warm'][1]:.4f}")
    assert figures["warm"][1] < 1e-3 < figures["cold"][1]
    assert figures["warm"][0] < figures["cold"][0]


def test_cut_and_missing_frames(tmp_path, live_server, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 5)
    (src / "shot.1004.exr").unlink()
    assert main(denoise(live_server, src, out, "--strict", "--quiet")) == 3
    assert "missing frame(s) 1004" in capsys.readouterr().err
    assert main(denoise(live_server, src, out, "--cut", "1002", "--json")) == 0
    seen = events(capsys.readouterr().out)
    resets = {e["frame"]: e["reset"] for e in seen if e["event"] == "frame"}
    assert resets == {1001: "first-frame", 1002: "cut", 1003: "none", 1005: "gap"}
    summary = seen[-1]
    assert summary["event"] == "summary" and "missing frame(s) 1004" in summary["warnings"][0]
    assert sum(e["event"] == "shot" for e in seen) == 2  # the first frame and the cut


def test_dry_run_checks_every_header_before_any_upload(tmp_path, live_server, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 4)
    assert main(denoise(live_server, src, out, "--dry-run", "--json")) == 0
    seen = events(capsys.readouterr().out)
    assert seen[0]["event"] == "preflight" and seen[0]["frames"] == 4
    assert seen[0]["size"] == [64, 48] and not list(out.glob("*.exr"))
    good = (src / "shot.1003.exr").read_bytes()
    (src / "shot.1003.exr").write_bytes(good[: len(good) - 100])  # a copy cut short
    small = write_exr(LAYOUTS["blender"](make_buffers(24, 32, motion=False)))
    (src / "shot.1004.exr").write_bytes(small)
    assert main(denoise(live_server, src, out, "--dry-run")) == 3
    err = capsys.readouterr().err
    assert "shot.1003.exr: the last pixel block runs past the end" in err
    assert "shot.1004.exr: is 32x24, the first frame 64x48" in err


def test_log_lines_when_stdout_is_not_a_terminal_and_sanitising_said_once(
    tmp_path, live_server
):
    src = tmp_path / "in"
    src.mkdir()
    for frame in (1, 2, 3):
        shutil.copy(FIXTURES / f"passes_float_zip.000{frame}.exr", src / f"f.000{frame}.exr")
    run = subprocess.run([*CLI, *denoise(live_server, src, tmp_path / "out")],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert [line.split()[:3] for line in lines if line.startswith("frame ")] == [
        ["frame", "1", "f.0001.exr"], ["frame", "2", "f.0002.exr"], ["frame", "3", "f.0003.exr"]]
    assert "\r" not in run.stdout and "sanitized=" not in run.stdout
    sanitised = [line for line in lines if "sanitised depth" in line]
    assert len(sanitised) == 1 and "harmless" in sanitised[0]
    assert any(line.startswith("quietframe: shot from frame 1: ") for line in lines)


def test_exit_codes_and_advice(tmp_path, live_server, capsys):
    src = tmp_path / "in"
    write_shot(src, 2)
    out = tmp_path / "out"
    assert main(denoise(live_server, src, out, "--quiet", "--model", "no-such-model")) == 2
    err = capsys.readouterr().err
    assert "unknown_model" in err and "quietframe models --server" in err
    assert "resume" not in err
    assert main(["denoise", "--server", "localhost:8000", str(src), "--out", str(out)]) == 2
    assert "http://" in capsys.readouterr().err
    down = ["denoise", "--server", "http://127.0.0.1:9", str(src), "--out", str(out),
            "--retries", "2", "--quiet"]
    assert main(down) == 75
    err = capsys.readouterr().err
    assert err.count("server http://127.0.0.1:9: ConnectError") == 2  # each retry said
    assert "cannot reach the quietframe server at http://127.0.0.1:9" in err
    v1 = denoise(live_server, src, out, "--quiet")
    v1[2] += "/v1"  # the API prefix in --server is dropped, not a bare 404
    assert main(v1) == 0


def test_two_view_layers_suggest_layer(tmp_path, live_server, capsys):
    src = tmp_path / "in"
    src.mkdir()
    shutil.copy(FIXTURES / "two_view_layers.0002.exr", src / "v.0002.exr")
    assert main(denoise(live_server, src, tmp_path / "out", "--quiet")) == 3
    err = capsys.readouterr().err
    assert "--layer NAME" in err and "ViewLayer" in err and "resume" not in err


def test_models_table_version_and_a_closed_pipe(live_server):
    listing = subprocess.run(
        f"{sys.executable} -m quietframe.client.cli models --server {live_server.url} | head -1",
        shell=True, capture_output=True, text=True, timeout=60)
    assert listing.stdout.startswith("MODEL") and "Traceback" not in listing.stderr
    version = subprocess.run([*CLI, "--version"], capture_output=True, text=True, timeout=60)
    assert version.returncode == 0 and version.stdout.startswith("quietframe ")


@pytest.mark.parametrize("text", ["1001-", "10-5", "a"])
def test_bad_frame_ranges_are_configuration_errors(tmp_path, text, capsys):
    write_shot(tmp_path / "in", 1)
    args = ["denoise", "--server", "http://127.0.0.1:9", str(tmp_path / "in"), "--out",
            str(tmp_path / "out"), "--frames", text]
    assert main(args) == 2 and "frame range" in capsys.readouterr().err
