"""Checks made before routing and before any body byte is read: the bearer token, the body
limit, the time allowed between body chunks, and a client that goes away mid-body.

A pure ASGI middleware because FastAPI reads and parses a JSON body before any dependency runs:
the token check in a dependency came after an unbounded read. Small JSON bodies are read here,
whole and bounded, then handed on; a frame body is handed on as a bounded, timed stream that the
frame route reads itself (it checks the EXR header as the first bytes arrive).
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import math
import re
import resource
import time
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from starlette.datastructures import Headers
from starlette.requests import ClientDisconnect
from uvicorn.protocols.http.auto import AutoHTTPProtocol

from quietframe.service.errors import BodyReadTimeout, BodyTooLarge, error_body
from quietframe.service.settings import Settings

log = logging.getLogger("quietframe.service")

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]

FRAME_PATH = re.compile(r"^/v1/sessions/[^/]+/frames/[^/]+/?$")
_AUTH_CHALLENGE = 'Bearer realm="quietframe"'
_RESERVED_FILES = 64  # open files kept from the connection cap, at least (connection_cap)


def token_matches(authorization: str, token: str) -> bool:
    """`Authorization: Bearer <token>`, compared in constant time."""
    scheme, _, given = authorization.partition(" ")
    return scheme.lower() == "bearer" and hmac.compare_digest(
        given.strip().encode(), token.encode()
    )


def timed_receive(
    receive: Receive, limit_bytes: int, timeout_s: float, min_rate_bytes_s: float = 0.0
) -> Receive:
    """`receive` that raises BodyTooLarge past `limit_bytes`, BodyReadTimeout when no chunk
    arrives for `timeout_s` or when the body falls behind `min_rate_bytes_s` after `timeout_s`
    of grace (a byte every few seconds would otherwise hold the connection and its buffer for
    ever), ClientDisconnect when the client leaves before the body's end. Once the body is
    complete it passes messages through (disconnect listeners wait freely)."""
    state = {"size": 0, "done": False}
    start = time.monotonic()

    async def wrapped() -> Message:
        if state["done"]:
            return await receive()
        wait, slow = timeout_s, False
        if min_rate_bytes_s > 0:  # the time by which the body must have more than it has
            due = start + timeout_s + state["size"] / min_rate_bytes_s - time.monotonic()
            wait, slow = min(wait, due), due < wait
        try:
            message = await asyncio.wait_for(receive(), max(wait, 0.0))
        except asyncio.TimeoutError:
            detail = f"no request body bytes for {timeout_s:g} s; send the body without pauses"
            if slow:
                rate = state["size"] / max(time.monotonic() - start, 1e-9)
                detail = (
                    f"the body arrived at {rate:.0f} bytes/s; after {timeout_s:g} s this "
                    f"server needs at least {min_rate_bytes_s:.0f} bytes/s "
                    "(QUIETFRAME_MIN_BODY_RATE_KIB_S)"
                )
            raise BodyReadTimeout(detail, headers={"Connection": "close"}) from None
        if message["type"] == "http.disconnect":
            raise ClientDisconnect()
        if message["type"] == "http.request":
            state["size"] += len(message.get("body", b""))
            if state["size"] > limit_bytes:
                raise BodyTooLarge(
                    f"body exceeds the limit of {limit_bytes} bytes",
                    headers={"Connection": "close"},
                )
            state["done"] = not message.get("more_body", False)
        return message

    return wrapped


class RequestGuard:
    def __init__(self, app, settings: Settings, count_error: Callable[[int, str], None]) -> None:
        self.app, self.settings, self.count_error = app, settings, count_error

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        settings, path = self.settings, scope["path"]
        headers = Headers(scope=scope)
        token = settings.auth_token
        if path.startswith("/v1") and token is not None:
            if not token_matches(headers.get("authorization", ""), token.get_secret_value()):
                await self._reject(
                    send,
                    401,
                    "unauthorized",
                    "missing or wrong bearer token (header 'Authorization: Bearer <token>')",
                    {"WWW-Authenticate": _AUTH_CHALLENGE},
                )
                return
        if "content-length" in headers and "transfer-encoding" in headers:
            # RFC 9112 6.3: the two disagree about where the body ends (request smuggling)
            await self._reject(
                send,
                400,
                "bad_request",
                "the request has both Content-Length and Transfer-Encoding; send one (a chunked "
                "body has no Content-Length)",
            )
            return
        frame = FRAME_PATH.match(path) is not None
        limit = settings.max_body_bytes if frame else settings.max_json_body_bytes
        declared = headers.get("content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > limit):
            await self._reject(
                send,
                413 if declared.isdigit() else 400,
                "body_too_large" if declared.isdigit() else "bad_request",
                f"body is {declared} bytes; the limit for {path} is {limit} bytes"
                if declared.isdigit()
                else f"Content-Length {declared!r} is not a byte count",
            )
            return
        bounded = timed_receive(
            receive, limit, settings.body_read_timeout_s, settings.min_body_rate_bytes_s
        )
        if frame:  # the frame route streams the body itself (errors reach the app's handlers)
            await self.app(scope, bounded, send)
            return
        try:
            body = await _read_all(bounded)
        except (BodyTooLarge, BodyReadTimeout) as exc:
            await self._reject(send, exc.status, exc.code, exc.detail)
            return
        except ClientDisconnect:
            log.info("client disconnected before its request body ended", extra={"path": path})
            self.count_error(499, "client_disconnected")
            return
        await self.app(scope, _replay(body, receive), send)

    async def _reject(
        self, send: Send, status: int, code: str, detail: str, headers: dict | None = None
    ) -> None:
        """Answer without reading the body; `Connection: close` so the unread rest is dropped."""
        self.count_error(status, code)
        payload = json.dumps(error_body(code, detail)).encode()
        raw = [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(payload)).encode()),
            (b"connection", b"close"),
        ]
        raw += [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
        await send({"type": "http.response.start", "status": status, "headers": raw})
        await send({"type": "http.response.body", "body": payload})


async def _read_all(receive: Receive) -> bytes:
    chunks = []
    while True:
        message = await receive()
        if message["type"] != "http.request":
            continue
        chunks.append(message.get("body", b""))
        if not message.get("more_body", False):
            return b"".join(chunks)  # bounded by the JSON limit (a few KiB)


def _replay(body: bytes, receive: Receive) -> Receive:
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()  # after the body: disconnect listeners

    return replay


class HeaderDeadline:
    """Mixed into uvicorn's HTTP protocol (h11 or httptools; `guarded_protocol`). uvicorn closes
    idle keep-alive connections, but one that has sent part of a request line or of its headers
    (or nothing) it keeps for ever, each holding a file descriptor. Here a request's line and
    headers must be complete within `header_timeout_s` of the connection's opening or of the
    request's first byte, however slowly they drip; and past `max_connections` open connections
    the one that has waited longest without a request in progress is closed to make room (a
    probe's /healthz, sent at once, gets through while hundreds of connections stall)."""

    header_timeout_s: float = 10.0
    max_connections: int = 0  # 0: no cap
    waiting: dict[HeaderDeadline, None]  # per server, oldest first: no request in progress
    _header_timer: asyncio.TimerHandle | None = None
    # uvicorn's protocol sets these (both implementations)
    transport: asyncio.Transport
    connections: set
    cycle: Any

    def connection_made(self, transport: asyncio.Transport) -> None:
        super().connection_made(transport)
        self._wait_for_headers()
        self._keep_under_cap()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self._in_request():
            self._stop_waiting()
        else:
            self._wait_for_headers()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self._in_request() and not self.transport.is_closing():
            self.waiting.setdefault(self, None)  # idle: uvicorn's keep-alive timeout closes it

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_waiting()
        super().connection_lost(exc)

    def _in_request(self) -> bool:
        """A request's headers have arrived and its response is not complete yet."""
        cycle = self.cycle
        return cycle is not None and not cycle.response_complete

    def _wait_for_headers(self) -> None:
        """Arm the deadline unless it is armed (more bytes of the same headers do not move it)."""
        if self.transport.is_closing():
            return
        self.waiting.setdefault(self, None)
        if self._header_timer is None:
            loop = asyncio.get_running_loop()
            self._header_timer = loop.call_later(self.header_timeout_s, self._headers_too_slow)

    def _stop_waiting(self) -> None:
        self.waiting.pop(self, None)
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_too_slow(self) -> None:
        self._header_timer = None
        log.debug("closed a connection whose request headers did not arrive in time")
        self._close()

    def _keep_under_cap(self) -> None:
        """Past the cap, close the connection that has waited longest for a request (this one
        when every other has a request in progress). One per new connection: closed ones stay
        in `connections` until the loop reports them lost."""
        if self.max_connections and len(self.connections) > self.max_connections and self.waiting:
            _warn_at_cap(self.max_connections)
            next(iter(self.waiting))._close()

    def _close(self) -> None:
        self._stop_waiting()
        if not self.transport.is_closing():
            self.transport.close()


_last_cap_warning = 0.0


def _warn_at_cap(cap: int) -> None:
    """One warning every 10 s at most: a flood of connections is one event, not thousands."""
    global _last_cap_warning
    now = time.monotonic()
    if now - _last_cap_warning >= 10:
        _last_cap_warning = now
        log.warning(
            "open connections reached the cap: closing those that have waited longest without "
            "a request", extra={"max_connections": cap}
        )


_ACCEPT_FAILED = "socket.accept() out of system resource"


def summarise_accept_failures(loop: asyncio.AbstractEventLoop) -> None:
    """asyncio logs a traceback for every accept() that fails at the open-file limit (up to
    the listen backlog, 2048, each second while it lasts) and retries a second later: one
    warning every 10 s says the same."""
    previous = loop.get_exception_handler()
    last = -math.inf

    def handler(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        nonlocal last
        if context.get("message") != _ACCEPT_FAILED:
            if previous is not None:
                previous(loop, context)
            else:
                loop.default_exception_handler(context)
            return
        if time.monotonic() - last >= 10:
            last = time.monotonic()
            log.warning(
                "cannot accept connections: %s (new ones wait in the listen queue; raise the "
                "open-file limit, or lower QUIETFRAME_MAX_CONNECTIONS)",
                context.get("exception"),
            )

    loop.set_exception_handler(handler)


def guarded_protocol(header_timeout_s: float, max_connections: int) -> type[asyncio.Protocol]:
    """uvicorn's HTTP protocol (what its `http="auto"` picks: httptools when installed, else h11)
    with HeaderDeadline, for uvicorn's `http` parameter; one class per server (its `waiting`)."""
    return type(
        "GuardedHTTPProtocol",
        (HeaderDeadline, AutoHTTPProtocol),
        {"header_timeout_s": header_timeout_s, "max_connections": max_connections, "waiting": {}},
    )


def connection_cap(configured: int) -> int:
    """`configured`, or (0) the open-file limit less a quarter of it (at least 64): files the
    server opens itself (models, state, logs, its store), and connections accepted in one burst
    before the cap closes the oldest (past the limit accept() fails, and asyncio tries again
    only a second later). 0: no cap (no limit)."""
    if configured:
        return configured
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return 0
    return max(soft - max(_RESERVED_FILES, soft // 4), 16)
