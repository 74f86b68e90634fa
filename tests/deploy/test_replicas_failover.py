"""Past one box, for real: two `quietframe serve` replicas, HAProxy with the shipped
deploy/haproxy.cfg and a redis-server, all on loopback. Two sequences stream through the load
balancer; the replica holding one is killed with SIGKILL mid-sequence; the sequence goes on
without a reset, a retry of its last frame gets the stored reply, every output is bit-identical
to an uninterrupted run, and the restarted replica rejoins (takes its sessions back).

Skipped where redis-server or haproxy is not installed (.ci/run installs both).
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import hard_timeout, write_exr

ROOT = Path(__file__).resolve().parents[2]
HARD_TIMEOUT_S = 150
W, H = 64, 48
FRAMES = 10  # per sequence: 4 before the kill, 4 after it, 2 after the rejoin
KILL_AFTER, REJOIN_AT = 4, 8

pytestmark = pytest.mark.skipif(
    not (shutil.which("redis-server") and shutil.which("haproxy")),
    reason="needs redis-server and haproxy (Debian packages; .ci/run installs them)",
)


@pytest.fixture(autouse=True)
def time_limit():
    with hard_timeout(HARD_TIMEOUT_S):
        yield


@pytest.fixture(scope="module")
def cluster():
    from conftest import service_settings

    from quietframe.bench.replicas import Cluster

    service_settings()  # skips without an installed model
    with Cluster(replicas=2, threads=1, workers=1,
                 haproxy_cfg=ROOT / "deploy" / "haproxy.cfg") as c:
        yield c


def sequence(seed: int) -> list[bytes]:
    """A moving shot: the scene shifts one pixel per frame, fresh colour noise each frame, so
    the temporal history changes every output."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(H, W, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    albedo = (0.2 + 0.6 * rng.random((H, W, 3))).astype(np.float32)
    depth = (2 + rng.random((H, W))).astype(np.float32)
    frames = []
    for i in range(FRAMES):
        noise = np.random.default_rng(seed * 1000 + i).random((H, W, 3))
        color = np.roll(albedo, i, axis=1) * (0.5 + noise)
        b = {"color": color, "albedo": np.roll(albedo, i, axis=1),
             "normal": np.roll(normal, i, axis=1), "depth": np.roll(depth, i, axis=1)}
        channels = {f"{'RGB'[c]}": b["color"][..., c] for c in range(3)}
        channels.update({f"albedo.{'RGB'[c]}": b["albedo"][..., c] for c in range(3)})
        channels.update({f"normal.{'XYZ'[c]}": b["normal"][..., c] for c in range(3)})
        channels["Z"] = b["depth"]
        channels["motion.X"] = np.full((H, W), -1.0 if i else 0.0, np.float32)
        channels["motion.Y"] = np.zeros((H, W), np.float32)
        frames.append(write_exr(channels))
    return frames


def client(url: str):
    from quietframe.client import Client
    from quietframe.client.core import RetryPolicy

    # The farm's client as shipped: retries 5xx and connection errors with backoff.
    return Client(url, timeout_s=60, retry=RetryPolicy(retries=8, backoff_s=0.3,
                                                       max_backoff_s=2))


def holder(url: str, sid: str) -> str:
    """The replica the load balancer sends this session to (HAProxy's response header)."""
    import httpx

    r = httpx.get(f"{url}/v1/sessions/{sid}", timeout=10)
    assert r.status_code == 200, r.text
    return r.headers["x-quietframe-replica"]


def test_kill_9_a_replica_mid_sequence_then_it_rejoins(cluster):
    started = time.monotonic()
    shots = {"a": sequence(1), "b": sequence(2)}
    with client(cluster.url) as qf:
        # The uninterrupted run: both shots, start to end, before anything is killed.
        reference = {}
        for name, frames in shots.items():
            sid = qf.create_session(W, H, model="nbg-2l-3g")["id"]
            reference[name] = [qf.send_frame(sid, i, f).exr for i, f in enumerate(frames)]
        # The run that loses a replica.
        sids = {name: qf.create_session(W, H, model="nbg-2l-3g")["id"] for name in shots}
        out: dict[str, list[bytes]] = {name: [] for name in shots}

        def send(name: str, index: int):
            result = qf.send_frame(sids[name], index, shots[name][index])
            out[name].append(result.exr)
            return result

        for i in range(KILL_AFTER):
            for name in shots:
                send(name, i)
        victim = holder(cluster.url, sids["a"])
        survivor = next(n for n in cluster.ports if n != victim)
        cluster.kill(victim)

        # A retry of the last frame (the farm did not get the reply, say): the survivor loads
        # the session from the store and answers with the stored reply, byte for byte.
        retried = qf.send_frame(sids["a"], KILL_AFTER - 1, shots["a"][KILL_AFTER - 1])
        assert retried.replayed and retried.exr == out["a"][-1]
        assert holder(cluster.url, sids["a"]) == survivor
        for i in range(KILL_AFTER, REJOIN_AT):
            for name in shots:
                result = send(name, i)
                assert result.reset == "none", (name, i, result.reset)

        # The replica comes back (same address, fresh process: it holds nothing in memory).
        cluster.start_replica(victim)
        cluster.wait_replica(victim)
        deadline = time.monotonic() + 20
        while holder(cluster.url, sids["a"]) != victim:  # HAProxy's checks: rise 2 x 1 s
            assert time.monotonic() < deadline, "the restarted replica did not rejoin"
            time.sleep(0.2)
        for i in range(REJOIN_AT, FRAMES):
            for name in shots:
                result = send(name, i)
                assert result.reset == "none", (name, i, result.reset)
        assert holder(cluster.url, sids["a"]) == victim

        for name in shots:
            status = qf.session(sids[name])
            assert status["frames_done"] == FRAMES and status["resets"] == 1  # the first frame
            assert len(out[name]) == FRAMES
            for i, (got, want) in enumerate(zip(out[name], reference[name], strict=True)):
                assert got == want, f"shot {name} frame {i} differs from the uninterrupted run"
    print(f"\nfailover test: {time.monotonic() - started:.1f} s (killed {victim}, "
          f"survivor {survivor})")


def test_two_replicas_never_both_advance_one_session(cluster):
    """Fencing: a replica holding a stale copy (the session moved on elsewhere) cannot commit
    over its successor; it reloads the session instead. Frames sent straight to each replica,
    past the load balancer, as a split-brain would."""
    import httpx

    from quietframe.service.state_store_redis import RedisStore

    frames = sequence(3)
    urls = [cluster.replica_url(n) for n in sorted(cluster.ports)]
    with httpx.Client(timeout=60) as http:
        sid = http.post(f"{urls[0]}/v1/sessions", json={"width": W, "height": H,
                                                          "model": "nbg-2l-3g"}).json()["id"]
        post = lambda url, i: http.post(  # noqa: E731
            f"{url}/v1/sessions/{sid}/frames/{i}", content=frames[i],
            headers={"content-type": "image/x-exr"})
        assert post(urls[0], 0).status_code == 200
        assert post(urls[1], 1).status_code == 200  # r2 loads frame 0's state from the store
        r = post(urls[0], 2)  # r1's copy is at frame 0: it must follow the store, not fork
        assert r.status_code == 200 and r.headers["x-quietframe-reset"] == "none"
        again = post(urls[1], 2)  # r2 last saw frame 1: now a retry, answered from the store
        assert again.status_code == 200 and again.headers["x-quietframe-replayed"] == "true"
        assert again.content == r.content
    store = RedisStore(f"redis://127.0.0.1:{cluster.redis_port}/0", 60, 5)
    version = store.version(sid)
    assert version.startswith("4-")  # creation + three frames: nothing committed twice
    # The compare-and-set itself: a writer holding an older token is fenced out, and so is one
    # holding the right count with another token (a write a restarted Redis lost).
    from quietframe.service.state_store_redis import SessionMoved

    meta = store.find(sid)[0]
    for stale in ("3-" + "0" * 16, "4-" + "0" * 16):
        with pytest.raises(SessionMoved):
            store.write(meta, None, None, expect=stale)
    assert store.version(sid) == version


def test_store_outage_refuses_frames_then_continues(cluster):
    """redis-server killed: a frame gets 503 state_store_unavailable and the session is not
    changed; restarted (append-only file, fsync always), the sequence continues without a
    reset."""
    import httpx

    frames = sequence(4)
    url = cluster.url
    with httpx.Client(timeout=60) as http:
        sid = http.post(f"{url}/v1/sessions", json={"width": W, "height": H,
                                                     "model": "nbg-2l-3g"}).json()["id"]
        post = lambda i: http.post(  # noqa: E731
            f"{url}/v1/sessions/{sid}/frames/{i}", content=frames[i],
            headers={"content-type": "image/x-exr"})
        assert post(0).status_code == 200
        cluster.kill("redis")
        r = post(1)
        assert r.status_code == 503 and r.json()["error"] == "state_store_unavailable", r.text
        assert r.headers.get("retry-after")
        cluster.start_redis()
        r = post(1)
        assert r.status_code == 200 and r.headers["x-quietframe-reset"] == "none", r.text
