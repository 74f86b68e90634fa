"""Durable sessions: each session's settings and, after every frame, its record (progress, the
shot's choice), state and last reply go to the store (service/session_store.py: a local folder,
or Redis shared by replicas). A restarted server restores the folder's sessions; a replica
adopts a shared store's sessions on demand and follows the store's version of each (another
replica may have advanced it). Damaged state is quarantined and its session continues from a
fresh history (state-lost). Every store call but the start-up restore runs on the worker pool
(service/worker_pool.py): a store that hangs holds its request (until the store's timeout:
503), never the event loop."""

from __future__ import annotations

import logging

from quietframe.runtime import ModelInfo
from quietframe.runtime.motion_evidence import history_shapes
from quietframe.service import lookahead_queue
from quietframe.service.choice_policy import Choice
from quietframe.service.errors import ServiceError, SessionNotFound
from quietframe.service.model_registry import ModelRegistry
from quietframe.service.session import ProcessedFrame, Session
from quietframe.service.session_spec import SessionSpec, spec_difference
from quietframe.service.session_store import SessionStore, StateDamaged, Store
from quietframe.service.session_table import SessionTable
from quietframe.service.state_store_redis import RedisStore
from quietframe.service.worker_pool import WorkerPool

log = logging.getLogger("quietframe.service")


class SessionDurability:
    """The store behind `table`'s sessions: writes their records, reads their state back into
    the table (making room in its history budget) and registers sessions found in the store."""

    def __init__(
        self, store: Store, models: ModelRegistry, table: SessionTable, pool: WorkerPool
    ) -> None:
        self.store = store
        self._models, self._table, self._pool = models, table, pool

    @property
    def shared(self) -> bool:
        """Replicas share the store (Redis): sessions are adopted from it on demand."""
        return self.store.shared

    @property
    def _redis(self) -> RedisStore:
        assert isinstance(self.store, RedisStore)  # adopting and following: a shared store's
        return self.store

    async def store_new(self, session: Session) -> None:
        """Store a new session: its settings, then its first record. Where the store refuses
        the second write (full, say), what the first wrote is deleted before the error goes
        out: a session the client was refused must not appear later (a restart restores a
        settings file alone as a session)."""
        try:
            await self._pool.write_spec(self.store, session.meta())
            session.store_version = await self._pool.write_record(
                self.store, session.meta(), None, None, ""
            )
        except Exception:
            try:
                await self._pool.delete_session(self.store, session.id)
            except Exception as exc:  # the store is gone too: a Redis key expires by itself
                log.warning("could not delete a session whose creation failed",
                            extra={"session": session.id, "error": repr(exc)})
            raise

    async def persist(self, session: Session, frame: ProcessedFrame) -> None:
        """Store the frame's outcome before it is committed; with a shared store, only if no
        other replica advanced the session meanwhile (fencing: SessionMoved, and this copy is
        reloaded before its next frame)."""
        try:
            version = await self._pool.write_record(
                self.store, session.meta(frame), frame.state, frame.reply, session.store_version
            )
        except ServiceError as exc:
            if exc.code == "session_moved":
                session.state, session.reply, session.resident = None, None, False
                session.store_version = None
            raise
        session.store_version = version

    async def delete(self, session_id: str) -> None:
        await self._pool.delete_session(self.store, session_id)

    def forget(self, sessions: list[Session]) -> None:
        """The files of sessions the table dropped (expired), deleted on the worker pool without
        waiting. A shared store forgets idle sessions itself: another replica may hold one."""
        if not self.store.shared:
            for session in sessions:
                self._pool.delete_session_soon(self.store, session.id)

    async def adopt(self, session_id: str) -> Session | None:
        """A session this replica does not hold, registered from the shared store (its state is
        loaded with its next frame)."""
        found = await self._pool.find_record(self._redis, session_id)
        held = self._table.find(session_id)
        if held is not None:  # another request adopted it while this one waited
            return held
        if found is None:
            return None
        meta, lost = found
        self._restore(session_id, meta, lost)
        session = self._table.find(session_id)
        if session is not None:
            session.store_version = None  # load what the store holds before the next frame
            log.info("session adopted from the store", extra={"session": session_id})
        return session

    async def committed_progress(self, session_id: str) -> dict:
        """Shared store: the Session fields of the store's record of the session (another
        replica may have committed frames since this one's copy was loaded), read without
        loading its state; {} where only its settings survive. SessionNotFound where it is
        gone (expired in the store, or deleted through another replica)."""
        found = await self._pool.find_record(self._redis, session_id)
        if found is None:
            raise SessionNotFound(f"session {session_id!r} is gone (expired or deleted)")
        meta, lost = found
        return {} if lost else self._stored_progress(meta)

    async def ensure_resident(self, session: Session) -> None:
        """The session's state and last reply in memory before its next frame (a retry needs
        the reply), read from the store where they were evicted or not loaded yet."""
        if self.store.shared:
            return await self._follow_store(session)
        if session.resident:
            return
        self._table.make_room(session.reserve_bytes, keep=session)
        if session.state_lost:  # nothing on disk to read: the next frame starts afresh
            session.resident = True
            return
        spec = session.spec
        shapes = history_shapes(session.info.state_specs, spec.height, spec.width)
        shapes |= lookahead_queue.shapes(spec.lookahead, spec.height, spec.width)
        try:
            session.state, session.reply = await self._pool.read_state(
                self.store, session.id, shapes
            )
        except StateDamaged as exc:
            # Continue the sequence from a fresh history, said so in X-Quietframe-Reset; the
            # damaged file is kept aside for a look, never read again.
            aside = await self._pool.quarantine(self.store, session.id)
            log.error(
                "stored session state is damaged; the next frame starts a fresh history",
                extra={"session": session.id, "error": str(exc), "quarantined": str(aside)},
            )
            session.state, session.reply, session.state_lost = None, None, True
            session.pending = []  # held-back frames went with the state
        session.resident = True
        self._table.update_gauges()

    async def _follow_store(self, session: Session) -> None:
        """Shared store: its version is the truth. Another replica may have advanced this session
        since this copy was loaded (a failover, then back): load what it committed."""
        store = self._redis
        version = await self._pool.stored_version(store, session.id)
        if version is None:  # expired in the store, or deleted through another replica
            self._table.remove(session, "gone")
            raise SessionNotFound(f"session {session.id!r} is gone (expired or deleted)")
        if session.resident and version == session.store_version:
            return
        self._table.make_room(session.reserve_bytes, keep=session)
        loaded = await self._pool.load_session(store, session.id, self._shapes_of)
        if loaded is None:
            self._table.remove(session, "gone")
            raise SessionNotFound(f"session {session.id!r} is gone (expired or deleted)")
        if loaded.meta is not None:
            for name, value in self._stored_progress(loaded.meta).items():
                setattr(session, name, value)
        elif loaded.damage != "no stored state":
            aside = await self._pool.quarantine(store, session.id)
            log.error(
                "stored session state is damaged; the next frame starts a fresh history",
                extra={"session": session.id, "error": loaded.damage, "quarantined": aside},
            )
        session.state, session.reply = loaded.state, loaded.reply
        session.state_lost = loaded.meta is None
        if session.state_lost:
            session.pending = []  # held-back frames went with the state
        session.store_version, session.resident = loaded.version, True
        self._table.update_gauges()

    def _stored_progress(self, meta: dict) -> dict:
        """The Session fields a stored record sets: progress, the shot's choice, its model."""
        choice = meta.get("choice")
        return {
            "last_index": meta["last_index"],
            "frames_done": meta["frames_done"],
            "resets": meta["resets"],
            "choice": Choice.from_dict(choice) if choice else None,
            "shot_spp": meta.get("shot_spp"),
            "info": self._info_of(meta),
            "pending": list(meta.get("pending") or []),
        }

    def _info_of(self, meta: dict) -> ModelInfo:
        """The model a stored session uses: its shot's choice (auto), else its model."""
        choice = meta.get("choice")
        name = choice["model"] if choice else self._models.resolve(meta["model"])
        return self._models.denoiser(name).info

    def _shapes_of(self, meta: dict) -> dict[str, tuple[int, ...]]:
        info, (w, h) = self._info_of(meta), (meta["width"], meta["height"])
        return (history_shapes(info.state_specs, h, w)
                | lookahead_queue.shapes(meta.get("lookahead") or 0, h, w))

    def restore_all(self) -> None:
        """A local folder's sessions of an earlier run, registered in the table (state stays on
        disk until their next frame); runs at start-up, before the event loop serves. A damaged
        file is quarantined; its session continues from a fresh history (state-lost) when its
        settings file (written at creation) is intact."""
        store = self.store
        assert isinstance(store, SessionStore)  # a shared store's sessions are adopted on demand
        for path, meta in store.metas():
            lost = "error" in meta  # unreadable, truncated, or another session's file
            settings = None if lost else store.read_spec(path.stem)
            if settings is not None and (difference := spec_difference(meta, settings)):
                # The settings file is the session as created: a state file that says otherwise
                # (another session's, rewritten under this id) is not this session's history.
                lost = True
                meta = {"error": f"its settings differ from the session's settings file: "
                        f"{difference}"}
            if lost:
                aside = store.quarantine_path(path)
                log.error(
                    "stored session file is damaged; moved aside",
                    extra={"file": path.name, "error": meta["error"], "quarantined": str(aside)},
                )
                meta = store.read_spec(path.stem)
                if meta is None:
                    log.error("no settings file either: session %s is gone", path.stem)
                    continue
            self._restore(path.stem, meta, lost)
        for session_id in store.spec_ids():  # settings without a state file
            if self._table.find(session_id) is None and not store.path(session_id).exists():
                meta = store.read_spec(session_id)
                if meta is not None:
                    log.error("session %s has no state file; continues afresh", session_id)
                    self._restore(session_id, meta, lost=True)
        if len(self._table):
            log.info("restored %d sessions from %s", len(self._table), store.folder)

    def _restore(self, session_id: str, meta: dict, lost: bool) -> None:
        try:
            spec = SessionSpec.from_record(meta, self._models.requested(meta["model"]))
            self._models.check_options(spec.model, spec.model_options)  # the models may differ
            choice = Choice.from_dict(meta["choice"]) if meta.get("choice") else None
            if choice is not None and choice.model not in self._models.names:
                choice = None  # its model is gone: the next frame chooses again
        except Exception as exc:  # model no longer installed, or an incomplete meta
            log.warning("skipping stored session %s: %s", session_id, exc)
            return
        progress = {"last_index": None, "frames_done": 0, "resets": 0}
        if not lost:
            progress = {k: meta[k] for k in progress}
            progress["pending"] = list(meta.get("pending") or [])
            progress["shot_spp"] = meta.get("shot_spp")
        session = self._table.build(
            session_id,
            spec,
            choice=choice,
            created_at=meta["created_at"],
            resident=lost,  # a lost session has nothing on disk to load
            state_lost=lost,
            **progress,
        )
        self._table.add(session)
