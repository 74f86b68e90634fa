"""The add-on's upload loop (no bpy) against a real quietframe server over a socket, with frames
Cycles wrote (tests/fixtures/blender_sequences): one session per camera shot, the denoised EXRs
beside the renders or in a folder, frames not rendered skipped, refusals and an unreachable
server reported in words, the server's Retry-After honoured, cancelling, and the queue that
denoises while Blender renders."""

from __future__ import annotations

import json
import threading
import urllib.request
from pathlib import Path

import pytest
from blender_addon_support import SEQUENCES, assert_denoised, copy_sequence
from conftest import LiveServer, hard_timeout
from quietframe_blender.denoise_job import JobSettings, LiveJob, denoise_shots
from quietframe_blender.server_api import DenoiseError, RetryPolicy
from quietframe_blender.shots import CameraMarker, plan_shots

SIZE = (128, 72)


def session_exists(url: str, session_id: str) -> bool:
    try:
        urllib.request.urlopen(f"{url}/v1/sessions/{session_id}", timeout=10).close()
        return True
    except urllib.error.HTTPError as exc:
        assert exc.code == 404
        return False


def test_each_camera_shot_gets_a_fresh_session_and_the_files_are_written_beside(
        tmp_path, live_server):
    sources = copy_sequence(tmp_path / "render", "motion_blur", range(1, 6))
    shots = plan_shots(sources, [CameraMarker(1, "A"), CameraMarker(4, "B")], "A")
    seen = []
    with hard_timeout(60):
        result = denoise_shots(shots, sources, JobSettings(live_server.url), seen.append)
    assert [o.frame for o in result.outcomes] == [1, 2, 3, 4, 5]
    assert result.shots == 2 and not result.missing and not result.cancelled
    by_frame = {o.frame: o for o in result.outcomes}
    first, second = by_frame[1].session, by_frame[4].session
    assert first != second
    assert [by_frame[f].session for f in (1, 2, 3, 4, 5)] == [first] * 3 + [second] * 2
    # the second shot starts afresh; inside a shot the history carries on
    assert by_frame[4].reset == "first-frame" and by_frame[2].reset != "first-frame"
    for frame, source in sources.items():
        output = source.with_name(f"shot_{frame:04d}_denoised.exr")
        assert by_frame[frame].output == output
        assert_denoised(source, output, SIZE)
    assert not session_exists(live_server.url, first)  # each shot's history freed at its end
    assert not session_exists(live_server.url, second)
    assert seen[-1].done == seen[-1].total == 5 and "2 shots" in seen[-1].message


def test_frames_not_rendered_are_skipped_and_named(tmp_path, live_server):
    sources = copy_sequence(tmp_path, "locked_off", (1, 2, 4))
    sources[3] = tmp_path / "shot_0003.exr"  # never rendered
    sources[5] = tmp_path / "shot_0005.exr"
    sources[5].write_bytes(b"")  # Blender's placeholder for a frame another node renders
    out = tmp_path / "denoised"
    settings = JobSettings(live_server.url, out_folder=out)
    with hard_timeout(60):
        result = denoise_shots(plan_shots(sources, [], "Cam"), sources, settings)
    assert result.missing == [3, 5]
    assert "not rendered, skipped: 3, 5" in result.summary()
    assert sorted(p.name for p in out.iterdir()) == [f"shot_000{f}.exr" for f in (1, 2, 4)]
    resets = {o.frame: o.reset for o in result.outcomes}
    assert resets[4] == "gap"  # the server restarts the history at the missing frame
    for frame in (1, 2, 4):
        assert_denoised(sources[frame], out / sources[frame].name, SIZE)


def test_nothing_rendered_is_refused_before_anything_is_sent(tmp_path):
    sources = {1: tmp_path / "shot_0001.exr"}
    with pytest.raises(DenoiseError, match="render the animation first"):
        denoise_shots(plan_shots(sources, [], "Cam"), sources, JobSettings("http://127.0.0.1:9"))


def test_the_render_folder_is_not_a_denoised_folder(tmp_path, live_server):
    sources = copy_sequence(tmp_path, "locked_off", (1,))
    settings = JobSettings(live_server.url, out_folder=tmp_path)
    with pytest.raises(DenoiseError, match="would replace the renders"):
        denoise_shots(plan_shots(sources, [], "Cam"), sources, settings)
    assert sources[1].read_bytes() == (SEQUENCES / "locked_off.0001.exr").read_bytes()


def test_a_refusal_shows_the_servers_message_and_stops(tmp_path):
    sources = copy_sequence(tmp_path, "locked_off", (1, 2))
    with LiveServer(auth_token="s3cret") as server, hard_timeout(60):
        with pytest.raises(DenoiseError) as refused:
            denoise_shots(plan_shots(sources, [], "Cam"), sources,
                          JobSettings(server.url, token="wrong"))
        assert "401 unauthorized" in str(refused.value)
        assert "token in the add-on's preferences" in str(refused.value)
        result = denoise_shots(plan_shots(sources, [], "Cam"), sources,
                               JobSettings(server.url, token="s3cret"))
    assert len(result.outcomes) == 2
    assert not list(tmp_path.glob("*_denoised.exr.part"))


def test_an_unknown_model_is_refused_in_the_servers_words(tmp_path, live_server):
    sources = copy_sequence(tmp_path, "locked_off", (1,))
    with pytest.raises(DenoiseError, match="422") as refused:
        denoise_shots(plan_shots(sources, [], "Cam"), sources,
                      JobSettings(live_server.url, model="no-such-model"))
    assert "no-such-model" in str(refused.value)
    assert not (tmp_path / "shot_0001_denoised.exr").exists()


def test_an_unreachable_server_is_named_at_once(tmp_path):
    sources = copy_sequence(tmp_path, "locked_off", (1,))
    retries = []
    with hard_timeout(20), pytest.raises(DenoiseError) as unreachable:
        denoise_shots(plan_shots(sources, [], "Cam"), sources,
                      JobSettings("http://127.0.0.1:9/v1/"), lambda p: retries.append(p))
    message = str(unreachable.value)
    assert "http://127.0.0.1:9 " in message and "connection refused" in message
    assert not any("retry" in p.message for p in retries)  # a wrong URL is said at once


def test_a_busy_server_is_waited_for_as_its_retry_after_says(tmp_path):
    sources = copy_sequence(tmp_path, "locked_off", (1, 2))
    with LiveServer(max_sessions=1, session_ttl_s=2.0) as server, hard_timeout(60):
        request = urllib.request.Request(
            f"{server.url}/v1/sessions", json.dumps({"width": 8, "height": 8}).encode(),
            {"Content-Type": "application/json"})
        urllib.request.urlopen(request, timeout=10).close()  # holds the one session slot
        seen = []
        result = denoise_shots(plan_shots(sources, [], "Cam"), sources,
                               JobSettings(server.url, retry=RetryPolicy(retries=8)),
                               seen.append)
    waits = [p.message for p in seen if "retry" in p.message]
    assert waits and waits[0].startswith("429 too_many_sessions; retry 1 of 8 in ")
    assert 0 < float(waits[0].split(" in ")[1].split()[0]) <= 2.0  # the server's Retry-After
    assert len(result.outcomes) == 2


def test_a_server_that_stays_busy_is_reported_after_the_retries(tmp_path):
    sources = copy_sequence(tmp_path, "locked_off", (1,))
    with LiveServer(max_sessions=1) as server, hard_timeout(60):
        request = urllib.request.Request(
            f"{server.url}/v1/sessions", json.dumps({"width": 8, "height": 8}).encode(),
            {"Content-Type": "application/json"})
        urllib.request.urlopen(request, timeout=10).close()
        policy = RetryPolicy(retries=2, max_wait_s=0.2)
        with pytest.raises(DenoiseError, match="stayed busy after 2 retries.*429"):
            denoise_shots(plan_shots(sources, [], "Cam"), sources,
                          JobSettings(server.url, retry=policy))


def test_cancelling_stops_after_the_frame_in_flight(tmp_path, live_server):
    sources = copy_sequence(tmp_path, "locked_off", range(1, 5))
    cancel = threading.Event()

    def on_progress(progress) -> None:
        if progress.done == 2:
            cancel.set()

    with hard_timeout(60):
        result = denoise_shots(plan_shots(sources, [], "Cam"), sources,
                               JobSettings(live_server.url), on_progress, cancel)
    assert result.cancelled and [o.frame for o in result.outcomes] == [1, 2]
    assert result.summary().startswith("cancelled: denoised 2 frames")
    assert sorted(p.name for p in tmp_path.glob("*_denoised.exr")) == [
        "shot_0001_denoised.exr", "shot_0002_denoised.exr"]
    assert not session_exists(live_server.url, result.outcomes[0].session)


def test_a_view_layer_is_chosen_where_the_render_has_several(tmp_path, live_server):
    fixture = Path(__file__).resolve().parents[1] / "fixtures" / "blender"
    source = tmp_path / "layers_0002.exr"
    source.write_bytes((fixture / "two_view_layers.0002.exr").read_bytes())
    sources = {2: source}
    with pytest.raises(DenoiseError, match="Objects, ViewLayer.*now Missing"):
        denoise_shots(plan_shots(sources, [], "Cam"), sources,
                      JobSettings(live_server.url, layer="Missing"))
    result = denoise_shots(plan_shots(sources, [], "Cam"), sources,
                           JobSettings(live_server.url, layer="Objects"))
    assert [o.frame for o in result.outcomes] == [2]
    assert (tmp_path / "layers_0002_denoised.exr").stat().st_size > 0


def test_denoising_while_rendering_opens_a_session_per_camera(tmp_path, live_server):
    sources = copy_sequence(tmp_path, "motion_blur", range(1, 5))
    job = LiveJob(JobSettings(live_server.url))
    for frame, camera in zip(sources, ("A", "A", "B", "A"), strict=True):
        job.add(frame, sources[frame], camera)  # as the render_write handler does
    job.finish()
    with hard_timeout(60):
        result = job.wait()
    assert result.error is None and result.shots == 3
    sessions = [o.session for o in result.outcomes]
    assert sessions[0] == sessions[1] and len(set(sessions)) == 3
    assert [o.reset for o in result.outcomes][2:] == ["first-frame", "first-frame"]
    for frame, source in sources.items():
        assert_denoised(source, source.with_name(f"shot_{frame:04d}_denoised.exr"), SIZE)


def test_denoising_while_rendering_stops_at_an_error_and_keeps_it(tmp_path, live_server):
    sources = copy_sequence(tmp_path, "locked_off", (1, 3))
    broken = tmp_path / "shot_0002.exr"
    broken.write_bytes(b"not an exr")
    job = LiveJob(JobSettings(live_server.url))
    for frame, source in ((1, sources[1]), (2, broken), (3, sources[3])):
        job.add(frame, source, "Cam")
    job.finish()
    with hard_timeout(60):
        result = job.wait()
    assert result.error is not None and "shot_0002.exr is not a readable EXR" in result.error
    assert [o.frame for o in result.outcomes] == [1]  # nothing sent after the error
    assert not (tmp_path / "shot_0003_denoised.exr").exists()
