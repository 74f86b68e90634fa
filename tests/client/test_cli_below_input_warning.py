"""`quietframe denoise --model NAME` on frames at an spp where that model's card says it is below
its own noisy input: the server's X-Quietframe-Warning is said once per run as a warning (not
once per frame), the frames are written as asked and the exit code stays 0. Likewise the
server's estimate of the shot's spp (X-Quietframe-Samples) where the model reads one and
neither the header nor --model-option states it, with how to state it. Against a real server,
with the shipped cards."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest
from conftest import LAYOUTS, make_buffers, write_exr

from quietframe.client.cli import main

LEARNED = "nbg-2l-3g"  # below its input from 11.6 spp on a validation shot (its card)
WARNING = f"{LEARNED} is below its own noisy input from 11.6 spp"


def render(folder: Path, spp: int | None, frames: int = 3) -> None:
    """`frames` Cycles frames of a locked-off shot, each stating `spp` in its header (None: a
    renderer that states none, Mitsuba's or Arnold's layout)."""
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(frames):
        buffers = make_buffers(noise=100 + i)
        buffers["motion"][:] = 0
        if spp is None:
            data = write_exr(LAYOUTS["plain-normal"](buffers))
        else:
            data = write_exr(LAYOUTS["blender"](buffers), {"cycles.ViewLayer.samples": str(spp)})
        (folder / f"shot.{1001 + i:04d}.exr").write_bytes(data)


def run(url: str, src: Path, out: Path, model: str, *flags: str) -> int:
    return main(["denoise", "--server", url, str(src / "shot.####.exr"), "--out", str(out),
                 "--model", model, *flags])


@pytest.fixture
def learned(live_server) -> str:
    models = {m["name"] for m in httpx.get(f"{live_server.url}/v1/models").json()["models"]}
    if LEARNED not in models:
        pytest.skip(f"needs {LEARNED} installed")
    return live_server.url


def test_the_warning_is_said_once_per_run_on_stderr_and_the_run_succeeds(
        tmp_path, learned, capsys):
    render(tmp_path / "src", 64)
    assert run(learned, tmp_path / "src", tmp_path / "out", LEARNED, "--quiet") == 0
    assert len(list((tmp_path / "out").glob("shot.*.exr"))) == 3
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if WARNING in line]
    assert lines == [f"quietframe: warning: frame 1001: {WARNING} on a validation-zoo shot "
                     "(this frame: 64 spp, -1.35 dB there); use model=auto or an OIDN tier "
                     "(said once per run)"], captured.err
    assert WARNING not in captured.out


def test_json_says_it_as_one_warning_event_and_in_the_summary(tmp_path, learned, capsys):
    render(tmp_path / "src", 64)
    assert run(learned, tmp_path / "src", tmp_path / "out", LEARNED, "--json") == 0
    events = [json.loads(line) for line in capsys.readouterr().out.splitlines()
              if line.startswith("{")]
    warnings = [e for e in events if e["event"] == "warning" and WARNING in e["message"]]
    assert len(warnings) == 1
    summary = next(e for e in events if e["event"] == "summary")
    assert sum(WARNING in w for w in summary["warnings"]) == 1


@pytest.mark.parametrize("spp, model", [(2, LEARNED), (64, "auto")])
def test_no_warning_in_the_models_range_or_with_auto(tmp_path, learned, capsys, spp, model):
    render(tmp_path / "src", spp, frames=2)
    assert run(learned, tmp_path / "src", tmp_path / "out", model, "--quiet") == 0
    captured = capsys.readouterr()
    assert "below its own noisy input" not in captured.err + captured.out


ESTIMATED = f"{LEARNED} reads the frame's samples per pixel and neither the file's header"


@pytest.mark.parametrize("spp, flags, said", [
    (None, (), True),
    (None, ("--model-option", "spp=8"), False),
    (8, (), False),
])
def test_the_estimated_spp_is_said_once_unless_the_spp_is_stated(tmp_path, learned, capsys, spp,
                                                                flags, said):
    render(tmp_path / "src", spp)
    assert run(learned, tmp_path / "src", tmp_path / "out", LEARNED, "--quiet", *flags) == 0
    assert len(list((tmp_path / "out").glob("shot.*.exr"))) == 3
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if ESTIMATED in line]
    assert len(lines) == int(said), err
    if said:
        assert lines[0].startswith("quietframe: warning: frame 1001: ")
        assert "--model-option spp=N" in lines[0] and lines[0].endswith("(said once per run)")
