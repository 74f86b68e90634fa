"""Look-ahead sessions over a real socket (docs/service.md, "Look-ahead"): 202 while frames are
held back, then 200 carrying frame t - k with its own headers, finish (in order only: 409
otherwise), idempotent replays of frames and finishes, the status, DELETE, a refused
`lookahead`, a model without an OIDN stage, and pending frames surviving kill -9."""

from __future__ import annotations

import shutil
import signal

import httpx
import numpy as np
import pytest
from conftest import LiveServer, read_exr, shot
from server_support import free_port, start_cli_server

from quietframe.wire.protocol import Header

SIZE = {"width": 64, "height": 48}
MODEL = "oidn-fast-history"


@pytest.fixture(scope="module")
def server():
    with LiveServer() as live:
        yield live


@pytest.fixture(scope="module")
def frames() -> list[bytes]:
    return shot(5)  # a static shot: the later frames see the same surfaces


def create(c: httpx.Client, lookahead: int | None, model: str = MODEL) -> str:
    body = {**SIZE, "model": model} | ({} if lookahead is None else {"lookahead": lookahead})
    r = c.post("/v1/sessions", json=body)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def post(c: httpx.Client, sid: str, index: int, data: bytes) -> httpx.Response:
    return c.post(f"/v1/sessions/{sid}/frames/{index}", content=data,
                  headers={"content-type": "image/x-exr"})


def finish(c: httpx.Client, sid: str, index: int) -> httpx.Response:
    return c.post(f"/v1/sessions/{sid}/frames/{index}/finish")


def colour(data: bytes) -> np.ndarray:
    _, channels = read_exr(data)
    return np.stack([channels[c] for c in "RGB"], -1)


def causal(c: httpx.Client, frames: list[bytes], model: str = MODEL) -> list[httpx.Response]:
    sid = create(c, None, model)
    replies = [post(c, sid, i, f) for i, f in enumerate(frames)]
    c.delete(f"/v1/sessions/{sid}")
    return replies


def test_frames_leave_k_later_and_finish_returns_the_rest(server, frames) -> None:
    with httpx.Client(base_url=server.url, timeout=60) as c:
        today = causal(c, frames)
        assert all(Header.PENDING not in r.headers for r in today)  # k = 0 as before
        sid = create(c, 2)
        replies = [post(c, sid, i, f) for i, f in enumerate(frames)]
        assert [r.status_code for r in replies] == [202, 202, 200, 200, 200]
        assert [r.headers[Header.PENDING] for r in replies] == ["1", "2", "2", "2", "2"]
        assert replies[0].content == b"" and Header.FRAME not in replies[0].headers
        assert [r.headers[Header.FRAME] for r in replies[2:]] == ["0", "1", "2"]
        assert replies[2].headers[Header.RESET] == "first-frame"  # frame 0's own headers
        assert replies[3].headers[Header.RESET] == "none"
        assert "lookahead;dur=" in replies[2].headers["server-timing"]
        status = c.get(f"/v1/sessions/{sid}").json()
        assert status["lookahead"] == 2 and status["pending"] == [3, 4]
        assert status["frames_done"] == 5 and status["last_index"] == 4
        out_of_order = finish(c, sid, 4)
        assert out_of_order.status_code == 409
        assert out_of_order.json()["error"] == "frame_not_pending"
        assert "finish frame 3 first" in out_of_order.json()["detail"]
        last = [finish(c, sid, 3), finish(c, sid, 4)]
        assert [(r.status_code, r.headers[Header.FRAME], r.headers[Header.PENDING])
                for r in last] == [(200, "3", "1"), (200, "4", "0")]
        none = finish(c, sid, 5)
        assert none.status_code == 409 and "no frame of this session is pending" in none.text
        assert c.get(f"/v1/sessions/{sid}").json()["pending"] == []
        held = [*replies[2:], *last]
    # The last frame had nothing to look at: today's output, byte for byte. The others took
    # in their later frames of the static shot: steadier, never the causal output itself.
    assert held[4].content == today[4].content
    for got, was in zip(held[:4], today[:4], strict=True):
        assert not np.array_equal(colour(got.content), colour(was.content))
    header, _ = read_exr(held[0].content)
    assert header["quietframe.frame"] == "0"  # the frame's own file, its own attributes


def test_retries_replay_the_stored_reply(server, frames) -> None:
    with httpx.Client(base_url=server.url, timeout=60) as c:
        sid = create(c, 1)
        first = post(c, sid, 0, frames[0])
        again = post(c, sid, 0, frames[0])
        assert (first.status_code, again.status_code) == (202, 202)
        assert again.headers[Header.REPLAYED] == "true"
        second = post(c, sid, 1, frames[1])
        repeat = post(c, sid, 1, frames[1])
        assert second.status_code == repeat.status_code == 200
        assert repeat.content == second.content and repeat.headers[Header.FRAME] == "0"
        assert repeat.headers[Header.REPLAYED] == "true"
        assert post(c, sid, 1, frames[2]).status_code == 409  # the same index, another body
        done = finish(c, sid, 1)
        retry = finish(c, sid, 1)
        assert retry.status_code == 200 and retry.content == done.content
        assert retry.headers[Header.REPLAYED] == "true" and done.headers[Header.REPLAYED] == "false"
        late = post(c, sid, 1, frames[1])  # the frame's reply was followed by a finish
        assert late.status_code == 409 and "finished after it" in late.json()["detail"]
        assert c.get(f"/v1/sessions/{sid}").json()["frames_done"] == 2  # nothing ran twice


def test_pending_frames_count_against_memory_and_delete_frees_them(server, frames) -> None:
    with httpx.Client(base_url=server.url, timeout=60) as c:
        plain, ahead = create(c, 0), create(c, 3)
        reserved = {sid: c.get(f"/v1/sessions/{sid}").json()["reserved_bytes"]
                    for sid in (plain, ahead)}
        assert reserved[ahead] > reserved[plain] + 3 * 4 * 18 * 64 * 48  # 3 frames' planes
        for i, f in enumerate(frames[:3]):
            post(c, plain, i, f)
            post(c, ahead, i, f)
        held = c.get(f"/v1/sessions/{ahead}").json()
        assert held["pending"] == [0, 1, 2]
        assert held["memory_bytes"] > c.get(f"/v1/sessions/{plain}").json()["memory_bytes"] + (
            3 * sum(len(f) for f in frames[:3]) // 3)
        for sid in (plain, ahead):
            assert c.delete(f"/v1/sessions/{sid}").status_code == 204
        assert c.get(f"/v1/sessions/{ahead}").status_code == 404
        assert finish(c, ahead, 0).status_code == 404


@pytest.mark.parametrize("value", [5, -1, "2", True, 1.5])
def test_lookahead_out_of_range_is_refused(server, value) -> None:
    with httpx.Client(base_url=server.url, timeout=60) as c:
        r = c.post("/v1/sessions", json={**SIZE, "lookahead": value})
    assert r.status_code == 422 and r.json()["error"] == "invalid_request"
    assert "lookahead" in r.json()["detail"]


def test_finish_on_a_session_without_lookahead_says_so(server, frames) -> None:
    with httpx.Client(base_url=server.url, timeout=60) as c:
        sid = create(c, None)
        post(c, sid, 0, frames[0])
        r = finish(c, sid, 0)
    assert r.status_code == 409 and "lookahead 0" in r.json()["detail"]


def test_a_model_without_an_oidn_stage_keeps_the_delay_and_its_output(server, frames) -> None:
    with httpx.Client(base_url=server.url, timeout=60) as c:
        today = causal(c, frames[:3], "nbg-2l-1g")
        sid = create(c, 1, "nbg-2l-1g")
        replies = [post(c, sid, i, f) for i, f in enumerate(frames[:3])] + [finish(c, sid, 2)]
    assert [r.status_code for r in replies] == [202, 200, 200, 200]
    for got, was in zip(replies[1:], today, strict=True):
        assert got.content == was.content  # queued and returned unchanged


def test_pending_frames_survive_a_kill(tmp_path, frames) -> None:
    """kill -9 with two frames held back: the restarted server still holds them, and every
    reply is the one a session of the same server never killed gives, byte for byte."""
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    server = start_cli_server(port, tmp_path)
    try:
        with httpx.Client(base_url=url, timeout=60) as c:
            sid = create(c, 2)
            reference = [post(c, sid, i, f) for i, f in enumerate(frames)]
            reference += [finish(c, sid, 3), finish(c, sid, 4)]
            c.delete(f"/v1/sessions/{sid}")
            sid = create(c, 2)
            before = [post(c, sid, i, f) for i, f in enumerate(frames[:3])]
        server.send_signal(signal.SIGKILL)  # only what was on disk survives
        server.wait(timeout=30)
        server = start_cli_server(port, tmp_path)
        with httpx.Client(base_url=url, timeout=60) as c:
            assert c.get(f"/v1/sessions/{sid}").json()["pending"] == [1, 2]
            repeat = post(c, sid, 2, frames[2])  # the last reply survived too
            assert repeat.headers[Header.REPLAYED] == "true"
            after = [post(c, sid, i, frames[i]) for i in (3, 4)]
            after += [finish(c, sid, 3), finish(c, sid, 4)]
            c.delete(f"/v1/sessions/{sid}")
        got = before + after
        assert [r.status_code for r in got] == [r.status_code for r in reference]
        for a, b in zip(got, reference, strict=True):
            assert a.headers.get(Header.FRAME) == b.headers.get(Header.FRAME)
            assert a.content == b.content
        assert repeat.content == before[2].content
    finally:
        server.kill()
        server.wait(timeout=30)


@pytest.mark.skipif(not shutil.which("redis-server"), reason="needs redis-server")
def test_pending_frames_fail_over_between_replicas(tmp_path, frames) -> None:
    """Two replicas sharing Redis: frames 0-2 on one, 3 on the other (which adopts the
    session with its held-back frames), the finishes on the first again (which follows the
    store): the replies of a session that never moved, byte for byte."""
    from conftest import redis_server, service_settings
    from fastapi.testclient import TestClient

    from quietframe.service.main import create_app

    with redis_server(tmp_path) as url:
        a, b = (TestClient(create_app(service_settings(replica_id=name, store_url=url)))
                for name in "ab")
        with a, b:
            sid = create(a, 2)
            reference = [post(a, sid, i, f) for i, f in enumerate(frames[:4])]
            reference += [finish(a, sid, 2), finish(a, sid, 3)]
            sid = create(a, 2)
            got = [post(a, sid, i, f) for i, f in enumerate(frames[:3])]
            got.append(post(b, sid, 3, frames[3]))
            assert b.get(f"/v1/sessions/{sid}").json()["pending"] == [2, 3]
            got += [finish(a, sid, 2), finish(a, sid, 3)]
    assert [r.status_code for r in got] == [202, 202, 200, 200, 200, 200]
    for x, y in zip(got, reference, strict=True):
        assert x.headers.get(Header.FRAME) == y.headers.get(Header.FRAME)
        assert x.content == y.content
