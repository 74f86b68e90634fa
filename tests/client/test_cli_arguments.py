"""How `quietframe denoise` reads its command line: Blender's `A..B` frame ranges, options
never abbreviated, and what --force redoes, named in the refusal and counted in the progress."""

from __future__ import annotations

import pytest
from conftest import read_exr, shot, write_exr
from farm_cli_support import denoise, events, write_shot

from quietframe.client.cli import main


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
