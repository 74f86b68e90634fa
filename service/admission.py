"""Memory admission: a frame reserves the memory it will hold before any of it is allocated.

One budget (QUIETFRAME_MEMORY_BUDGET_MB) counts every frame in flight: the header bytes while
they arrive, then the body's bytes as they arrive (a slow upload holds what it sent, not its
frame's peak), then, once the body is complete, the whole frame: its body, the channels the
decoder returns, the canonical float32 buffers, the model's working set and new state, and the
reply being encoded. A frame that does not fit waits a little (QUIETFRAME_ADMISSION_WAIT_S) for
others to finish, then gets 429 with Retry-After; a frame larger than the whole budget gets 413
as soon as its header is read (no retry can help). The history budget
(session_table.py) counts what sessions keep between frames; together they bound the server's
memory above its base (models, interpreter).

Everything here runs on the event loop thread: no locks.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Iterable

from quietframe.runtime import Denoiser, aux_motion
from quietframe.runtime.motion_evidence import history_nbytes
from quietframe.service.errors import FrameOverMemoryBudget, MemoryBusy
from quietframe.service.frames import ExrHeader

CANONICAL_CHANNELS = 12  # color 3, albedo 3, normal 3, depth 1, motion 2: float32 planes
RETRY_AFTER_S = 2  # frames at test sizes finish in well under this; large ones free it sooner
_SLACK_BYTES = 1 << 20  # decoder chunk buffers, Python objects, response framing


def model_working_set(denoiser: Denoiser, height: int, width: int) -> int:
    """Bytes a model holds while denoising one height x width frame, beside the frame's
    buffers: its working set (the runtime's estimate: graph tiles, OIDN's filters and scratch),
    its new state (the old one is in the history budget) and, for a temporal model, motion
    estimated from the aux (runtime/aux_motion.py)."""
    temporal = bool(denoiser.info.state_specs)  # may estimate motion from the aux
    return (denoiser.working_set_bytes(height, width)
            + history_nbytes(denoiser.info.state_specs, height, width)
            + (aux_motion.working_set_bytes(height, width) if temporal else 0))


# Memory one EXR part holds beyond its pixels while the frame is decoded and its reply written
# (OpenEXR's part structures and offset tables, the part's attribute and channel dicts): the
# 2026-12-06 audit's 20 000 one-channel parts grew RSS by 4.7 GiB, ~240 KiB a part.
PART_OVERHEAD_BYTES = 256 << 10


def frame_need(header: ExrHeader, body_bytes: int, models: Iterable[Denoiser]) -> int:
    """What one frame holds at its peak, in bytes, from its header alone; `models`: those that
    may denoise it (model=auto: any installed one, the largest counts)."""
    pixels = header.width * header.height
    model = max(model_working_set(m, header.height, header.width) for m in models)
    decoded = header.pixel_bytes  # every channel of every part, as the decoder returns them
    buffers = CANONICAL_CHANNELS * 4 * pixels
    # The reply: the input's channels again (written uncompressed at worst), the denoised
    # colour, the header's attributes as Python objects and written back.
    reply = header.pixel_bytes + 3 * 4 * pixels + 2 * header.header_bytes
    parts = header.parts * PART_OVERHEAD_BYTES  # the decoder's and the writer's own per part
    return (body_bytes + decoded + buffers + model + reply + header.header_bytes + parts
            + _SLACK_BYTES)


class Reservation:
    """Bytes held in the budget by one frame; grows, and is released exactly once."""

    def __init__(self, budget: MemoryBudget, nbytes: int) -> None:
        self.budget, self.nbytes = budget, nbytes

    def grow_to(self, nbytes: int) -> None:
        """Grow now or raise MemoryBusy (for bytes already arriving: no waiting)."""
        if nbytes > self.nbytes:
            self.budget._take(nbytes - self.nbytes)
            self.nbytes = nbytes

    def check_fits(self, nbytes: int, what: str) -> None:
        """FrameOverMemoryBudget (413) when `nbytes` is more than the whole budget: no wait or
        retry can help, so it is said before any of them is reserved."""
        budget = self.budget
        if nbytes > budget.limit_bytes:
            raise FrameOverMemoryBudget(
                f"{what} needs {nbytes / 2**20:.0f} MiB in flight; this server's memory budget "
                f"is {budget.limit_bytes / 2**20:.0f} MiB (QUIETFRAME_MEMORY_BUDGET_MB): send "
                "fewer or half-float channels, or raise the budget"
            )

    async def admit(self, nbytes: int, what: str) -> None:
        """Grow to `nbytes`, waiting up to the budget's wait for frames in flight to finish;
        FrameOverMemoryBudget when it can never fit, MemoryBusy when it does not in time."""
        self.check_fits(nbytes, what)
        budget = self.budget
        deadline = time.monotonic() + budget.wait_s
        while True:
            try:
                self.grow_to(nbytes)
                return
            except MemoryBusy:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise
                await budget._changed(left)

    def shrink_to(self, nbytes: int) -> None:
        """Give back what is held above `nbytes` (a buffer that no longer grows)."""
        if nbytes < self.nbytes:
            self.budget._give(self.nbytes - nbytes)
            self.nbytes = nbytes

    def release(self) -> None:
        if self.nbytes:
            self.budget._give(self.nbytes)
            self.nbytes = 0


class MemoryBudget:
    def __init__(self, limit_bytes: int, wait_s: float) -> None:
        self.limit_bytes, self.wait_s = limit_bytes, wait_s
        self.used_bytes = 0
        self.peak_bytes = 0  # for the status and tests: the most ever reserved at once
        self._waiters: list[asyncio.Future] = []

    def reserve(self, nbytes: int) -> Reservation:
        """A new reservation of `nbytes` now (MemoryBusy if they do not fit)."""
        self._take(nbytes)
        return Reservation(self, nbytes)

    def _take(self, nbytes: int) -> None:
        if self.used_bytes + nbytes > self.limit_bytes:
            raise MemoryBusy(
                f"the frames in flight hold {self.used_bytes / 2**20:.0f} of this server's "
                f"{self.limit_bytes / 2**20:.0f} MiB memory budget; this one needs "
                f"{nbytes / 2**20:.1f} MiB more: retry after Retry-After seconds",
                headers={"Retry-After": str(RETRY_AFTER_S), "Connection": "close"},
            )
        self.used_bytes += nbytes
        self.peak_bytes = max(self.peak_bytes, self.used_bytes)

    def _give(self, nbytes: int) -> None:
        self.used_bytes -= nbytes
        waiters, self._waiters = self._waiters, []
        for waiter in waiters:
            if not waiter.done():
                waiter.set_result(None)

    async def _changed(self, timeout_s: float) -> None:
        """Wait until some memory is given back (or `timeout_s`)."""
        waiter = asyncio.get_running_loop().create_future()
        self._waiters.append(waiter)
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(waiter, timeout_s)
