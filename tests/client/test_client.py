"""quietframe.client: retry policy (mock transport), and the CLI against a real server."""

from __future__ import annotations

import asyncio
import socket
import threading
import time

import httpx
import numpy as np
import pytest
from conftest import LiveServer, read_exr, service_settings, shot

from quietframe.client import AsyncClient, Client, QuietframeError, RetryPolicy
from quietframe.client.cli import main
from quietframe.client.sequence import JOB_FILE, Job, SequenceError, find_frames, job_settings

FAST = RetryPolicy(retries=3, backoff_s=0.001, max_backoff_s=0.01)


def scripted(*steps):
    """A transport answering with the given statuses (or raising ConnectError for 'down')."""
    calls = []

    def handler(request: httpx.Request) -> httpx.Response:
        step = steps[min(len(calls), len(steps) - 1)]
        calls.append(request)
        if step == "down":
            raise httpx.ConnectError("connection refused", request=request)
        if step == "reset":
            raise httpx.ReadError("connection reset", request=request)
        if step >= 400:
            headers = {"Retry-After": "0"} if step == 429 else {}
            return httpx.Response(step, json={"error": f"e{step}", "detail": "x"}, headers=headers)
        if request.url.path == "/v1/sessions":
            return httpx.Response(201, json={"id": "s"})
        return httpx.Response(
            200,
            content=b"exr",
            headers={
                "X-Quietframe-Reset": "none",
                "X-Quietframe-Missing": "motion",
                "Server-Timing": "total;dur=1.5",
            },
        )

    return httpx.MockTransport(handler), calls


@pytest.mark.parametrize("steps", [(503, 200), (429, 500, 200), ("down", 502, 200), ("reset", 200)])
def test_frames_retry_on_429_5xx_and_connection_errors(steps):
    transport, calls = scripted(*steps)
    with Client("http://qf", retry=FAST, transport=transport) as client:
        result = client.send_frame("s", 3, b"data")
    assert len(calls) == len(steps) and result.exr == b"exr"
    assert result.missing == ("motion",) and result.timings_ms == {"total": 1.5}
    assert all(c.url.path == "/v1/sessions/s/frames/3" and c.content == b"data" for c in calls)


def test_no_retry_on_client_errors_and_give_up_after_retries():
    transport, calls = scripted(422)
    with Client("http://qf", retry=FAST, transport=transport) as client:
        with pytest.raises(QuietframeError) as err:
            client.send_frame("s", 0, b"x")
    assert (err.value.status, err.value.code, len(calls)) == (422, "e422", 1)
    transport, calls = scripted(503)
    with Client("http://qf", retry=FAST, transport=transport) as client:
        with pytest.raises(QuietframeError, match="503"):
            client.send_frame("s", 0, b"x")
    assert len(calls) == 4


def test_create_session_is_not_retried_when_it_may_have_succeeded():
    transport, calls = scripted("reset", 200)
    with Client("http://qf", retry=FAST, transport=transport) as client:
        with pytest.raises(QuietframeError, match="connection_error"):
            client.create_session(64, 48)
    assert len(calls) == 1
    transport, calls = scripted("down", 429, 200)
    with Client("http://qf", retry=FAST, transport=transport) as client:
        client.create_session(64, 48)
    assert len(calls) == 3


def test_async_client_retries():
    transport, calls = scripted(503, "down", 200)

    async def go():
        async with AsyncClient("http://qf", retry=FAST, transport=transport) as client:
            return await client.send_frame("s", 1, b"x")

    assert asyncio.run(go()).reset == "none" and len(calls) == 3


def test_retry_delay_uses_retry_after_and_caps():
    policy = RetryPolicy(backoff_s=1.0, max_backoff_s=5.0)
    assert policy.delay(0, "2") == 2.0 and policy.delay(0, "900") == 5.0
    assert 0.5 <= policy.delay(0) <= 1.0 and policy.delay(10) <= 5.0


def test_client_waits_for_a_server_that_starts_late():
    service_settings()  # skips without an installed model
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    holder = {}

    def start_later():
        time.sleep(1.0)
        holder["server"] = LiveServer(port=port).__enter__()

    thread = threading.Thread(target=start_later)
    thread.start()
    try:
        policy = RetryPolicy(retries=30, backoff_s=0.1, max_backoff_s=0.3)
        with Client(f"http://127.0.0.1:{port}", retry=policy) as client:
            assert client.create_session(64, 48)["id"]
    finally:
        thread.join()
        holder["server"].__exit__()


# ---- sequences and the CLI -----------------------------------------------------------------


def write_shot(folder, n=5, prefix="shot_", start=1001, layout="blender"):
    folder.mkdir(parents=True, exist_ok=True)
    for i, data in enumerate(shot(n, layout)):
        (folder / f"{prefix}{start + i}.exr").write_bytes(data)


def test_find_frames_sorts_by_number(tmp_path):
    for name in ("a.10.exr", "a.9.exr", "a.100.exr", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in find_frames(tmp_path)] == ["a.9.exr", "a.10.exr", "a.100.exr"]
    assert [p.name for p in find_frames(str(tmp_path / "a.1*.exr"))] == ["a.10.exr", "a.100.exr"]
    with pytest.raises(SequenceError):
        find_frames(tmp_path / "empty*")


def test_cli_denoise_writes_outputs_and_resumes(tmp_path, live_server, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src)
    args = ["denoise", "--server", live_server.url, str(src), "--out", str(out), "--quiet"]
    assert main(args) == 0
    names = sorted(p.name for p in out.glob("*.exr"))
    assert names == [f"shot_{1001 + i}.exr" for i in range(5)]
    _, channels = read_exr((out / "shot_1003.exr").read_bytes())
    assert "ViewLayer.Combined.R" in channels
    reference = (out / "shot_1005.exr").read_bytes()
    # An interrupted run: the last two outputs are gone; the session was deleted at the end,
    # so a new one is warmed up with the finished frames and the sequence continues.
    (out / "shot_1004.exr").unlink()
    (out / "shot_1005.exr").unlink()
    assert main(args) == 0
    resumed = (out / "shot_1005.exr").read_bytes()
    np.testing.assert_allclose(colour(resumed), colour(reference), rtol=1e-4, atol=1e-5)
    assert (out / JOB_FILE).exists()
    assert main(args) == 0  # nothing left to do


def colour(data):
    _, ch = read_exr(data)
    return np.stack([ch[k] for k in sorted(ch)], -1)


def test_cli_resume_continues_the_same_session(tmp_path, live_server):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, n=4)
    job = Job.plan(src, out)
    with Client(live_server.url) as client:  # a run that stopped after two frames
        sid = client.create_session(job.width, job.height)["id"]
        for i in range(2):
            exr = client.send_frame(sid, job.indices[i], job.files[i].read_bytes()).exr
            job.write_output(i, exr, job_settings())  # with its record: this job's output
        job.write_job(server=live_server.url, session=sid, last_index=job.indices[1])
        assert (
            main(["denoise", "--server", live_server.url, str(src), "--out", str(out), "--quiet"])
            == 0
        )
        assert len(list(out.glob("*.exr"))) == 4
        with pytest.raises(QuietframeError, match="404"):  # finished: the session was closed
            client.session(sid)


def test_cli_failure_is_clear_and_resumable(tmp_path, live_server, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, n=4)
    good = (src / "shot_1003.exr").read_bytes()
    (src / "shot_1003.exr").write_bytes(good[: len(good) // 2])  # truncated render
    args = ["denoise", "--server", live_server.url, str(src), "--out", str(out), "--quiet"]
    assert main(args) == 3  # an input error, found by the pre-flight before any upload
    err = capsys.readouterr().err
    assert "shot_1003.exr" in err and "cut short" in err and "re-render" in err
    assert not list(out.glob("*.exr"))
    (src / "shot_1003.exr").write_bytes(good)
    assert main(args) == 0 and len(list(out.glob("*.exr"))) == 4


def test_cli_usage_errors(tmp_path, capsys):
    src = tmp_path / "in"
    write_shot(src, n=1)
    assert main(["denoise", "--server", "http://127.0.0.1:9", str(src), "--out", str(src)]) == 2
    assert "must differ" in capsys.readouterr().err
    code = main(
        [
            "denoise",
            "--server",
            "http://127.0.0.1:9",
            str(src),
            "--out",
            str(tmp_path / "o"),
            "--quiet",
            "--retries",
            "0",
        ]
    )
    err = capsys.readouterr().err  # server unavailable: retryable, the URL named
    assert code == 75 and "cannot reach the quietframe server at http://127.0.0.1:9" in err


def test_cli_models(live_server, capsys):
    assert main(["models", "--server", live_server.url]) == 0
    out = capsys.readouterr().out
    assert "[auto's fallback]" in out and "color,albedo" in out
    assert main(["models"]) == 0 and "[session default]" in capsys.readouterr().out


def test_serve_is_a_quietframe_command_registered_by_the_service(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["serve", "--help"])
    assert exit_.value.code == 0 and "--state-dir" in capsys.readouterr().out


def test_imports_stay_in_their_extra():
    """The client needs neither the server nor onnxruntime; the server never imports torch."""
    import subprocess
    import sys

    probe = (
        "import sys, quietframe.client.cli, quietframe.client.sequence;"
        "quietframe.client.cli.build_parser();"  # with the commands other packages register
        "assert not {'onnxruntime', 'fastapi', 'torch'} & set(sys.modules), sys.modules.keys();"
        "import quietframe.service.main;"
        "assert 'torch' not in sys.modules"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]


def test_clients_stream_a_directory(tmp_path, live_server):
    src = tmp_path / "in"
    write_shot(src, n=3, layout="arnold")
    with Client(live_server.url) as client:
        seen = []
        assert client.denoise_sequence(src, tmp_path / "sync", on_progress=seen.append)
    assert [p.result.reset for p in seen] == ["first-frame", "none", "none"]

    async def go():
        async with AsyncClient(live_server.url) as client:
            return await client.denoise_sequence(str(src / "*.exr"), tmp_path / "async")

    assert asyncio.run(go())
    for name in ("shot_1001.exr", "shot_1003.exr"):
        sync, other = (tmp_path / d / name for d in ("sync", "async"))
        np.testing.assert_allclose(
            colour(sync.read_bytes()), colour(other.read_bytes()), rtol=1e-5, atol=1e-6
        )


def test_locked_off_flag_asks_the_session_to_trust_zero_motion():
    from quietframe.client.cli import build_parser, session_options

    parser = build_parser()
    base = ["denoise", "frames/", "--out", "out/", "--server", "http://127.0.0.1:1"]
    assert session_options(parser.parse_args(base))["camera"] is None  # the server's default
    assert session_options(parser.parse_args([*base, "--locked-off"]))["camera"] == "locked"
