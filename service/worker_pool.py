"""Everything a server runs off its event loop, one method per kind of work. The loop only
keeps the books (sessions, locks, budgets): a frame's heavy part (a retry's digest, decoding,
the model choice, denoising, encoding) and every call to the session store (disk or Redis I/O,
which may hang until the store's timeout) run on the bounded worker pool, so /healthz and other
sessions' requests go on being answered meanwhile."""

from __future__ import annotations

import asyncio
import mmap
from collections.abc import Callable, Mapping, MutableMapping
from concurrent.futures import Executor
from typing import TypeVar

import numpy as np

from quietframe.runtime.stream import Stream
from quietframe.service.choice_policy import Choice
from quietframe.service.frame_context import FrameContext
from quietframe.service.frame_path import finish_frame, process_frame
from quietframe.service.model_registry import ModelRegistry
from quietframe.service.session import ProcessedFrame, Session
from quietframe.service.session_spec import SessionSpec
from quietframe.service.session_store import Reply, Store
from quietframe.service.shot_choice import choose_for_shot, estimate_for_shot
from quietframe.service.state_store_redis import Loaded, RedisStore
from quietframe.wire.protocol import Reset

T = TypeVar("T")
Body = bytes | bytearray | mmap.mmap
Shapes = Mapping[str, tuple[int, ...]]


class WorkerPool:
    def __init__(self, executor: Executor) -> None:
        self._executor = executor

    async def _run(self, fn: Callable[..., T], *args) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._executor, fn, *args)

    # ---- a frame, while its session's lock is held ------------------------------------------

    async def plan_frame(self, session: Session, index: int, body: Body, cut: bool
                         ) -> Reply | Reset:
        """`Session.plan`: a retry hashes its whole body (up to ~2 s at 2 GiB)."""
        return await self._run(session.plan, index, body, cut)

    async def choose_for_shot(self, context: FrameContext, body: Body, spec: SessionSpec,
                              models: ModelRegistry, keep: str | None
                              ) -> tuple[FrameContext, Choice]:
        """model=auto at a shot's first frame: decode, measure the noise, choose."""
        return await self._run(choose_for_shot, context, body, spec, models, keep)

    async def estimate_for_shot(self, context: FrameContext, body: Body,
                                models: ModelRegistry) -> tuple[FrameContext, float | None]:
        """A named model reading the spp, none stated, at a shot's first frame: decode and
        estimate the shot's spp."""
        return await self._run(estimate_for_shot, context, body, models)

    async def process_frame(self, stream: Stream, spec: SessionSpec, index: int, body: Body,
                            context: FrameContext, reset: Reset,
                            state: dict[str, np.ndarray] | None, choice: Choice | None,
                            window: dict[str, np.ndarray] | None = None,
                            shot_spp: float | None = None) -> ProcessedFrame:
        """Decode, denoise, encode (service/frame_path.py)."""
        return await self._run(process_frame, stream, spec, index, body, context, reset, state,
                               choice, window, shot_spp)

    async def finish_frame(self, session: Session) -> ProcessedFrame:
        """A look-ahead session's oldest pending frame finished (service/frame_path.py)."""
        return await self._run(finish_frame, session)

    # ---- the session store ------------------------------------------------------------------
    # `store.<method>` is looked up at each call, not bound once: a test may replace one.

    async def write_spec(self, store: Store, meta: Mapping) -> None:
        await self._run(store.write_spec, meta)

    async def write_record(self, store: Store, meta: Mapping,
                           state: MutableMapping[str, np.ndarray] | None, reply: Reply | None,
                           expect: str | None) -> str | None:
        """A session's record, state and last reply; its new version (shared store: fenced
        on `expect`)."""
        return await self._run(store.write, meta, state, reply, expect)

    async def read_state(self, store: Store, session_id: str, shapes: Shapes
                         ) -> tuple[dict[str, np.ndarray] | None, Reply | None]:
        return await self._run(store.read, session_id, shapes)

    async def find_record(self, store: RedisStore, session_id: str
                          ) -> tuple[dict, bool] | None:
        return await self._run(store.find, session_id)

    async def stored_version(self, store: RedisStore, session_id: str) -> str | None:
        return await self._run(store.version, session_id)

    async def load_session(self, store: RedisStore, session_id: str,
                           shapes_of: Callable[[dict], Shapes]) -> Loaded | None:
        return await self._run(store.load, session_id, shapes_of)

    async def quarantine(self, store: Store, session_id: str) -> object:
        return await self._run(store.quarantine, session_id)

    async def delete_session(self, store: Store, session_id: str) -> None:
        await self._run(store.delete, session_id)

    def delete_session_soon(self, store: Store, session_id: str) -> None:
        """Delete on the pool without waiting for it (an expired session's files)."""
        self._executor.submit(store.delete, session_id)
