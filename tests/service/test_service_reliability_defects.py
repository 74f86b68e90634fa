"""The audit of 2026-12-02: the defects it found (D4-D6, L1, L2, nits), each with the case that
showed it. In-process app with the installed models; 64x48 frames."""

from __future__ import annotations

import io
import json
import logging
import struct

import numpy as np
import pytest
from conftest import frame_bytes, layout_plain, make_buffers, read_exr, write_exr
from test_service_reliability import EXR, SIZE, app_client, assert_error, new_session, send


def box(x0: int, y0: int, x1: int, y1: int) -> bytes:
    return struct.pack("<iiii", x0, y0, x1, y1)


def set_box(data: bytes, name: bytes, value: bytes, occurrence: int = 0) -> bytes:
    """`data` with its `occurrence`-th box2i attribute `name` set to `value`."""
    needle = name + b"\0box2i\0\x10\0\0\0"
    at = -1
    for _ in range(occurrence + 1):
        at = data.index(needle, at + 1)
    at += len(needle)
    return data[:at] + value + data[at + 16 :]


def no_internal_errors(c) -> None:
    assert 'code="internal_error"' not in c.get("/metrics").text


# ---- D4: a layer name that cannot be an EXR channel name -------------------------------------


@pytest.mark.parametrize("name", ["\u0000", "Denoised\u0000", "a\nb", "x" * 300])
def test_unwritable_denoised_layer_is_refused_at_creation(name):
    with app_client() as c:
        for field in ("denoised_layer", "layer"):
            r = c.post("/v1/sessions", json={**SIZE, field: name})
            assert_error(r, 422, "invalid_request")


def test_unicode_denoised_layer_is_written():
    with app_client() as c:
        sid = new_session(c, denoised_layer="Débruité")
        r = send(c, sid, 0, frame_bytes())
        assert r.status_code == 200, r.text
        assert "Débruité.R" in read_exr(r.content)[1]
        no_internal_errors(c)


# ---- D5: tiled RANDOM_Y ------------------------------------------------------------------------


def test_tiled_random_y_frame_is_denoised():
    import OpenEXR

    tiles = OpenEXR.TileDescription()
    tiles.xSize = tiles.ySize = 16
    tiles.mode = OpenEXR.ONE_LEVEL
    header = {"type": OpenEXR.tiledimage, "tiles": tiles, "lineOrder": OpenEXR.RANDOM_Y}
    data = write_exr(layout_plain(make_buffers()), header)
    with app_client() as c:
        r = send(c, new_session(c), 0, data)
        assert r.status_code == 200, r.text
        out_header, channels = read_exr(r.content)
        assert out_header["lineOrder"] == OpenEXR.INCREASING_Y  # scanlines have no random order
        assert np.isfinite(channels["R"]).all()


# ---- D6 and L1: durable state that does not belong --------------------------------------------


def rewrite_npz(path, change) -> None:
    """Rewrite a session file, `change(arrays, meta)` in place; a valid zip with its manifest."""
    with np.load(path) as z:
        arrays = {name: z[name] for name in z.files}
    meta = json.loads(arrays.pop("meta").tobytes())
    change(arrays, meta)
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


@pytest.mark.parametrize("dtype", [np.float16, np.float64])
def test_state_of_another_dtype_is_quarantined(tmp_path, dtype, caplog):
    with app_client(state_dir=str(tmp_path)) as c:
        sid = new_session(c, model="nbg-2l-3g")
        assert send(c, sid, 0, frame_bytes()).status_code == 200

    def retype(arrays, _):
        for name in [n for n in arrays if n.startswith("state.")]:
            arrays[name] = arrays[name].astype(dtype)

    rewrite_npz(tmp_path / f"{sid}.npz", retype)
    with app_client(state_dir=str(tmp_path)) as c, caplog.at_level(logging.INFO):
        r = send(c, sid, 1, frame_bytes(seed=1))
        assert r.status_code == 200, r.text
        assert r.headers["x-quietframe-reset"] == "state-lost"
        assert list((tmp_path / "quarantine").iterdir())
        no_internal_errors(c)


def _meta_text(change):
    def edit(meta: dict) -> bytes:
        changed = change(meta)
        return (changed if isinstance(changed, bytes) else json.dumps(meta).encode())
    return edit


@pytest.mark.parametrize("change", [
    lambda m: m.update(reply="x"),
    lambda m: m.update(last_index="2"),
    lambda m: m.pop("last_index"),
    lambda m: m.update(frames_done=-1),
    lambda m: m.update(choice={"reason": "no model"}),
    lambda m: m.update(width="64"),
    lambda m: m.update(shot_spp="16"),
    lambda m: m.update(shot_spp=0.5),
    lambda m: m.update(shot_spp=float("nan")),
    lambda m: b"[]",
    lambda m: b"[" * 200_000,
], ids=["reply-str", "last_index-str", "no-last_index", "negative-count", "choice-without-model",
        "width-str", "shot_spp-str", "shot_spp-below-1", "shot_spp-nan", "meta-list",
        "deep-nesting"])
def test_a_wrongly_shaped_record_is_quarantined_not_a_500(tmp_path, change, caplog):
    """Audit R4-4: the stored meta is untrusted input. Each of these gave a 500 on every frame
    (and some on GET); now the record is quarantined and the session goes on afresh."""
    with app_client(state_dir=str(tmp_path)) as c:
        sid = new_session(c, model="nbg-2l-3g")
        assert send(c, sid, 0, frame_bytes()).status_code == 200
    path = tmp_path / f"{sid}.npz"
    with np.load(path) as z:
        arrays = {name: z[name] for name in z.files}
    meta = json.loads(arrays["meta"].tobytes())
    arrays["meta"] = np.frombuffer(_meta_text(change)(meta), np.uint8)
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    with caplog.at_level(logging.INFO), app_client(state_dir=str(tmp_path)) as c:
        assert c.get(f"/v1/sessions/{sid}").status_code == 200
        r = send(c, sid, 1, frame_bytes(seed=1))
        assert r.status_code == 200, r.text
        assert r.headers["x-quietframe-reset"] == "state-lost"
        no_internal_errors(c)
    assert list((tmp_path / "quarantine").iterdir())


def test_a_full_state_folder_is_503_with_retry_after_and_leaves_nothing(tmp_path, monkeypatch):
    """Audit R4-20: ENOSPC on the state folder answered 500 without Retry-After, and a refused
    creation left `.<id>.json.tmp`. Now 503 + Retry-After, no temp file, no session, and the
    session that existed goes on once there is space."""
    import errno

    import quietframe.service.session_store as store_module

    real_replace = store_module.os.replace

    def full(*_):
        raise OSError(errno.ENOSPC, "No space left on device")

    with app_client(state_dir=str(tmp_path)) as c:
        sid = new_session(c, model="nbg-2l-3g")
        assert send(c, sid, 0, frame_bytes()).status_code == 200
        monkeypatch.setattr(store_module.os, "replace", full)
        r = c.post("/v1/sessions", json={**SIZE, "model": "nbg-2l-3g"})
        assert r.status_code == 503 and r.headers["retry-after"], r.text
        assert "No space left" in r.json()["detail"]
        r = send(c, sid, 1, frame_bytes(seed=1))
        assert r.status_code == 503 and r.headers["retry-after"], r.text
        assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
        assert {p.stem for p in tmp_path.glob("*.json")} == {sid}  # the refused one is gone
        monkeypatch.setattr(store_module.os, "replace", real_replace)
        r = send(c, sid, 1, frame_bytes(seed=1))
        assert r.status_code == 200 and r.headers["x-quietframe-reset"] == "none", r.text
        no_internal_errors(c)


def test_state_file_cannot_change_the_sessions_settings(tmp_path, caplog):
    """Another session's file rewritten under this id: the settings file (<id>.json) says what
    the session is; the state file is quarantined and the session continues afresh."""
    with app_client(state_dir=str(tmp_path)) as c:
        sid = new_session(c, model="nbg-2l-3g")
        other = new_session(c, model="nbg-2l-3g", width=32, height=24)
        assert send(c, sid, 0, frame_bytes()).status_code == 200
    foreign = tmp_path / f"{other}.npz"
    rewrite_npz(foreign, lambda _, meta: meta.update(id=sid))
    foreign.replace(tmp_path / f"{sid}.npz")
    with caplog.at_level(logging.INFO), app_client(state_dir=str(tmp_path)) as c:
        status = c.get(f"/v1/sessions/{sid}").json()
        assert (status["width"], status["height"]) == (64, 48)
        r = send(c, sid, 1, frame_bytes(seed=1))
        assert r.status_code == 200, r.text
        assert r.headers["x-quietframe-reset"] == "state-lost"
        no_internal_errors(c)
    assert len(list((tmp_path / "quarantine").iterdir())) == 1
    assert any("settings file" in str(getattr(r, "error", "")) for r in caplog.records)


# ---- L2: colour-channel quirks -----------------------------------------------------------------


def test_bare_rgb_beside_lower_case_rgb_is_ambiguous():
    channels = layout_plain(make_buffers())
    channels.update({c.lower(): channels[c] * 2 for c in "RGB"})
    with app_client() as c:
        detail = assert_error(send(c, new_session(c), 0, write_exr(channels)), 422,
                              "ambiguous_channels")
        assert "'R'" in detail and "'r'" in detail and "mapping" in detail
        sid = new_session(c, channels={"color": ["r", "g", "b"]})  # the way out it names
        assert send(c, sid, 0, write_exr(channels)).status_code == 200


def test_precision_input_keeps_each_colour_channels_type():
    import OpenEXR

    channels = layout_plain(make_buffers())
    arrays = {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}
    arrays["R"], arrays["B"] = arrays["R"].astype(np.float16), arrays["B"].astype(np.float16)
    out = io.BytesIO()
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, arrays).write(out)
    with app_client() as c:
        r = send(c, new_session(c), 0, out.getvalue())
        assert r.status_code == 200, r.text
        got = read_exr(r.content)[1]
        assert [got[n].dtype for n in "RGB"] == [np.float16, np.float32, np.float16]


def test_parts_with_different_origins_are_refused():
    from exr_corpus import multipart

    data = set_box(multipart(), b"dataWindow", box(10, 0, 73, 47), occurrence=1)
    with app_client() as c:
        detail = assert_error(send(c, new_session(c), 0, data), 422, "unsupported_exr")
        assert "data window" in detail and "origin" in detail


# ---- windows against the session, from the header ----------------------------------------------


def test_display_window_must_match_the_session():
    data = set_box(frame_bytes(), b"displayWindow", box(0, 0, 127, 95))
    with app_client() as c:
        detail = assert_error(send(c, new_session(c), 0, data), 422, "size_mismatch")
        assert "display window 128x96" in detail


# ---- nits ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("value", ["true", '"10"', "0", "NaN"])
def test_latency_ms_is_a_positive_number(value):
    with app_client() as c:
        body = f'{{"width": 64, "height": 48, "latency_ms": {value}}}'
        r = c.post("/v1/sessions", content=body, headers={"content-type": "application/json"})
        assert_error(r, 422, "invalid_request")
        assert new_session(c, latency_ms=10)  # an integer is a number


def test_content_length_with_chunked_encoding_is_refused():
    """Both headers disagree about where the body ends: refused before the body is read."""
    import httpx
    from conftest import LiveServer
    from test_service_reliability import raw_request, status_of

    data = frame_bytes()
    with LiveServer() as server:
        sid = httpx.post(f"{server.url}/v1/sessions", json=SIZE).json()["id"]
        chunked = f"{len(data):x}\r\n".encode() + data + b"\r\n0\r\n\r\n"
        head = (
            f"POST /v1/sessions/{sid}/frames/0 HTTP/1.1\r\nHost: x\r\n"
            f"Content-Type: {EXR['content-type']}\r\nContent-Length: {len(data)}\r\n"
            "Transfer-Encoding: chunked\r\n\r\n"
        )
        raw = raw_request(server.port, head, chunked)
        assert status_of(raw) == 400 and b"Transfer-Encoding" in raw, raw[:300]
