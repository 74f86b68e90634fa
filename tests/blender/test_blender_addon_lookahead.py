"""The add-on's look-ahead setting (no bpy) against the stand-in of the look-ahead protocol
(tests/lookahead_support.py), whose replies are their frames' own uploads: each camera shot's
session is created with the look-ahead, every output is written from the reply that carries its
frame, and the frames the session still holds are finished at the end of each shot, in order,
after the render (denoise_shots) and while it renders (LiveJob); and once against the real
server (skipped where it has no look-ahead yet)."""

from __future__ import annotations

import json
import urllib.request

import pytest
from blender_addon_support import assert_denoised, copy_sequence
from conftest import hard_timeout
from lookahead_support import FakeServer
from quietframe_blender.denoise_job import JobSettings, LiveJob, denoise_shots
from quietframe_blender.shots import CameraMarker, plan_shots


def own_frames(sources, out) -> bool:
    return all((out / source.name).read_bytes() == source.read_bytes()
               for source in sources.values())


def test_each_shot_looks_ahead_and_is_finished_at_its_end(tmp_path):
    sources = copy_sequence(tmp_path / "render", "motion_blur", range(1, 6))
    shots = plan_shots(sources, [CameraMarker(1, "A"), CameraMarker(4, "B")], "A")
    out = tmp_path / "denoised"
    with FakeServer() as server, hard_timeout(60):
        result = denoise_shots(shots, sources, JobSettings(server.url, out_folder=out,
                                                           lookahead=2))
        log = server.fake.log
        sessions = {sid: server.fake.sessions.get(sid) for _, sid, _ in log}
    assert result.error is None and result.shots == 2
    assert [o.frame for o in result.outcomes] == [1, 2, 3, 4, 5]
    assert own_frames(sources, out)
    # shot A (1-3): 1, 2 held, 3 carries 1, then 2 and 3 finished; shot B (4-5): both finished
    assert [(kind, i) for kind, _, i in log if kind in ("frame", "finish")] == [
        ("frame", 1), ("frame", 2), ("frame", 3), ("finish", 2), ("finish", 3),
        ("frame", 4), ("frame", 5), ("finish", 4), ("finish", 5)]
    assert all(session is None for session in sessions.values())  # each deleted at its end


def test_denoising_while_rendering_finishes_each_camera_and_the_end(tmp_path):
    sources = copy_sequence(tmp_path, "motion_blur", range(1, 5))
    out = tmp_path / "denoised"
    with FakeServer() as server:
        job = LiveJob(JobSettings(server.url, out_folder=out, lookahead=1))
        for frame, camera in zip(sources, ("A", "A", "B", "B"), strict=True):
            job.add(frame, sources[frame], camera)
        job.finish()
        with hard_timeout(60):
            result = job.wait()
        finished = server.fake.sent("finish")
        created = server.fake.sent("create")
    assert result.error is None and result.shots == 2 and len(created) == 2
    assert [o.frame for o in result.outcomes] == [1, 2, 3, 4]
    assert finished == [2, 4]  # the camera switch, then the end of the render
    assert own_frames(sources, out)


def test_the_real_server_returns_every_frame_of_each_shot(tmp_path, live_server):
    paths = json.loads(urllib.request.urlopen(f"{live_server.url}/openapi.json",
                                              timeout=60).read())["paths"]
    if "/v1/sessions/{session_id}/frames/{index}/finish" not in paths:
        pytest.skip("this server has no look-ahead (no finish route)")
    sources = copy_sequence(tmp_path, "motion_blur", range(1, 6))
    shots = plan_shots(sources, [CameraMarker(1, "A"), CameraMarker(4, "B")], "A")
    with hard_timeout(60):
        result = denoise_shots(shots, sources, JobSettings(live_server.url, lookahead=2))
    assert [o.frame for o in result.outcomes] == [1, 2, 3, 4, 5] and result.shots == 2
    assert [o.reset for o in result.outcomes][3] == "first-frame"  # shot B's own history
    for frame, source in sources.items():
        assert_denoised(source, source.with_name(f"shot_{frame:04d}_denoised.exr"), (128, 72))
