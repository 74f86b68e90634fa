"""Upload slots: at most QUIETFRAME_MAX_UPLOADS frame bodies are received at once, and slow ones
cannot keep every other session out.

An upload's share of its slot is the pause grace (QUIETFRAME_BODY_READ_TIMEOUT_S) plus its
body's size at QUIETFRAME_UPLOAD_SHARE_RATE_KIB_S; the size is the Content-Length, or for a
chunked body the header's largest possible file once the header is in (the frame limit before).
- While a slot is free nobody waits, so an upload may run past its share: a slow link still
  delivers to a quiet server (the minimum rate and the pause limit of guard.py still apply).
- When every slot is taken, a new upload takes the slot of the one furthest past its share,
  which is closed with 408 `upload_too_slow`; when none is past it, the new one gets 429 with
  Retry-After: the seconds until the first slot is expected to free (an upload's finish at its
  rate so far, or the end of its share, whichever is sooner), 1 to 30 s. A session waits at
  most one share for a slot, however long the slow uploads would take.
- Whether a slot is wanted or not, no body may take longer than QUIETFRAME_MAX_UPLOAD_S (408).
- One session holds at most QUIETFRAME_MAX_UPLOADS_PER_SESSION slots (429 past it): its frames
  come one at a time, so one session's slow uploads cannot take every slot in the first place.
A cut ends only the body's reading (its reservation is given back, the session is not touched);
a body already complete (its frame waiting for memory or being denoised) is never cut.

Slots are counted per session, not per client address: behind the load balancer every client
has its address (deploy/haproxy.cfg), so a limit per address belongs there.
Everything here runs on the event loop thread: no locks.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import AsyncIterator

from quietframe.service.errors import TooManyUploads, UploadTooSlow
from quietframe.service.settings import Settings

MAX_RETRY_AFTER_S = 30  # the client's longest wait between tries; a later try is as good


class Upload:
    """One frame body being received: its size, its progress, its share and its cut."""

    def __init__(self, session_id: str, expected: int, started: float, slots: UploadSlots,
                 task: asyncio.Task) -> None:
        self.session_id, self.started, self._slots, self._task = session_id, started, slots, task
        self.received = 0
        self.complete = False
        self.cut_detail: str | None = None  # why it was cut: the 408's detail
        self.sized(expected)
        self._timer = asyncio.get_running_loop().call_at(
            started + slots.cap_s, self.cut, f"the body took longer than {slots.cap_s:.0f} s "
            "(QUIETFRAME_MAX_UPLOAD_S), the most this server gives one frame body")

    def sized(self, expected: int) -> None:
        """The body's size (its bound, for a chunked body once its header is in): its share."""
        self.expected = expected
        self.share_ends = self.started + self._slots.share_s(expected)

    def finished(self) -> None:
        """The whole body is in: from here on the upload is never cut."""
        self.complete = True
        self._timer.cancel()

    def cut(self, why: str) -> None:
        """End the reading at the await it is suspended at (inside read_frame: the body is not
        complete), to be answered 408 `upload_too_slow`."""
        if self.complete or self.cut_detail is not None:
            return
        elapsed = asyncio.get_running_loop().time() - self.started
        self.cut_detail = (f"{why}; {self.received} of {self.expected} bytes arrived in "
                           f"{elapsed:.1f} s ({self.received / max(elapsed, 1e-9):.0f} bytes/s): "
                           "send frame bodies from a faster link, or when the server is less busy")
        self._timer.cancel()
        self._task.cancel()

    def frees_at(self, now: float, by_share: bool) -> float:
        """When its slot is expected to free: at once once complete, else its finish at its rate
        so far, the end of its share (`by_share`: a new upload may take its slot then) or its
        cap, whichever is soonest."""
        if self.complete:
            return now
        ends = min(self.share_ends, self._timer.when()) if by_share else self._timer.when()
        if self.received:
            ends = min(ends, self.started + (now - self.started) * self.expected / self.received)
        return ends


class UploadSlots:
    def __init__(self, limit: int, per_session: int, share_rate_bytes_s: float, grace_s: float,
                 cap_s: float) -> None:
        self.limit, self.per_session, self.cap_s = limit, per_session, cap_s
        self.share_rate_bytes_s, self.grace_s = share_rate_bytes_s, grace_s
        self._held: list[Upload] = []  # cut ones too, until their reading has unwound

    @classmethod
    def from_settings(cls, settings: Settings) -> UploadSlots:
        return cls(settings.max_uploads, settings.max_uploads_per_session,
                   settings.upload_share_rate_bytes_s, settings.body_read_timeout_s,
                   settings.upload_cap_s)

    @property
    def count(self) -> int:
        """Slots taken (a cut upload's slot is free already)."""
        return len(self._live())

    def share_s(self, nbytes: int) -> float:
        return self.grace_s + nbytes / self.share_rate_bytes_s

    @contextlib.asynccontextmanager
    async def hold(self, session_id: str, expected: int) -> AsyncIterator[Upload]:
        """A slot for one body of at most `expected` bytes while the block reads it; TooManyUploads
        (429) when none can be had, UploadTooSlow (408) when the upload is cut."""
        task = asyncio.current_task()
        assert task is not None
        loop = asyncio.get_running_loop()
        self._make_room(session_id, loop.time())
        upload = Upload(session_id, expected, loop.time(), self, task)
        self._held.append(upload)
        try:
            yield upload
        except asyncio.CancelledError:
            if upload.cut_detail is None:
                raise  # not ours: the server stopping, the client gone
            _uncancel(task)
            raise UploadTooSlow(upload.cut_detail, headers={"Connection": "close"}) from None
        finally:
            upload.finished()
            self._held.remove(upload)

    def _live(self) -> list[Upload]:
        return [u for u in self._held if u.cut_detail is None]

    def _make_room(self, session_id: str, now: float) -> None:
        """Return when a new upload of `session_id` may take a slot (cutting the one furthest
        past its share when every slot is taken); TooManyUploads otherwise."""
        live = self._live()
        mine = [u for u in live if u.session_id == session_id]
        if len(mine) >= self.per_session:
            raise TooManyUploads(
                f"{len(mine)} frame bodies of this session are being received "
                f"(QUIETFRAME_MAX_UPLOADS_PER_SESSION is {self.per_session}): send a session's "
                "frames one at a time; retry after Retry-After seconds",
                headers=_retry_headers(mine, now, by_share=False))
        if len(live) < self.limit:
            return
        overdue = [u for u in live if not u.complete and u.share_ends <= now]
        if not overdue:
            raise TooManyUploads(
                f"{len(live)} frame bodies are being received (QUIETFRAME_MAX_UPLOADS), each "
                "within its share of time; retry after Retry-After seconds",
                headers=_retry_headers(live, now, by_share=True))
        slowest = min(overdue, key=lambda u: u.share_ends)
        slowest.cut(f"every upload slot was taken and this body had had its share, "
                    f"{slowest.share_ends - slowest.started:.0f} s (QUIETFRAME_BODY_READ_TIMEOUT_S "
                    f"+ its size at QUIETFRAME_UPLOAD_SHARE_RATE_KIB_S "
                    f"{self.share_rate_bytes_s / 1024:g}), so another upload took its slot")


def _retry_headers(uploads: list[Upload], now: float, by_share: bool) -> dict[str, str]:
    soonest = min(u.frees_at(now, by_share) for u in uploads)
    seconds = min(MAX_RETRY_AFTER_S, max(1, math.ceil(soonest - now)))
    return {"Retry-After": str(seconds), "Connection": "close"}


def _uncancel(task: asyncio.Task) -> None:
    """Python 3.11+ counts a task's pending cancellations: the cut is handled, so it no longer
    counts (asyncio.timeout does the same for its own)."""
    uncancel = getattr(task, "uncancel", None)
    if uncancel is not None:
        uncancel()
