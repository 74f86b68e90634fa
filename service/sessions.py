"""Per-camera sessions and the one owner of a frame's journey.

`SessionRegistry.denoise_frame` takes a frame from request body to reply: header checks →
lock → plan (retry / reset reason; for `model=auto` at a shot's first frame, the model choice)
→ decode → denoise → encode → persist → commit. The service keeps each session's state tensors
without knowing what they mean (DESIGN.md). Registry
bookkeeping runs on the event loop thread; the heavy part of a frame (decode, denoise, encode,
disk writes) runs on the worker pool while the session's lock is held, so the frames of one
session run in order and sessions run in parallel. A frame changes its session only in
`_commit`, after everything succeeded: a rejected frame never changes the state.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import mmap
import secrets
import time
from collections import OrderedDict
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone

import numpy as np

from quietframe.client.protocol import (
    Header,
    Reset,
    format_counts,
    format_timings,
    join_list,
)
from quietframe.runtime import Denoiser, ModelInfo
from quietframe.runtime.buffers import BUFFER_NAMES
from quietframe.runtime.motion_evidence import (
    HistoryGate,
    gate_history,
    history_nbytes,
    history_shapes,
    keep_probe,
)
from quietframe.runtime.sanitize import clamp_to_half
from quietframe.runtime.usable_buffers import unusable_buffers
from quietframe.service import admission, frames, model_choice, state_codec
from quietframe.service.admission import MemoryBudget
from quietframe.service.errors import (
    FrameConflict,
    FrameOutOfOrder,
    MemoryBudgetExceeded,
    ServiceError,
    SessionNotFound,
    TooManySessions,
)
from quietframe.service.metrics import Metrics
from quietframe.service.model_choice import Choice
from quietframe.service.model_registry import AUTO, ModelRegistry, options_for
from quietframe.service.schemas import (
    ChoicePublic,
    ModelRef,
    SessionCreate,
    SessionPublic,
    StageTimings,
)
from quietframe.service.session_store import (
    Reply,
    StateDamaged,
    is_session_id,
    open_store,
    request_digest,
)
from quietframe.service.settings import Settings

log = logging.getLogger("quietframe.service")

STAGES = ("decode", "denoise", "encode", "total")


@dataclass(frozen=True)
class SessionSpec:
    """What a session is, fixed at creation (and stored with a durable session)."""

    model: str  # an installed model's name, or "auto" (chosen per shot: model_choice.py)
    width: int
    height: int
    precision: str
    compression: str
    channels: dict | None
    motion_scale: tuple[float, float]
    layer: str | None = None
    denoised_layer: str | None = None
    quality: str | None = None
    latency_ms: float | None = None
    # Run-time options (e.g. kernel_size), checked at creation; each model that runs gets those
    # it declares (options_for).
    model_options: dict[str, float | int] = field(default_factory=dict)


# A choice is revisited only where the history starts afresh for a new shot anyway: switching
# models inside a shot would change its look from one frame to the next (flicker). A gap keeps
# the shot's model (it is a skipped frame more often than a new shot).
CHOICE_RESETS = (Reset.FIRST_FRAME, Reset.CUT)


@dataclass
class FrameOutcome:
    """What the route turns into a response."""

    reply: Reply
    replayed: bool


@dataclass
class _Processed:
    """A denoised frame not yet committed to its session."""

    reply: Reply
    state: dict[str, np.ndarray]
    reset: Reset
    sources: dict[str, list[str]]
    missing: list[str]
    sanitized: dict[str, int]
    timings_ms: dict[str, float]
    info: ModelInfo  # the model that denoised it
    choice: Choice | None = None  # model=auto: set when this frame made (or kept) the choice


@dataclass
class Session:
    id: str
    spec: SessionSpec
    info: ModelInfo  # the model in use (model=auto: the current shot's choice)
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
    state_lost: bool = False  # the stored state was damaged: the next frame starts afresh
    # A shared store's version of the session this copy is (its fencing token); None: unknown,
    # load the session from the store before the next frame.
    store_version: str | None = ""  # "": a new session, not stored yet
    closed: bool = False
    sources: dict[str, list[str]] = field(default_factory=dict)
    missing: list[str] = field(default_factory=list)
    choice: Choice | None = None  # model=auto only
    timing_sum: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    timing_last: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    lock: asyncio.Lock = field(default_factory=asyncio.Lock, repr=False)

    def memory_bytes(self) -> int:
        state = sum(a.nbytes for a in self.state.values()) if self.state else 0
        return state + (len(self.reply.body) if self.reply else 0)

    def plan(self, index: int, body: bytes | bytearray, cut: bool) -> Reply | Reset:
        """The stored reply for a retry of the last index, else why history resets;
        FrameOutOfOrder / FrameConflict for a refused index. After lost state (no reply to
        compare with), the last index and later ones start from a fresh history."""
        if self.state_lost and (self.last_index is None or index >= self.last_index):
            return Reset.STATE_LOST
        if self.last_index is not None and index == self.last_index:
            reply = self.reply
            if reply and reply.matches(body):
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
            return Reset.FIRST_FRAME
        if cut:
            return Reset.CUT
        return Reset.GAP if index > self.last_index + 1 else Reset.NONE

    def commit(self, frame: _Processed) -> None:
        self.state_lost = False
        self.state = frame.state
        self.reply = frame.reply
        self.last_index = frame.reply.index
        self.frames_done += 1
        self.resets += frame.reset is not Reset.NONE
        self.sources, self.missing = frame.sources, frame.missing
        self.info = frame.info
        if frame.choice is not None:
            self.choice = frame.choice
        for stage in STAGES:
            self.timing_sum[stage] += frame.timings_ms[stage]
            self.timing_last[stage] = frame.timings_ms[stage]
        self.last_used = time.monotonic()

    def meta(self, after: _Processed | None = None) -> dict:
        """The stored record of the session, as it will be once `after` is committed."""
        choice = after.choice if after is not None and after.choice else self.choice
        return {
            "choice": choice.to_dict() if choice else None,
            "id": self.id,
            **asdict(self.spec),
            "created_at": self.created_at,
            "last_index": after.reply.index if after else self.last_index,
            "frames_done": self.frames_done + (after is not None),
            "resets": self.resets + (after is not None and after.reset is not Reset.NONE),
        }

    def public(self, ttl_s: float) -> SessionPublic:
        done = max(self.frames_done, 1)
        spec = self.spec
        return SessionPublic(
            id=self.id,
            model=ModelRef(name=self.info.name, version=self.info.version),
            requested_model=spec.model,
            latency_ms=spec.latency_ms,
            choice=ChoicePublic(**self.choice.to_dict()) if self.choice else None,
            width=spec.width,
            height=spec.height,
            precision=spec.precision,  # type: ignore[arg-type]
            compression=spec.compression,  # type: ignore[arg-type]
            required_buffers=list(self.info.required_buffers),
            optional_buffers=list(self.info.optional_buffers),
            channels=spec.channels,
            layer=spec.layer,
            denoised_layer=spec.denoised_layer,
            quality=spec.quality,  # type: ignore[arg-type]
            model_options=dict(spec.model_options),
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


REPLY_MARGIN_BYTES = 2**16  # headers and EXR framing around the pixels


def reserve_bytes(info: ModelInfo, spec: SessionSpec) -> int:
    """What a new session counts against the history budget: its state and a reply of at least
    the denoised colour planes (the reply is the whole input file: `_reserve_reply` grows the
    reservation to its real size on the first frame)."""
    reply = 3 * spec.width * spec.height * (2 if spec.precision == "half" else 4)
    return history_nbytes(info.state_specs, spec.height, spec.width) + reply + REPLY_MARGIN_BYTES


def choice_header(choice: Choice) -> str:
    spp = "unknown" if choice.spp is None else f"{choice.spp:g}"
    text = f"{choice.model}; spp={spp}; source={choice.noise_source}; reason={choice.reason}"
    for symbol, word in HEADER_WORDS.items():  # spelled out, not turned into "?"
        text = text.replace(symbol, word)
    return text.encode("ascii", "replace").decode()  # an HTTP header value is latin-1


# The non-ASCII symbols the choice's reason uses, as the header spells them.
HEADER_WORDS = {"σ": "sigma", "×": "x", "≤": "<=", "≥": ">=", "–": "-", "—": "-", "·": "*"}


# The reason of a shot's model kept from an earlier choice (`shot_model`, e.g. another farm
# chunk's): the choice is made once per shot, so chunks of one shot never switch models.
KEPT_REASON = "kept: the shot's model, chosen before for this shot (shot_model)"


def kept_choice(name: str, present: list[str], noise: model_choice.NoiseLevel,
                profiles: list[model_choice.ModelProfile], pixels: int) -> Choice:
    """A shot's choice made earlier, as the session reports it: that model, with what this
    frame carries and how noisy it is, and what the model's table expects there."""
    have = tuple(sorted(set(present)))
    profile = next((p for p in profiles if p.name == name), None)
    psnr = ms = None
    if profile is not None and profile.measured:
        by_noise = noise if profile.psnr_by_noise else None
        psnr = round(profile.expected_psnr(noise.spp, have, by_noise), 2)
        ms = round(profile.expected_ms(pixels), 3)
    sigma = None if noise.log2_sigma is None else round(noise.log2_sigma, 3)
    return Choice(name, KEPT_REASON, noise.spp, noise.source, have, sigma, psnr, ms)


def noise_kind(choice: Choice) -> str:
    """Where the choice's spp came from, as the choices metric counts it: a header attribute
    is `header`, the session's model_options `session`, else `estimate` or `unknown`."""
    if choice.noise_source == model_choice.SESSION_SAMPLES:
        return "session"
    return choice.noise_source if choice.noise_source in ("estimate", "unknown") else "header"


def motion_header(gate: HistoryGate) -> str:
    """X-Quietframe-Motion of a temporal model's frame without motion vectors: what its aux
    showed and whether the history was used."""
    assert gate.evidence is not None
    used = "history not used" if gate.state is None else "history used"
    return f"{gate.evidence.describe()}; {used}"


def frame_samples(header: frames.ExrHeader, spec: SessionSpec,
                  choice: Choice | None) -> float | None:
    """The frame's spp for a model that takes it: the session's or the renderer's stated count,
    else (model=auto) the shot's estimate, else None (the model's default)."""
    stated = model_choice.stated_samples(header.attributes, spec.layer, spec.model_options)
    if stated is not None:
        return stated.spp
    return choice.spp if choice is not None else None


def process_frame(
    denoiser: Denoiser,
    spec: SessionSpec,
    index: int,
    body: bytes | bytearray,
    sources: dict[str, frames.Source],
    reset: Reset,
    state: dict[str, np.ndarray] | None,
    choice: Choice | None = None,
    samples: float | None = None,
    renderer: str | None = None,
) -> _Processed:
    """Decode, denoise, encode one frame (worker thread; touches no session field). `state`
    is None when the history starts afresh; `choice` (model=auto) is said in a header;
    `samples`: the frame's spp where known (a model that takes it is given it); `renderer`:
    which renderer wrote it, where the header says (the row order OIDN sees follows it)."""
    start = time.perf_counter()
    frame = frames.decode(body, sources)
    decoded = time.perf_counter()
    options = options_for(denoiser.info, spec.model_options, samples)  # auto: this model's
    # A temporal model reads its history only where the motion is evidence (motion_evidence):
    # a frame without vectors whose aux moved starts afresh, as after a cut.
    gate = gate_history(frame.buffers, state) if denoiser.info.state_specs else None
    if gate is not None and gate.dropped:
        assert gate.evidence is not None
        reset = Reset.DETECTED_CUT if gate.evidence.verdict == "cut" else Reset.NO_MOTION
    result = denoiser.denoise(frame.buffers, gate.state if gate else state, options, renderer)
    new_state = keep_probe(result.state, gate.probe) if gate else result.state
    denoised = time.perf_counter()
    info = denoiser.info
    model = f"{info.name} {info.version}"
    extra = {"quietframe.model": model, "quietframe.frame": str(index)}
    color, clamped = result.color, 0
    dtypes = frames.output_dtypes(frame, spec.precision)
    half = [i for i, d in enumerate(dtypes) if d == np.float16]
    if half:  # a plain cast would turn values beyond ±65504 into ±Inf
        rows, clamped = clamp_to_half(color[half])
        if clamped:
            color = color.copy()
            color[half] = rows
    body_out = frames.encode(
        color,
        frame,
        sources["color"].channels,
        spec.precision,
        extra,
        spec.compression,
        spec.denoised_layer,
    )
    done = time.perf_counter()
    timings = {
        "decode": 1e3 * (decoded - start),
        "denoise": 1e3 * (denoised - decoded),
        "encode": 1e3 * (done - denoised),
        "total": 1e3 * (done - start),
    }
    sanitized = {k: v for k, v in result.sanitized.items() if v}
    if clamped:
        sanitized["denoised"] = sanitized.get("denoised", 0) + clamped
    headers = {
        Header.FRAME: str(index),
        Header.RESET: reset.value,
        Header.MODEL: model,
        Header.SANITIZED: str(sum(sanitized.values())),
        Header.SERVER_TIMING: format_timings(timings),
    }
    if sanitized:
        headers[Header.SANITIZED_BUFFERS] = format_counts(sanitized)
    if result.missing:
        headers[Header.MISSING] = join_list(result.missing)
    if gate is not None and gate.evidence is not None:
        headers[Header.MOTION] = motion_header(gate)
    if choice is not None:
        headers[Header.CHOICE] = choice_header(choice)
    # Where the colour is a state plane, a store keeps how to write the reply, not its bytes
    recipe = state_codec.reply_recipe(result.color, new_state, dtypes, sources["color"].channels,
                                      spec.precision, spec.compression, spec.denoised_layer, extra)
    return _Processed(
        reply=Reply(index, body_out, headers, len(body), request_digest(body), recipe=recipe),
        state=new_state,
        reset=reset,
        sources={b: list(s.channels) for b, s in sources.items()},
        missing=list(result.missing),
        sanitized=sanitized,
        timings_ms=timings,
        info=info,
        choice=choice,
    )


class SessionRegistry:
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
        if self.store is not None and not self.store.shared:  # a shared one: sessions on demand
            self._load_durable()
        self._update_gauges()

    # ---- lookup, limits, expiry -------------------------------------------------------------

    def get(self, session_id: str, touch: bool = True) -> Session:
        """The session; `touch` counts as use (LRU order, TTL), status reads do not. Every
        route finds its session here: an id of another form is unknown (404) before any store
        is asked (a store refuses to build a key or a file name from it)."""
        if not is_session_id(session_id):
            raise self._not_found(session_id)
        session = self.sessions.get(session_id)
        if session is None and self.store is not None and self.store.shared:
            session = self._adopt(session_id)
        if session is None:
            raise self._not_found(session_id)
        if touch:
            session.last_used = time.monotonic()
            self.sessions.move_to_end(session_id)
        return session

    def _not_found(self, session_id: str) -> SessionNotFound:
        return SessionNotFound(
            f"no session {session_id!r} (expired after {self.settings.session_ttl_s:g} s idle, "
            "deleted, or never created)"
        )

    async def status(self, session_id: str) -> SessionPublic:
        """The session's status (not counted as use). With a shared store, another replica may
        have advanced the session since this one's copy was loaded: the progress shown is the
        store's record (its small meta; the state stays where it is)."""
        shared = self.store is not None and self.store.shared
        held = session_id in self.sessions  # else `get` adopts it from the record just read
        session = self.get(session_id, touch=False)
        ttl = self.settings.session_ttl_s
        if not (shared and held):
            return session.public(ttl)
        found = await self._on_pool(self.store.find, session_id)  # type: ignore[union-attr]
        if found is None:  # expired in the store, or deleted through another replica
            raise SessionNotFound(f"session {session_id!r} is gone (expired or deleted)")
        meta, lost = found
        if lost:  # only its settings survive: this copy's progress is all there is
            return session.public(ttl)
        return dataclasses.replace(session, **self._stored_progress(meta)).public(ttl)

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

    async def create(self, request: SessionCreate) -> Session:
        self.expire()
        if len(self.sessions) >= self.settings.max_sessions:
            raise TooManySessions(
                f"{len(self.sessions)} sessions are open (the maximum); retry after the "
                "Retry-After seconds, or delete finished sessions",
                headers={"Retry-After": self._retry_after()},
            )
        spec = SessionSpec(
            model=self.models.requested(request.model),
            width=request.width,
            height=request.height,
            precision=request.precision,
            compression=request.compression,
            channels=request.channels,
            motion_scale=tuple(request.motion_scale),  # type: ignore[arg-type]
            layer=request.layer,
            denoised_layer=request.denoised_layer,
            quality=request.quality,
            latency_ms=request.latency_ms,
            model_options=dict(request.model_options),
        )
        self.models.check_options(spec.model, spec.model_options)  # before anything is kept
        session = self._session(secrets.token_urlsafe(16), spec)
        self._make_room(session.reserve_bytes)
        if self.store is not None:
            await self._store_new(session)
        self.sessions[session.id] = session
        self.metrics.sessions_created.inc()
        self._update_gauges()
        return session

    async def _store_new(self, session: Session) -> None:
        """Store a new session: its settings, then its first record. Where the store refuses
        the second write (full, say), what the first wrote is deleted before the error goes
        out: a session the client was refused must not appear later (a restart restores a
        settings file alone as a session)."""
        assert self.store is not None
        try:
            await self._on_pool(self.store.write_spec, session.meta())
            session.store_version = await self._on_pool(
                self.store.write, session.meta(), None, None, ""
            )
        except Exception:
            try:
                await self._on_pool(self.store.delete, session.id)
            except Exception as exc:  # the store is gone too: a Redis key expires by itself
                log.warning("could not delete a session whose creation failed",
                            extra={"session": session.id, "error": repr(exc)})
            raise

    async def delete(self, session_id: str) -> None:
        session = self.get(session_id)
        async with session.lock:  # let a frame in flight finish (and write its state) first
            if not session.closed:
                self._remove(session, "deleted")
                if self.store is not None:  # gone from disk when DELETE answers
                    await self._on_pool(self.store.delete, session.id)

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

    # ---- frames -------------------------------------------------------------------------------

    def frame_need(self, session: Session, header: frames.ExrHeader, body_bytes: int,
                   cut: bool = False) -> int:
        """A frame's peak memory for the admission budget: for the model it will run. With
        model=auto that is the shot's choice, except where this frame may choose again (a
        shot's first frame, a cut: CHOICE_RESETS) and any installed model may run (the
        largest counts)."""
        return admission.frame_need(header, body_bytes, [
            self.models.denoiser(name) for name in self._models_for(session, cut or header.cut)])

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
        session = self.get(session_id)
        spec = session.spec
        settings = self.settings
        if header is None:
            header = frames.read_header(
                body, settings.max_width, settings.max_height, settings.max_header_bytes
            )
        frames.check_windows(header, spec.width, spec.height)
        auto = spec.model == AUTO
        # UnknownModel before the lock; a fixed model's session has no choice to keep
        keep = self.models.resolve(shot_model) if auto and shot_model else None
        # model=auto: every buffer the frame carries (the choice's input, from the header); the
        # chosen model's own check follows once the plan says which model this frame uses.
        sources = self._sources(header, spec, None if auto else session.info)
        async with session.lock:
            if session.closed:
                raise SessionNotFound(f"session {session_id!r} was closed while this frame waited")
            await self._ensure_resident(session)  # a retry needs the stored reply
            # On the pool: a retry hashes its whole body (up to ~2 s at 2 GiB), never on the loop
            plan = await self._on_pool(session.plan, index, body, cut or header.cut)
            if isinstance(plan, Reply):
                self.metrics.replays.inc()
                return FrameOutcome(plan, replayed=True)
            history = session.state if plan is Reset.NONE else None
            info, choice, chose, starts_shot = session.info, None, False, False
            if auto:
                starts_shot = plan in CHOICE_RESETS or session.choice is None
                chose = starts_shot and keep is None
                choice = await self._choose(session, header, body, sources, keep) if (
                    starts_shot) else session.choice
                assert choice is not None
                info = self.models.denoiser(choice.model).info
                sources = self._sources(header, spec, info)
                if info.name != session.info.name:  # another model's state means nothing here
                    history = None
            denoiser = self.models.denoiser(info.name)
            frame = await self._on_pool(
                process_frame, denoiser, spec, index, body, sources, plan, history, choice,
                frame_samples(header, spec, choice),
                model_choice.renderer_from_header(header.attributes),
            )
            self._reserve_reply(session, len(frame.reply.body), info)
            if self.store is not None:
                await self._persist(session, frame)
            self._commit(session, frame)
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

    def _sources(
        self, header: frames.ExrHeader, spec: SessionSpec, info: ModelInfo | None
    ) -> dict[str, frames.Source]:
        """Where the model's buffers are in the file (header only; MissingChannels for an absent
        required one). `info` None: every canonical buffer the file has, colour required."""
        if info is None:
            required, optional = ("color",), tuple(b for b in BUFFER_NAMES if b != "color")
        else:
            required, optional = info.required_buffers, info.optional_buffers
        return frames.resolve(
            header.channels,
            required,
            optional,
            spec.channels,
            spec.motion_scale,
            model=info.name if info else AUTO,
            layer=spec.layer,
            installed=self.models.buffers(),
        )

    async def _choose(
        self,
        session: Session,
        header: frames.ExrHeader,
        body: bytes | bytearray,
        sources: dict[str, frames.Source],
        keep: str | None = None,
    ) -> Choice:
        """model=auto for a shot: the sample count the session (model_options) or the header
        states, else estimated from the decoded colour (and albedo) on the worker pool, which
        also measures how noisy the frame looks (model_choice.noise_statistic). `keep`: the
        model already chosen for this shot (`shot_model`), described with what the frame shows."""
        spec = session.spec
        stated = model_choice.stated_samples(header.attributes, spec.layer, spec.model_options)
        noise, unusable = await self._on_pool(self._estimate_noise, body, sources, stated)
        # Present in the pixels, not just named; except an all-zero Vector, which is no
        # evidence either way (a locked-off camera, motion blur, a first frame): the chosen
        # model's history follows the aux's evidence frame by frame (motion_evidence).
        present = [b for b in sources if b not in unusable or b == "motion"]
        profiles = self.models.profiles_for(model_choice.renderer_from_header(header.attributes))
        if keep is not None:
            return kept_choice(keep, present, noise, profiles, spec.width * spec.height)
        return model_choice.choose(
            present,
            noise,
            profiles,
            self.models.default,
            quality=spec.quality,
            latency_ms=spec.latency_ms,
            pixels=spec.width * spec.height,
        )

    def _estimate_noise(
        self,
        body: bytes | bytearray,
        sources: dict[str, frames.Source],
        stated: model_choice.NoiseLevel | None,
    ) -> tuple[model_choice.NoiseLevel, tuple[str, ...]]:
        """The frame's noise level, and the buffers it names that hold nothing usable
        (runtime.usable_buffers: all-zero motion, constant depth; decode drops the former)."""
        wanted = ("color", "albedo", "motion", "depth")
        planes = frames.decode(body, {b: sources[b] for b in wanted if b in sources})
        dropped = [b for b in wanted if b in sources and b not in planes.buffers]
        unusable = (*dropped, *unusable_buffers(planes.buffers))
        noise = model_choice.estimate_spp(
            planes.buffers["color"], planes.buffers.get("albedo"), self.models.calibration,
            header=stated,
        )
        return noise, unusable

    def _reserve_reply(self, session: Session, reply_bytes: int, info: ModelInfo) -> None:
        """The reply is the whole input file with the denoised colour in it, larger than the
        creation-time estimate when the farm sends many passes: grow the session's reservation
        to what it will hold (MemoryBudgetExceeded, before anything changed, if that does not
        fit)."""
        need = history_nbytes(info.state_specs, session.spec.height, session.spec.width)
        need += reply_bytes + REPLY_MARGIN_BYTES
        if need > session.reserve_bytes:
            self._make_room(need - session.reserve_bytes, keep=session)
            session.reserve_bytes = need

    async def _on_pool(self, fn, *args):
        return await asyncio.get_running_loop().run_in_executor(self.pool, fn, *args)

    async def _persist(self, session: Session, frame: _Processed) -> None:
        """Store the frame's outcome before it is committed; with a shared store, only if no
        other replica advanced the session meanwhile (fencing: SessionMoved, and this copy is
        reloaded before its next frame)."""
        assert self.store is not None
        try:
            version = await self._on_pool(
                self.store.write, session.meta(frame), frame.state, frame.reply,
                session.store_version,
            )
        except ServiceError as exc:
            if exc.code == "session_moved":
                session.state, session.reply, session.resident = None, None, False
                session.store_version = None
            raise
        session.store_version = version

    def _adopt(self, session_id: str) -> Session | None:
        """A session this replica does not hold, registered from the shared store (its state is
        loaded with its next frame). Runs on the event loop: one small read."""
        assert self.store is not None
        found = self.store.find(session_id)  # type: ignore[attr-defined]
        if found is None:
            return None
        meta, lost = found
        self._restore(session_id, meta, lost)
        session = self.sessions.get(session_id)
        if session is not None:
            session.store_version = None  # load what the store holds before the next frame
            log.info("session adopted from the store", extra={"session": session_id})
        return session

    async def _follow_store(self, session: Session) -> None:
        """Shared store: its version is the truth. Another replica may have advanced this session
        since this copy was loaded (a failover, then back): load what it committed."""
        store = self.store
        assert store is not None
        version = await self._on_pool(store.version, session.id)  # type: ignore[attr-defined]
        if version is None:  # expired in the store, or deleted through another replica
            self._remove(session, "gone")
            raise SessionNotFound(f"session {session.id!r} is gone (expired or deleted)")
        if session.resident and version == session.store_version:
            return
        self._make_room(session.reserve_bytes, keep=session)
        loaded = await self._on_pool(store.load, session.id, self._shapes_of)  # type: ignore
        if loaded is None:
            self._remove(session, "gone")
            raise SessionNotFound(f"session {session.id!r} is gone (expired or deleted)")
        if loaded.meta is not None:
            for name, value in self._stored_progress(loaded.meta).items():
                setattr(session, name, value)
        elif loaded.damage != "no stored state":
            aside = await self._on_pool(store.quarantine, session.id)
            log.error(
                "stored session state is damaged; the next frame starts a fresh history",
                extra={"session": session.id, "error": loaded.damage, "quarantined": aside},
            )
        session.state, session.reply = loaded.state, loaded.reply
        session.state_lost = loaded.meta is None
        session.store_version, session.resident = loaded.version, True
        self._update_gauges()

    def _stored_progress(self, meta: dict) -> dict:
        """The Session fields a stored record sets: progress, the shot's choice, its model."""
        choice = meta.get("choice")
        return {
            "last_index": meta["last_index"],
            "frames_done": meta["frames_done"],
            "resets": meta["resets"],
            "choice": Choice.from_dict(choice) if choice else None,
            "info": self._info_of(meta),
        }

    def _info_of(self, meta: dict) -> ModelInfo:
        """The model a stored session uses: its shot's choice (auto), else its model."""
        choice = meta.get("choice")
        name = choice["model"] if choice else self.models.resolve(meta["model"])
        return self.models.denoiser(name).info

    def _shapes_of(self, meta: dict) -> dict[str, tuple[int, ...]]:
        info, (w, h) = self._info_of(meta), (meta["width"], meta["height"])
        return history_shapes(info.state_specs, h, w)

    async def _ensure_resident(self, session: Session) -> None:
        if self.store is not None and self.store.shared:
            return await self._follow_store(session)
        if session.resident:
            return
        self._make_room(session.reserve_bytes, keep=session)
        if session.state_lost:  # nothing on disk to read: the next frame starts afresh
            session.resident = True
            return
        assert self.store is not None  # only durable sessions leave memory
        spec = session.spec
        shapes = history_shapes(session.info.state_specs, spec.height, spec.width)
        try:
            session.state, session.reply = await self._on_pool(
                self.store.read, session.id, shapes
            )
        except StateDamaged as exc:
            # Continue the sequence from a fresh history, said so in X-Quietframe-Reset; the
            # damaged file is kept aside for a look, never read again.
            aside = await self._on_pool(self.store.quarantine, session.id)
            log.error(
                "stored session state is damaged; the next frame starts a fresh history",
                extra={"session": session.id, "error": str(exc), "quarantined": str(aside)},
            )
            session.state, session.reply, session.state_lost = None, None, True
        session.resident = True
        self._update_gauges()

    def _commit(self, session: Session, frame: _Processed) -> None:
        session.commit(frame)
        self.sessions.move_to_end(session.id)
        self.metrics.frames.labels(frame.info.name, frame.reset.value).inc()
        for stage, ms in frame.timings_ms.items():
            self.metrics.latency.labels(stage).observe(ms / 1e3)
        for buffer, count in frame.sanitized.items():
            self.metrics.sanitized.labels(buffer).inc(count)
        self._update_gauges()

    def _update_gauges(self) -> None:
        self.metrics.sessions.set(len(self.sessions))
        self.metrics.history_bytes.set(sum(s.memory_bytes() for s in self.sessions.values()))

    # ---- durable state ------------------------------------------------------------------------

    def _load_durable(self) -> None:
        """Register the sessions of an earlier run (state stays on disk until their next frame).
        A damaged file is quarantined; its session continues from a fresh history (state-lost)
        when its settings file (written at creation) is intact."""
        assert self.store is not None
        for path, meta in self.store.metas():
            lost = "error" in meta  # unreadable, truncated, or another session's file
            settings = None if lost else self.store.read_spec(path.stem)
            if settings is not None and _spec_fields(meta) != _spec_fields(settings):
                # The settings file is the session as created: a state file that says otherwise
                # (another session's, rewritten under this id) is not this session's history.
                lost = True
                meta = {"error": "its settings differ from the session's settings file: "
                        f"{_spec_difference(meta, settings)}"}
            if lost:
                aside = self.store.quarantine_path(path)
                log.error(
                    "stored session file is damaged; moved aside",
                    extra={"file": path.name, "error": meta["error"], "quarantined": str(aside)},
                )
                meta = self.store.read_spec(path.stem)
                if meta is None:
                    log.error("no settings file either: session %s is gone", path.stem)
                    continue
            self._restore(path.stem, meta, lost)
        for session_id in self.store.spec_ids():  # settings without a state file
            if session_id not in self.sessions and not self.store.path(session_id).exists():
                meta = self.store.read_spec(session_id)
                if meta is not None:
                    log.error("session %s has no state file; continues afresh", session_id)
                    self._restore(session_id, meta, lost=True)
        if self.sessions:
            log.info("restored %d sessions from %s", len(self.sessions), self.store.folder)

    def _restore(self, session_id: str, meta: dict, lost: bool) -> None:
        try:
            spec = SessionSpec(
                model=self.models.requested(meta["model"]),
                width=meta["width"],
                height=meta["height"],
                precision=meta["precision"],
                compression=meta["compression"],
                channels=meta["channels"],
                motion_scale=tuple(meta["motion_scale"]),  # type: ignore[arg-type]
                layer=meta.get("layer"),
                denoised_layer=meta.get("denoised_layer"),
                quality=meta.get("quality"),
                latency_ms=meta.get("latency_ms"),
                model_options=dict(meta.get("model_options") or {}),  # absent in older files
            )
            self.models.check_options(spec.model, spec.model_options)  # the models may differ
            choice = Choice.from_dict(meta["choice"]) if meta.get("choice") else None
            if choice is not None and choice.model not in self.models.names:
                choice = None  # its model is gone: the next frame chooses again
        except Exception as exc:  # model no longer installed, or an incomplete meta
            log.warning("skipping stored session %s: %s", session_id, exc)
            return
        progress = {"last_index": None, "frames_done": 0, "resets": 0}
        if not lost:
            progress = {k: meta[k] for k in progress}
        session = self._session(
            session_id,
            spec,
            choice=choice,
            created_at=meta["created_at"],
            resident=lost,  # a lost session has nothing on disk to load
            state_lost=lost,
            **progress,
        )
        self.sessions[session.id] = session


def _spec_fields(meta: dict) -> dict:
    """What a stored record says the session is (SessionSpec's fields)."""
    fields = {name: meta.get(name) for name in SessionSpec.__dataclass_fields__}
    fields["model_options"] = fields["model_options"] or {}  # absent in older files
    return fields


def _spec_difference(meta: dict, settings: dict) -> str:
    a, b = _spec_fields(meta), _spec_fields(settings)
    return ", ".join(f"{k} {a[k]!r} (settings file: {b[k]!r})" for k in a if a[k] != b[k])
