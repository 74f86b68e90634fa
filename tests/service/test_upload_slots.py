"""Upload slots under slow uploads: trickling bodies cannot keep other sessions out for longer
than their share, no body outlasts the upload cap, one session cannot take every slot, and a
body cut for its time leaves its session as it was. Real sockets against a real server with
small slots, rates and times; the slot rules alone without one."""

from __future__ import annotations

import asyncio
import select
import socket
import threading
import time

import httpx
import pytest
from conftest import LiveServer, frame_bytes, hard_timeout

MODEL = "nbg-2l-3g"
GRACE_S = 0.5  # the pause limit, and the grace of every share
SHARE_S = 1.5  # a frame body's share of its slot: the grace + its size at the share rate
CAP_S = 3.5  # QUIETFRAME_MAX_UPLOAD_S
STEP, EVERY_S = 2048, 0.1  # the trickle: 20 KiB/s, above the 1 KiB/s minimum, never pausing


@pytest.fixture(autouse=True)
def time_limit():
    with hard_timeout(60):
        yield


@pytest.fixture(scope="module")
def frame() -> bytes:
    return frame_bytes()


@pytest.fixture(scope="module")
def server(frame):
    share_rate_kib_s = len(frame) / 1024 / (SHARE_S - GRACE_S)
    with LiveServer(max_uploads=2, max_uploads_per_session=1, body_read_timeout_s=GRACE_S,
                    min_body_rate_kib_s=1, upload_share_rate_kib_s=share_rate_kib_s,
                    max_upload_s=CAP_S) as server:
        yield server


def new_session(server) -> str:
    r = httpx.post(f"{server.url}/v1/sessions", json={"width": 64, "height": 48, "model": MODEL})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def post(server, sid: str, data: bytes) -> httpx.Response:
    return httpx.post(f"{server.url}/v1/sessions/{sid}/frames/0", content=data,
                      headers={"content-type": "image/x-exr"}, timeout=30)


class Trickle(threading.Thread):
    """One frame body sent STEP bytes every EVERY_S until the server answers: its status, its
    body and when the answer came (seconds after the first byte)."""

    def __init__(self, server, sid: str, data: bytes) -> None:
        super().__init__(daemon=True)
        self.port, self.sid, self.data = server.port, sid, data
        self.status: int | None = None
        self.answer, self.after_s = b"", 0.0

    def run(self) -> None:
        head = (f"POST /v1/sessions/{self.sid}/frames/0 HTTP/1.1\r\nHost: x\r\n"
                f"Content-Type: image/x-exr\r\nContent-Length: {len(self.data)}\r\n\r\n")
        start = time.monotonic()
        with socket.create_connection(("127.0.0.1", self.port), timeout=10) as s:
            s.sendall(head.encode())
            for at in range(0, len(self.data), STEP):
                try:
                    s.sendall(self.data[at : at + STEP])
                except OSError:
                    break  # answered and closed
                if select.select([s], [], [], EVERY_S)[0]:
                    break  # answered before the body's end
            self.answer = _read_all(s)
        self.after_s = time.monotonic() - start
        if self.answer.startswith(b"HTTP/1.1 "):
            self.status = int(self.answer.split(b" ", 2)[1])


def _read_all(s: socket.socket) -> bytes:
    """The answer, up to the server's close (every refusal of a body closes the connection)."""
    got = b""
    try:
        while chunk := s.recv(65536):
            got += chunk
    except (TimeoutError, ConnectionResetError):
        pass
    return got


def test_slow_uploads_give_their_slots_to_other_sessions_after_their_share(server, frame):
    """Both slots held by trickling bodies (at 20 KiB/s a body takes 6 s): another session is
    refused with a Retry-After that points at the end of a share, then takes the slot of the
    slowest once its share is over (it used to wait until the trickles ended); the cut upload
    gets 408 upload_too_slow, the other one is cut at the upload cap though nobody waits; both
    sessions are untouched and take their frame at once afterwards."""
    slow = {sid: Trickle(server, sid, frame) for sid in (new_session(server), new_session(server))}
    other = new_session(server)
    start = time.monotonic()
    for trickle in slow.values():
        trickle.start()
    time.sleep(0.3)

    busy = post(server, other, frame)
    assert busy.status_code == 429 and busy.json()["error"] == "too_many_uploads", busy.text
    assert 1 <= int(busy.headers["retry-after"]) <= 2  # the shares end 1.5 s after the start
    second = post(server, next(iter(slow)), frame)  # a second body of a slow session
    assert second.status_code == 429, second.text
    assert "QUIETFRAME_MAX_UPLOADS_PER_SESSION" in second.json()["detail"]

    while (r := post(server, other, frame)).status_code == 429:
        assert time.monotonic() - start < SHARE_S + 1.5, "still no slot long after a share"
        time.sleep(0.1)
    assert r.status_code == 200, r.text
    assert time.monotonic() - start < SHARE_S + 1.5
    for trickle in slow.values():
        trickle.join(15)
    cut, capped = sorted(slow.values(), key=lambda t: t.after_s)
    assert cut.status == 408 and b"upload_too_slow" in cut.answer, cut.answer[-400:]
    assert b"another upload took its slot" in cut.answer
    assert SHARE_S - 0.2 < cut.after_s < SHARE_S + 1.5, cut.after_s
    assert capped.status == 408 and b"QUIETFRAME_MAX_UPLOAD_S" in capped.answer, capped.answer
    assert CAP_S - 0.2 < capped.after_s < CAP_S + 1.0, capped.after_s
    for sid in slow:
        state = httpx.get(f"{server.url}/v1/sessions/{sid}").json()
        assert state["frames_done"] == 0 and state["last_index"] is None, state
        assert post(server, sid, frame).status_code == 200  # its slot was given back


def test_a_body_of_unknown_length_gets_its_share_from_its_header(server, frame):
    """A chunked body's share is the header's largest possible file at the share rate once the
    header is in (the frame limit before): a whole frame sent chunked is denoised."""
    def chunks():
        for at in range(0, len(frame), 16384):
            yield frame[at : at + 16384]

    r = httpx.post(f"{server.url}/v1/sessions/{new_session(server)}/frames/0", content=chunks(),
                   headers={"content-type": "image/x-exr"}, timeout=30)
    assert r.status_code == 200, r.text


# ---- the rules alone ------------------------------------------------------------------------


def test_a_complete_body_is_never_cut_and_a_late_one_gives_way():
    """With one slot: a body past its share whose bytes are all in (its frame waiting for memory
    or denoised) keeps its slot, the newcomer gets 429 with Retry-After 1; a body past its share
    still arriving is cut (408 upload_too_slow) and the newcomer has the slot."""
    from quietframe.service.errors import TooManyUploads, UploadTooSlow
    from quietframe.service.upload_slots import UploadSlots

    async def run() -> None:
        slots = UploadSlots(limit=1, per_session=1, share_rate_bytes_s=1e12, grace_s=0.0,
                            cap_s=60.0)
        entered = asyncio.Event()

        async def hold(session_id: str, complete: bool) -> None:
            async with slots.hold(session_id, 1000) as upload:
                upload.received = 500
                if complete:
                    upload.finished()
                entered.set()
                await asyncio.sleep(0.3)

        done = asyncio.create_task(hold("a", complete=True))
        await entered.wait()
        with pytest.raises(TooManyUploads) as refused:
            async with slots.hold("b", 1000):
                pass
        assert refused.value.headers["Retry-After"] == "1"
        await done  # not cut
        entered.clear()
        late = asyncio.create_task(hold("a", complete=False))
        await entered.wait()
        async with slots.hold("b", 1000):
            assert slots.count == 1
        with pytest.raises(UploadTooSlow, match="another upload took its slot"):
            await late
        assert slots.count == 0

    asyncio.run(run())
