"""The sessions a server holds in memory and what they may keep: the table (least recently used
first), the history budget (eviction of durable sessions' state, then refusal), expiry, and the
gauges. Runs on the event loop thread and touches no store: the registry (service/sessions.py)
has a durable session's files deleted (service/session_durability.py)."""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict

from quietframe.service.choice_policy import Choice
from quietframe.service.errors import MemoryBudgetExceeded, SessionNotFound
from quietframe.service.metrics import Metrics
from quietframe.service.model_registry import ModelRegistry
from quietframe.service.session import Session, reserve_bytes
from quietframe.service.session_spec import SessionSpec
from quietframe.service.settings import Settings

log = logging.getLogger("quietframe.service")


class SessionTable:
    """`durable`: the server has a store, so its sessions' state may leave memory (evicted, or
    not loaded yet) and be read back before their next frame."""

    def __init__(
        self, settings: Settings, models: ModelRegistry, metrics: Metrics, durable: bool
    ) -> None:
        self._settings, self._models, self._metrics = settings, models, metrics
        self.durable = durable
        # least recently used first; read it freely, change it through the methods below
        self.sessions: OrderedDict[str, Session] = OrderedDict()

    def __len__(self) -> int:
        return len(self.sessions)

    def find(self, session_id: str) -> Session | None:
        return self.sessions.get(session_id)

    def build(
        self, session_id: str, spec: SessionSpec, choice: Choice | None = None, **progress
    ) -> Session:
        """The one constructor, for a new session and for one restored from a store. An auto
        session counts as the default model until its first frame chooses."""
        model = choice.model if choice else spec.model
        info = self._models.denoiser(self._models.resolve(model)).info
        return Session(
            choice=choice,
            id=session_id,
            spec=spec,
            info=info,
            reserve_bytes=reserve_bytes(info, spec),
            durable=self.durable,
            **progress,
        )

    def add(self, session: Session) -> None:
        self.sessions[session.id] = session

    def touch(self, session: Session) -> None:
        """Count as use: most recently used, and its TTL starts again."""
        session.last_used = time.monotonic()
        self.sessions.move_to_end(session.id)

    def not_found(self, session_id: str) -> SessionNotFound:
        return SessionNotFound(
            f"no session {session_id!r} (expired after {self._settings.session_ttl_s:g} s idle, "
            "deleted, or never created)"
        )

    def reserved_bytes(self) -> int:
        """The history budget in use: resident sessions' state and reply reservations, and
        what every session's stream keeps between frames (OIDN's filters)."""
        return sum((s.reserve_bytes if s.resident else 0) + s.kept_bytes
                   for s in self.sessions.values())

    def retry_after(self) -> str:
        """Seconds until the first idle session expires (a Retry-After header)."""
        now, ttl = time.monotonic(), self._settings.session_ttl_s
        idle = [ttl - (now - s.last_used) for s in self.sessions.values() if not s.lock.locked()]
        return str(max(1, math.ceil(min(idle, default=ttl))))

    def expire(self) -> list[Session]:
        """Remove sessions idle for longer than the TTL (not those with a frame in flight)."""
        now, ttl = time.monotonic(), self._settings.session_ttl_s
        expired = [
            s for s in self.sessions.values() if now - s.last_used > ttl and not s.lock.locked()
        ]
        for session in expired:
            self.remove(session, "expired")
        return expired

    def _release_kept(self, need: int, keep: Session | None) -> None:
        """Let idle sessions' streams go of what they keep (LRU first) until `need` more bytes
        fit: it costs their next frame a rebuild, nothing else."""
        budget = self._settings.history_budget_bytes
        for other in list(self.sessions.values()):
            if self.reserved_bytes() + need <= budget:
                return
            if other is not keep and other.kept_bytes and not other.lock.locked():
                assert other.stream is not None
                other.stream.release()

    def fit_kept(self, session: Session) -> None:
        """After `session`'s frame: what its stream now keeps must fit in the history budget
        beside the others'; other idle streams let go first, then its own."""
        if self.reserved_bytes() > self._settings.history_budget_bytes:
            self._release_kept(0, session)
        if self.reserved_bytes() > self._settings.history_budget_bytes and session.stream:
            session.stream.release()

    def make_room(self, need: int, keep: Session | None = None) -> None:
        """Fit `need` more bytes in the history budget: idle streams let go of their OIDN
        filters first, then durable sessions' state is evicted to disk (LRU first); in-memory
        sessions' state cannot be."""
        budget = self._settings.history_budget_bytes
        self._release_kept(need, keep)
        for other in list(self.sessions.values()):
            if self.reserved_bytes() + need <= budget:
                return
            if other is not keep and other.durable and other.resident and not other.lock.locked():
                other.state, other.reply, other.resident = None, None, False
                log.info("evicted session state to disk", extra={"session": other.id})
        if self.reserved_bytes() + need > budget:
            raise MemoryBudgetExceeded(
                f"the history budget of {self._settings.history_budget_mb:g} MiB is in use "
                f"({self.reserved_bytes() / 2**20:.0f} MiB reserved, this session needs "
                f"{need / 2**20:.1f} MiB); retry later or delete finished sessions",
                headers={"Retry-After": self.retry_after()},
            )

    def remove(self, session: Session, reason: str) -> None:
        """Forget the session now (its stored files are the registry's to delete)."""
        session.closed = True
        session.state, session.reply = None, None
        session.close_stream()
        self.sessions.pop(session.id, None)
        self._metrics.sessions_closed.labels(reason).inc()
        self.update_gauges()
        log.info("session closed", extra={"session": session.id, "reason": reason})

    def update_gauges(self) -> None:
        self._metrics.sessions.set(len(self.sessions))
        self._metrics.history_bytes.set(sum(s.memory_bytes() for s in self.sessions.values()))
