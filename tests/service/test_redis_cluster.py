"""Sessions in a Redis Cluster (`QUIETFRAME_STORE_URL=redis+cluster://seed:port`): three
primaries with one replica each, on loopback in a temp folder. Sessions spread over the
primaries (one hash tag per session: its keys share a slot), frames run through two in-process
replicas of the service, and a failover of a primary to its replica loses no acknowledged frame:
the sequence goes on with no reset, bit-identical to an uninterrupted run. Cluster errors that
mean "retry later" are 503 `state_store_unavailable`.

Skipped where redis-server or redis-cli is not installed (.ci/run installs both).
"""

from __future__ import annotations

import random
import shutil
import socket
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import hard_timeout, shot

from quietframe.bench.replicas import stop_processes

HARD_TIMEOUT_S = 90
NODES = 6  # 3 primaries, each with one replica
SESSIONS = 12
FRAMES, FAILOVER_AFTER = 6, 4
SIZE = {"width": 64, "height": 48}
EXR = {"content-type": "image/x-exr"}

pytestmark = pytest.mark.skipif(
    not (shutil.which("redis-server") and shutil.which("redis-cli")),
    reason="needs redis-server and redis-cli (Debian package redis-server; .ci/run installs it)",
)


@pytest.fixture(autouse=True)
def time_limit():
    with hard_timeout(HARD_TIMEOUT_S):
        yield


def wait_until(check: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        assert time.monotonic() < deadline, f"{what}: not after {timeout_s:g} s"
        time.sleep(0.05)


def port_pair_free(port: int) -> bool:
    """A node listens on `port` and on its cluster bus, `port` + 10000."""
    for p in (port, port + 10000):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", p))
            except OSError:
                return False
    return True


def cluster_ports(n: int) -> list[int]:
    ports: list[int] = []
    while len(ports) < n:
        port = random.randrange(20000, 40000)
        if port not in ports and port_pair_free(port):
            ports.append(port)
    return ports


class LoopbackCluster:
    """`redis-server --cluster-enabled yes` x 6, joined by `redis-cli --cluster create`."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.ports = cluster_ports(NODES)
        self.procs: dict[int, subprocess.Popen] = {}

    def start(self) -> None:
        for port in self.ports:
            self.start_node(port)
        wait_until(lambda: all(self.answers(p) for p in self.ports), 10, "redis-server nodes")
        self.cli(self.ports[0], "--cluster", "create",
                 *(f"127.0.0.1:{p}" for p in self.ports),
                 "--cluster-replicas", "1", "--cluster-yes")
        wait_until(self.settled, 20, "cluster state ok with every replica in sync")

    def start_node(self, port: int) -> None:
        folder = self.folder / str(port)
        folder.mkdir(exist_ok=True)
        self.procs[port] = subprocess.Popen(
            ["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--dir", str(folder),
             "--cluster-enabled", "yes", "--cluster-config-file", "nodes.conf",
             "--cluster-node-timeout", "1000", "--appendonly", "yes", "--save", ""],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=folder,
        )

    def cli(self, port: int, *args: str) -> str:
        return subprocess.run(["redis-cli", "-p", str(port), *args], capture_output=True,
                              text=True, timeout=30, check=True).stdout

    def answers(self, port: int) -> bool:
        try:
            return self.cli(port, "ping").strip() == "PONG"
        except subprocess.CalledProcessError:
            return False

    def info(self, port: int, *command: str) -> dict[str, str]:
        lines = self.cli(port, *command).splitlines()
        return dict(line.strip().split(":", 1) for line in lines if ":" in line)

    def settled(self) -> bool:
        """Every node sees the cluster ok, and every replica is linked to its primary."""
        for port in self.ports:
            if self.info(port, "cluster", "info").get("cluster_state") != "ok":
                return False
            replication = self.info(port, "info", "replication")
            if replication["role"] == "slave" and replication["master_link_status"] != "up":
                return False
        return sum(self.info(p, "info", "replication")["role"] == "master"
                   for p in self.ports) == NODES // 2

    def replica_of(self, primary: int) -> int:
        return next(p for p in self.ports
                    if self.info(p, "info", "replication").get("master_port") == str(primary))

    def close(self) -> None:
        stop_processes(self.procs.values())


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    nodes = LoopbackCluster(tmp_path_factory.mktemp("redis-cluster"))
    try:
        nodes.start()
        yield nodes
    finally:
        nodes.close()


@pytest.fixture(scope="module")
def store_url(cluster) -> str:
    return f"redis+cluster://127.0.0.1:{cluster.ports[0]}"


@pytest.fixture(scope="module")
def replicas(store_url):
    """Two in-process replicas sharing the cluster, as behind the load balancer."""
    from conftest import service_settings
    from fastapi.testclient import TestClient

    from quietframe.service.main import create_app

    pair = [TestClient(create_app(service_settings(replica_id=name, store_url=store_url)),
                       raise_server_exceptions=False) for name in ("a", "b")]
    for client in pair:
        client.__enter__()
    yield pair
    for client in pair:
        client.__exit__(None, None, None)


def direct(cluster):
    """A cluster client of the test's own, to look at where keys live."""
    from redis.cluster import RedisCluster

    return RedisCluster(host="127.0.0.1", port=cluster.ports[0], socket_timeout=5)


def new_session(client) -> str:
    r = client.post("/v1/sessions", json={**SIZE, "model": "nbg-2l-3g"})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def send(client, sid: str, index: int, body: bytes, retries: int = 20):
    """A frame, retried on 503 as the farm's client does (a failover settling)."""
    for _ in range(retries):
        r = client.post(f"/v1/sessions/{sid}/frames/{index}", content=body, headers=EXR)
        if r.status_code != 503:
            return r
        time.sleep(0.2)
    return r


def test_sessions_spread_over_the_primaries(cluster, replicas):
    a, _ = replicas
    frames = shot(1)
    sids = [new_session(a) for _ in range(SESSIONS)]
    for sid in sids:
        r = send(a, sid, 0, frames[0])
        assert r.status_code == 200, r.text
    rc = direct(cluster)
    primaries = set()
    for sid in sids:
        spec, ver, data = (f"qf:{{{sid}}}:{name}" for name in ("spec", "ver", "data"))
        slots = {rc.keyslot(key) for key in (spec, ver, data)}
        assert len(slots) == 1, f"session {sid}'s keys span slots {slots}"
        primaries.add(rc.get_node_from_key(ver).name)
    assert len(primaries) >= 2, f"12 sessions all on {primaries}"
    # SCAN over every primary finds each session's three keys
    found = {key.decode() for key in rc.scan_iter(match="qf:*", count=1000)}
    assert {f"qf:{{{sid}}}:ver" for sid in sids} <= found
    assert sum(key.startswith(tuple(f"qf:{{{sid}}}" for sid in sids)) for key in found) == 36


def test_a_primary_fails_over_and_no_acknowledged_frame_is_lost(cluster, replicas):
    """Frames 0-3 on replica a; the primary holding the session hands over to its replica
    (CLUSTER FAILOVER); the store's record shows all four frames, and frames 4-5 (one on each
    service replica, b loading the state from the new primary) continue with no reset,
    bit-identical to a run without the failover."""
    a, b = replicas
    frames = shot(FRAMES)
    reference_sid = new_session(a)
    reference = [send(a, reference_sid, i, f).content for i, f in enumerate(frames)]

    sid = new_session(a)
    for i in range(FAILOVER_AFTER):
        r = send(a, sid, i, frames[i])
        assert r.status_code == 200 and r.content == reference[i], r.text
    rc = direct(cluster)
    primary = rc.get_node_from_key(f"qf:{{{sid}}}:ver").port
    replica = cluster.replica_of(primary)
    started = time.monotonic()
    cluster.cli(replica, "cluster", "failover")
    wait_until(lambda: cluster.info(replica, "info", "replication")["role"] == "master", 15,
               "the replica promoted")
    wait_until(cluster.settled, 15, "the cluster settled after the failover")
    print(f"\nfailover of 127.0.0.1:{primary} to {replica}: {time.monotonic() - started:.1f} s")

    status = b.get(f"/v1/sessions/{sid}")  # b never held it: the store's record
    assert status.status_code == 200, status.text
    assert status.json()["last_index"] == FAILOVER_AFTER - 1
    assert status.json()["frames_done"] == FAILOVER_AFTER
    r = send(a, sid, FAILOVER_AFTER, frames[FAILOVER_AFTER])
    assert r.status_code == 200, r.text
    assert r.headers["x-quietframe-reset"] == "none" and r.content == reference[FAILOVER_AFTER]
    r = send(b, sid, FAILOVER_AFTER + 1, frames[FAILOVER_AFTER + 1])  # b loads the state
    assert r.status_code == 200, r.text
    assert r.headers["x-quietframe-reset"] == "none" and r.content == reference[-1]
    after = direct(cluster)  # a fresh client: the new slot map
    assert after.get_node_from_key(f"qf:{{{sid}}}:ver").port == replica
    version = after.get(f"qf:{{{sid}}}:ver").decode()
    assert version.startswith(f"{FRAMES + 1}-")  # creation + six frames, none twice


def test_quarantine_stays_in_the_sessions_slot(cluster, store_url):
    """A damaged record is renamed aside; a cluster renames only within one slot."""
    from quietframe.service.state_store_redis import RedisStore

    store = RedisStore(store_url, ttl_s=60, timeout_s=5)
    sid = "q" * 22
    store.write_spec({"id": sid, "model": "nbg-2l-3g"})
    store.write({"id": sid, "model": "nbg-2l-3g"}, None, None, "")
    aside = store.quarantine(sid)
    assert aside is not None and aside.startswith(f"qf:{{{sid}}}:quarantine:")
    rc = direct(cluster)
    assert rc.exists(aside) and not rc.exists(f"qf:{{{sid}}}:data")
    assert store.version(sid).startswith("1-")  # fencing intact
    store.delete(sid)
    rc.delete(aside)


def test_an_unreachable_cluster_is_503_not_a_failed_start():
    """The cluster client is built on first use: a replica starts while the cluster is down,
    and every store call is StoreUnavailable until it is up."""
    from quietframe.service.state_store_redis import RedisStore, StoreUnavailable

    closed = cluster_ports(1)[0]
    store = RedisStore(f"redis+cluster://127.0.0.1:{closed}", ttl_s=60, timeout_s=1)
    with pytest.raises(StoreUnavailable, match="did not answer"):
        store.version("u" * 22)


def test_cluster_urls_and_errors_that_mean_retry_later():
    from redis.exceptions import AskError, MovedError, ResponseError, TryAgainError

    from quietframe.service.state_store_redis import cluster_seed, refuses_for_now

    assert cluster_seed("redis+cluster://10.0.0.5:7000") == "redis://10.0.0.5:7000"
    assert cluster_seed("rediss+cluster://u:p@h:7000/0") == "rediss://u:p@h:7000/0"
    assert cluster_seed("redis://h:6379/0") is None
    with pytest.raises(ValueError, match="database 0"):
        cluster_seed("redis+cluster://h:7000/3")
    assert refuses_for_now(MovedError("3999 127.0.0.1:7001"))
    assert refuses_for_now(AskError("3999 127.0.0.1:7001"))
    assert refuses_for_now(TryAgainError("TRYAGAIN Multiple keys request during rehashing"))
    assert not refuses_for_now(ResponseError("CROSSSLOT Keys in request don't hash to the same"))


class WatchLost:
    """A transaction whose WATCH ends with an error: its connection dropped (`cause`, as a
    cluster's slot moving or its node lost ends it), or none (the key changed)."""

    def __init__(self, cause: Exception | None) -> None:
        self.cause = cause

    def __enter__(self) -> WatchLost:
        return self

    def __exit__(self, *_) -> None:
        pass

    def watch(self, *_) -> None:
        import redis

        if self.cause is None:
            raise redis.WatchError("Watched variable changed.")
        raise redis.WatchError("An error occurred while watching keys") from self.cause


@pytest.mark.parametrize(("cause", "code"), [
    (None, "session_moved"),
    (ConnectionResetError("lost"), "state_store_unavailable"),
])
def test_a_watch_lost_with_its_connection_is_unavailable_not_moved(cause, code):
    """Only another replica's write is SessionMoved (this replica drops its copy); a watch lost
    with its connection or slot is the store failing for now (503, the copy kept)."""
    from types import SimpleNamespace

    from quietframe.service.errors import ServiceError
    from quietframe.service.state_store_redis import RedisStore

    store = RedisStore("redis+cluster://127.0.0.1:1", ttl_s=60, timeout_s=1)
    store._client = SimpleNamespace(pipeline=lambda transaction: WatchLost(cause))
    with pytest.raises(ServiceError) as refused:
        store.write({"id": "w" * 22, "model": "nbg-2l-3g"}, None, None, "")
    assert refused.value.code == code
