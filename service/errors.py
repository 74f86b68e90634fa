"""Errors a client can act on, and their one conversion to HTTP (`{"error", "detail"}`).

Service code raises these exception types; `install_handlers` maps them (and request-validation
errors and unexpected exceptions) to JSON responses at the boundary, and counts every error
response by code. A frame's buffers are checked once, from its header (frames.resolve ->
missing_channels); a runtime BufferError after that would be a bug, so it is a 500.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.responses import Response

from quietframe.runtime.frame_errors import ServiceError

log = logging.getLogger("quietframe.service")


class Unauthorized(ServiceError):
    status, code = 401, "unauthorized"


class SessionNotFound(ServiceError):
    status, code = 404, "session_not_found"


class FrameOutOfOrder(ServiceError):
    status, code = 409, "frame_out_of_order"


class FrameConflict(ServiceError):
    """Same index retried with a different body."""

    status, code = 409, "frame_conflict"


class FrameNotPending(ServiceError):
    """A finish for a frame that is not a look-ahead session's oldest pending one."""

    status, code = 409, "frame_not_pending"


def not_pending(session, index: int, held: list[int]) -> str:
    """FrameNotPending's detail: which frame can be finished instead, if any."""
    if not session.spec.lookahead:
        return (f"frame {index}: session {session.id} has lookahead 0 and holds no frame back; "
                "every frame's reply carries that frame")
    if not held:
        return f"frame {index} is not pending: no frame of this session is pending"
    return (f"frame {index} is not the oldest pending frame; finish frame {held[0]} first "
            f"(pending: {', '.join(map(str, held))})")


class BodyReadTimeout(ServiceError):
    """The client paused sending its body for longer than QUIETFRAME_BODY_READ_TIMEOUT_S."""

    status, code = 408, "body_read_timeout"


class UploadTooSlow(ServiceError):
    """A body cut for its time: past QUIETFRAME_MAX_UPLOAD_S, or past its share of an upload
    slot that another upload wanted (upload_slots.py)."""

    status, code = 408, "upload_too_slow"


class BodyTooLarge(ServiceError):
    status, code = 413, "body_too_large"


class FrameOverMemoryBudget(ServiceError):
    """One frame needs more than the whole memory budget: no retry can succeed."""

    status, code = 413, "frame_over_memory_budget"


class UnsupportedMediaType(ServiceError):
    status, code = 415, "unsupported_media_type"


class InvalidRequest(ServiceError):
    status, code = 422, "invalid_request"


class StoreUnavailable(ServiceError):
    """The session store (Redis, or the state folder: full, read-only) did not answer or
    refused the write for now: nothing is committed (nor lost); retry."""

    status, code = 503, "state_store_unavailable"


class UnknownModel(ServiceError):
    status, code = 422, "unknown_model"


class ModelUnavailable(ServiceError):
    """An installed model this server cannot run (oidn-temporal without pyoidn)."""

    status, code = 422, "model_unavailable"


class InvalidModelOptions(ServiceError):
    """A session's model_options that its model (or, for auto, no installed model) takes."""

    status, code = 422, "invalid_model_options"


class TooManySessions(ServiceError):
    status, code = 429, "too_many_sessions"


class MemoryBudgetExceeded(ServiceError):
    status, code = 429, "memory_budget_exceeded"


class MemoryBusy(ServiceError):
    """The frames in flight hold the memory budget: retry after Retry-After."""

    status, code = 429, "memory_busy"


class TooManyUploads(ServiceError):
    status, code = 429, "too_many_uploads"


class NotReady(ServiceError):
    status, code = 503, "not_ready"


ERROR_EXAMPLES = {
    400: ("bad_exr", "body is not an OpenEXR file (bad magic number)"),
    401: ("unauthorized", "missing or wrong bearer token"),
    404: ("session_not_found", "no session 'Jx3…' (expired, deleted or never created)"),
    408: ("body_read_timeout", "no request body bytes for 30 s; send the body without pauses"),
    409: ("frame_out_of_order", "frame 11 is older than the last frame 12 of this session"),
    413: ("resolution_too_large", "frame is 16384x16384; this server accepts at most 8192x8192"),
    422: ("missing_channels", "no channels for required buffer 'albedo'; found [...]"),
    415: ("unsupported_media_type", "send the EXR as image/x-exr (got text/plain)"),
    429: ("too_many_sessions", "64 sessions are open; retry after the time in Retry-After"),
}


def error_body(code: str, detail: str) -> dict[str, str]:
    return {"error": code, "detail": detail}


def install_handlers(app: FastAPI, count_error: Callable[[int, str], None]) -> None:
    def respond(status: int, code: str, detail: str, headers=None) -> JSONResponse:
        count_error(status, code)
        return JSONResponse(error_body(code, detail), status_code=status, headers=headers)

    @app.exception_handler(ServiceError)
    async def service_error(_: Request, exc: ServiceError) -> JSONResponse:
        return respond(exc.status, exc.code, exc.detail, exc.headers)

    @app.exception_handler(RequestValidationError)
    async def validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
        parts = []
        for err in exc.errors():
            where = ".".join(str(p) for p in err.get("loc", ()) if p != "body")
            parts.append(f"{where}: {err.get('msg')}" if where else str(err.get("msg")))
        return respond(422, "invalid_request", "; ".join(parts) or "invalid request")

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        if exc.status_code == 400:  # FastAPI's "error parsing the body": not UTF-8 JSON
            return respond(
                422, "invalid_request", "the body is not JSON (send UTF-8 application/json)"
            )
        code = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
        return respond(exc.status_code, code, str(exc.detail), getattr(exc, "headers", None))

    @app.exception_handler(ClientDisconnect)
    async def client_disconnect(request: Request, _: ClientDisconnect) -> Response:
        # Not a server error: one info line, no traceback; nobody reads the response.
        log.info(
            "client disconnected before its request body ended", extra={"path": request.url.path}
        )
        count_error(499, "client_disconnected")
        return Response(status_code=499)

    @app.exception_handler(Exception)
    async def unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error", extra={"path": request.url.path})
        return respond(500, "internal_error", f"{type(exc).__name__}: see the server log")
