"""Sessions in Redis, shared by every replica behind the load balancer (docs/deployment.md).

One session is three keys with one hash tag, so a Redis Cluster keeps them in one slot and a
transaction may span them:
- `qf:{id}:spec` — the settings at creation (JSON), as `<id>.json` on disk;
- `qf:{id}:ver`  — the version, the fencing token: `<n>-<random>`, n = 1 at creation, +1 per
  committed frame; the random part makes every write's token unique, so a Redis that lost its
  last writes (restarted from an older file) never hands out a token a replica already holds;
- `qf:{id}:data` — a hash: `meta` (JSON: progress, reply identity, the state's layout, manifest
  of lengths), one field per stored plane of the state (`state.plane<i>`: state_codec's compact
  form, as on disk) and, unless the meta holds the reply's recipe, `reply` (the reply's bytes).
  A record of the earlier form (`state.<name>` raw float32 tensors) still loads.

A write is a compare-and-set on the version (WATCH / MULTI / EXEC): it succeeds only when the
stored version is the one the writing replica loaded, so after a failover the replica that lost
the session cannot overwrite what its successor committed; it gets SessionMoved and reloads.
Reads of the version and the data are one transaction, so a reader never sees a half-written
session. Every write renews the keys' expiry (the session TTL): Redis, not a replica, forgets
abandoned sessions, so a replica that drops its copy of an idle session never deletes it under
another replica's feet.

`redis+cluster://host:port` (or `rediss+cluster://`) names a seed node of a Redis Cluster: every
command above touches one session's keys only, so each runs on the primary of that session's
slot, transactions included; nothing lists or scans keys. The cluster client redirects itself
while slots move or a replica takes over (MOVED, ASK); what it cannot ride out is a 503.
"""

from __future__ import annotations

import contextlib
import json
import secrets
import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping, MutableMapping
from dataclasses import dataclass

import numpy as np
import redis
from redis.cluster import RedisCluster
from redis.connection import parse_url
from redis.exceptions import (
    AskError,
    ClusterDownError,
    ClusterError,
    OutOfMemoryError,
    ReadOnlyError,
    RedisClusterUnreachableError,
    SlotNotCoveredError,
    TryAgainError,
)

from quietframe.service.errors import ServiceError, StoreUnavailable
from quietframe.service.session_store import (
    Reply,
    StateDamaged,
    checked_session_id,
    record,
    unpack,
)
from quietframe.service.stored_record import parse_meta

QUARANTINE_S = 7 * 86400  # a damaged record is kept this long for a look

# Error replies of a Redis that answers but cannot take a write for now, as when it is down:
# full (maxmemory with noeviction: "OOM command not allowed"), a read-only replica (a failover
# under way), a master or cluster slot down (MASTERDOWN, CLUSTERDOWN), a slot moving (TRYAGAIN),
# a slot elsewhere (MOVED, ASK: the cluster client follows them; one reaches here only when its
# redirections ran out, as while a failover settles).
# Every other error reply (WRONGTYPE, a syntax error, NOPERM) is a bug or a misconfiguration
# that no retry mends: it stays a 500.
REFUSALS_FOR_NOW = (OutOfMemoryError, ReadOnlyError, ClusterDownError, TryAgainError, AskError)
# Snapshots failing (stop-writes-on-bgsave-error, e.g. a full disk); no exception class of its own.
MISCONF = "MISCONF"
# A store that does not answer: a server down or slow, and for a cluster no node reachable, a
# slot that no known node serves yet, or redirections and retries run out (ClusterError).
UNANSWERED = (
    redis.ConnectionError,
    redis.TimeoutError,
    ClusterError,
    RedisClusterUnreachableError,
    SlotNotCoveredError,
)
CLUSTER_SCHEMES = {"redis+cluster": "redis", "rediss+cluster": "rediss"}
# redis-py runs a cluster pipeline as MULTI/EXEC, WATCH included, from 6.1 on; before, it
# refused transaction=True in cluster mode: every frame would be a 500.
CLUSTER_TRANSACTIONS = (6, 1)


class SessionMoved(ServiceError):
    """Another replica advanced this session since this one loaded it (a failover): this
    replica reloads it; the client's retry then continues the sequence (or gets the reply)."""

    status, code = 503, "session_moved"


@dataclass
class Loaded:
    """A session as stored: `meta` None when only its settings survive (state lost)."""

    meta: dict | None
    state: dict[str, np.ndarray] | None
    reply: Reply | None
    version: str
    damage: str | None = None  # why the stored state could not be used


class RedisStore:
    shared = True

    def __init__(
        self, url: str, ttl_s: float, timeout_s: float, replica: str | None = None
    ) -> None:
        options = {"socket_timeout": timeout_s, "socket_connect_timeout": min(timeout_s, 2.0)}
        seed = cluster_seed(url)
        self._client: redis.Redis | RedisCluster | None = None
        self._connect: Callable[[], redis.Redis | RedisCluster]
        if seed is None:
            self._client = redis.Redis.from_url(url, **options)  # connects on its first command
        else:  # asks the seed for the cluster's nodes when built: on first use, not at start-up
            self._connect = lambda: RedisCluster.from_url(seed, **options)
        self._connecting = threading.Lock()
        self.ttl_ms = int(ttl_s * 1000)
        self.replica = replica or socket.gethostname()

    @property
    def redis(self) -> redis.Redis | RedisCluster:
        """The client; a cluster's is built on first use (inside `_answering`), so a replica
        starts, and answers 503, while the cluster is not up yet."""
        if self._client is None:
            with self._connecting:
                if self._client is None:
                    self._client = self._connect()
        return self._client

    @staticmethod
    def keys(session_id: str) -> tuple[str, str, str]:
        tag = f"qf:{{{checked_session_id(session_id)}}}"
        return f"{tag}:spec", f"{tag}:ver", f"{tag}:data"

    @contextlib.contextmanager
    def _answering(self) -> Iterator[None]:
        try:
            yield
        except redis.ResponseError as exc:  # first: CLUSTERDOWN is a ClusterError too
            if not refuses_for_now(exc):
                raise
            raise _unavailable(f"refused the write for now ({type(exc).__name__}: {exc})") from exc
        except UNANSWERED as exc:
            raise _unavailable(f"did not answer ({type(exc).__name__})") from exc

    # ---- settings ----------------------------------------------------------------------------

    def write_spec(self, meta: Mapping) -> None:
        spec, _, _ = self.keys(meta["id"])
        with self._answering():
            self.redis.set(spec, json.dumps(dict(meta)), px=self.ttl_ms)

    def read_spec(self, session_id: str) -> dict | None:
        spec, _, _ = self.keys(session_id)
        with self._answering():
            raw = self.redis.get(spec)
        return _json_record(raw, session_id, progress=False)

    def find(self, session_id: str) -> tuple[dict, bool] | None:
        """(meta, state lost) of a session this replica does not hold, or None (no such one):
        its progress when its data is stored, else its settings alone."""
        spec, ver, data = self.keys(session_id)
        with self._answering():
            version, meta, settings = (
                self.redis.pipeline(transaction=True)
                .get(ver).hget(data, "meta").get(spec).execute()
            )
        if version is None:
            return None
        found = _json_record(meta, session_id, progress=True)
        if found is not None:
            return found, False
        settings = _json_record(settings, session_id, progress=False)
        return (settings, True) if settings is not None else None

    # ---- state -------------------------------------------------------------------------------

    def version(self, session_id: str) -> str | None:
        _, ver, _ = self.keys(session_id)
        with self._answering():
            raw = self.redis.get(ver)
        return None if raw is None else raw.decode()

    def write(
        self,
        meta: Mapping,
        state: MutableMapping[str, np.ndarray] | None,
        reply: Reply | None,
        expect: str | None = None,
    ) -> str:
        """Store the session as `meta`/`state`/`reply` if its version is still `expect`
        ("" or None: a new session); returns the new version. SessionMoved otherwise."""
        spec, ver, data = self.keys(meta["id"])
        stored, arrays = record(meta, state, reply)
        stored["writer"] = self.replica
        fields: dict[str, bytes | memoryview] = {"meta": json.dumps(stored).encode()}
        for name, array in arrays.items():  # no copy: redis-py sends a memoryview as it is
            fields[name] = memoryview(np.ascontiguousarray(array)).cast("B")
        expect = expect or ""
        with self._answering(), self.redis.pipeline(transaction=True) as pipe:
            try:
                pipe.watch(ver)
                current = pipe.get(ver)
                if (b"" if current is None else current).decode() != expect:
                    raise self._moved(meta["id"], expect, current)
                count = int(expect.split("-")[0]) if expect else 0
                new = f"{count + 1}-{secrets.token_hex(8)}"
                pipe.multi()
                pipe.delete(data)  # a model switch (auto) changes the state's fields
                pipe.hset(data, mapping=fields)  # type: ignore[arg-type]
                pipe.set(ver, new, px=self.ttl_ms)
                pipe.pexpire(data, self.ttl_ms)
                pipe.pexpire(spec, self.ttl_ms)
                pipe.execute()
            except redis.WatchError as exc:
                lost = exc.__cause__ or exc.__context__
                if lost is not None:  # the connection dropped or the slot moved while watching
                    raise _unavailable(f"lost the transaction ({type(lost).__name__})") from exc
                # another replica wrote between our read and our write
                raise self._moved(meta["id"], expect, None) from None
        return new

    def _moved(self, session_id: str, expect: str, current: bytes | None) -> SessionMoved:
        now = "changed" if current is None else f"is {current.decode()}"
        return SessionMoved(
            f"session {session_id} was advanced by another replica (version {now}, this replica "
            f"held {expect}); it reloads the session: retry the frame",
            headers={"Retry-After": "1"},
        )

    def load(
        self, session_id: str, shapes_of: Callable[[dict], Mapping[str, tuple[int, ...]]]
    ) -> Loaded | None:
        """The stored session (one transaction: version and data agree), verified against
        `shapes_of(meta)` (the state's shapes for the model the meta names); None if gone."""
        _, ver, data = self.keys(session_id)
        with self._answering():
            version, fields = (
                self.redis.pipeline(transaction=True).get(ver).hgetall(data).execute()
            )
        if version is None:
            return None
        if not fields:
            return Loaded(None, None, None, version.decode(), "no stored state")
        try:
            meta = parse_meta(fields.pop(b"meta"), session_id)
            arrays = _arrays(meta, fields)
            state, reply = unpack(meta, arrays, session_id, shapes_of(meta))
        except (ValueError, KeyError, TypeError) as exc:
            return Loaded(None, None, None, version.decode(), f"{type(exc).__name__}: {exc}")
        return Loaded(meta, state, reply, version.decode())

    def read(
        self, session_id: str, shapes: Mapping[str, tuple[int, ...]]
    ) -> tuple[dict[str, np.ndarray] | None, Reply | None]:
        loaded = self.load(session_id, lambda _: shapes)
        if loaded is None or loaded.damage is not None:
            raise StateDamaged(loaded.damage if loaded else "no such session")
        return loaded.state, loaded.reply

    def quarantine(self, session_id: str) -> str | None:
        """Move the damaged data aside (kept a week); the version stays, so the session goes on
        from a fresh history and fencing still holds."""
        _, _, data = self.keys(session_id)
        # the session's hash tag: a cluster renames only within one slot
        aside = f"qf:{{{session_id}}}:quarantine:{time.strftime('%Y%m%dT%H%M%S')}"
        with self._answering():
            try:
                self.redis.rename(data, aside)
            except redis.ResponseError:  # no such key
                return None
            self.redis.expire(aside, QUARANTINE_S)
        return aside

    def delete(self, session_id: str) -> None:
        with self._answering():
            self.redis.delete(*self.keys(session_id))


def cluster_seed(url: str) -> str | None:
    """The seed node's plain URL when `url` names a Redis Cluster (redis+cluster://host:port),
    else None. Checked here, at start-up: a cluster has database 0 only."""
    scheme, sep, rest = url.partition("://")
    plain = CLUSTER_SCHEMES.get(scheme.lower()) if sep else None
    if plain is None:
        return None
    seed = f"{plain}://{rest}"
    if parse_url(seed).get("db", 0) != 0:
        raise ValueError(f"a Redis Cluster has database 0 only: {url!r}")
    if _version(redis.__version__) < CLUSTER_TRANSACTIONS:
        raise ValueError(
            f"{url!r}: a Redis Cluster needs redis-py >= 6.1 (transactions on a cluster); "
            f"this is {redis.__version__}"
        )
    return seed


def _version(text: str) -> tuple[int, ...]:
    return tuple(int("".join(c for c in part if c.isdigit()) or 0) for part in text.split(".")[:2])


def refuses_for_now(exc: redis.ResponseError) -> bool:
    """Whether an error reply means the store cannot take writes for now (REFUSALS_FOR_NOW,
    MISCONF), not that the request was wrong."""
    if isinstance(exc, REFUSALS_FOR_NOW):
        return True
    # redis-py keeps the reply's code in `status_code` (5.x: only as the message's first word)
    code = getattr(exc, "status_code", None) or str(exc).split(" ", 1)[0]
    return code == MISCONF


def _unavailable(what: str) -> StoreUnavailable:
    return StoreUnavailable(
        f"the session store {what}; nothing was stored: retry after Retry-After",
        headers={"Retry-After": "1"},
    )


def _json_record(raw: bytes | None, session_id: str, progress: bool) -> dict | None:
    """A stored meta (stored_record.parse_meta), or None where there is none or it is not
    one."""
    try:
        return parse_meta(raw, session_id, progress) if raw is not None else None
    except ValueError:
        return None


def _arrays(meta: dict, fields: dict[bytes, bytes]) -> dict[str, np.ndarray]:
    """The stored members as arrays of the manifest's shapes (bytes; in the earlier form, state
    float32); a member of the wrong length is a ValueError (reshape), as a truncated file is on
    disk."""
    legacy = meta.get("codec") is None
    arrays = {}
    for raw_name, raw in fields.items():
        name = raw_name.decode()
        dtype = np.float32 if legacy and name.startswith("state.") else np.uint8
        shape = meta["manifest"][name]
        arrays[name] = np.frombuffer(raw, dtype).reshape(shape)
    return arrays
