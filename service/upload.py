"""Receiving a frame body: refused as early as its bytes allow, held in memory it reserved.

1. The magic number and the EXR header are checked as they arrive: each chunk's attributes are
   parsed once (exr_header.HeaderScan), on a worker thread once the header is past 64 KiB (16 MiB
   of tiny attributes is seconds of Python, and the event loop must keep answering). The
   header's bytes count against the memory budget as they grow, and it may be at most
   QUIETFRAME_MAX_HEADER_BYTES (its attribute values are not copied while it is parsed).
2. The header's data and display windows must be the session's size (422), the body at most
   the header's largest possible file (413), and the frame's peak memory
   (admission.frame_need) within the whole budget (413): all before any body buffer exists.
3. The body is received into one buffer: with Content-Length, an anonymous mapping of that
   size whose pages become memory only as bytes are written; chunked, a buffer that grows with
   the bytes received. The budget holds the bytes received, not the frame's peak: a slow upload
   holds what it sent, and other frames do not wait for memory it does not use yet (a full
   budget pauses the reading, then 429, as admission does).
4. Once the body is complete, the rest of the frame's peak is reserved, waiting briefly when
   other frames hold the budget (429 after that).
The request guard (guard.py) has already held the body to the frame limit, a pause limit and a
minimum rate; the upload's slot (upload_slots.py) learns its size and progress from here, and
may cut the reading for its time.
"""

from __future__ import annotations

import asyncio
import mmap
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import NoReturn

from starlette.requests import Request

from quietframe.service import frames
from quietframe.service.admission import MemoryBudget, Reservation
from quietframe.service.errors import BodyTooLarge, InvalidRequest
from quietframe.service.settings import Settings
from quietframe.service.upload_slots import Upload

Body = bytearray | mmap.mmap
Need = Callable[[frames.ExrHeader, int], int]
_FIRST_RESERVE = 1 << 16
# A header up to this size is parsed on the event loop (a few ms); a larger one on the parser
# thread. One thread: however many large headers arrive, the event loop shares the GIL with one.
_INLINE_HEADER_BYTES = 1 << 16
_header_parser = ThreadPoolExecutor(1, thread_name_prefix="quietframe-header")


async def read_frame(
    request: Request,
    settings: Settings,
    size: tuple[int, int],
    budget: MemoryBudget,
    need: Need,
    upload: Upload | None = None,
) -> tuple[Body, frames.ExrHeader, Reservation]:
    """The body, its parsed header and the reservation it holds (the caller releases it once
    the frame is done). `size`: the session's (width, height); `need(header, body_bytes)`:
    the frame's peak memory; `upload`: its slot, told the body's size and progress."""
    reservation = budget.reserve(_FIRST_RESERVE)
    try:
        body, header = await _receive(request, settings, size, reservation, need, upload)
    except BaseException:
        reservation.release()
        raise
    return body, header, reservation


async def _receive(
    request: Request,
    settings: Settings,
    size: tuple[int, int],
    reservation: Reservation,
    need: Need,
    upload: Upload | None,
) -> tuple[Body, frames.ExrHeader]:
    expected = declared_length(request)
    scan = frames.HeaderScan(settings.max_width, settings.max_height, settings.max_header_bytes)
    head, header = bytearray(), None
    body: Body = head
    received, bound = 0, settings.max_body_bytes
    async for chunk in request.stream():
        if not chunk:
            continue
        if header is None:
            head += chunk
            received = len(head)
            if upload is not None:
                upload.received = received
            reservation.grow_to(2 * received)  # the buffer and its copy while it grows
            header = await _header_so_far(scan, head)
            if header is None:
                continue
            bound = _check_header(header, size, expected, bound, reservation, need)
            if upload is not None and expected is None:
                upload.sized(bound)  # a chunked body: its share from the header's bound
            if expected is not None:
                body = mmap.mmap(-1, expected)  # pages become memory as they are written
                body[:received] = head
                head.clear()
            continue
        if received + len(chunk) > bound:
            _check_size(received + len(chunk), bound, header)
        if expected is not None:
            if received + len(chunk) > expected:
                raise InvalidRequest(f"body is longer than its Content-Length {expected}")
            await _hold(reservation, received + len(chunk), header)
            body[received : received + len(chunk)] = chunk
        else:
            await _hold(reservation, 2 * (received + len(chunk)), header)  # and its copy
            head += chunk
        received += len(chunk)
        if upload is not None:
            upload.received = received
    if header is None:
        _ended_inside_header(head, settings)
    if expected is not None and received != expected:
        raise InvalidRequest(f"body ended after {received} of its {expected} declared bytes")
    if upload is not None:
        upload.finished()  # never cut from here on
    await _admit(reservation, need, header, received)  # the rest of the frame's peak
    return body, header


def declared_length(request: Request) -> int | None:
    """The body's Content-Length (the guard refused one that is no byte count); None: chunked."""
    declared = request.headers.get("content-length")
    return int(declared) if declared and declared.isdigit() else None


async def _header_so_far(scan: frames.HeaderScan, head: bytearray) -> frames.ExrHeader | None:
    """The header once `head` holds all of it, else None; a large one is parsed on the parser
    thread (`head` does not change meanwhile: the next chunk is read after this returns)."""
    if len(head) <= _INLINE_HEADER_BYTES:
        return scan.advance(head)
    return await asyncio.get_running_loop().run_in_executor(_header_parser, scan.advance, head)


def _ended_inside_header(head: bytearray, settings: Settings) -> NoReturn:
    """Raise for a body that ended before its header did (parsed already: not again)."""
    if len(head) < 8:
        frames.read_header(head, settings.max_width, settings.max_height)  # bad magic number
    raise frames.TruncatedExr("EXR header is truncated")


def _check_header(
    header: frames.ExrHeader,
    size: tuple[int, int],
    expected: int | None,
    bound: int,
    reservation: Reservation,
    need: Need,
) -> int:
    """422 / 413 from the header alone, before any body buffer exists: the session's size, the
    body's size, the frame's peak against the whole budget. Returns the body's bound."""
    frames.check_windows(header, *size)
    bound = min(bound, header.max_bytes)
    if expected is not None:
        _check_size(expected, bound, header)
    peak = need(header, expected if expected is not None else bound)
    reservation.check_fits(peak, _what(header))
    return bound


async def _hold(reservation: Reservation, nbytes: int, header: frames.ExrHeader) -> None:
    """Hold `nbytes` of received body; when the budget is full the body waits (unread) for
    frames in flight to finish, as admission does."""
    if nbytes > reservation.nbytes:
        await reservation.admit(nbytes, _what(header))


async def _admit(
    reservation: Reservation, need: Need, header: frames.ExrHeader, body_bytes: int
) -> None:
    """Hold the frame's peak: grow to it (waiting, then 429), or give back what a chunked
    body's growing buffer held above it."""
    peak = need(header, body_bytes)
    await reservation.admit(peak, _what(header))
    reservation.shrink_to(peak)


def _what(header: frames.ExrHeader) -> str:
    return f"a {header.width}x{header.height} frame with {len(header.channels)} channels"


def _check_size(size: int, bound: int, header: frames.ExrHeader) -> None:
    if size > bound:
        raise BodyTooLarge(
            f"body is {size} bytes; a {header.width}x{header.height} EXR with these "
            f"{len(header.channels)} channels has at most {bound} bytes (this server's frame "
            "limit or the file's uncompressed size)",
            headers={"Connection": "close"},
        )
