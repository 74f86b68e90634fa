"""The /v1 API: each route with passing and rejecting cases, frame order, retries, resets,
limits, auth. Every test runs twice: through TestClient, and over HTTP against a real uvicorn
server on 127.0.0.1. Real runtime and the installed model; 64x48 frames."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest
from conftest import LAYOUTS, frame_bytes, make_buffers, read_exr, shot, write_exr

SIZE = {"width": 64, "height": 48}
EXR = {"content-type": "image/x-exr"}
KINDS = ["testclient", "uvicorn"]


@pytest.fixture(scope="module", params=KINDS)
def client(request):
    from conftest import close, serve

    c, server = serve(request.param)
    yield c
    close(c, server)


@pytest.fixture(params=KINDS)
def make_client(request):
    """conftest's factory, once per kind of server."""
    from conftest import close, serve

    opened = []

    def make(**overrides):
        c, server = serve(request.param, **overrides)
        opened.append((c, server))
        return c

    yield make
    for c, server in opened:
        close(c, server)


def new_session(c, **body) -> str:
    r = c.post("/v1/sessions", json={**SIZE, **body})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def send(c, sid, index, data, **params):
    return c.post(f"/v1/sessions/{sid}/frames/{index}", content=data, headers=EXR, params=params)


def pixels(response) -> np.ndarray:
    """The denoised colour of a reply (the reply holds every channel of the input)."""
    _, channels = read_exr(response.content)
    for prefix in ("ViewLayer.Combined.", "Ci.", "beauty.", ""):
        for names in ([prefix + c for c in "RGB"], [prefix + c for c in "rgb"]):
            if all(n in channels for n in names):
                return np.stack([channels[n] for n in names], -1)
    raise AssertionError(f"no colour channels in {sorted(channels)}")


def assert_error(response, status, code):
    assert response.status_code == status, response.text
    body = response.json()
    assert body["error"] == code and body["detail"], body
    return body["detail"]


# ---- sessions -------------------------------------------------------------------------------


def test_create_session(client):
    r = client.post("/v1/sessions", json={**SIZE, "model": "auto", "precision": "half"})
    assert r.status_code == 201
    body = r.json()
    assert len(body["id"]) == 22 and r.headers["location"] == f"/v1/sessions/{body['id']}"
    # auto: no model is in use until the first frame chooses one (the reply named a fallback)
    assert body["model"] is None and body["requested_model"] == "auto" and body["choice"] is None
    assert "color" in body["required_buffers"]
    named = client.post("/v1/sessions", json={**SIZE, "model": "nbg-2l-3g"}).json()
    assert named["model"]["name"] == "nbg-2l-3g"
    assert body["frames_done"] == 0 and body["last_index"] is None and body["reserved_bytes"] > 0
    other = client.post("/v1/sessions", json=SIZE).json()
    assert other["id"] != body["id"] and other["precision"] == "input"
    assert other["layer"] is None and other["denoised_layer"] is None
    assert other["camera"] == "auto"
    options = {"layer": "Objects", "denoised_layer": "Denoised", "quality": "fast",
               "camera": "locked"}
    chosen = client.post("/v1/sessions", json={**SIZE, **options}).json()
    assert {k: chosen[k] for k in options} == options


@pytest.mark.parametrize(
    "body",
    [
        {"width": 0, "height": 48},
        {"width": 64},
        {**SIZE, "precision": "double"},
        {**SIZE, "unknown": 1},
        {**SIZE, "channels": {"colour": "beauty"}},
        {**SIZE, "channels": {"albedo": ["a.R", "a.G"]}},
        {**SIZE, "layer": ""},
        {**SIZE, "denoised_layer": "Denoised."},
        {**SIZE, "quality": "ultra"},
        {**SIZE, "camera": "tripod"},
    ],
)
def test_create_session_rejects_invalid_bodies(client, body):
    assert_error(client.post("/v1/sessions", json=body), 422, "invalid_request")


def test_create_session_rejects_unknown_model_and_oversize(client):
    detail = assert_error(
        client.post("/v1/sessions", json={**SIZE, "model": "nope"}), 422, "unknown_model"
    )
    assert "installed" in detail
    r = client.post("/v1/sessions", json={"width": 100000, "height": 48})
    assert "maximum frame size" in assert_error(r, 422, "invalid_request")


def test_get_and_delete_session(client):
    sid = new_session(client)
    send(client, sid, 0, frame_bytes())
    status = client.get(f"/v1/sessions/{sid}").json()
    assert status["frames_done"] == 1 and status["last_index"] == 0
    assert status["memory_bytes"] > 0 and status["mean_ms"]["total"] > 0
    assert status["sources"]["albedo"] == ["albedo.R", "albedo.G", "albedo.B"]
    assert client.delete(f"/v1/sessions/{sid}").status_code == 204
    assert_error(client.get(f"/v1/sessions/{sid}"), 404, "session_not_found")
    assert_error(client.delete(f"/v1/sessions/{sid}"), 404, "session_not_found")
    assert_error(send(client, sid, 1, frame_bytes()), 404, "session_not_found")


def test_models(client):
    """Every installed model but the internal stages (files other models compose, never offered
    alone) is listed as its own file's metadata describes it."""
    import onnx

    from quietframe.runtime import Denoiser, default_model_path, installed_models
    from quietframe.runtime.card import GraphStage, ModelCard

    body = client.get("/v1/models").json()
    files = {p.name: p for p in installed_models()}
    cards = [ModelCard.from_props({m.key: m.value for m in onnx.load(
        str(p), load_external_data=False).metadata_props}, p.stem) for p in files.values()]
    stages = {s.file for card in cards for s in card.stages if isinstance(s, GraphStage) and s.file}
    assert stages >= {"accumulation.onnx", "aligned-accumulation.onnx"}
    assert sorted(m["file"] for m in body["models"]) == sorted(set(files) - stages)
    for model in body["models"]:
        info = Denoiser(files[model["file"]], threads=1).info
        assert (model["name"], model["version"]) == (info.name, info.version)
        assert model["required_buffers"] == list(info.required_buffers)
        assert model["optional_buffers"] == list(info.optional_buffers)
        state = [{"name": s.name, "channels": s.channels} for s in info.state_specs]
        assert model["state"] == state
        assert model["metrics"] == info.metrics and model["training"] == info.training
        assert model["default"] == (model["name"] == body["default"])
    assert body["default"] == Denoiser(default_model_path(), threads=1).info.name


def test_health_ready_metrics(client):
    assert client.get("/healthz").json()["status"] == "ok"
    ready = client.get("/readyz").json()
    assert ready["status"] == "ready" and ready["detail"]["models"]
    sid = new_session(client)
    send(client, sid, 0, frame_bytes())
    send(client, sid, 0, b"not an exr")
    text = client.get("/metrics").text
    assert 'quietframe_frames_total{model="' in text
    assert 'quietframe_frame_seconds_bucket{le="0.005",stage="denoise"}' in text
    assert 'quietframe_errors_total{code="bad_exr",status="400"}' in text
    assert "quietframe_sessions " in text and "quietframe_request_bytes_total" in text


def test_openapi_documents_the_api(client):
    spec = client.get("/openapi.json").json()
    frame = spec["paths"]["/v1/sessions/{session_id}/frames/{index}"]["post"]
    assert "image/x-exr" in frame["requestBody"]["content"]
    assert "image/x-exr" in frame["responses"]["200"]["content"]
    assert frame["responses"]["409"]["content"]["application/json"]["example"]["error"]
    create = spec["components"]["schemas"]["SessionCreate"]
    assert create["examples"] and {"/v1/models", "/healthz", "/metrics"} <= set(spec["paths"])


# ---- frames -------------------------------------------------------------------------------


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_renderer_layouts_round_trip(client, layout):
    sid = new_session(client)
    data = write_exr(LAYOUTS[layout](make_buffers(seed=3)), {"comment": layout})
    r = send(client, sid, 7, data)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/x-exr"
    header, channels = read_exr(r.content)
    in_header, in_channels = read_exr(data)
    assert sorted(channels) == sorted(in_channels)  # every channel comes back
    changed = [n for n in in_channels if not np.array_equal(channels[n], in_channels[n])]
    assert len(changed) == 3, changed  # the colour, nothing else
    assert header["comment"] == layout
    out = pixels(r)
    assert out.shape == (48, 64, 3) and np.isfinite(out).all()


def test_sequence_carries_state_and_cut_resets_it(client):
    # A fixed model that keeps history: on a static shot (all-zero motion) `auto` now picks the
    # per-frame tier, since Blender writes an all-zero Vector under motion blur too.
    frames = shot(3)
    stateful = {"model": "nbg-2l-3g"}
    sid = new_session(client, **stateful)
    resets = [send(client, sid, i, f).headers["x-quietframe-reset"] for i, f in enumerate(frames)]
    assert resets == ["first-frame", "none", "none"]
    with_history = pixels(send(client, sid, 3, frames[0]))
    cut = send(client, sid, 4, frames[0], cut="true")
    assert cut.headers["x-quietframe-reset"] == "cut"
    fresh = pixels(send(client, new_session(client, **stateful), 0, frames[0]))
    # A cut output depends on the frame alone (equals a first frame); history changes it.
    np.testing.assert_allclose(pixels(cut), fresh, rtol=1e-5, atol=1e-6)
    assert not np.allclose(with_history, fresh, rtol=1e-5, atol=1e-6)


def test_gap_and_header_flag_are_cuts(client):
    sid = new_session(client)
    send(client, sid, 10, frame_bytes(seed=0))
    assert send(client, sid, 12, frame_bytes(seed=1)).headers["x-quietframe-reset"] == "gap"
    flagged = frame_bytes(seed=2, header={"quietframe.cut": 1})
    assert send(client, sid, 13, flagged).headers["x-quietframe-reset"] == "cut"
    assert send(client, sid, 14, frame_bytes(seed=3)).headers["x-quietframe-reset"] == "none"
    assert client.get(f"/v1/sessions/{sid}").json()["resets"] == 3


def test_idempotent_retry_and_order(client):
    frames = shot(3)
    sid, ref = new_session(client), new_session(client)
    first = send(client, sid, 0, frames[0])
    retry = send(client, sid, 0, frames[0])
    assert retry.status_code == 200 and retry.content == first.content
    assert retry.headers["x-quietframe-replayed"] == "true"
    assert client.get(f"/v1/sessions/{sid}").json()["frames_done"] == 1
    for i in (0, 1):
        expected = send(client, ref, i, frames[i])
    np.testing.assert_array_equal(pixels(send(client, sid, 1, frames[1])), pixels(expected))
    assert_error(send(client, sid, 0, frames[0]), 409, "frame_out_of_order")
    assert_error(send(client, sid, 1, frames[2]), 409, "frame_conflict")


def test_rejected_frames_never_change_state(client):
    frames = shot(3)
    # A model that needs albedo and keeps history (auto serves this static shot per frame).
    sid, ref = new_session(client, model="oidn-acc"), new_session(client, model="oidn-acc")
    for i in range(2):
        send(client, sid, i, frames[i])
        send(client, ref, i, frames[i])
    before = client.get(f"/v1/sessions/{sid}").json()
    no_albedo = {
        k: v
        for k, v in LAYOUTS["plain-normal"](make_buffers()).items()
        if not k.startswith("albedo")
    }
    assert_error(send(client, sid, 2, write_exr(no_albedo)), 422, "missing_channels")
    assert_error(send(client, sid, 2, frames[2][:-100]), 400, "bad_exr")
    assert_error(send(client, sid, 2, frame_bytes(width=32)), 422, "size_mismatch")
    after = client.get(f"/v1/sessions/{sid}").json()
    assert (after["frames_done"], after["last_index"]) == (before["frames_done"], 1)
    good = send(client, sid, 2, frames[2])
    assert good.headers["x-quietframe-reset"] == "none"
    np.testing.assert_array_equal(pixels(good), pixels(send(client, ref, 2, frames[2])))


def test_shot_model_is_one_auto_chooses_from(client):
    """Audit R4-1: `shot_model` names a model auto may choose; an internal stage
    (accumulation: not listed) or 'auto' itself is refused and changes nothing."""
    sid = new_session(client)  # auto
    frame = frame_bytes()
    for name in ("accumulation", "auto", "no-such-model"):
        assert "auto chooses from" in assert_error(send(client, sid, 0, frame, shot_model=name),
                                                   422, "unknown_model")
    assert client.get(f"/v1/sessions/{sid}").json()["frames_done"] == 0
    kept = send(client, sid, 0, frame, shot_model="nbg-2l-3g")
    assert kept.status_code == 200 and kept.headers["x-quietframe-model"].startswith("nbg-2l-3g")


def test_bad_bodies(client):
    sid = new_session(client)
    assert "magic" in assert_error(send(client, sid, 0, b"GIF89a" + bytes(64)), 400, "bad_exr")
    data = frame_bytes()
    for cut in (0, 20, 300, len(data) // 2, len(data) - 1):
        assert_error(send(client, sid, 0, data[:cut]), 400, "bad_exr")
    r = client.post(
        f"/v1/sessions/{sid}/frames/0", content=data, headers={"content-type": "application/json"}
    )
    assert_error(r, 415, "unsupported_media_type")
    assert_error(send(client, sid, -1, data), 422, "invalid_request")
    assert_error(send(client, "no-such-session", 0, data), 404, "session_not_found")


def test_missing_channels_name_found_and_expected(client):
    sid = new_session(client, model="accumulation")  # needs normal (nbg-2l-3g v3 does not)
    channels = LAYOUTS["arnold"](make_buffers())
    channels = {k: v for k, v in channels.items() if not k.startswith("N.")}
    detail = assert_error(send(client, sid, 0, write_exr(channels)), 422, "missing_channels")
    assert "'normal'" in detail and "denoise_albedo.R" in detail and "Nn" in detail


def test_missing_motion_is_reported(client):
    sid = new_session(client, model="nbg-2l-3g")  # a model that reads motion, optional
    r = send(client, sid, 0, frame_bytes("renderman-ci", motion=False))
    assert r.status_code == 200 and r.headers["x-quietframe-missing"] == "motion"
    r = send(client, sid, 1, frame_bytes("renderman-ci"))
    assert "x-quietframe-missing" not in r.headers


def test_nan_inf_negative_are_sanitised_and_counted(client):
    b = make_buffers()
    b["color"][0, 0, 0] = np.nan
    b["color"][1, 1, 1] = np.inf
    b["color"][2, 2, 2] = -4.0
    b["albedo"][3, 3, 0] = -np.inf
    r = send(client, new_session(client), 0, write_exr(LAYOUTS["plain-normal"](b)))
    assert r.status_code == 200
    assert r.headers["x-quietframe-sanitized"] == "4"
    assert r.headers["x-quietframe-sanitized-buffers"] == "albedo=1, color=3"
    assert np.isfinite(pixels(r)).all()


def test_output_precision_follows_the_input_by_default(client):
    for dtype in (np.float16, np.float32):
        r = send(client, new_session(client), 0, frame_bytes(dtype=dtype))
        assert all(c.dtype == dtype for c in read_exr(r.content)[1].values())
    r = send(client, new_session(client, precision="float"), 0, frame_bytes(dtype=np.float16))
    types = {n: c.dtype for n, c in read_exr(r.content)[1].items()}
    assert {n for n, t in types.items() if t == np.float32} == {"R", "G", "B"}  # the colour only


def test_session_channel_mapping(client):
    b = make_buffers()
    channels = {f"beauty.{c}": b["color"][..., i] for i, c in enumerate("RGB")}
    channels.update({f"alb.{c}": b["albedo"][..., i] for i, c in enumerate("RGB")})
    channels.update({f"nrm.{c}": b["normal"][..., i] for i, c in enumerate("XYZ")})
    channels["dist"] = b["depth"]
    mapping = {
        "color": "beauty",
        "albedo": ["alb.R", "alb.G", "alb.B"],
        "normal": "nrm",
        "depth": "dist",
    }
    sid = new_session(client, channels=mapping, precision="half", compression="none",
                      model="nbg-2l-3g")  # reads depth (auto may pick a model that does not)
    r = send(client, sid, 0, write_exr(channels))
    assert r.status_code == 200, r.text
    header, out = read_exr(r.content)
    assert str(header["compression"]) == "Compression.NO_COMPRESSION"
    assert sorted(out) == sorted(channels)
    assert out["beauty.R"].dtype == np.float16 and out["dist"].dtype == np.float32
    assert client.get(f"/v1/sessions/{sid}").json()["sources"]["depth"] == ["dist"]


# ---- limits and auth ------------------------------------------------------------------------


def test_body_and_resolution_limits(make_client):
    c = make_client(max_body_mb=0.01, max_width=40, max_height=40)
    assert_error(c.post("/v1/sessions", json=SIZE), 422, "invalid_request")
    sid = new_session(c, width=32, height=32)
    big = frame_bytes(width=32, height=32, seed=1) + bytes(20000)
    assert_error(send(c, sid, 0, big), 413, "body_too_large")
    # A header that claims 64x48 with no pixel data after it: refused as too large (413) from
    # the header alone; decoding would have failed with 400.
    data = frame_bytes()
    from quietframe.service.frames import read_header

    cut = read_header(data, 8192, 8192).header_bytes
    assert "64x48" in assert_error(send(c, sid, 0, data[:cut]), 413, "resolution_too_large")


def test_too_many_sessions_and_memory_budget(make_client):
    c = make_client(max_sessions=2)
    new_session(c)
    new_session(c)
    r = c.post("/v1/sessions", json=SIZE)
    assert_error(r, 429, "too_many_sessions")
    assert int(r.headers["retry-after"]) >= 1
    c = make_client(history_budget_mb=0.3)  # one 64x48 session reserves ~0.19 MiB
    new_session(c)
    r = c.post("/v1/sessions", json=SIZE)
    assert_error(r, 429, "memory_budget_exceeded")
    assert int(r.headers["retry-after"]) >= 1


def test_reservation_grows_to_the_whole_file_reply(make_client):
    """Replies carry every input pass: a frame whose reply does not fit the budget is refused
    before it changes the session, and the reservation then covers what the session holds."""
    import OpenEXR

    c = make_client(history_budget_mb=0.6)  # a 64x48 session first reserves ~0.19 MiB
    sid = new_session(c, model="nbg-2l-3g")
    channels = LAYOUTS["plain-normal"](make_buffers())
    extra = {f"aov{i}.{c}": np.full((48, 64), i, np.float32) for i in range(30) for c in "RGB"}
    big = write_exr({**channels, **extra}, compression=OpenEXR.NO_COMPRESSION)  # ~1.1 MiB of passes
    assert_error(send(c, sid, 0, big), 429, "memory_budget_exceeded")
    assert c.get(f"/v1/sessions/{sid}").json()["frames_done"] == 0
    few = dict(list(extra.items())[:9])
    small = write_exr({**channels, **few}, compression=OpenEXR.NO_COMPRESSION)
    assert send(c, sid, 0, small).status_code == 200
    status = c.get(f"/v1/sessions/{sid}").json()
    assert status["reserved_bytes"] >= status["memory_bytes"] > len(small) // 2


def test_idle_sessions_expire(make_client):
    c = make_client(session_ttl_s=0.3)
    sid = new_session(c)
    send(c, sid, 0, frame_bytes())
    time.sleep(1.0)  # the reaper runs every ttl/4
    assert_error(c.get(f"/v1/sessions/{sid}"), 404, "session_not_found")
    assert 'quietframe_sessions_closed_total{reason="expired"} 1.0' in c.get("/metrics").text


def test_bearer_token(make_client):
    c = make_client(auth_token="s3cret")
    r = c.get("/v1/models")
    assert_error(r, 401, "unauthorized")
    assert r.headers["www-authenticate"].startswith("Bearer")
    assert_error(
        c.get("/v1/models", headers={"Authorization": "Bearer wrong"}), 401, "unauthorized"
    )
    ok = {"Authorization": "Bearer s3cret"}
    assert c.get("/v1/models", headers=ok).status_code == 200
    sid = c.post("/v1/sessions", json=SIZE, headers=ok).json()["id"]
    r = c.post(f"/v1/sessions/{sid}/frames/0", content=frame_bytes(), headers={**EXR, **ok})
    assert r.status_code == 200
    assert_error(
        c.post(f"/v1/sessions/{sid}/frames/1", content=frame_bytes(), headers=EXR),
        401,
        "unauthorized",
    )
    assert c.get("/healthz").status_code == 200 and c.get("/readyz").status_code == 200


def test_header_parser_rejects_short_dataWindow(client):
    data = bytearray(frame_bytes())
    at = bytes(data).index(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0")
    data[at : at + 4] = struct.pack("<i", 8)
    assert_error(send(client, new_session(client), 0, bytes(data)), 400, "bad_exr")


def test_durable_sessions_are_evicted_to_disk_under_memory_pressure(make_client, tmp_path):
    frames = shot(3)
    # room for one session with its whole-file reply (~0.27 MiB), not for two
    c = make_client(state_dir=str(tmp_path), history_budget_mb=0.4)
    a = new_session(c, model="nbg-2l-3g")  # an NBG-sized state (auto may pick a larger one)
    outputs = [send(c, a, i, frames[i]).content for i in range(2)]
    b = new_session(c, model="nbg-2l-3g")  # evicts a's state to disk instead of refusing
    assert c.get(f"/v1/sessions/{a}").json()["reserved_bytes"] == 0
    send(c, b, 0, frames[0])
    third = send(c, a, 2, frames[2])  # a comes back from disk, b goes out
    assert third.headers["x-quietframe-reset"] == "none"
    assert c.get(f"/v1/sessions/{b}").json()["reserved_bytes"] == 0
    ref = new_session(c, model="nbg-2l-3g")
    for i, f in enumerate(frames):
        expected = send(c, ref, i, f)
    np.testing.assert_array_equal(pixels(third), pixels(expected))
    assert send(c, a, 1, frames[1]).status_code == 409 and outputs


def test_durable_session_keeps_its_layer_options_across_a_restart(make_client, tmp_path):
    options = {"layer": "ViewLayer", "denoised_layer": "Denoised", "quality": "best"}
    sid = new_session(make_client(state_dir=str(tmp_path)), **options)
    restarted = make_client(state_dir=str(tmp_path))  # a second server on the same folder
    status = restarted.get(f"/v1/sessions/{sid}").json()
    assert {k: status[k] for k in options} == options
