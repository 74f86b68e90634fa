"""The session registry, the one owner of a frame's journey.

`SessionRegistry.denoise_frame` takes a frame from request body to reply: header checks and the
frame's context (service/frame_context.py) → lock → plan (retry / reset reason; for `model=auto`
at a shot's first frame, the model choice: service/shot_choice.py) → decode → denoise → encode
(service/frame_path.py) → persist (service/session_durability.py) → commit. The service keeps
each session's state tensors without knowing what they mean.

The registry composes three parts: the table of sessions in memory with their history budget
and expiry (`table`: service/session_table.py), the store behind them (`durability`:
service/session_durability.py; None when sessions live in memory only) and the worker pool
(`pool`: service/worker_pool.py). Registry bookkeeping runs on the event loop thread; the heavy
part of a frame (decode, denoise, encode, store I/O) runs on the worker pool while the session's
lock is held, so the frames of one session run in order and sessions run in parallel. A frame
changes its session only in `_commit`, after everything succeeded: a rejected frame never
changes the state.
"""

from __future__ import annotations

import dataclasses
import logging
import mmap
import secrets
from collections.abc import Mapping
from concurrent.futures import Executor

from quietframe.client.session_fields import AUTO
from quietframe.runtime import ModelInfo
from quietframe.runtime.motion_evidence import history_nbytes
from quietframe.runtime.stream import Stream
from quietframe.service import admission, frames, lookahead_queue
from quietframe.service.errors import (
    FrameNotPending,
    SessionNotFound,
    TooManySessions,
    not_pending,
)
from quietframe.service.frame_context import frame_context
from quietframe.service.measured_speed import MeasuredSpeeds
from quietframe.service.metrics import Metrics
from quietframe.service.model_registry import ModelRegistry
from quietframe.service.schemas import SessionCreate, SessionPublic
from quietframe.service.session import REPLY_MARGIN_BYTES, ProcessedFrame, Session
from quietframe.service.session_durability import SessionDurability
from quietframe.service.session_spec import SessionSpec
from quietframe.service.session_store import Reply, Store, is_session_id
from quietframe.service.session_table import SessionTable
from quietframe.service.settings import Settings
from quietframe.service.shot_choice import CHOICE_RESETS, noise_kind
from quietframe.service.stores import open_store
from quietframe.service.upload_slots import UploadSlots
from quietframe.service.worker_pool import WorkerPool
from quietframe.wire.protocol import Reset

log = logging.getLogger("quietframe.service")


@dataclasses.dataclass
class FrameOutcome:
    """What the route turns into a response."""

    reply: Reply
    replayed: bool


class SessionRegistry:
    def __init__(
        self, settings: Settings, models: ModelRegistry, metrics: Metrics, executor: Executor
    ) -> None:
        self.settings, self.models, self.metrics = settings, models, metrics
        self.pool = WorkerPool(executor)
        self.speeds = MeasuredSpeeds()  # each model's denoise time per frame size, here
        # frames in flight (admission.py), beside the history budget of what sessions keep
        self.admission = admission.MemoryBudget(settings.memory_budget_bytes,
                                                settings.admission_wait_s)
        self.upload_slots = UploadSlots.from_settings(settings)  # bodies being received
        store = open_store(settings)
        self.table = SessionTable(settings, models, metrics, durable=store is not None)
        self.durability = (
            SessionDurability(store, models, self.table, self.pool) if store is not None else None
        )
        if self.durability is not None and not self.durability.shared:  # shared: on demand
            self.durability.restore_all()
        self.table.update_gauges()

    @property
    def sessions(self) -> Mapping[str, Session]:
        """The sessions held in memory, least recently used first (read only)."""
        return self.table.sessions

    @property
    def store(self) -> Store | None:
        return self.durability.store if self.durability is not None else None

    def expire(self) -> list[str]:
        """Delete sessions idle for longer than the TTL (not those with a frame in flight); a
        local store's files of them are deleted on the worker pool, not waited for."""
        expired = self.table.expire()
        if self.durability is not None:
            self.durability.forget(expired)
        return [s.id for s in expired]

    async def get(self, session_id: str, touch: bool = True) -> Session:
        """The session; `touch` counts as use (LRU order, TTL), status reads do not. Every
        route finds its session here: an id of another form is unknown (404) before any store
        is asked (a store refuses to build a key or a file name from it). A session another
        replica holds is adopted from the shared store on the worker pool: a hung store must not
        freeze the event loop (audit R4-10; /healthz goes on answering)."""
        if not is_session_id(session_id):
            raise self.table.not_found(session_id)
        session = self.table.find(session_id)
        if session is None and self.durability is not None and self.durability.shared:
            session = await self.durability.adopt(session_id)
        if session is None:
            raise self.table.not_found(session_id)
        if touch:
            self.table.touch(session)
        return session

    async def status(self, session_id: str) -> SessionPublic:
        """The session's status (not counted as use). With a shared store, another replica may
        have advanced the session since this one's copy was loaded: the progress shown is the
        store's record (its small meta; the state stays where it is)."""
        held = self.table.find(session_id) is not None  # else `get` adopts it from the record
        session = await self.get(session_id, touch=False)
        ttl = self.settings.session_ttl_s
        if self.durability is None or not (self.durability.shared and held):
            return session.public(ttl, self.speeds)
        progress = await self.durability.committed_progress(session_id)
        if not progress:  # only its settings survive: this copy's progress is all there is
            return session.public(ttl, self.speeds)
        return dataclasses.replace(session, **progress).public(ttl, self.speeds)

    # ---- create / delete ----------------------------------------------------------------------

    async def create(self, request: SessionCreate) -> Session:
        self.expire()
        if len(self.table) >= self.settings.max_sessions:
            raise TooManySessions(
                f"{len(self.table)} sessions are open (the maximum); retry after the "
                "Retry-After seconds, or delete finished sessions",
                headers={"Retry-After": self.table.retry_after()},
            )
        spec = SessionSpec.model_validate(
            {**request.model_dump(), "model": self.models.requested(request.model)})
        self.models.check_options(spec.model, spec.model_options)  # before anything is kept
        session = self.table.build(secrets.token_urlsafe(16), spec)
        self.table.make_room(session.reserve_bytes)
        if self.durability is not None:
            await self.durability.store_new(session)
        self.table.add(session)
        self.metrics.sessions_created.inc()
        self.table.update_gauges()
        return session

    async def delete(self, session_id: str) -> None:
        session = await self.get(session_id)
        async with session.lock:  # let a frame in flight finish (and write its state) first
            if not session.closed:
                self.table.remove(session, "deleted")
                if self.durability is not None:  # gone from the store when DELETE answers
                    await self.durability.delete(session.id)

    def close_streams(self) -> None:
        """At shutdown (no frame running): let go of every session's stream (its kept OIDN
        filters and device); a durable session's state stays in its store."""
        for session in list(self.table.sessions.values()):
            session.close_stream()

    # ---- frames -------------------------------------------------------------------------------

    def frame_need(self, session: Session, header: frames.ExrHeader, body_bytes: int,
                   cut: bool = False) -> int:
        """A frame's peak memory for the admission budget: for the model it will run. With
        model=auto that is the shot's choice, except where this frame may choose again (a
        shot's first frame, a cut: CHOICE_RESETS) and any installed model may run (the
        largest counts)."""
        spec = session.spec
        return admission.frame_need(header, body_bytes, [
            self.models.denoiser(name) for name in self._models_for(session, cut or header.cut)]
        ) + lookahead_queue.frame_need(spec.lookahead, header.height, header.width, body_bytes)

    def _models_for(self, session: Session, cut: bool) -> list[str]:
        """The models a frame of `session` may run (`cut`: flagged by query or header)."""
        if session.spec.model != AUTO:
            return [session.info.name]
        if session.choice is None or cut or session.last_index is None:
            return list(self.models.names)
        return [session.choice.model]

    async def denoise_frame(
        self,
        session_id: str,
        index: int,
        body: bytes | bytearray | mmap.mmap,
        cut: bool,
        header: frames.ExrHeader | None = None,
        shot_model: str | None = None,
    ) -> FrameOutcome:
        """The frame protocol: everything that can be checked from the header is checked before
        the lock; the session changes only once the reply is encoded (and stored). `header`:
        the body's, when the caller parsed it already. `shot_model` (model=auto): the model
        already chosen for the shot this frame belongs to (another chunk of the same shot chose
        it); a frame that starts the shot's history takes it instead of choosing."""
        session = await self.get(session_id)
        spec = session.spec
        settings = self.settings
        if header is None:
            header = frames.read_header(
                body, settings.max_width, settings.max_height, settings.max_header_bytes
            )
        frames.check_windows(header, spec.width, spec.height)
        auto = spec.model == AUTO
        # UnknownModel before the lock; a fixed model's session has no choice to keep
        keep = self.models.shot_model(shot_model) if auto and shot_model else None
        # model=auto: every buffer the frame carries (the choice's input, from the header); the
        # chosen model's own check follows once the plan says which model this frame uses.
        installed = self.models.buffers()
        context = frame_context(header, spec, None if auto else session.info, installed)
        async with session.lock:
            if session.closed:
                raise SessionNotFound(f"session {session_id!r} was closed while this frame waited")
            if self.durability is not None:  # a retry needs the stored reply
                await self.durability.ensure_resident(session)
            plan = await self.pool.plan_frame(session, index, body, cut or header.cut)
            if isinstance(plan, Reply):
                self.metrics.replays.inc()
                return FrameOutcome(plan, replayed=True)
            history = session.history if plan is Reset.NONE else None
            info, choice, chose, starts_shot = session.info, None, False, False
            if auto:
                starts_shot = plan in CHOICE_RESETS or session.choice is None
                chose = starts_shot and keep is None
                if starts_shot:  # decoded once: the choice measures its noise, the model runs
                    context, choice = await self.pool.choose_for_shot(
                        context, body, spec, self.models, keep)
                else:
                    choice = session.choice
                assert choice is not None
                info = self.models.denoiser(choice.model).info
                context = context.for_model(info, installed)
                if info.name != session.info.name:  # another model's state means nothing here
                    history = None
            stream = self._stream(session, info.name)
            shot_spp = None
            if not auto and stream.wants_estimate(None if context.stated is None
                                                  else context.stated.spp):
                # a named model reading the spp, none stated: the shot's estimate, made at its
                # first frame as auto's choice is, kept for its other frames (durably)
                shot_spp = None if plan in CHOICE_RESETS else session.shot_spp
                if shot_spp is None:  # a new shot, or none measurable yet (a black frame)
                    context, shot_spp = await self.pool.estimate_for_shot(context, body,
                                                                          self.models)
            frame = await self.pool.process_frame(
                stream, spec, index, body, context, plan, history, choice,
                session.window if spec.lookahead else None, shot_spp
            )
            self._reserve_reply(session, len(frame.reply.body), info, len(body))
            if self.durability is not None:
                await self.durability.persist(session, frame)
            self._commit(session, frame)
            self.table.fit_kept(session)
            if chose and choice is not None:
                self.metrics.choices.labels(
                    choice.model, spec.quality or "balanced", noise_kind(choice)
                ).inc()
                log.info(
                    "model chosen",
                    extra={"session": session.id, "index": index, **choice.to_dict()},
                )
            elif auto and starts_shot:
                log.info("model kept for the shot",
                         extra={"session": session.id, "index": index, "model": keep})
        log.info(
            "frame",
            extra={
                "session": session.id,
                "index": index,
                "reset": frame.reset.value,
                "ms": round(frame.timings_ms["total"], 1),
                "sanitized": frame.sanitized,
            },
        )
        return FrameOutcome(frame.reply, replayed=False)

    async def finish_frame(self, session_id: str, index: int) -> FrameOutcome:
        """POST .../frames/{index}/finish: a look-ahead session's oldest pending frame now,
        finished with the later frames it has (docs/service.md, "Look-ahead"); the stored reply
        again for a retry of the last finish; FrameNotPending (409) for any other index."""
        session = await self.get(session_id)
        async with session.lock:
            if session.closed:
                raise SessionNotFound(f"session {session_id!r} was closed while this waited")
            if self.durability is not None:  # a retry needs the stored reply, the window
                await self.durability.ensure_resident(session)
            reply = session.reply
            if reply is not None and reply.finish and reply.index == index:
                self.metrics.replays.inc()
                return FrameOutcome(reply, replayed=True)
            held = lookahead_queue.pending(session.state)
            if not held or held[0] != index:
                raise FrameNotPending(not_pending(session, index, held))
            need = lookahead_queue.finish_need(session.state, session.spec)
            reservation = self.admission.reserve(0)
            try:
                await reservation.admit(need, f"finishing frame {index}")
                frame = await self.pool.finish_frame(session)
            finally:
                reservation.release()
            if self.durability is not None:
                await self.durability.persist(session, frame)
            session.commit(frame)
            self.table.touch(session)
            self.table.update_gauges()
        log.info("frame finished", extra={"session": session.id, "index": index,
                                          "pending": len(frame.pending)})
        return FrameOutcome(frame.reply, replayed=False)

    def _stream(self, session: Session, model: str) -> Stream:
        """The session's sequence on `model`: kept from frame to frame, built anew when the
        shot's model changes (the old one's filters let go)."""
        stream, denoiser = session.stream, self.models.denoiser(model)
        if stream is None or stream.denoiser is not denoiser:
            session.close_stream()
            spec = session.spec
            stream = Stream(denoiser, camera=spec.camera, options=spec.model_options,
                            motion=spec.motion)
            session.stream = stream
        return stream

    def _reserve_reply(self, session: Session, reply_bytes: int, info: ModelInfo,
                       body_bytes: int) -> None:
        """The reply is the whole input file with the denoised colour in it, larger than the
        creation-time estimate when the farm sends many passes (and a look-ahead session holds
        `lookahead` such requests back): grow the session's reservation to what it will hold
        (MemoryBudgetExceeded, before anything changed, if that does not fit)."""
        spec = session.spec
        need = history_nbytes(info.state_specs, spec.height, spec.width)
        need += max(reply_bytes, body_bytes if spec.lookahead else 0) + REPLY_MARGIN_BYTES
        need += lookahead_queue.reserve_bytes(spec.lookahead, spec.height, spec.width,
                                              body_bytes)
        if need > session.reserve_bytes:
            self.table.make_room(need - session.reserve_bytes, keep=session)
            session.reserve_bytes = need

    def _commit(self, session: Session, frame: ProcessedFrame) -> None:
        session.commit(frame)
        self.table.touch(session)
        self.metrics.frames.labels(frame.info.name, frame.reset.value).inc()
        for stage, ms in frame.timings_ms.items():
            self.metrics.latency.labels(stage).observe(ms / 1e3)
        spec = session.spec
        self.speeds.record(frame.info.name, spec.height, spec.width, frame.timings_ms["denoise"])
        for buffer, count in frame.sanitized.items():
            self.metrics.sanitized.labels(buffer).inc(count)
        self.table.update_gauges()
