"""The audit of 2026-12-01: the defects found from outside, each with the case that showed it,
and the malformed-EXR corpus (tests/exr_corpus.py) with the status each case must get. Real
runtime and installed model; 64x48 frames; sockets only on 127.0.0.1."""

from __future__ import annotations

import json
import logging
import re
import socket
import sys
import time
import zlib

import numpy as np
import pytest
from conftest import LAYOUTS, LiveServer, frame_bytes, make_buffers, read_exr, shot, write_exr
from exr_corpus import cases, multipart, tiled, with_values

SIZE = {"width": 64, "height": 48}
EXR = {"content-type": "image/x-exr"}
TOKEN = {"Authorization": "Bearer s3cret"}


def app_client(**overrides):
    """An in-process app (the installed models loaded once per run: conftest.app_for)."""
    from conftest import app_for, service_settings
    from fastapi.testclient import TestClient

    return TestClient(app_for(service_settings(**overrides)))


def new_session(c, headers=None, **body) -> str:
    r = c.post("/v1/sessions", json={**SIZE, **body}, headers=headers or {})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def send(c, sid, index, data, headers=None, **params):
    return c.post(
        f"/v1/sessions/{sid}/frames/{index}",
        content=data,
        headers={**EXR, **(headers or {})},
        params=params,
    )


def assert_error(response, status, code):
    assert response.status_code == status, response.text
    assert response.json()["error"] == code, response.text
    return response.json()["detail"]


def colour(response) -> np.ndarray:
    _, channels = read_exr(response.content)
    return np.stack([channels[n] for n in ("R", "G", "B")]).astype(np.float32)


def raw_request(port: int, head: str, body: bytes = b"", wait_s: float = 5.0) -> bytes:
    """Send a request head and the first body bytes, then wait for an answer without sending
    the rest: what comes back within `wait_s` (b"" when the server waits for the body)."""
    answer = b""
    with socket.create_connection(("127.0.0.1", port), timeout=wait_s) as s:
        s.sendall(head.encode() + body)
        try:
            while not _complete(answer):
                chunk = s.recv(65536)
                if not chunk:
                    break
                answer += chunk
        except (TimeoutError, ConnectionResetError):
            pass
    return answer


def _complete(answer: bytes) -> bool:
    head, sep, body = answer.partition(b"\r\n\r\n")
    if not sep:
        return False
    for line in head.split(b"\r\n"):
        if line.lower().startswith(b"content-length:"):
            return len(body) >= int(line.split(b":")[1])
    return True


def status_of(raw: bytes) -> int | None:
    return int(raw.split(b" ", 2)[1]) if raw.startswith(b"HTTP/1.1 ") else None


@pytest.fixture(scope="module")
def auth_server():
    from conftest import service_settings  # noqa: F401  (skips without a model)

    with LiveServer(auth_token="s3cret", body_read_timeout_s=1.0) as server:
        yield server


# ---- 1. auth and body limits before any body is read ------------------------------------------


@pytest.mark.parametrize("path", ["/v1/sessions", "/v1/sessions/x/frames/0", "/v1/models"])
def test_401_before_the_body_is_read(auth_server, path):
    """A 1 GiB body announced, none sent: 401 at once (the server used to read it first)."""
    head = (
        f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
        "Content-Length: 1073741824\r\n\r\n"
    )
    assert status_of(raw_request(auth_server.port, head, b"{")) == 401


def test_json_body_limit_while_streaming(auth_server):
    import httpx

    url = f"{auth_server.url}/v1/sessions"
    big = json.dumps({**SIZE, "model": "auto" + " " * 100_000}).encode()
    r = httpx.post(url, content=big, headers={**TOKEN, "content-type": "application/json"})
    assert_error(r, 413, "body_too_large")

    def chunks():  # chunked: no Content-Length to refuse up front
        for _ in range(64):
            yield b" " * 4096

    r = httpx.post(url, content=chunks(), headers={**TOKEN, "content-type": "application/json"})
    assert_error(r, 413, "body_too_large")


def test_no_token_with_invalid_body_is_401_not_422():
    with app_client(auth_token="s3cret") as c:
        json_type = {"content-type": "application/json"}
        r = c.post("/v1/sessions", content=b"0" * 5000, headers=json_type)
        assert_error(r, 401, "unauthorized")


# ---- 2. nothing non-finite leaves; a radiance ceiling for the history ------------------------


def test_half_output_is_clamped_not_inf():
    with app_client() as c:
        sid = new_session(c, precision="half")
        r = send(c, sid, 0, with_values(1e5))
        assert r.status_code == 200, r.text
        out = colour(r)
        assert np.isfinite(out).all() and out.max() <= 65504
        assert int(r.headers["x-quietframe-sanitized"]) > 0


def test_half_input_after_a_huge_float_frame_is_finite():
    """precision=input: a half frame after a float frame with 1e30 in it (history)."""

    def static(noise: int, dtype, value=None) -> bytes:
        b = make_buffers(48, 64, noise=noise)
        b["motion"][:] = 0
        if value is not None:
            b["color"][8:12, 8:12] = value
        return write_exr(LAYOUTS["plain-normal"](b), dtype=dtype)

    with app_client() as c:
        sid = new_session(c)
        assert send(c, sid, 0, static(100, np.float32, 1e30)).status_code == 200
        r = send(c, sid, 1, static(101, np.float16))
        assert read_exr(r.content)[1]["R"].dtype == np.float16
        assert np.isfinite(colour(r)).all()


def test_huge_radiance_does_not_poison_the_history():
    frames = shot(6)
    with app_client() as c:
        sid = new_session(c, precision="float")
        r = send(c, sid, 0, with_values(1e30))
        assert int(r.headers["x-quietframe-sanitized-buffers"].split("color=")[1][:2]) >= 16
        for i, data in enumerate(frames[1:], 1):
            out = colour(send(c, sid, i, data))
            assert np.isfinite(out).all() and out.max() <= 65504, (i, out.max())


# ---- 3. frame bodies checked as they arrive ------------------------------------------------------


def test_non_exr_body_is_refused_at_its_first_bytes(auth_server):
    import httpx

    sid = httpx.post(f"{auth_server.url}/v1/sessions", json=SIZE, headers=TOKEN).json()["id"]
    head = (
        f"POST /v1/sessions/{sid}/frames/0 HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer s3cret\r\n"
        "Content-Type: image/x-exr\r\nContent-Length: 500000000\r\n\r\n"
    )
    raw = raw_request(auth_server.port, head, b"GIF89a" + bytes(70000))
    assert status_of(raw) == 400 and b"bad_exr" in raw


def test_body_longer_than_its_header_allows_is_refused_from_the_header(auth_server):
    """A valid 64x48 header announcing 400 MB: 413 before the rest is sent."""
    import httpx

    sid = httpx.post(f"{auth_server.url}/v1/sessions", json=SIZE, headers=TOKEN).json()["id"]
    head = (
        f"POST /v1/sessions/{sid}/frames/0 HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer s3cret\r\n"
        "Content-Type: image/x-exr\r\nContent-Length: 400000000\r\n\r\n"
    )
    raw = raw_request(auth_server.port, head, frame_bytes())
    assert status_of(raw) == 413 and b"body_too_large" in raw


def test_chunked_frame_body_is_held_to_its_header_size(auth_server):
    import httpx

    sid = httpx.post(f"{auth_server.url}/v1/sessions", json=SIZE, headers=TOKEN).json()["id"]
    data = frame_bytes()

    def chunks():  # no Content-Length: the bound applies while streaming
        yield data
        for _ in range(200):
            yield bytes(65536)

    r = httpx.post(
        f"{auth_server.url}/v1/sessions/{sid}/frames/0", content=chunks(), headers={**TOKEN, **EXR}
    )
    assert "at most" in assert_error(r, 413, "body_too_large")


def test_header_claiming_a_huge_attribute_is_refused_at_once(auth_server):
    import httpx

    sid = httpx.post(f"{auth_server.url}/v1/sessions", json=SIZE, headers=TOKEN).json()["id"]
    head = (
        f"POST /v1/sessions/{sid}/frames/0 HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer s3cret\r\n"
        "Content-Type: image/x-exr\r\nContent-Length: 500000000\r\n\r\n"
    )
    for size in (b"\x00\x00\x00\x7f", b"\xff\xff\xff\xff"):  # 2 GiB, -1
        start = b"\x76\x2f\x31\x01\x02\0\0\0owner\0string\0" + size
        raw = raw_request(auth_server.port, head, start + bytes(70000))
        assert status_of(raw) == 400 and b"bad_exr" in raw


def test_default_frame_limit_fits_an_8k_multilayer_float_exr():
    from quietframe.service.settings import Settings

    uncompressed = 7680 * 4320 * 15 * 4  # 8K UHD, 15 float channels
    assert uncompressed < Settings().max_body_bytes < 2**31


def test_frame_body_is_decoded_from_the_one_buffer():
    """decode reads a bytearray in place (io.BytesIO would have copied it whole)."""
    import tracemalloc

    from quietframe.service import frames

    data = frame_bytes(height=256, width=256, dtype=np.float16)
    header = frames.read_header(data, 8192, 8192)
    sources = frames.resolve(header.channels, ["color"], [])

    def peak(body) -> int:
        tracemalloc.start()
        frames.decode(body, sources)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return peak

    shared = peak(data)  # io.BytesIO shares a bytes object's buffer
    assert peak(bytearray(data)) < shared + len(data) // 2, (shared, len(data))


# ---- 4. damaged durable state --------------------------------------------------------------------


def test_damaged_state_continues_from_a_fresh_history(tmp_path, caplog):
    frames = shot(4)
    with app_client(state_dir=str(tmp_path)) as c:
        sid = new_session(c)
        for i in range(2):
            assert send(c, sid, i, frames[i]).status_code == 200
    path = tmp_path / f"{sid}.npz"
    data = bytearray(path.read_bytes())
    for i in range(200, len(data) // 2, 501):  # flip bytes in the state tensors
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))
    with app_client(state_dir=str(tmp_path)) as c, caplog.at_level(logging.INFO):
        assert c.get(f"/v1/sessions/{sid}").status_code == 200
        r = send(c, sid, 2, frames[2])
        assert r.status_code == 200, r.text
        assert r.headers["x-quietframe-reset"] == "state-lost"
        assert any("damaged" in rec.getMessage() for rec in caplog.records)
        assert list((tmp_path / "quarantine").iterdir())
        assert send(c, sid, 3, frames[3]).headers["x-quietframe-reset"] == "none"
        assert c.get("/metrics").text.count('code="internal_error"') == 0


def test_retry_of_the_last_index_after_lost_state_is_denoised_again(tmp_path):
    """With the stored reply lost there is nothing to compare a retry with: it is denoised
    from a fresh history (state-lost), not refused as a conflict."""
    frames = shot(2)
    with app_client(state_dir=str(tmp_path)) as c:
        sid = new_session(c)
        send(c, sid, 0, frames[0])
        send(c, sid, 1, frames[1])
    path = tmp_path / f"{sid}.npz"
    data = bytearray(path.read_bytes())
    data[300] ^= 0xFF
    path.write_bytes(bytes(data))
    with app_client(state_dir=str(tmp_path)) as c:
        r = send(c, sid, 1, frames[1])
        assert r.status_code == 200, r.text
        assert r.headers["x-quietframe-reset"] == "state-lost"
        assert_error(send(c, sid, 0, frames[0]), 409, "frame_out_of_order")


def test_truncated_and_foreign_state_files_are_quarantined(tmp_path, caplog):
    """A truncated file and a file under another id are moved aside at start-up; their sessions
    continue from a fresh history when their settings file is intact, else they are gone."""
    with app_client(state_dir=str(tmp_path)) as c:
        a, b, gone = new_session(c), new_session(c), new_session(c)
        send(c, a, 0, frame_bytes())
        send(c, b, 0, frame_bytes())
    for sid in (b, gone):  # truncated
        (tmp_path / f"{sid}.npz").write_bytes((tmp_path / f"{sid}.npz").read_bytes()[:50])
    (tmp_path / f"{gone}.json").unlink()
    foreign = "A" * 22  # a copy of a's file under another id
    (tmp_path / f"{foreign}.npz").write_bytes((tmp_path / f"{a}.npz").read_bytes())
    with caplog.at_level(logging.INFO), app_client(state_dir=str(tmp_path)) as c:
        assert send(c, a, 1, frame_bytes(seed=1)).headers["x-quietframe-reset"] == "none"
        r = send(c, b, 1, frame_bytes(seed=1))
        assert r.status_code == 200 and r.headers["x-quietframe-reset"] == "state-lost"
        assert_error(send(c, foreign, 0, frame_bytes()), 404, "session_not_found")
        assert_error(c.get(f"/v1/sessions/{gone}"), 404, "session_not_found")
    assert sorted(p.name for p in tmp_path.glob("*.npz")) == sorted([f"{a}.npz", f"{b}.npz"])
    assert len(list((tmp_path / "quarantine").iterdir())) == 3
    assert sum("damaged" in rec.getMessage() for rec in caplog.records) == 3


# ---- 5. deep parts and mip/ripmaps ---------------------------------------------------------------


def test_deep_part_and_mipmaps_get_specific_4xx():
    with app_client() as c:
        sid = new_session(c)
        detail = assert_error(send(c, sid, 0, multipart("deepscanline")), 422, "unsupported_exr")
        assert "deep" in detail and "flat" in detail
        import OpenEXR

        for mode, word in ((OpenEXR.MIPMAP_LEVELS, "mipmap"), (OpenEXR.RIPMAP_LEVELS, "ripmap")):
            detail = assert_error(send(c, sid, 0, tiled(mode)), 422, "unsupported_exr")
            assert word in detail and "scanline" in detail
        assert send(c, sid, 0, tiled()).status_code == 200


# ---- 6. disconnects and stalled bodies ---------------------------------------------------------


def test_client_disconnect_is_not_an_internal_error(auth_server, caplog):
    import httpx

    sid = httpx.post(f"{auth_server.url}/v1/sessions", json=SIZE, headers=TOKEN).json()["id"]
    data = frame_bytes()
    head = (
        f"POST /v1/sessions/{sid}/frames/0 HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer s3cret\r\n"
        f"Content-Type: image/x-exr\r\nContent-Length: {len(data)}\r\n\r\n"
    )
    with caplog.at_level(logging.INFO):
        for _ in range(3):
            with socket.create_connection(("127.0.0.1", auth_server.port)) as s:
                s.sendall(head.encode() + data[: len(data) // 2])
            time.sleep(0.2)
        time.sleep(0.3)
    metrics = httpx.get(f"{auth_server.url}/metrics").text
    assert 'code="internal_error"' not in metrics
    assert re.search(r'code="client_disconnected"[^}]*} 3.0', metrics), metrics
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_stalled_body_gets_408(auth_server):
    import httpx

    sid = httpx.post(f"{auth_server.url}/v1/sessions", json=SIZE, headers=TOKEN).json()["id"]
    data = frame_bytes()
    head = (
        f"POST /v1/sessions/{sid}/frames/0 HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer s3cret\r\n"
        f"Content-Type: image/x-exr\r\nContent-Length: {len(data)}\r\n\r\n"
    )
    start = time.monotonic()
    raw = raw_request(auth_server.port, head, data[:1000], wait_s=5)
    assert status_of(raw) == 408 and b"body_read_timeout" in raw
    assert time.monotonic() - start < 4


# ---- 7. idempotent retry compares a cryptographic digest ---------------------------------------


def forge_same_crc(data: bytes, flip_at: int, fix_at: int) -> bytes:
    """A different body of the same length and CRC-32: flip one byte, then solve for 32 bits at
    `fix_at` (CRC-32 is affine over GF(2))."""
    zero = zlib.crc32(bytes(len(data)))

    def delta(position: int, bit: int) -> int:
        d = bytearray(len(data))
        d[position] = 1 << bit
        return zlib.crc32(bytes(d)) ^ zero

    target = delta(flip_at, 0)  # the change to cancel
    basis = [(delta(fix_at + i // 8, i % 8), 1 << i) for i in range(32)]
    rows: list[tuple[int, int]] = []  # Gaussian elimination: (vector, which bits make it)
    for vector, bits in basis:
        for r_vec, r_bits in rows:
            if vector ^ r_vec < vector:
                vector, bits = vector ^ r_vec, bits ^ r_bits
        if vector:
            rows.append((vector, bits))
    rows.sort(reverse=True)
    chosen = 0
    for r_vec, r_bits in rows:
        if target ^ r_vec < target:
            target, chosen = target ^ r_vec, chosen ^ r_bits
    assert target == 0
    forged = bytearray(data)
    forged[flip_at] ^= 1
    for i in range(32):
        if chosen >> i & 1:
            forged[fix_at + i // 8] ^= 1 << (i % 8)
    return bytes(forged)


def test_retry_with_a_forged_crc_is_a_conflict():
    data = frame_bytes()
    forged = forge_same_crc(data, len(data) - 300, len(data) - 200)
    assert forged != data and zlib.crc32(forged) == zlib.crc32(data) and len(forged) == len(data)
    with app_client() as c:
        sid = new_session(c)
        assert send(c, sid, 0, data).status_code == 200
        assert send(c, sid, 0, data).headers["x-quietframe-replayed"] == "true"
        assert_error(send(c, sid, 0, forged), 409, "frame_conflict")


def test_old_state_files_with_a_crc_still_replay(tmp_path):
    from quietframe.service.session_store import Reply

    data = frame_bytes()
    old = Reply(0, b"out", {}, len(data), None, zlib.crc32(data))
    assert old.matches(data) and not old.matches(data[:-1] + b"x")


# ---- 8. smaller ones ------------------------------------------------------------------------


def test_empty_auth_token_refuses_to_start(monkeypatch):
    from pydantic import ValidationError

    from quietframe.service.settings import Settings

    with pytest.raises(ValidationError, match="empty"):
        Settings(auth_token="")
    monkeypatch.setenv("QUIETFRAME_AUTH_TOKEN", " ")
    with pytest.raises(ValidationError, match="empty"):
        Settings()


@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity", "true", '"1"'])
def test_motion_scale_must_be_finite_numbers(value):
    with app_client() as c:
        body = f'{{"width": 64, "height": 48, "motion_scale": [{value}, 1.0]}}'
        r = c.post("/v1/sessions", content=body, headers={"content-type": "application/json"})
        assert_error(r, 422, "invalid_request")


def test_non_json_session_body_is_a_documented_422():
    with app_client() as c:
        for body in (b"\xff\xfe not json", b"width=64"):
            r = c.post("/v1/sessions", content=body, headers={"content-type": "application/json"})
            assert_error(r, 422, "invalid_request")
        assert "422" in c.get("/openapi.json").json()["paths"]["/v1/sessions"]["post"]["responses"]


def test_openapi_has_size_maxima_and_bearer_scheme():
    with app_client(max_width=4096, max_height=2160) as c:
        assert "securitySchemes" not in c.get("/openapi.json").json()["components"]
    with app_client(max_width=4096, max_height=2160, auth_token="s3cret") as c:
        spec = c.get("/openapi.json").json()
    fields = spec["components"]["schemas"]["SessionCreate"]["properties"]
    assert fields["width"]["maximum"] == 4096 and fields["height"]["maximum"] == 2160
    schemes = spec["components"]["securitySchemes"]
    assert any(s.get("scheme", "").lower() == "bearer" for s in schemes.values())
    assert spec["paths"]["/v1/sessions"]["post"].get("security")


def test_invalid_compression_byte_is_rejected():
    from quietframe.runtime import frame_errors as errors
    from quietframe.service import frames

    data = frame_bytes()
    needle = b"compression\0compression\0\x01\0\0\0"
    at = data.index(needle) + len(needle)
    with pytest.raises(errors.BadExr, match="compression"):
        frames.read_header(data[:at] + b"\xee" + data[at + 1 :], 8192, 8192)


def test_openexr_warnings_go_to_the_log(capsys, caplog):
    from quietframe.runtime import frame_errors as errors
    from quietframe.service import frames

    data = bytearray(frame_bytes())
    header = frames.read_header(data, 8192, 8192)
    for i in range(header.header_bytes + 400, len(data) - 100, 7):
        data[i] ^= 0x5A
    sources = frames.resolve(header.channels, ["color"], [])
    stdout = sys.stdout
    with caplog.at_level(logging.WARNING), pytest.raises(errors.BadExr):
        frames.decode(bytes(data), sources)
    assert sys.stdout is stdout  # routed while decoding only, not replaced for the process
    assert "Warning:" not in capsys.readouterr().out
    records = [r for r in caplog.records if getattr(r, "openexr", None)]
    assert records and any("Warning:" in line for line in records[0].openexr)


def test_openexr_warnings_of_concurrent_decodes_stay_with_their_frame(capsys, caplog):
    """Each decoding thread's printed warning goes to its own record, none to stdout."""
    from concurrent.futures import ThreadPoolExecutor

    from quietframe.runtime import frame_errors as errors
    from quietframe.service import frames

    data = bytearray(frame_bytes())
    header = frames.read_header(data, 8192, 8192)
    for i in range(header.header_bytes + 400, len(data) - 100, 7):
        data[i] ^= 0x5A
    sources = frames.resolve(header.channels, ["color"], [])

    def decode(_: int) -> None:
        with pytest.raises(errors.BadExr):
            frames.decode(bytes(data), sources)

    stdout = sys.stdout
    with caplog.at_level(logging.WARNING), ThreadPoolExecutor(4) as pool:
        list(pool.map(decode, range(8)))
    assert sys.stdout is stdout
    assert "Warning:" not in capsys.readouterr().out
    records = [r.openexr for r in caplog.records if getattr(r, "openexr", None)]
    assert len(records) == 8 and all(len(lines) == 1 for lines in records), records


# ---- the corpus --------------------------------------------------------------------------------


def test_malformed_exr_corpus():
    """Every case gets its status; every 200 is a finite EXR; no 5xx."""
    with app_client() as c:
        failures = []
        for case in cases():
            sid = new_session(c)
            r = send(c, sid, 0, case.data)
            if r.status_code != case.status:
                failures.append((case.name, case.status, r.status_code, r.text[:200]))
                continue
            if case.status == 200:
                assert np.isfinite(colour(r)).all(), case.name
            else:
                assert r.json()["error"] == case.code, (case.name, r.text)
            c.delete(f"/v1/sessions/{sid}")
        assert not failures, failures
        assert 'code="internal_error"' not in c.get("/metrics").text
