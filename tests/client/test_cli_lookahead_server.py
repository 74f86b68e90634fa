"""`quietframe denoise --lookahead` against the real server over a socket (skipped where the
server has no finish route yet): a chunk whose post-roll holds the frames after it writes its
last frames as one unchunked run does, and without the post-roll they differ (the look-ahead's
seam, as the pre-roll's pop); the frames held at the end are finished in order; and a run stopped
mid-way is continued in the same session by its rerun, with outputs equal to a run never
stopped."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest
from conftest import read_exr
from farm_cli_support import events, write_shot

from quietframe.client.api import Client
from quietframe.client.cli import main

MODEL = "oidn-fast-history"  # an OIDN history tier: its look-ahead changes the pixels


@pytest.fixture(scope="module")
def server(live_server):
    paths = httpx.get(f"{live_server.url}/openapi.json", timeout=60).json()["paths"]
    if "/v1/sessions/{session_id}/frames/{index}/finish" not in paths:
        pytest.skip("this server has no look-ahead (no finish route)")
    return live_server


@pytest.fixture(scope="module")
def shot_folder(tmp_path_factory):
    src = tmp_path_factory.mktemp("lookahead") / "in"
    write_shot(src, 8)
    return src


def denoise(server, src, out, *flags: str) -> list[str]:
    return ["denoise", "--server", server.url, str(src / "shot.####.exr"), "--out", str(out),
            "--model", MODEL, *flags]


def colour(folder, frame: int) -> np.ndarray:
    _, channels = read_exr((folder / f"shot.{frame}.exr").read_bytes())
    return np.stack([channels[f"ViewLayer.Combined.{c}"] for c in "RGB"]).astype(np.float64)


def test_the_post_roll_gives_a_chunk_the_look_ahead_of_one_unchunked_run(
        tmp_path, server, shot_folder, capsys):
    src = shot_folder
    assert main(denoise(server, src, tmp_path / "causal", "--quiet")) == 0
    assert main(denoise(server, src, tmp_path / "whole", "--lookahead", "2", "--json")) == 0
    seen = [e for e in events(capsys.readouterr().out) if e["event"] == "frame"]
    assert [(e["frame"], e["reply_to"], e["finished"]) for e in seen] == [
        *((n, n + 2, False) for n in range(1001, 1007)), (1007, None, True),
        (1008, None, True)]  # each 2 frames later; the last two finished, in order
    chunk = ("--frames", "1004-1006", "--pre-roll", "3", "--lookahead", "2", "--quiet")
    assert main(denoise(server, src, tmp_path / "post", *chunk, "--post-roll", "2")) == 0
    assert main(denoise(server, src, tmp_path / "bare", *chunk)) == 0
    off = {kind: {n: np.abs(colour(tmp_path / kind, n) - colour(tmp_path / "whole", n)).max()
                  for n in (1004, 1005, 1006)} for kind in ("post", "bare", "causal")}
    assert off["causal"][1004] > 1e-4  # the look-ahead changes the frame
    assert max(off["post"].values()) < 1e-6  # with the post-roll: the unchunked run's frames
    assert off["bare"][1004] < 1e-6  # its later frames are in the chunk
    assert off["bare"][1006] > 1e-4  # without the post-roll the last frame has none: a seam
    assert sorted(p.name for p in (tmp_path / "post").glob("*.exr")) == [
        "shot.1004.exr", "shot.1005.exr", "shot.1006.exr"]


def test_a_stopped_run_is_continued_in_its_session(tmp_path, server, shot_folder):
    src = shot_folder
    assert main(denoise(server, src, tmp_path / "whole", "--lookahead", "2", "--quiet")) == 0
    out = tmp_path / "out"

    def stop_after_three(p) -> None:
        if p.result is not None and p.position == 2:
            raise KeyboardInterrupt  # as Ctrl-C after the third output was written

    with Client(server.url) as client, pytest.raises(KeyboardInterrupt):
        client.denoise_sequence(src, out, model=MODEL, lookahead=2,
                                on_progress=stop_after_three)
    job = json.loads((out / ".quietframe-job.json").read_text())
    assert job["held"] == [1004, 1005] and job["last_index"] == 1005
    assert main(denoise(server, src, out, "--lookahead", "2", "--quiet")) == 0
    after = json.loads((out / ".quietframe-job.json").read_text())
    assert after["sessions"] == job["sessions"]  # the same session went on
    for n in range(1001, 1009):
        assert np.array_equal(colour(out, n), colour(tmp_path / "whole", n)), n
