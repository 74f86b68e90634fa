"""Requests the session stores must answer with a client's error, not a 500: an id not of the
server's form, a Redis that is full, a status read on a replica that did not commit the last
frame; and session bodies whose numbers do not fit (model_options), and an `auto` session's own
spp at the model choice. Redis cases run a redis-server on 127.0.0.1 (skipped where it is not
installed); two in-process replicas share it. 64x48 frames."""

from __future__ import annotations

import shutil
import socket

import pytest
from conftest import LAYOUTS, frame_bytes, hard_timeout, make_buffers, write_exr

SIZE = {"width": 64, "height": 48}
EXR = {"content-type": "image/x-exr"}
JSON = {"content-type": "application/json"}
HARD_TIMEOUT_S = 60

needs_redis = pytest.mark.skipif(
    not shutil.which("redis-server"), reason="needs redis-server (Debian package redis-server)"
)


@pytest.fixture(autouse=True)
def time_limit():
    with hard_timeout(HARD_TIMEOUT_S):
        yield


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def redis_url(tmp_path_factory):
    """A redis-server on loopback, no persistence, ended with the module."""
    from conftest import redis_server

    with redis_server(tmp_path_factory.mktemp("redis")) as url:
        yield url


@pytest.fixture
def redis_db(redis_url):
    """The test's Redis, emptied, and given its memory back however the test ends."""
    import redis

    db = redis.Redis.from_url(redis_url, socket_timeout=5)
    db.flushdb()
    yield db
    db.config_set("maxmemory", 0)


def replica(name: str, **settings):
    """An in-process replica (its lifespan started); a 500 comes back as a response."""
    from conftest import service_settings
    from fastapi.testclient import TestClient

    from quietframe.service.main import create_app

    client = TestClient(create_app(service_settings(replica_id=name, **settings)),
                        raise_server_exceptions=False)
    client.__enter__()
    return client


@pytest.fixture(scope="module")
def replicas(redis_url):
    """Two replicas sharing one Redis, as behind the load balancer."""
    pair = replica("a", store_url=redis_url), replica("b", store_url=redis_url)
    yield pair
    for client in pair:
        client.__exit__(None, None, None)


def new_session(c, **body) -> str:
    r = c.post("/v1/sessions", json={**SIZE, "model": "nbg-2l-3g", **body})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def send(c, sid: str, index: int, data: bytes | None = None):
    return c.post(f"/v1/sessions/{sid}/frames/{index}",
                  content=data or frame_bytes(seed=index), headers=EXR)


def assert_error(response, status: int, code: str) -> str:
    assert response.status_code == status, response.text
    assert response.json()["error"] == code, response.text
    return response.json()["detail"]


def session_keys(db) -> list[bytes]:
    return sorted(db.scan_iter("qf:*"))


# ---- an id of another form ---------------------------------------------------------------------


@needs_redis
@pytest.mark.parametrize("session_id", ["abc", "a" * 23, "a" * 21 + "."])
def test_a_malformed_session_id_is_404_on_a_redis_store(replicas, redis_db, session_id):
    """Every route answers as for any unknown session, before the store is asked (the store
    refuses to build a key from such an id: that was a 500)."""
    a, _ = replicas
    unknown = a.get("/v1/sessions/" + "z" * 22)
    for response in (
        a.get(f"/v1/sessions/{session_id}"),
        a.delete(f"/v1/sessions/{session_id}"),
        send(a, session_id, 0),
    ):
        detail = assert_error(response, 404, "session_not_found")
        assert detail == unknown.json()["detail"].replace("z" * 22, session_id)


def test_a_session_id_with_a_trailing_newline_is_not_one(tmp_path):
    """`$` matches before a final newline: neither store may take such an id for a key."""
    from quietframe.service.session_store import SessionStore
    from quietframe.service.state_store_redis import RedisStore

    almost = "a" * 22 + "\n"
    with pytest.raises(ValueError, match="not a session id"):
        SessionStore(tmp_path, fsync=False).path(almost)
    with pytest.raises(ValueError, match="not a session id"):
        RedisStore.keys(almost)


# ---- a full Redis ------------------------------------------------------------------------------


@needs_redis
def test_a_full_redis_refuses_a_frame_with_503_and_the_session_continues(replicas, redis_db):
    """maxmemory with noeviction: Redis refuses every write ("OOM command not allowed"). The
    frame is 503 state_store_unavailable, nothing of it is committed, and once memory is
    freed the retry continues the sequence (no reset)."""
    a, _ = replicas
    sid = new_session(a)
    assert send(a, sid, 0).status_code == 200
    ver = f"qf:{{{sid}}}:ver"
    version = redis_db.get(ver)
    redis_db.config_set("maxmemory", 1)
    refused = send(a, sid, 1)
    assert_error(refused, 503, "state_store_unavailable")
    assert refused.headers.get("retry-after")
    assert redis_db.get(ver) == version  # not committed
    redis_db.config_set("maxmemory", 0)
    assert a.get(f"/v1/sessions/{sid}").json()["last_index"] == 0
    retried = send(a, sid, 1)
    assert retried.status_code == 200, retried.text
    assert retried.headers["x-quietframe-reset"] == "none"
    assert a.get(f"/v1/sessions/{sid}").json()["last_index"] == 1


@needs_redis
def test_a_full_redis_refuses_a_creation_with_503_and_leaves_no_session(replicas, redis_db):
    """Full from the start, or only once the settings were written (the first record does not
    fit): 503, and nothing of the session is left in the store or the replica."""
    a, _ = replicas
    registry = a.app.state.sessions
    held = set(registry.sessions)
    redis_db.config_set("maxmemory", 1)
    assert_error(a.post("/v1/sessions", json=SIZE), 503, "state_store_unavailable")
    redis_db.config_set("maxmemory", 0)
    assert session_keys(redis_db) == []

    store = registry.store
    write = store.write

    def fills_up_first(*args, **kwargs):  # the settings key was written: now Redis is full
        redis_db.config_set("maxmemory", 1)
        return write(*args, **kwargs)

    store.write = fills_up_first
    try:
        assert_error(a.post("/v1/sessions", json=SIZE), 503, "state_store_unavailable")
    finally:
        del store.write
        redis_db.config_set("maxmemory", 0)
    assert session_keys(redis_db) == []
    assert set(registry.sessions) == held
    new_session(a)  # memory freed: creations work again


@needs_redis
def test_only_redis_refusals_for_now_are_store_unavailable(redis_url, redis_db):
    """A Redis that cannot take writes for now is StoreUnavailable (503, retry); any other
    error reply is a bug or a misconfiguration, left to be a 500."""
    import redis
    from redis.exceptions import MasterDownError, ReadOnlyError

    from quietframe.service.state_store_redis import (
        RedisStore,
        StoreUnavailable,
        refuses_for_now,
    )

    store = RedisStore(redis_url, ttl_s=60, timeout_s=5)
    meta = {"id": "s" * 22, "model": "nbg-2l-3g"}
    redis_db.config_set("maxmemory", 1)
    with pytest.raises(StoreUnavailable, match="maxmemory"):
        store.write_spec(meta)
    with pytest.raises(StoreUnavailable, match="maxmemory"):
        store.write(meta, None, None, "")
    redis_db.config_set("maxmemory", 0)
    redis_db.hset(f"qf:{{{'w' * 22}}}:ver", "not", "a string")
    with pytest.raises(redis.ResponseError, match="WRONGTYPE"):
        store.version("w" * 22)
    assert refuses_for_now(ReadOnlyError("You can't write against a read only replica."))
    assert refuses_for_now(MasterDownError("Link with MASTER is down"))
    assert refuses_for_now(redis.ResponseError("MISCONF Redis is configured to save RDB ..."))
    assert not refuses_for_now(redis.ResponseError("ERR syntax error"))


# ---- a status read on another replica -----------------------------------------------------------


@needs_redis
def test_status_on_one_replica_shows_the_frames_another_committed(replicas, redis_db):
    """Frames 1-2 on replica a, 3 on b: a's status reads the store's record (not its own copy,
    and without loading the state)."""
    a, b = replicas
    sid = new_session(a)
    for c, index in ((a, 1), (a, 2), (b, 3)):
        assert send(c, sid, index).status_code == 200
    status = a.get(f"/v1/sessions/{sid}").json()
    assert (status["last_index"], status["frames_done"]) == (3, 3)
    copy = a.app.state.sessions.sessions[sid]
    assert copy.last_index == 2  # the status read did not load (nor touch) a's copy
    nxt = send(a, sid, 4)  # a's next frame follows the store
    assert nxt.status_code == 200 and nxt.headers["x-quietframe-reset"] == "none"
    assert a.get(f"/v1/sessions/{sid}").json()["last_index"] == 4


# ---- numbers in a session's body ---------------------------------------------------------------


@pytest.fixture(scope="module")
def server():
    client = replica("solo")
    yield client
    client.__exit__(None, None, None)


@pytest.mark.parametrize("value", ["1" + "0" * 400, "-1" + "0" * 400, "1e39", "1e308",
                                   str(2**53)])
def test_a_model_option_beyond_2_53_is_a_422(server, value):
    """A JSON integer has no bound in Python: 10**400 passed and overflowed on its way to a
    float (500, connection dropped); 1e39 passed and became inf as the graph's float32."""
    body = f'{{"width": 64, "height": 48, "model": "auto", "model_options": {{"spp": {value}}}}}'
    detail = assert_error(server.post("/v1/sessions", content=body, headers=JSON),
                          422, "invalid_request")
    assert "model_options.spp" in detail and "9007199254740991" in detail


@pytest.mark.parametrize("body", [
    '{"width": 1%s, "height": 48}' % ("0" * 400),
    '{"width": 1e400, "height": 48}',
    '{"width": 64, "height": 48, "latency_ms": 1%s}' % ("0" * 400),
    '{"width": 64, "height": 48, "latency_ms": 1e400}',
    '{"width": 64, "height": 48, "motion_scale": [1%s, 1]}' % ("0" * 400),
    '{"width": 64, "height": 48, "model_options": {"spp": 1e400}}',
])
def test_other_huge_numbers_in_a_session_body_are_a_422(server, body):
    """The other numeric fields: a 422 naming the field, never a 500."""
    response = server.post("/v1/sessions", content=body, headers=JSON)
    assert response.status_code == 422, response.text
    assert response.json()["error"] == "invalid_request"


# ---- an auto session's own spp -----------------------------------------------------------------


@pytest.mark.parametrize("header_spp", [None, 16])
def test_an_auto_sessions_spp_reaches_the_model_choice(server, header_spp):
    """model_options.spp is the spp the chosen model is given, so the choice plans for it
    (docs/service.md, "How auto chooses", 2. and 6.): at 4096 spp, beyond every temporal
    table, a model without history; not the noise estimate's (~16 spp) temporal tier."""
    models = {m["name"]: m for m in server.get("/v1/models").json()["models"]}
    if not any(o["name"] == "spp" for m in models.values() for o in m["options"]):
        pytest.skip("no installed model takes spp (the oidn-history tiers need pyoidn)")
    sid = new_session(server, model="auto", model_options={"spp": 4096})
    header = None if header_spp is None else {"cycles.ViewLayer.samples": str(header_spp)}
    data = write_exr(LAYOUTS["blender"](make_buffers(seed=0)), header)
    r = send(server, sid, 0, data)
    assert r.status_code == 200, r.text
    assert "spp=4096; source=model_options.spp" in r.headers["x-quietframe-choice"]
    choice = server.get(f"/v1/sessions/{sid}").json()["choice"]
    assert (choice["spp"], choice["noise_source"]) == (4096, "model_options.spp")
    assert models[choice["model"]]["state"] == [], choice
    assert 'noise_source="session"' in server.get("/metrics").text  # not "header"


# ---- a hung store (audit R4-10) ----------------------------------------------------------------


@needs_redis
def test_a_hung_store_holds_the_request_not_the_event_loop(tmp_path):
    """Redis stopped (SIGSTOP) while a replica adopts a session another replica created: the
    adoption waits on the worker pool and ends in 503 with Retry-After after the store's
    timeout, while /healthz on the same replica answers at once (HAProxy keeps it up)."""
    import os
    import signal
    import threading
    import time

    import httpx
    import redis
    from conftest import LiveServer, redis_server

    with redis_server(tmp_path) as url:
        pid = redis.Redis.from_url(url).info("server")["process_id"]
        writer = replica("a", store_url=url)
        try:
            sid = new_session(writer)
        finally:
            writer.__exit__(None, None, None)
        with LiveServer(store_url=url, store_timeout_s=2.0, replica_id="b") as server:
            answers: dict = {}
            os.kill(pid, signal.SIGSTOP)
            try:
                def adopt() -> None:
                    answers["get"] = httpx.get(f"{server.url}/v1/sessions/{sid}", timeout=30)

                waiting = threading.Thread(target=adopt)
                waiting.start()
                time.sleep(0.3)  # the adoption is waiting on Redis now
                started = time.monotonic()
                health = httpx.get(f"{server.url}/healthz", timeout=5)
                answered_in = time.monotonic() - started
                waiting.join(timeout=20)
            finally:
                os.kill(pid, signal.SIGCONT)
    assert health.status_code == 200 and answered_in < 1.0, answered_in
    assert not waiting.is_alive()
    got = answers["get"]
    assert got.status_code == 503 and got.headers["retry-after"], got.text
    assert got.json()["error"] == "state_store_unavailable"
