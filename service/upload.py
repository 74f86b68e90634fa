"""Receiving a frame body: refused as early as its bytes allow, held in memory it reserved.

1. The magic number and the EXR header are checked as they arrive; the header's bytes count
   against the memory budget as they grow, and it may be at most QUIETFRAME_MAX_HEADER_BYTES
   (its attribute values are not copied while it is parsed).
2. The header's data and display windows must be the session's size, and the body at most the
   header's largest possible file: 422 / 413 before any body buffer exists.
3. The frame's whole peak memory (admission.frame_need) is reserved, waiting briefly when
   other frames hold the budget (429 after that).
4. The body is received into one buffer: with Content-Length, an anonymous mapping of that
   size whose pages become memory only as bytes are written (a stalled upload holds what it
   sent, not what it announced); chunked, a buffer that grows with the bytes received.
The request guard (guard.py) has already held the body to the frame limit, a pause limit and a
minimum rate.
"""

from __future__ import annotations

import mmap
from collections.abc import Callable

from starlette.requests import Request

from quietframe.service import frames
from quietframe.service.admission import MemoryBudget, Reservation
from quietframe.service.errors import BodyTooLarge, InvalidRequest
from quietframe.service.settings import Settings

Body = bytearray | mmap.mmap
_FIRST_RESERVE = 1 << 16


async def read_frame(
    request: Request,
    settings: Settings,
    size: tuple[int, int],
    budget: MemoryBudget,
    need: Callable[[frames.ExrHeader, int], int],
) -> tuple[Body, frames.ExrHeader, Reservation]:
    """The body, its parsed header and the reservation it holds (the caller releases it once
    the frame is done). `size`: the session's (width, height); `need(header, body_bytes)`:
    the frame's peak memory."""
    reservation = budget.reserve(_FIRST_RESERVE)
    try:
        body, header = await _receive(request, settings, size, reservation, need)
    except BaseException:
        reservation.release()
        raise
    return body, header, reservation


async def _receive(
    request: Request,
    settings: Settings,
    size: tuple[int, int],
    reservation: Reservation,
    need: Callable[[frames.ExrHeader, int], int],
) -> tuple[Body, frames.ExrHeader]:
    declared = request.headers.get("content-length")
    expected = int(declared) if declared and declared.isdigit() else None
    head, header, next_parse = bytearray(), None, 8
    body: Body = head
    received, bound = 0, settings.max_body_bytes
    async for chunk in request.stream():
        if not chunk:
            continue
        if header is None:
            head += chunk
            received = len(head)
            reservation.grow_to(2 * received)  # the buffer and its copy while it grows
            if received < next_parse:
                continue
            header = _header_so_far(head, settings)
            if header is None:  # more header to come: parse again once the bytes double
                next_parse = 2 * received
                continue
            frames.check_windows(header, *size)  # 422 before any body buffer exists
            bound = min(bound, header.max_bytes)
            if expected is not None:
                _check_size(expected, bound, header)
            await _admit(reservation, need, header, expected if expected is not None else bound)
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
            body[received : received + len(chunk)] = chunk
        else:
            head += chunk
        received += len(chunk)
    if header is None:  # the whole body arrived before the next parse
        header = frames.read_header(
            head, settings.max_width, settings.max_height, settings.max_header_bytes
        )  # raises BadExr
        frames.check_windows(header, *size)
        await _admit(reservation, need, header, received)
    if expected is not None and received != expected:
        raise InvalidRequest(f"body ended after {received} of its {expected} declared bytes")
    return body, header


async def _admit(
    reservation: Reservation,
    need: Callable[[frames.ExrHeader, int], int],
    header: frames.ExrHeader,
    body_bytes: int,
) -> None:
    what = f"a {header.width}x{header.height} frame with {len(header.channels)} channels"
    await reservation.admit(need(header, body_bytes), what)


def _header_so_far(data: bytearray, settings: Settings) -> frames.ExrHeader | None:
    try:
        return frames.read_header(
            data, settings.max_width, settings.max_height, settings.max_header_bytes
        )
    except frames.TruncatedExr:
        return None


def _check_size(size: int, bound: int, header: frames.ExrHeader) -> None:
    if size > bound:
        raise BodyTooLarge(
            f"body is {size} bytes; a {header.width}x{header.height} EXR with these "
            f"{len(header.channels)} channels has at most {bound} bytes (this server's frame "
            "limit or the file's uncompressed size)",
            headers={"Connection": "close"},
        )
