"""`quietframe denoise --model NAME` with a model that reads the frame's spp, on frames whose
header states none: the server estimates the shot's spp (X-Quietframe-Samples) and the CLI says
so once per run, as a warning naming --model-option spp=N; with that option, or frames that state
their spp, it says nothing. Against a real server with the shipped models."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest
from conftest import LAYOUTS, make_buffers, write_exr

from quietframe.client.cli import main

LEARNED = "nbg-2l-3g"
NOTE = f"{LEARNED} reads the frame's samples per pixel and neither the file's header"


def render(folder: Path, spp: int | None, frames: int = 3) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(frames):
        buffers = make_buffers(noise=100 + i)
        buffers["motion"][:] = 0
        if spp is None:  # a renderer that states no spp (Mitsuba, Arnold)
            data = write_exr(LAYOUTS["plain-normal"](buffers))
        else:
            data = write_exr(LAYOUTS["blender"](buffers), {"cycles.ViewLayer.samples": str(spp)})
        (folder / f"shot.{1001 + i:04d}.exr").write_bytes(data)


@pytest.fixture
def learned(live_server) -> str:
    models = {m["name"] for m in httpx.get(f"{live_server.url}/v1/models").json()["models"]}
    if LEARNED not in models:
        pytest.skip(f"needs {LEARNED} installed")
    return live_server.url


@pytest.mark.parametrize("spp, flags, said", [
    (None, (), True),
    (None, ("--model-option", "spp=8"), False),
    (8, (), False),
])
def test_the_estimate_is_said_once_unless_the_spp_is_stated(tmp_path, learned, capsys, spp,
                                                          flags, said):
    render(tmp_path / "src", spp)
    code = main(["denoise", "--server", learned, str(tmp_path / "src" / "shot.####.exr"),
                 "--out", str(tmp_path / "out"), "--model", LEARNED, "--quiet", *flags])
    assert code == 0 and len(list((tmp_path / "out").glob("shot.*.exr"))) == 3
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if NOTE in line]
    assert len(lines) == int(said), err
    if said:
        assert lines[0].startswith("quietframe: warning: frame 1001: ")
        assert "--model-option spp=N" in lines[0] and lines[0].endswith("(said once per run)")
