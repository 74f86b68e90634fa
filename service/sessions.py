"""Per-camera sessions: history state, frame order, idempotent replies, limits, durable state.

The service keeps each session's state tensors without knowing what they mean (DESIGN.md). All
registry bookkeeping runs on the event loop thread; the heavy part of a frame (decode, denoise,
encode, write) runs on the worker pool while the session's lock is held, so the frames of one
session run in order and sessions run in parallel. A frame changes its session only in
`commit`, after everything succeeded: a rejected frame never changes the state.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import re
import secrets
import time
import zlib
from collections import OrderedDict
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from quietframe.runtime import Denoiser
from quietframe.service import frames
from quietframe.service.errors import (
    FrameConflict,
    FrameOutOfOrder,
    MemoryBudgetExceeded,
    SessionNotFound,
    TooManySessions,
)
from quietframe.service.metrics import Metrics
from quietframe.service.model_registry import ModelRegistry
from quietframe.service.schemas import ModelRef, SessionCreate, SessionPublic, StageTimings
from quietframe.service.settings import Settings

log = logging.getLogger("quietframe.service")

SESSION_ID = re.compile(r"^[A-Za-z0-9_-]{22}$")  # secrets.token_urlsafe(16): 128 random bits
STAGES = ("decode", "denoise", "encode", "total")


@dataclass
class Reply:
    """The last frame's response, kept for an idempotent retry of the same index."""

    index: int
    body: bytes
    headers: dict[str, str]
    request_crc: int
    request_len: int


@dataclass
class FrameOutcome:
    reply: Reply
    state: dict[str, np.ndarray]
    reset: str
    sources: dict[str, list[str]]
    missing: list[str]
    sanitized: dict[str, int]
    timings_ms: dict[str, float]


@dataclass
class Session:
    id: str
    model: str
    version: str
    width: int
    height: int
    precision: str
    compression: str
    channels: dict | None
    motion_scale: tuple[float, float]
    required: tuple[str, ...]
    optional: tuple[str, ...]
    reserve_bytes: int
    durable: bool
    created_at: float = field(default_factory=time.time)
    last_used: float = field(default_factory=time.monotonic)
    last_index: int | None = None
    frames_done: int = 0
    resets: int = 0
    state: dict[str, np.ndarray] | None = None
    reply: Reply | None = None
    resident: bool = True  # False: durable state is on disk only (restart or evicted)
    closed: bool = False
    sources: dict[str, list[str]] = field(default_factory=dict)
    missing: list[str] = field(default_factory=list)
    timing_sum: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    timing_last: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    lock: asyncio.Lock = field(default_factory=asyncio.Lock, repr=False)

    def memory_bytes(self) -> int:
        state = sum(a.nbytes for a in self.state.values()) if self.state else 0
        return state + (len(self.reply.body) if self.reply else 0)

    def plan(self, index: int, body: bytes, cut: bool) -> Reply | str:
        """The stored reply for a retry of the last index, else why history resets ("none",
        "first-frame", "gap", "cut"); FrameOutOfOrder / FrameConflict for a refused index."""
        if self.last_index is not None and index == self.last_index:
            reply = self.reply
            if reply and reply.request_len == len(body) and reply.request_crc == zlib.crc32(body):
                return reply
            raise FrameConflict(
                f"frame {index} was already denoised from a different body; send the next index "
                "for a new frame (or create a new session)"
            )
        if self.last_index is not None and index < self.last_index:
            raise FrameOutOfOrder(
                f"frame {index} is older than the last frame {self.last_index} of this session; "
                "indices must increase (a gap is treated as a camera cut)"
            )
        if self.last_index is None:
            return "first-frame"
        if cut:
            return "cut"
        return "gap" if index > self.last_index + 1 else "none"

    def commit(self, outcome: FrameOutcome) -> None:
        self.state = outcome.state
        self.reply = outcome.reply
        self.last_index = outcome.reply.index
        self.frames_done += 1
        self.resets += outcome.reset != "none"
        self.sources, self.missing = outcome.sources, outcome.missing
        for stage in STAGES:
            self.timing_sum[stage] += outcome.timings_ms[stage]
            self.timing_last[stage] = outcome.timings_ms[stage]
        self.last_used = time.monotonic()

    def public(self, ttl_s: float) -> SessionPublic:
        done = max(self.frames_done, 1)
        return SessionPublic(
            id=self.id,
            model=ModelRef(name=self.model, version=self.version),
            width=self.width,
            height=self.height,
            precision=self.precision,  # type: ignore[arg-type]
            compression=self.compression,  # type: ignore[arg-type]
            required_buffers=list(self.required),
            optional_buffers=list(self.optional),
            channels=self.channels,
            created_at=datetime.fromtimestamp(self.created_at, timezone.utc).isoformat(),
            frames_done=self.frames_done,
            last_index=self.last_index,
            resets=self.resets,
            sources=self.sources,
            missing=self.missing,
            mean_ms=StageTimings(**{k: round(v / done, 2) for k, v in self.timing_sum.items()}),
            last_ms=StageTimings(**{k: round(v, 2) for k, v in self.timing_last.items()}),
            memory_bytes=self.memory_bytes(),
            reserved_bytes=self.reserve_bytes if self.resident else 0,
            expires_in_s=round(max(0.0, ttl_s - (time.monotonic() - self.last_used)), 1),
            durable=self.durable,
        )


def run_frame(
    denoiser: Denoiser,
    session: Session,
    index: int,
    body: bytes,
    sources: dict[str, frames.Source],
    reset: str,
    state: dict[str, np.ndarray] | None,
) -> FrameOutcome:
    """Decode, denoise, encode one frame (worker thread; touches no session field)."""
    start = time.perf_counter()
    frame = frames.decode(body, sources)
    decoded = time.perf_counter()
    result = denoiser.denoise(frame.buffers, state, reset=reset != "none")
    denoised = time.perf_counter()
    info = denoiser.info
    extra = {"quietframe.model": f"{info.name} {info.version}", "quietframe.frame": str(index)}
    precision = session.precision
    if precision == "input":
        precision = "half" if frame.color_half else "float"
    body_out = frames.encode(
        result.color, frame.header, sources["color"].channels, precision, extra, session.compression
    )
    done = time.perf_counter()
    timings = {
        "decode": 1e3 * (decoded - start),
        "denoise": 1e3 * (denoised - decoded),
        "encode": 1e3 * (done - denoised),
        "total": 1e3 * (done - start),
    }
    sanitized = {k: v for k, v in result.sanitized.items() if v}
    headers = {
        "X-Quietframe-Frame": str(index),
        "X-Quietframe-Reset": reset,
        "X-Quietframe-Model": f"{info.name} {info.version}",
        "X-Quietframe-Sanitized": str(sum(sanitized.values())),
        "Server-Timing": ", ".join(f"{k};dur={v:.1f}" for k, v in timings.items()),
    }
    if sanitized:
        headers["X-Quietframe-Sanitized-Buffers"] = ", ".join(
            f"{k}={v}" for k, v in sorted(sanitized.items())
        )
    if result.missing:
        headers["X-Quietframe-Missing"] = ", ".join(result.missing)
    reply = Reply(index, body_out, headers, zlib.crc32(body), len(body))
    return FrameOutcome(
        reply=reply,
        state=result.state,
        reset=reset,
        sources={b: list(s.channels) for b, s in sources.items()},
        missing=list(result.missing),
        sanitized=sanitized,
        timings_ms=timings,
    )


class SessionRegistry:
    def __init__(self, settings: Settings, models: ModelRegistry, metrics: Metrics) -> None:
        self.settings, self.models, self.metrics = settings, models, metrics
        self.sessions: OrderedDict[str, Session] = OrderedDict()  # least recently used first
        self.state_dir = Path(settings.state_dir) if settings.state_dir else None
        if self.state_dir is not None:
            self.state_dir.mkdir(parents=True, exist_ok=True)
            self._load_durable()
        self._update_gauges()

    # ---- lookup, limits, expiry -------------------------------------------------------------

    def get(self, session_id: str, touch: bool = True) -> Session:
        """The session; `touch` counts as use (LRU order, TTL), status reads do not."""
        session = self.sessions.get(session_id)
        if session is None:
            raise SessionNotFound(
                f"no session {session_id!r} (expired after {self.settings.session_ttl_s:g} s idle, "
                "deleted, or never created)"
            )
        if touch:
            session.last_used = time.monotonic()
            self.sessions.move_to_end(session_id)
        return session

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

    # ---- create / delete ----------------------------------------------------------------------

    def create(self, spec: SessionCreate) -> Session:
        self.expire()
        if len(self.sessions) >= self.settings.max_sessions:
            raise TooManySessions(
                f"{len(self.sessions)} sessions are open (the maximum); retry after the "
                "Retry-After seconds, or delete finished sessions",
                headers={"Retry-After": self._retry_after()},
            )
        name = self.models.resolve(spec.model)
        denoiser = self.models.models[name]
        info = denoiser.info
        reply_bytes = 3 * spec.width * spec.height * (2 if spec.precision == "half" else 4)
        reserve = denoiser.state_nbytes(spec.height, spec.width) + reply_bytes + 2**16
        self._make_room(reserve)
        session = Session(
            id=secrets.token_urlsafe(16),
            model=name,
            version=info.version,
            width=spec.width,
            height=spec.height,
            precision=spec.precision,
            compression=spec.compression,
            channels=spec.channels,
            motion_scale=tuple(spec.motion_scale),  # type: ignore[arg-type]
            required=info.required_buffers,
            optional=info.optional_buffers,
            reserve_bytes=reserve,
            durable=self.state_dir is not None,
        )
        if session.durable:
            self.persist(session, None)
        self.sessions[session.id] = session
        self.metrics.sessions_created.inc()
        self._update_gauges()
        return session

    async def delete(self, session_id: str) -> None:
        session = self.get(session_id)
        async with session.lock:  # let a frame in flight finish (and write its state) first
            if not session.closed:
                self._remove(session, "deleted")

    def _remove(self, session: Session, reason: str) -> None:
        session.closed = True
        session.state, session.reply = None, None
        self.sessions.pop(session.id, None)
        if self.state_dir is not None:
            self._path(session.id).unlink(missing_ok=True)
        self.metrics.sessions_closed.labels(reason).inc()
        self._update_gauges()
        log.info("session closed", extra={"session": session.id, "reason": reason})

    # ---- frames -------------------------------------------------------------------------------

    async def ensure_resident(self, session: Session, loop, pool) -> None:
        if session.resident:
            return
        self._make_room(session.reserve_bytes, keep=session)
        state, reply = await loop.run_in_executor(pool, self._read_state, session.id)
        session.state, session.reply, session.resident = state, reply, True
        self._update_gauges()

    def committed(self, session: Session, outcome: FrameOutcome) -> None:
        session.commit(outcome)
        self.sessions.move_to_end(session.id)
        model = session.model
        self.metrics.frames.labels(model, outcome.reset).inc()
        for stage, ms in outcome.timings_ms.items():
            self.metrics.latency.labels(stage).observe(ms / 1e3)
        for buffer, count in outcome.sanitized.items():
            self.metrics.sanitized.labels(buffer).inc(count)
        self._update_gauges()

    def _update_gauges(self) -> None:
        self.metrics.sessions.set(len(self.sessions))
        self.metrics.history_bytes.set(sum(s.memory_bytes() for s in self.sessions.values()))

    # ---- durable state ------------------------------------------------------------------------

    def _path(self, session_id: str) -> Path:
        assert self.state_dir is not None and SESSION_ID.match(session_id)
        return self.state_dir / f"{session_id}.npz"

    def persist(self, session: Session, outcome: FrameOutcome | None) -> None:
        """Write the session as it will be after `outcome` (atomically: temp file + rename)."""
        reply = outcome.reply if outcome else session.reply
        meta = {
            "id": session.id,
            "model": session.model,
            "width": session.width,
            "height": session.height,
            "precision": session.precision,
            "compression": session.compression,
            "channels": session.channels,
            "motion_scale": list(session.motion_scale),
            "created_at": session.created_at,
            "last_index": reply.index if reply else session.last_index,
            "frames_done": session.frames_done + (1 if outcome else 0),
            "resets": session.resets + (outcome.reset != "none" if outcome else 0),
            "reply": None
            if reply is None
            else {
                "index": reply.index,
                "headers": reply.headers,
                "crc": reply.request_crc,
                "len": reply.request_len,
            },
        }
        arrays = {"meta": np.frombuffer(json.dumps(meta).encode(), np.uint8)}
        state = outcome.state if outcome else session.state
        for name, tensor in (state or {}).items():
            arrays[f"state.{name}"] = tensor
        if reply is not None:
            arrays["reply"] = np.frombuffer(reply.body, np.uint8)
        path = self._path(session.id)
        temp = path.with_name(f".{path.name}.tmp")
        try:
            with open(temp, "wb") as f:
                np.savez(f, **arrays)
                f.flush()
                if self.settings.state_fsync:
                    os.fsync(f.fileno())
            os.replace(temp, path)
        except BaseException:
            temp.unlink(missing_ok=True)  # the previous state file stays as it was
            raise

    def _read_state(self, session_id: str) -> tuple[dict[str, np.ndarray] | None, Reply | None]:
        with np.load(self._path(session_id)) as z:
            meta = json.loads(z["meta"].tobytes())
            state = {k[6:]: z[k] for k in z.files if k.startswith("state.")} or None
            r = meta["reply"]
            reply = None
            if r is not None and "reply" in z.files:
                reply = Reply(r["index"], z["reply"].tobytes(), r["headers"], r["crc"], r["len"])
        return state, reply

    def _load_durable(self) -> None:
        """Register the sessions of an earlier run (state stays on disk until their next frame)."""
        assert self.state_dir is not None
        for path in sorted(self.state_dir.glob("*.npz")):
            if not SESSION_ID.match(path.stem):
                continue
            try:
                with np.load(path) as z:
                    meta = json.loads(z["meta"].tobytes())
                name = self.models.resolve(meta["model"])
            except Exception as exc:  # unreadable file or model no longer installed
                log.warning("skipping stored session %s: %s", path.name, exc)
                continue
            info = self.models.models[name].info
            width, height = meta["width"], meta["height"]
            reply_bytes = 3 * width * height * (2 if meta["precision"] == "half" else 4)
            session = Session(
                id=meta["id"],
                model=name,
                version=info.version,
                width=width,
                height=height,
                precision=meta["precision"],
                compression=meta["compression"],
                channels=meta["channels"],
                motion_scale=tuple(meta["motion_scale"]),  # type: ignore[arg-type]
                required=info.required_buffers,
                optional=info.optional_buffers,
                reserve_bytes=self.models.models[name].state_nbytes(height, width)
                + reply_bytes
                + 2**16,
                durable=True,
                created_at=meta["created_at"],
                last_index=meta["last_index"],
                frames_done=meta["frames_done"],
                resets=meta["resets"],
                resident=False,
            )
            self.sessions[session.id] = session
        if self.sessions:
            log.info("restored %d sessions from %s", len(self.sessions), self.state_dir)
