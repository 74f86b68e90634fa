"""The sessions a server holds and what they may keep: the table (least recently used first),
the history budget (eviction of durable sessions' state to the store, then refusal), expiry,
and the gauges. Runs on the event loop thread; the layers above it store sessions
(service/session_durability.py) and run their frames (service/sessions.py)."""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import OrderedDict
from concurrent.futures import Executor

from quietframe.service.admission import MemoryBudget
from quietframe.service.choice_policy import Choice
from quietframe.service.errors import MemoryBudgetExceeded, SessionNotFound
from quietframe.service.metrics import Metrics
from quietframe.service.model_registry import ModelRegistry
from quietframe.service.session import Session, reserve_bytes
from quietframe.service.session_spec import SessionSpec
from quietframe.service.settings import Settings
from quietframe.service.stores import open_store

log = logging.getLogger("quietframe.service")


class SessionTable:
    def __init__(
        self, settings: Settings, models: ModelRegistry, metrics: Metrics, pool: Executor
    ) -> None:
        self.settings, self.models, self.metrics, self.pool = settings, models, metrics, pool
        self.sessions: OrderedDict[str, Session] = OrderedDict()  # least recently used first
        # frames in flight (admission.py), beside the history budget of what sessions keep
        self.admission = MemoryBudget(
            settings.memory_budget_bytes, settings.admission_wait_s, settings.max_uploads
        )
        self.store = open_store(settings)

    def _session(
        self, session_id: str, spec: SessionSpec, choice: Choice | None = None, **progress
    ) -> Session:
        """The one constructor, for a new session and for one restored from disk. An auto
        session counts as the default model until its first frame chooses."""
        model = choice.model if choice else spec.model
        info = self.models.denoiser(self.models.resolve(model)).info
        return Session(
            choice=choice,
            id=session_id,
            spec=spec,
            info=info,
            reserve_bytes=reserve_bytes(info, spec),
            durable=self.store is not None,
            **progress,
        )

    def _not_found(self, session_id: str) -> SessionNotFound:
        return SessionNotFound(
            f"no session {session_id!r} (expired after {self.settings.session_ttl_s:g} s idle, "
            "deleted, or never created)"
        )

    def reserved_bytes(self) -> int:
        return sum(s.reserve_bytes for s in self.sessions.values() if s.resident)

    def _retry_after(self) -> str:
        now, ttl = time.monotonic(), self.settings.session_ttl_s
        idle = [ttl - (now - s.last_used) for s in self.sessions.values() if not s.lock.locked()]
        return str(max(1, math.ceil(min(idle, default=ttl))))

    def expire(self) -> list[str]:
        """Delete sessions idle for longer than the TTL (not those with a frame in flight)."""
        now, ttl = time.monotonic(), self.settings.session_ttl_s
        expired = [
            s for s in self.sessions.values() if now - s.last_used > ttl and not s.lock.locked()
        ]
        for session in expired:
            self._remove(session, "expired")
        return [s.id for s in expired]

    def _make_room(self, need: int, keep: Session | None = None) -> None:
        """Fit `need` more bytes in the history budget; durable sessions can be evicted to disk
        (LRU first), in-memory ones cannot."""
        budget = self.settings.history_budget_bytes
        for other in list(self.sessions.values()):
            if self.reserved_bytes() + need <= budget:
                return
            if other is not keep and other.durable and other.resident and not other.lock.locked():
                other.state, other.reply, other.resident = None, None, False
                log.info("evicted session state to disk", extra={"session": other.id})
        if self.reserved_bytes() + need > budget:
            raise MemoryBudgetExceeded(
                f"the history budget of {self.settings.history_budget_mb:g} MiB is in use "
                f"({self.reserved_bytes() / 2**20:.0f} MiB reserved, this session needs "
                f"{need / 2**20:.1f} MiB); retry later or delete finished sessions",
                headers={"Retry-After": self._retry_after()},
            )

    def _remove(self, session: Session, reason: str) -> None:
        """Forget the session now; its files (durable) are deleted on the worker pool, off the
        event loop (DELETE waits for that, expiry does not)."""
        session.closed = True
        session.state, session.reply = None, None
        self.sessions.pop(session.id, None)
        if self.store is not None and reason != "deleted" and not self.store.shared:
            # (a shared store forgets idle sessions itself: another replica may hold this one)
            self.pool.submit(self.store.delete, session.id)
        self.metrics.sessions_closed.labels(reason).inc()
        self._update_gauges()
        log.info("session closed", extra={"session": session.id, "reason": reason})

    def _update_gauges(self) -> None:
        self.metrics.sessions.set(len(self.sessions))
        self.metrics.history_bytes.set(sum(s.memory_bytes() for s in self.sessions.values()))

    async def _on_pool(self, fn, *args):
        return await asyncio.get_running_loop().run_in_executor(self.pool, fn, *args)
