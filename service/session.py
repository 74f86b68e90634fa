"""One session: its settings, its state and progress, the frame order it enforces, and what it
reports and stores. A frame changes a session only through `commit`, after everything
succeeded: a rejected frame never changes the state."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone

import numpy as np

from quietframe.client.session_fields import AUTO
from quietframe.runtime import ModelInfo
from quietframe.runtime.motion_evidence import history_nbytes
from quietframe.runtime.stream import Stream
from quietframe.service import lookahead_queue
from quietframe.service.choice_policy import Choice
from quietframe.service.errors import FrameConflict, FrameOutOfOrder
from quietframe.service.measured_speed import MeasuredSpeeds
from quietframe.service.schemas import ChoicePublic, ModelRef, SessionPublic, StageTimings
from quietframe.service.session_spec import SessionSpec
from quietframe.service.session_store import Reply
from quietframe.wire.protocol import Reset

STAGES = ("decode", "denoise", "encode", "total")
REPLY_MARGIN_BYTES = 2**16  # headers and EXR framing around the pixels


@dataclass
class ProcessedFrame:
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
    pending: list[int] = field(default_factory=list)  # look-ahead: frames held back after it
    finish: bool = False  # a held-back frame finished (POST .../finish), not a frame denoised
    # a named model's estimate of the shot's spp as of this frame (see Session); None: none
    shot_spp: float | None = None


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
    # A named model reading the frame's spp, none stated: the spp estimated at the shot's first
    # frame (service/shot_choice.estimate_for_shot), kept for its other frames as auto's choice
    shot_spp: float | None = None
    pending: list[int] = field(default_factory=list)  # look-ahead: frames held back, oldest first
    timing_sum: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    timing_last: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    lock: asyncio.Lock = field(default_factory=asyncio.Lock, repr=False)
    # The sequence on the model in use (runtime/stream.py): built by the first frame, again
    # when auto's choice changes the model; what it keeps between frames (OIDN's filters)
    # counts in the history budget and is let go when the budget needs the room.
    stream: Stream | None = field(default=None, repr=False)

    @property
    def kept_bytes(self) -> int:
        """Bytes the session's stream keeps between frames beside the state (OIDN's filters)."""
        return self.stream.kept_bytes if self.stream is not None else 0

    def close_stream(self) -> None:
        """Let go of the stream (no frame of this session may be running)."""
        if self.stream is not None:
            self.stream.close()
            self.stream = None

    @property
    def history(self) -> dict[str, np.ndarray] | None:
        """The state the next frame's model reads (a look-ahead session's window aside)."""
        return lookahead_queue.split(self.state)[0]

    @property
    def window(self) -> dict[str, np.ndarray]:
        """A look-ahead session's frames held back (runtime/lookahead.py's window)."""
        return lookahead_queue.split(self.state)[1]

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
            if reply and reply.finish:  # a look-ahead session finished a frame since
                raise FrameConflict(
                    f"frame {index} was already denoised, and a pending frame was finished "
                    "after it (its reply is that finish's); send the next index for a new frame")
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

    def commit(self, frame: ProcessedFrame) -> None:
        self.state_lost = False
        self.state = frame.state
        self.reply = frame.reply
        self.pending = list(frame.pending)
        if frame.finish:  # a held-back frame left: no frame was denoised
            self.last_used = time.monotonic()
            return
        self.last_index = frame.reply.index
        self.frames_done += 1
        self.resets += frame.reset is not Reset.NONE
        self.sources, self.missing = frame.sources, frame.missing
        self.info = frame.info
        if frame.choice is not None:
            self.choice = frame.choice
        self.shot_spp = frame.shot_spp
        for stage in STAGES:
            self.timing_sum[stage] += frame.timings_ms[stage]
            self.timing_last[stage] = frame.timings_ms[stage]
        self.last_used = time.monotonic()

    def meta(self, after: ProcessedFrame | None = None) -> dict:
        """The stored record of the session, as it will be once `after` is committed."""
        choice = after.choice if after is not None and after.choice else self.choice
        frame = after if after is not None and not after.finish else None
        shot_spp = frame.shot_spp if frame is not None else self.shot_spp
        meta = {
            "choice": choice.to_dict() if choice else None,
            "shot_spp": shot_spp,
            "id": self.id,
            **self.spec.model_dump(),
            "created_at": self.created_at,
            "last_index": frame.reply.index if frame else self.last_index,
            "frames_done": self.frames_done + (frame is not None),
            "resets": self.resets + (frame is not None and frame.reset is not Reset.NONE),
        }
        if self.spec.lookahead:
            meta["pending"] = list(after.pending if after is not None else self.pending)
        return meta

    def public(self, ttl_s: float, speeds: MeasuredSpeeds | None = None) -> SessionPublic:
        """The session as the API shows it; `speeds`: this server's measured times, said in
        the choice beside the tables' figure."""
        done = max(self.frames_done, 1)
        return SessionPublic(
            **self.spec.model_dump(exclude={"model"}),
            id=self.id,
            model=(None if self.spec.model == AUTO and self.choice is None  # nothing chosen yet
                   else ModelRef(name=self.info.name, version=self.info.version)),
            requested_model=self.spec.model,
            choice=self.choice_public(speeds),
            required_buffers=list(self.info.required_buffers),
            optional_buffers=list(self.info.optional_buffers),
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
            pending=self.pending,
        )

    def choice_public(self, speeds: MeasuredSpeeds | None) -> ChoicePublic | None:
        if self.choice is None:
            return None
        measured = speeds.at(self.choice.model, self.spec.height, self.spec.width) if (
            speeds is not None) else None
        if measured is None:
            return ChoicePublic(**self.choice.to_dict())
        return ChoicePublic(**self.choice.to_dict(), measured_ms=measured.ms,
                            measured_frames=measured.frames,
                            measured_size=f"{measured.width}x{measured.height}")


def reserve_bytes(info: ModelInfo, spec: SessionSpec) -> int:
    """What a new session counts against the history budget: its state and a reply of at least
    the denoised colour planes (the reply is the whole input file: the registry grows the
    reservation to its real size on the first frame)."""
    reply = 3 * spec.width * spec.height * (2 if spec.precision == "half" else 4)
    held = lookahead_queue.reserve_bytes(spec.lookahead, spec.height, spec.width, reply)
    return (history_nbytes(info.state_specs, spec.height, spec.width) + reply + held
            + REPLY_MARGIN_BYTES)
