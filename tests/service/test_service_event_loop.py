"""The server keeps answering under hostile clients: a huge EXR header is parsed off the event
loop, a slow upload holds the memory of the bytes it sent (not its frame's peak), and
connections that never finish their request headers are closed, also at the open-file limit.
A real `quietframe serve` process on 127.0.0.1 with a small memory budget, a short header
timeout and a low open-file limit; every socket has a timeout."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
import threading
import time
from collections.abc import Iterator

import pytest
from conftest import hard_timeout, layout_plain, make_buffers, service_settings, write_exr
from test_service_reliability_memory import ServerProcess

BUDGET_MB = 64
HEADER_TIMEOUT_S = 3
OPEN_FILES = 256  # the server's RLIMIT_NOFILE: its connection cap is 192
MODEL = "nbg-2l-3g"


@pytest.fixture(autouse=True)
def time_limit():
    with hard_timeout(60):
        yield


class Server(ServerProcess):
    """A server process with an open-file limit, and raw connections to it."""

    def connect(self) -> socket.socket:
        return socket.create_connection(("127.0.0.1", self.port), timeout=10)


@pytest.fixture(scope="module")
def server():
    service_settings()  # skips without an installed model
    with Server(
        OPEN_FILES,
        memory_budget_mb=BUDGET_MB,
        admission_wait_s=1,
        header_timeout_s=HEADER_TIMEOUT_S,
        log_json="false",
    ) as server:
        yield server


def session(server: Server, width: int, height: int) -> str:
    import httpx

    r = httpx.post(f"{server.url}/v1/sessions",
                   json={"width": width, "height": height, "model": MODEL}, timeout=10)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def frame_request(sid: str, length: int, index: int = 0) -> bytes:
    return (f"POST /v1/sessions/{sid}/frames/{index} HTTP/1.1\r\nHost: x\r\n"
            f"Content-Type: image/x-exr\r\nContent-Length: {length}\r\n\r\n").encode()


def status_line(sock: socket.socket, wait_s: float) -> int | None:
    """The status of the answer on `sock`, or None when none comes in `wait_s`."""
    sock.settimeout(wait_s)
    data = b""
    with contextlib.suppress(TimeoutError, ConnectionResetError):
        while b"\r\n" not in data and (chunk := sock.recv(4096)):
            data += chunk
    return int(data.split(b" ", 2)[1]) if data.startswith(b"HTTP/1.1 ") else None


@contextlib.contextmanager
def health_probes(url: str, period_s: float = 0.05) -> Iterator[list[float]]:
    """/healthz asked every `period_s` on a second thread; yields the latencies (seconds, a
    probe that failed counts as 10)."""
    import httpx

    latencies: list[float] = []
    stop = threading.Event()

    def probe() -> None:
        with httpx.Client(timeout=10) as client:
            while not stop.is_set():
                start = time.monotonic()
                try:
                    ok = client.get(f"{url}/healthz").status_code == 200
                except httpx.HTTPError:
                    ok = False
                latencies.append(time.monotonic() - start if ok else 10.0)
                stop.wait(period_s)

    thread = threading.Thread(target=probe, daemon=True)
    thread.start()
    try:
        yield latencies
    finally:
        stop.set()
        thread.join(15)


def health_latency(url: str, timeout_s: float) -> float | None:
    """Seconds /healthz took on a new connection, None when it did not answer 200 in time."""
    import httpx

    start = time.monotonic()
    try:
        ok = httpx.get(f"{url}/healthz", timeout=timeout_s).status_code == 200
    except httpx.HTTPError:
        return None
    return time.monotonic() - start if ok else None


def _attribute(name: bytes, kind: bytes, value: bytes) -> bytes:
    return name + b"\0" + kind + b"\0" + struct.pack("<i", len(value)) + value


def tiny_attribute_header(size: int, width: int = 64, height: int = 48) -> bytes:
    """A multi-part EXR header of about `size` bytes: parts of 4000 four-byte int attributes
    each (the most a part may have is 4096) beside a valid part's own; ~0.8 M attributes for
    16 MiB."""
    window = struct.pack("<iiii", 0, 0, width - 1, height - 1)
    channels = b"".join(c + b"\0" + struct.pack("<iB3xii", 1, 0, 1, 1) for c in (b"R", b"G", b"B"))
    part = b"".join([
        _attribute(b"channels", b"chlist", channels + b"\0"),
        _attribute(b"compression", b"compression", b"\0"),
        _attribute(b"dataWindow", b"box2i", window),
        _attribute(b"displayWindow", b"box2i", window),
        _attribute(b"lineOrder", b"lineOrder", b"\0"),
        _attribute(b"type", b"string", b"scanlineimage"),
        *(_attribute(b"a%d" % k, b"int", struct.pack("<i", k)) for k in range(4000)),
    ]) + b"\0"
    parts = (size - 9) // len(part)
    return b"\x76\x2f\x31\x01" + struct.pack("<I", 2 | 0x1000) + part * parts + b"\0"


def test_health_answers_while_a_huge_header_is_parsed(server):
    """A frame whose header is 16 MiB of tiny attributes over ~240 parts
    (QUIETFRAME_MAX_HEADER_BYTES, seconds of parsing): /healthz answers within 1 s all along,
    and the frame gets its 422 (a 64x48 frame to a 32x32 session) once the header is read."""
    sid = session(server, 32, 32)
    data = tiny_attribute_header(16 << 20) + bytes(64 << 10)  # and the start of the pixels
    with health_probes(server.url) as latencies, server.connect() as s:
        start = time.monotonic()
        s.sendall(frame_request(sid, len(data)) + data)
        status = status_line(s, 40)
        took = time.monotonic() - start
    assert status == 422
    assert latencies and max(latencies) < 1.0, (
        f"/healthz took up to {max(latencies):.2f} s while the header was parsed ({took:.1f} s)"
    )
    print(f"16 MiB header answered in {took:.1f} s; {len(latencies)} /healthz, "
          f"slowest {max(latencies) * 1e3:.0f} ms")


def test_header_with_more_channels_than_a_render_is_refused():
    """Matching 650 000 channel names against the renderer aliases took 1.5 s of the event
    loop (after 2.2 s of parsing them): more than 4096 channels is refused from the header."""
    from quietframe.runtime.frame_errors import UnsupportedExr
    from quietframe.service import frames

    def header(count: int) -> bytes:
        window = struct.pack("<iiii", 0, 0, 7, 7)
        names = [b"R", b"G", b"B"] + [b"aov%05d" % i for i in range(count - 3)]
        channels = b"".join(n + b"\0" + struct.pack("<iB3xii", 1, 0, 1, 1) for n in names)
        return (b"\x76\x2f\x31\x01" + struct.pack("<I", 2)
                + _attribute(b"channels", b"chlist", channels + b"\0")
                + _attribute(b"compression", b"compression", b"\0")
                + _attribute(b"dataWindow", b"box2i", window)
                + _attribute(b"lineOrder", b"lineOrder", b"\0") + b"\0")

    assert len(frames.read_header(header(4096), 8192, 8192).channels) == 4096
    with pytest.raises(UnsupportedExr, match="4096 channels"):
        frames.read_header(header(4097), 8192, 8192)


def test_slow_upload_holds_only_the_bytes_it_sent(server):
    """Two 256x224 frames whose peaks (~40 MiB each) do not fit the 64 MiB budget together:
    one stalls after half its body; meanwhile the other session's frame is denoised, not
    refused with 429 memory_busy; then the slow one's body ends and it is denoised too."""
    import httpx

    slow_sid, sid = session(server, 256, 224), session(server, 256, 224)
    slow = write_exr(layout_plain(make_buffers(224, 256)))
    other = write_exr(layout_plain(make_buffers(224, 256, seed=1)))
    with server.connect() as s:
        s.sendall(frame_request(slow_sid, len(slow)) + slow[: len(slow) // 2])
        time.sleep(0.3)  # the header is read and the first half received
        r = httpx.post(f"{server.url}/v1/sessions/{sid}/frames/0", content=other,
                       headers={"content-type": "image/x-exr"}, timeout=30)
        s.sendall(slow[len(slow) // 2 :])
        slow_status = status_line(s, 30)
    assert r.status_code == 200, r.text
    assert slow_status == 200


def test_reservation_follows_the_body_then_takes_the_frame_peak():
    """Without a server: while a body arrives its reservation is the bytes received (twice
    them for a chunked body's growing buffer, and the header's while it is parsed), the frame's
    peak only once the body is complete; a peak over the whole budget is refused at the
    header; the budget is never overcommitted."""
    from starlette.requests import Request

    from quietframe.service.admission import MemoryBudget, Reservation
    from quietframe.service.errors import FrameOverMemoryBudget
    from quietframe.service.settings import Settings
    from quietframe.service.upload import read_frame

    data = write_exr(layout_plain(make_buffers(240, 320)))  # 2.9 MiB
    chunk = 64 << 10

    async def receive_in_chunks(
        budget: MemoryBudget, peak: int, held: list[int], chunked: bool = False
    ) -> Reservation:
        """The frame's reservation; `held` gets what the budget held before each chunk."""
        sent = 0

        async def receive() -> dict:
            nonlocal sent
            held.append(budget.used_bytes)
            body, sent = data[sent : sent + chunk], sent + chunk
            return {"type": "http.request", "body": body, "more_body": sent < len(data)}

        length = [] if chunked else [(b"content-length", str(len(data)).encode())]
        scope = {"type": "http", "method": "POST", "path": "/", "query_string": b"",
                 "headers": length}
        _, _, reservation = await read_frame(
            Request(scope, receive), Settings(), (320, 240), budget, lambda h, n: peak
        )
        return reservation

    async def run() -> None:
        budget = MemoryBudget(64 << 20, wait_s=0.1)
        held: list[int] = []
        reservation = await receive_in_chunks(budget, 40 << 20, held)
        assert max(held) <= len(data) + 2 * chunk, held  # not the 40 MiB peak
        assert reservation.nbytes == budget.used_bytes == 40 << 20
        reservation.release()
        held = []
        peak = len(data) + (1 << 20)
        reservation = await receive_in_chunks(budget, peak, held, chunked=True)
        assert max(held) <= 2 * len(data), held
        assert reservation.nbytes == budget.used_bytes == peak  # the buffer's copy given back
        reservation.release()
        held = []
        with pytest.raises(FrameOverMemoryBudget):
            await receive_in_chunks(budget, 65 << 20, held)
        assert len(held) <= 2 and budget.used_bytes == 0  # refused at the header's chunk
        assert budget.peak_bytes <= budget.limit_bytes

    asyncio.run(run())


def closed_by_server(sock: socket.socket, wait_s: float) -> bool:
    """Whether the server closes `sock` within `wait_s` (it sends nothing before)."""
    sock.settimeout(max(wait_s, 0.01))
    try:
        return sock.recv(1) == b""
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True


def test_connections_that_never_finish_their_headers_are_closed(server):
    """50 connections that send half a request line and 50 that send nothing are closed after
    QUIETFRAME_HEADER_TIMEOUT_S; /healthz answers meanwhile."""
    sockets = [server.connect() for _ in range(100)]
    try:
        for s in sockets[:50]:
            s.sendall(b"GET /hea")
        time.sleep(0.2)
        assert health_latency(server.url, 2) is not None
        deadline = time.monotonic() + HEADER_TIMEOUT_S + 3
        closed = sum(closed_by_server(s, deadline - time.monotonic()) for s in sockets)
    finally:
        for s in sockets:
            s.close()
    assert closed == len(sockets)


def test_health_answers_while_stalled_connections_exhaust_the_file_limit(server):
    """280 connections with half a request line on a server limited to 256 open files: the ones
    that have waited longest are closed to keep it under its connection cap (192), so /healthz
    answers before the header timeout has closed any of them (without the cap, accept() fails
    past ~244 open connections, and nobody is answered until the timeout frees some)."""
    sockets = []
    try:
        first = time.monotonic()
        for _ in range(280):
            s = server.connect()
            s.sendall(b"GET /hea")
            sockets.append(s)
        latency = health_latency(server.url, HEADER_TIMEOUT_S)
        answered = time.monotonic() - first
        oldest_closed = closed_by_server(sockets[0], 0.5)
        newest_open = not closed_by_server(sockets[-1], 0.1)
    finally:
        for s in sockets:
            s.close()
    assert latency is not None and answered < HEADER_TIMEOUT_S, (
        f"/healthz: {latency} s, {answered:.2f} s after the first stalled connection"
    )
    assert oldest_closed and newest_open
    print(f"/healthz with 280 stalled connections: {latency * 1e3:.0f} ms")
