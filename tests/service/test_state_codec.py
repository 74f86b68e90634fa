"""The stored form of a session (service/state_codec.py): what comes back is what the writer
continues from, float16 never overflows and nothing non-finite comes back, records of the
earlier float32 form still load, a damaged record is refused, and a stored reply is written
again byte for byte from the resent request, after a restart and on another replica."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import frame_bytes, shot

from quietframe.runtime.motion_evidence import DEPTH_STATE, PROBE_STATE
from quietframe.service import state_codec
from quietframe.service.session_store import (
    Reply,
    SessionStore,
    StateDamaged,
    record,
    request_digest,
    unpack,
)

H, W = 24, 32
SID = "A" * 22
# a stored record's meta as a session writes it (the stores check it: service/stored_record.py)
META = {"id": SID, "width": W, "height": H, "model": "nbg-2l-3g", "created_at": 0.0,
        "last_index": 0, "frames_done": 1, "resets": 1}
EXR = {"content-type": "image/x-exr"}


def two_stages(seed: int = 0, half_aux: bool = True) -> dict[str, np.ndarray]:
    """An oidn-history-like state: two accumulation stages with the same depth and normal
    (float16 values, as a half EXR's aux, unless `half_aux` is False), and the motion probe."""
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.5, 80, (1, 1, H, W)).astype(np.float32)
    normal = rng.normal(size=(1, 3, H, W)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    if half_aux:
        depth, normal = (x.astype(np.float16).astype(np.float32) for x in (depth, normal))
    state = {}
    for name in ("color_from.accumulation", "accumulation"):
        radiance = rng.gamma(2.0, 0.5, (1, 3, H, W)).astype(np.float32)
        count = rng.integers(1, 7, (1, 1, H, W)).astype(np.float32)
        state[name] = np.concatenate([radiance, depth, normal, count], axis=1)
    state[PROBE_STATE] = rng.random((4, H // 2, W // 2), dtype=np.float32)
    return state


def shapes_of(state):
    return {name: tensor.shape for name, tensor in state.items()}


def round_trip(state, recipe=None):
    encoded = state_codec.encode(state, recipe)
    return encoded, state_codec.decode(encoded.layout, encoded.planes, shapes_of(state))


def test_what_comes_back_is_what_the_writer_continues_from():
    state = two_stages()
    encoded, back = round_trip(state)
    for name, tensor in state.items():
        assert np.array_equal(back[name], encoded.state[name])
        assert back[name].dtype == np.float32 and back[name].shape == tensor.shape
    a = state["accumulation"][0]
    b = back["accumulation"][0]
    assert np.array_equal(b[7], a[7])  # history length: exact
    assert np.array_equal(back[PROBE_STATE], state[PROBE_STATE])  # the probe: exact
    relative = np.abs(b[:7] - a[:7]) / np.maximum(np.abs(a[:7]), 2**-14)
    assert relative.max() <= 2**-11  # float16's rounding, no more
    kinds = [(d["kind"], d["shape"][1] if len(d["shape"]) == 4 else "probe")
             for d in encoded.layout["planes"]]
    # radiance, depth, normal, count of the first stage; radiance and count of the second
    # (its depth and normal are the first's); the probe
    assert kinds == [("f16", 3), ("f16", 1), ("f16", 3), ("u8", 1), ("f16", 3), ("u8", 1),
                     ("f32", "probe")]
    stored = sum(p.size for p in encoded.planes)
    assert stored < 0.45 * sum(t.nbytes for t in state.values())


def test_float32_depth_and_normal_come_back_exact():
    """The aligned accumulation tells a repeated sample by depth and normal equal to the last
    bit (model/temporal.repeated_sample): aux that are not float16 values (a float EXR's) are
    stored as float32, so a restored session restarts exactly where the live one would."""
    state = two_stages(half_aux=False)
    encoded, back = round_trip(state)
    for name in ("accumulation", "color_from.accumulation"):
        assert np.array_equal(back[name][0, 3:7], state[name][0, 3:7])
        assert not np.array_equal(back[name][0, 0:3], state[name][0, 0:3])  # radiance: f16
    kinds = [(d["kind"], d["shape"][1]) for d in encoded.layout["planes"][:3]]
    assert kinds == [("f16", 3), ("f32", 1), ("f32", 3)]


def test_the_depth_probe_beside_the_probe_comes_back_exact():
    """The previous frame's inverse depth, kept for motion estimated from the aux, is stored
    like the probe: float32, compressed, exact."""
    state = two_stages()
    state[DEPTH_STATE] = np.random.default_rng(1).gamma(2.0, 0.1, (1, H // 2, W // 2)
                                                        ).astype(np.float32)
    encoded, back = round_trip(state)
    assert np.array_equal(back[DEPTH_STATE], state[DEPTH_STATE])
    assert encoded.layout["planes"][-1]["kind"] == "f32"


def test_radiance_beyond_half_range_is_kept_exactly_and_nothing_non_finite_comes_back():
    state = two_stages()
    a = state["accumulation"]
    a[0, 0, 0, :4] = [1e6, -7e4, 65505.0, 65504.0]
    a[0, 1, 0, 0], a[0, 1, 0, 1], a[0, 2, 0, 0] = np.inf, -np.inf, np.nan
    for stage in state.values():  # a depth beyond float16 too, in the depth both stages share
        if stage.ndim == 4:
            stage[0, 3, 1, 1] = 3e9
    encoded, back = round_trip(state)
    b = back["accumulation"]
    assert b[0, 0, 0, :4].tolist() == [1e6, -7e4, 65505.0, 65504.0]
    assert b[0, 1, 0, 0] == b[0, 1, 0, 1] == b[0, 2, 0, 0] == 0  # as the output guard does
    assert b[0, 3, 1, 1] == np.float32(3e9)
    assert back["color_from.accumulation"][0, 3, 1, 1] == np.float32(3e9)  # shared depth
    for tensor in back.values():
        assert np.isfinite(tensor).all()
    patches = [d["patches"] for d in encoded.layout["planes"]]
    assert patches == [0, 1, 0, 0, 3, 0, 0]  # depth (shared), the second stage's radiance


def test_a_plane_mostly_beyond_half_range_and_fractional_counts_stay_float32():
    state = two_stages()
    state["accumulation"][0, 0:3] *= 1e6
    state["accumulation"][0, 7] += 0.5
    encoded, back = round_trip(state)
    for channels in (slice(0, 3), slice(7, 8)):
        assert np.array_equal(back["accumulation"][0, channels], state["accumulation"][0, channels])
    kinds = {(p[1], encoded.layout["planes"][p[0]]["kind"])
             for p in encoded.layout["tensors"]["accumulation"]["parts"]}
    assert (0, "f32") in kinds and (7, "f32") in kinds


def test_other_layouts_are_stored_as_they_are():
    rng = np.random.default_rng(1)
    state = {"affinity": rng.normal(size=(1, 18, H, W)).astype(np.float32) * 1e5,
             "embedding": rng.normal(size=(1, 32, H // 2, W // 2)).astype(np.float32)}
    _, back = round_trip(state)
    for name in state:
        assert np.array_equal(back[name], state[name])


def test_a_float32_reply_keeps_its_colour_plane_exact():
    state = two_stages()
    color = state["accumulation"][0, 0:3]
    for dtypes, kind in (((np.float16,) * 3, "f16"), ((np.float32,) * 3, "f32")):
        recipe = state_codec.reply_recipe(color, state, dtypes, ("R", "G", "B"), "input",
                                          "input", None, {})
        assert recipe is not None and recipe.tensor == "accumulation"
        encoded, back = round_trip(state, recipe)
        radiance = encoded.layout["tensors"]["accumulation"]["parts"][0][0]
        assert encoded.layout["planes"][radiance]["kind"] == kind and encoded.reply
    assert np.array_equal(back["accumulation"][0, 0:3], color)
    other = color + 1
    assert state_codec.reply_recipe(other, state, (np.float16,) * 3, ("R", "G", "B"), "input",
                                    "input", None, {}) is None


def corrupt(encoded, plane: int, change) -> list[np.ndarray]:
    planes = [p.copy() for p in encoded.planes]
    planes[plane] = change(planes[plane])
    return planes


@pytest.mark.parametrize(("plane", "change"), [
    (0, lambda p: np.full_like(p, 0x7C)),  # radiance: every float16 0x7C7C, a NaN
    (1, lambda p: p[:-2]),  # depth (zlib), truncated
    (1, lambda p: np.zeros_like(p)),  # not zlib at all
])
def test_a_damaged_plane_is_refused(plane, change):
    state = two_stages()
    encoded = state_codec.encode(state)
    with pytest.raises(ValueError):
        state_codec.decode(encoded.layout, corrupt(encoded, plane, change), shapes_of(state))


def test_a_patch_out_of_range_or_a_foreign_shape_is_refused():
    state = two_stages()
    state["accumulation"][0, 0, 0, 0] = 1e6
    encoded = state_codec.encode(state)

    def move_patch(p):
        size = encoded.layout["planes"][4]["bytes"]
        p[size:size + 4] = np.frombuffer(np.uint32(10**8).tobytes(), np.uint8)
        return p

    with pytest.raises(ValueError):
        state_codec.decode(encoded.layout, corrupt(encoded, 4, move_patch), shapes_of(state))
    other = {**shapes_of(state), "accumulation": (1, 8, H, W + 1)}
    with pytest.raises(ValueError):
        state_codec.decode(encoded.layout, encoded.planes, other)


@pytest.mark.parametrize("shape", [[-1], [0], [-1, -1], [10**6, 10**6]])
def test_a_zlib_bomb_is_refused_before_it_inflates(shape):
    """Audit R4-5: a plane whose descriptor claims a shape beyond the session's (or none,
    [-1]) must not inflate without bound: 64 MiB of zeros in 64 KiB of zlib, refused before a
    byte of it is inflated (tracemalloc sees no allocation near its size)."""
    import tracemalloc
    import zlib

    state = two_stages()
    encoded = state_codec.encode(state)
    bomb = np.frombuffer(zlib.compress(bytes(64 << 20), 9), np.uint8)
    layout = json.loads(json.dumps(encoded.layout))
    layout["planes"][0] = {**layout["planes"][0], "kind": "u8", "shape": shape, "zlib": True,
                           "bytes": int(bomb.size), "patches": 0}
    planes = [bomb, *encoded.planes[1:]]
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match="at most"):
            state_codec.decode(layout, planes, shapes_of(state))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8 << 20, peak


def test_the_writer_continues_from_the_stored_values(tmp_path):
    state = two_stages()
    original = {k: v.copy() for k, v in state.items()}
    store = SessionStore(tmp_path, fsync=False)
    store.write(META, state, None)
    loaded, _ = store.read(SID, shapes_of(state))
    for name in state:
        assert np.array_equal(state[name], loaded[name])  # replaced in place by write
    assert not np.array_equal(state["accumulation"], original["accumulation"])


def legacy_file(path, state, reply: Reply) -> None:
    """A session file as written before the compact form: float32 tensors, the reply's bytes."""
    arrays = {f"state.{k}": v for k, v in state.items()}
    arrays["reply"] = np.frombuffer(reply.body, np.uint8)
    meta = {**META, "reply": {"index": reply.index, "headers": reply.headers,
                                 "digest": reply.request_digest, "crc": None,
                                 "len": reply.request_len},
            "manifest": {k: list(v.shape) for k, v in arrays.items()}}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def test_files_and_redis_records_of_the_earlier_form_still_load(tmp_path):
    from quietframe.service.state_store_redis import _arrays

    state = two_stages()
    request = b"request body"
    reply = Reply(3, b"the reply", {"X-Quietframe-Frame": "3"}, len(request),
                  request_digest(request))
    legacy_file(tmp_path / f"{SID}.npz", state, reply)
    loaded, back = SessionStore(tmp_path, fsync=False).read(SID, shapes_of(state))
    for name in state:
        assert np.array_equal(loaded[name], state[name])
    assert back.body == b"the reply" and back.matches(request)
    # Redis: one hash field per member, the tensors' raw float32 bytes
    with np.load(tmp_path / f"{SID}.npz") as z:
        fields = {name.encode(): z[name].tobytes() for name in z.files if name != "meta"}
        meta = json.loads(z["meta"].tobytes())
    loaded, back = unpack(meta, _arrays(meta, fields), SID, shapes_of(state))
    assert np.array_equal(loaded["accumulation"], state["accumulation"])
    assert back.body == b"the reply"


def test_a_compact_record_read_as_the_earlier_form_is_refused():
    """What a replica that predates the compact form does with one: its check of the state
    members' shapes and types refuses it (a fresh history), it never reads it as empty."""
    state = two_stages()
    meta, arrays = record(META, state, None)
    shapes = shapes_of(state)
    assert all(name.startswith("state.") for name in arrays)
    assert not any(arrays[n].shape == shapes.get(n[6:]) for n in arrays)


def test_a_damaged_compact_file_is_state_damaged(tmp_path):
    state = two_stages()
    store = SessionStore(tmp_path, fsync=False)
    store.write(META, state, None)
    path = tmp_path / f"{SID}.npz"
    with np.load(path) as z:
        arrays = {name: z[name] for name in z.files}
    arrays["state.plane0"] = np.full_like(arrays["state.plane0"], 0x7C)  # float16 Infs
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    with pytest.raises(StateDamaged):
        store.read(SID, shapes_of(state))


# ---- the reply: written again from the resent request ------------------------------------------


def app(**settings):
    from conftest import app_for, service_settings
    from fastapi.testclient import TestClient

    return TestClient(app_for(service_settings(**settings)), raise_server_exceptions=False)


@pytest.mark.parametrize("precision", ["half", "input"])  # input: the fixture's float32
def test_a_retry_after_a_restart_gets_the_same_bytes_from_a_recipe(tmp_path, precision):
    frames = shot(2)
    body = {"width": 64, "height": 48, "model": "oidn-fast-history", "precision": precision}
    with app(state_dir=str(tmp_path)) as c:
        sid = c.post("/v1/sessions", json=body).json()["id"]
        replies = [c.post(f"/v1/sessions/{sid}/frames/{i}", content=f, headers=EXR)
                   for i, f in enumerate(frames)]
        assert [r.status_code for r in replies] == [200, 200], replies[-1].text
    with np.load(tmp_path / f"{sid}.npz") as z:
        assert "reply" not in z.files  # the recipe, not the bytes
        meta = json.loads(z["meta"].tobytes())
    assert meta["reply"]["recipe"]["tensor"] == "accumulation"
    with app(state_dir=str(tmp_path)) as c:
        again = c.post(f"/v1/sessions/{sid}/frames/1", content=frames[1], headers=EXR)
        assert again.status_code == 200, again.text
        assert again.headers["x-quietframe-replayed"] == "true"
        assert again.content == replies[1].content
        assert again.headers["x-quietframe-frame"] == "1"
        conflict = c.post(f"/v1/sessions/{sid}/frames/1", content=frame_bytes(seed=5),
                          headers=EXR)
        assert conflict.status_code == 409, conflict.text


def test_a_model_without_its_colour_in_the_state_keeps_the_reply_bytes(tmp_path):
    with app(state_dir=str(tmp_path)) as c:
        sid = c.post("/v1/sessions", json={"width": 64, "height": 48,
                                           "model": "nbg-2l-3g"}).json()["id"]
        first = c.post(f"/v1/sessions/{sid}/frames/0", content=frame_bytes(), headers=EXR)
        assert first.status_code == 200, first.text
    with np.load(tmp_path / f"{sid}.npz") as z:
        assert z["reply"].tobytes() == first.content


@pytest.fixture
def redis_url(tmp_path):
    """A redis-server on loopback, no persistence, ended with the test."""
    from conftest import redis_server

    with redis_server(tmp_path) as url:
        yield url


def test_another_replica_answers_a_retry_with_the_same_bytes(redis_url):
    """Replica a denoised frame 1 and went away before its reply arrived; the retry reaches b,
    which writes the reply again from the resent request and the record in Redis."""
    import redis

    frames = shot(3)
    body = {"width": 64, "height": 48, "model": "oidn-fast-history", "precision": "half"}
    with app(store_url=redis_url, replica_id="a") as a, \
            app(store_url=redis_url, replica_id="b") as b:
        sid = a.post("/v1/sessions", json=body).json()["id"]
        first = [a.post(f"/v1/sessions/{sid}/frames/{i}", content=f, headers=EXR)
                 for i, f in enumerate(frames[:2])]
        assert [r.status_code for r in first] == [200, 200], first[-1].text
        fields = redis.Redis.from_url(redis_url).hkeys(f"qf:{{{sid}}}:data")
        assert b"reply" not in fields and b"meta" in fields
        again = b.post(f"/v1/sessions/{sid}/frames/1", content=frames[1], headers=EXR)
        assert again.status_code == 200, again.text
        assert again.headers["x-quietframe-replayed"] == "true"
        assert again.content == first[1].content
        nxt = b.post(f"/v1/sessions/{sid}/frames/2", content=frames[2], headers=EXR)
        assert nxt.status_code == 200 and nxt.headers["x-quietframe-reset"] == "none"
