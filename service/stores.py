"""Which session store a server uses: Redis when `store_url` is set (replicas share it;
`redis+cluster://`: a Redis Cluster), else the state folder, else none. Apart from the two
stores so that neither imports the other (service/session_store.py holds the folder store and
the stored form both use, service/state_store_redis.py the Redis one)."""

from __future__ import annotations

from quietframe.service.session_store import SessionStore, Store
from quietframe.service.settings import Settings
from quietframe.service.state_store_redis import RedisStore


def open_store(settings: Settings) -> Store | None:
    """The store the settings name, or None (sessions live in memory only)."""
    if settings.store_url:
        return RedisStore(
            settings.store_url, settings.session_ttl_s, settings.store_timeout_s,
            settings.replica_id,
        )
    if settings.state_dir:
        return SessionStore(settings.state_dir, settings.state_fsync)
    return None
