"""Memory bounded by configuration under hostile uploads. A real `quietframe serve`
in its own process (so its RSS is the server's alone), on 127.0.0.1, with a small memory budget;
peak RSS is the kernel's high-water mark (VmHWM), reset before each case. When the defences
work nothing here allocates more than a few tens of MiB; every socket has a timeout."""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from conftest import frame_bytes, hard_timeout, layout_plain, make_buffers, write_exr
from test_service_reliability_defects import box, set_box

BUDGET_MB = 64
# What the server may add above the budget under load: the allocator's and onnxruntime's
# arenas keeping freed memory, and Python objects of 16 connections (measured ~20-40 MiB).
OVERHEAD_MB = 96
MODEL = "nbg-2l-3g"
HARD_TIMEOUT_S = 120


@pytest.fixture(autouse=True)
def time_limit():
    with hard_timeout(HARD_TIMEOUT_S):
        yield


class ServerProcess:
    """`python -m quietframe.service.cli` with QUIETFRAME_* settings in the environment."""

    def __init__(self, open_files: int | None = None, **settings) -> None:
        """`open_files`: the server's RLIMIT_NOFILE (None: this process's)."""
        import resource

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        env = {**os.environ, **{f"QUIETFRAME_{k.upper()}": str(v) for k, v in settings.items()}}
        command = [sys.executable, "-m", "quietframe.service.cli", "--port", str(self.port),
                   "--threads", "1", "--workers", "2", "--log-level", "error"]

        def limit_files() -> None:
            resource.setrlimit(resource.RLIMIT_NOFILE, (open_files, open_files))

        self.process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL if open_files else None,
                                        preexec_fn=limit_files if open_files else None)
        self.url = f"http://127.0.0.1:{self.port}"

    def wait_ready(self, timeout_s: float = 90) -> None:
        import httpx

        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError("server exited")
            try:
                if httpx.get(f"{self.url}/v1/models", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError("server did not start")

    def status_kib(self, field: str) -> int:
        with open(f"/proc/{self.process.pid}/status") as f:
            line = next(line for line in f if line.startswith(field + ":"))
        return int(line.split()[1])

    def reset_peak(self) -> int:
        """Reset the high-water mark to the current RSS (Linux clear_refs 5); returns it, MiB."""
        with open(f"/proc/{self.process.pid}/clear_refs", "w") as f:
            f.write("5")
        return self.status_kib("VmRSS") // 1024

    def peak_mb(self) -> int:
        return self.status_kib("VmHWM") // 1024

    def __enter__(self):
        try:
            self.wait_ready()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *_) -> None:
        self.stop()

    def stop(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()


@pytest.fixture(scope="module")
def server():
    from conftest import service_settings

    service_settings()  # skips without an installed model
    with ServerProcess(
        memory_budget_mb=BUDGET_MB,
        admission_wait_s=10,
        body_read_timeout_s=1,
        min_body_rate_kib_s=64,
        max_uploads_per_session=16,  # the hostile uploads below share one session
        log_json="false",
    ) as server:
        yield server


def session(server, width=64, height=48) -> str:
    import httpx

    r = httpx.post(f"{server.url}/v1/sessions",
                   json={"width": width, "height": height, "model": MODEL}, timeout=10)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def head(sid: str, length: int | None, index: int = 0) -> bytes:
    size = f"Content-Length: {length}\r\n" if length is not None else ""
    return (f"POST /v1/sessions/{sid}/frames/{index} HTTP/1.1\r\nHost: x\r\n"
            f"Content-Type: image/x-exr\r\n{size}\r\n").encode()


def status_of(answer: bytes) -> int | None:
    return int(answer.split(b" ", 2)[1]) if answer.startswith(b"HTTP/1.1 ") else None


def rest_of_answer(sock: socket.socket, head: bytes, wait_s: float) -> bytes:
    """`head` (the first bytes of an answer) with the rest of its body: the headers may arrive
    in one recv and the JSON body in the next."""
    sock.settimeout(wait_s)
    data = head
    try:
        while True:
            headers, _, body = data.partition(b"\r\n\r\n")
            length = next((int(line.split(b":", 1)[1]) for line in headers.split(b"\r\n")
                           if line.lower().startswith(b"content-length:")), None)
            if _ and length is not None and len(body) >= length:
                return data
            chunk = sock.recv(65536)
            if not chunk:
                return data
            data += chunk
    except (TimeoutError, ConnectionResetError):
        return data


def answer(sock: socket.socket, wait_s: float) -> bytes:
    sock.settimeout(wait_s)
    data = b""
    try:
        while b"\r\n\r\n" not in data:
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    except (TimeoutError, ConnectionResetError):
        pass
    return data


def header_only(width: int, height: int) -> bytes:
    """The header of a valid 64x48 frame rewritten to claim width x height."""
    from quietframe.service import frames

    data = frame_bytes()
    end = frames.read_header(data, 8192, 8192).header_bytes
    claim = box(0, 0, width - 1, height - 1)
    return set_box(set_box(data[:end], b"dataWindow", claim), b"displayWindow", claim)


GIB = 1920 * 2**20  # the default frame limit


def test_stalled_uploads_hold_no_memory(server):
    """8 uploads announcing 1920 MiB to a 64x48 session (4 claiming 8192x8192 in the header,
    4 honest 64x48 headers), and 8 honest frames stalled half-way, all at once: the first
    eight are refused from their header, the others hold what they sent."""
    sid = session(server)
    data = frame_bytes()
    base = server.reset_peak()
    sockets = []
    try:
        for claim in [(8192, 8192)] * 4 + [(64, 48)] * 4:
            s = socket.create_connection(("127.0.0.1", server.port), timeout=5)
            s.sendall(head(sid, GIB) + header_only(*claim) + bytes(4096))
            sockets.append(s)
        for _ in range(8):
            s = socket.create_connection(("127.0.0.1", server.port), timeout=5)
            s.sendall(head(sid, len(data)) + data[: len(data) // 2])
            sockets.append(s)
        time.sleep(0.5)
        statuses = [status_of(answer(s, 5)) for s in sockets]
        grown = server.peak_mb() - base
    finally:
        for s in sockets:
            s.close()
    assert statuses == [422] * 4 + [413] * 4 + [408] * 8, statuses
    assert grown <= 256, f"RSS grew {grown} MiB"
    print(f"16 stalled uploads: RSS {base} MiB -> peak +{grown} MiB")


def test_dripped_body_is_cut_by_the_minimum_rate(server):
    """One byte every 0.2 s never pauses for the 1 s pause limit; the minimum rate ends it."""
    sid = session(server)
    data = frame_bytes()
    start = time.monotonic()
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as s:
        s.sendall(head(sid, len(data)) + data[:64])
        s.settimeout(0.2)
        got, sent = b"", 64
        while time.monotonic() - start < 6 and not got:
            try:
                s.sendall(data[sent : sent + 1])
                sent += 1
                got = s.recv(65536)
            except TimeoutError:
                continue
            except (BrokenPipeError, ConnectionResetError):
                break
        got = rest_of_answer(s, got or answer(s, 2), 2)
    assert status_of(got) == 408 and b"bytes/s" in got, got[:300]
    assert time.monotonic() - start < 4


@pytest.mark.parametrize("lie", ["longer", "shorter"])
def test_lying_content_length_is_a_4xx(server, lie):
    sid = session(server)
    data = frame_bytes()
    from quietframe.service import frames

    length = frames.read_header(data, 8192, 8192).max_bytes if lie == "longer" else len(data) // 2
    base = server.reset_peak()
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as s:
        s.sendall(head(sid, length) + data[:length])
        got = answer(s, 5)
    assert status_of(got) == (408 if lie == "longer" else 400), got[:300]
    assert server.peak_mb() - base <= 32


def _stream(port: int, start: bytes, blocks, wait_s: float = 20) -> bytes:
    """Send `start` and then `blocks` while a second thread reads the answer (the server
    answers, and closes, before the body ends)."""
    got = bytearray()
    with socket.create_connection(("127.0.0.1", port), timeout=wait_s) as s:

        def read() -> None:
            try:
                while chunk := s.recv(65536):
                    got.extend(chunk)
            except OSError:
                pass

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        try:
            s.sendall(start)
            for block in blocks:
                if got:  # answered: the rest would only fill the socket buffers
                    break
                s.sendall(block)
        except OSError:
            pass  # refused mid-body: the answer is in `got`
        reader.join(1 if got else wait_s)
    return bytes(got)


def test_200_mib_of_header_attributes_get_a_4xx(server):
    """25 string attributes of 8 MiB each (200 MiB): refused past QUIETFRAME_MAX_HEADER_BYTES
    (16 MiB), with the server's memory growing by a small multiple of that, not of 200 MiB."""
    sid = session(server)
    block = b"x" * 2**20

    def blocks():
        for i in range(25):
            yield f"blob{i}\0string\0".encode() + struct.pack("<i", 8 * 2**20)
            for _ in range(8):
                yield block

    start = head(sid, 8 + 25 * (8 * 2**20 + 20)) + b"\x76\x2f\x31\x01\x02\0\0\0"
    base = server.reset_peak()
    got = _stream(server.port, start, blocks())
    assert status_of(got) == 413 and b"exr_header_too_large" in got, got[:300]
    grown = server.peak_mb() - base
    assert grown <= 3 * 16, f"RSS grew {grown} MiB"
    print(f"200 MiB of attributes: RSS {base} MiB -> peak +{grown} MiB")


def test_16_concurrent_uploads_stay_within_the_budget(server):
    """16 frames of 128x128 at once against a 64 MiB budget (about three frames' worth): no
    5xx, each frame denoised (429s retried after Retry-After), peak RSS within budget +
    overhead."""
    import httpx

    data = write_exr(layout_plain(make_buffers(128, 128)))
    sids = [session(server, 128, 128) for _ in range(16)]
    base = server.reset_peak()

    def upload(sid: str) -> list[int]:
        statuses = []
        with httpx.Client(timeout=60) as client:
            for _ in range(20):
                r = client.post(f"{server.url}/v1/sessions/{sid}/frames/0", content=data,
                                headers={"content-type": "image/x-exr"})
                statuses.append(r.status_code)
                if r.status_code != 429:
                    break
                time.sleep(min(float(r.headers["retry-after"]), 0.5))
        return statuses

    with ThreadPoolExecutor(16) as pool:
        results = list(pool.map(upload, sids))
    grown = server.peak_mb() - base
    assert all(r[-1] == 200 for r in results), results
    assert not [s for r in results for s in r if s >= 500], results
    assert grown <= BUDGET_MB + OVERHEAD_MB, f"RSS grew {grown} MiB"
    print(f"16 uploads: RSS {base} MiB -> peak +{grown} MiB; statuses {results}")


def test_budget_waits_then_refuses_and_never_overcommits():
    """The admission rules without a server: a frame waits for memory given back, gets 429
    (Retry-After) when none comes in time, 413 when it could never fit (upload slots:
    test_upload_slots.py)."""
    import asyncio

    from quietframe.service.admission import MemoryBudget
    from quietframe.service.errors import FrameOverMemoryBudget, MemoryBusy

    async def run() -> None:
        budget = MemoryBudget(100, wait_s=0.3)
        first = budget.reserve(10)
        await first.admit(80, "first")
        second = budget.reserve(10)
        waiting = asyncio.create_task(second.admit(50, "second"))
        await asyncio.sleep(0.05)
        assert not waiting.done()
        first.release()  # gives back 80: the waiting frame goes on
        await asyncio.wait_for(waiting, 1)
        third = budget.reserve(0)
        with pytest.raises(MemoryBusy) as busy:
            await third.admit(60, "third")  # 50 held: waits 0.3 s, then 429
        assert busy.value.headers["Retry-After"]
        with pytest.raises(FrameOverMemoryBudget):
            await third.admit(101, "fourth")
        second.release()
        assert budget.used_bytes == 0 and budget.peak_bytes <= 100

    asyncio.run(run())
