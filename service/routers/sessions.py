"""/v1/sessions: create a camera sequence, send its frames in order, read its status, end it."""

from __future__ import annotations

import logging
from typing import Annotated

from fastapi import APIRouter, Path, Query, Request, Response, status

from quietframe.service.below_input import creation_warning
from quietframe.service.deps import MetricsDep, SessionsDep, SettingsDep
from quietframe.service.errors import ERROR_EXAMPLES, InvalidRequest, UnsupportedMediaType
from quietframe.service.schemas import ErrorBody, SessionCreate, SessionPublic
from quietframe.service.sessions import FrameOutcome
from quietframe.service.upload import declared_length, read_frame
from quietframe.wire.protocol import (
    ACCEPTED_FRAME_TYPES,
    CUT_ATTRIBUTE,
    CUT_QUERY,
    EXR_MEDIA_TYPE,
    Header,
    Reset,
)

router = APIRouter(prefix="/sessions", tags=["sessions"])
log = logging.getLogger("quietframe.service")


def errors(*codes: int) -> dict:
    return {
        code: {
            "model": ErrorBody,
            "content": {
                "application/json": {
                    "example": {"error": ERROR_EXAMPLES[code][0], "detail": ERROR_EXAMPLES[code][1]}
                }
            },
        }
        for code in codes
    }


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=SessionPublic,
    responses=errors(401, 408, 413, 422, 429),
    summary="Start a camera sequence",
)
async def create_session(
    spec: SessionCreate, response: Response, sessions: SessionsDep, settings: SettingsDep
) -> SessionPublic:
    """Returns the session id, the model chosen for it and the buffers each frame must carry.
    Every frame of the sequence must have this width and height. A model named at an `spp`
    option where its card says it is below its own noisy input: X-Quietframe-Warning."""
    if spec.width > settings.max_width or spec.height > settings.max_height:
        raise InvalidRequest(
            f"{spec.width}x{spec.height} exceeds this server's maximum frame size "
            f"{settings.max_width}x{settings.max_height}"
        )
    session = await sessions.create(spec)
    response.headers["Location"] = f"/v1/sessions/{session.id}"
    warning = creation_warning(session, sessions.models)
    if warning:
        response.headers[Header.WARNING] = warning
    log.info(
        "session created",
        extra={
            "session": session.id,
            "model": session.spec.model,
            "size": f"{spec.width}x{spec.height}",
            "model_options": session.spec.model_options,
        },
    )
    return session.public(settings.session_ttl_s)


@router.get(
    "/{session_id}",
    response_model=SessionPublic,
    responses=errors(401, 404),
    summary="Session status",
)
async def get_session(session_id: str, sessions: SessionsDep) -> SessionPublic:
    """Frames done, last index, mean and last timings per stage, memory held, time to expiry.
    Reading the status does not keep the session alive."""
    return await sessions.status(session_id)


@router.delete(
    "/{session_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses=errors(401, 404),
    summary="End a session and free its history",
)
async def delete_session(session_id: str, sessions: SessionsDep) -> Response:
    await sessions.delete(session_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


_FRAME_DOC = f"""Denoise frame `index` of the sequence. Body: one EXR (`{EXR_MEDIA_TYPE}`) with
colour and AOVs under any of the recognised renderer names (or the session's mapping). Response: the
input EXR with the beauty's R, G, B denoised: every part, channel and header attribute kept.

Order: `index` must increase. The same index as the last frame is an idempotent retry (the same
bytes come back, history is not advanced twice); a lower index is refused (409). A gap in the
indices, `?{CUT_QUERY}=true`, or a header attribute `{CUT_ATTRIBUTE}` = 1 starts from a fresh
history.

Response headers: `{Header.RESET}` ({", ".join(f"`{r.value}`" for r in Reset)}),
`{Header.SANITIZED}` (input values replaced: NaN/Inf, negative colour/albedo/depth) with
`{Header.SANITIZED_BUFFERS}`, `{Header.MISSING}` (optional buffers that were absent and
filled: motion -> static camera), `{Header.REPLAYED}`, `{Header.SERVER_TIMING}` (ms per stage),
`{Header.WARNING}` (a model asked for by name at an spp where its card says it is below its own
noisy input; the frame is denoised as asked).

Look-ahead (session `lookahead` k > 0): the frame is held back; the reply carries the oldest
pending frame once more than k are pending (200, `{Header.FRAME}` its index, the headers its own),
else 202 with no body; every reply says `{Header.PENDING}` (frames held back after it)."""


@router.post(
    "/{session_id}/frames/{index}",
    response_class=Response,
    summary="Denoise one frame",
    description=_FRAME_DOC,
    responses={
        200: {
            "content": {EXR_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
            "description": "the denoised EXR (with look-ahead: of the frame X-Quietframe-Frame "
            "names)",
        },
        202: {"description": "look-ahead: the frame is held back; nothing to write yet"},
        **errors(400, 401, 404, 408, 409, 413, 415, 422, 429),
    },
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {EXR_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        }
    },
)
async def post_frame(
    session_id: str,
    index: Annotated[int, Path(ge=0, description="frame number; must increase")],
    request: Request,
    sessions: SessionsDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    cut: Annotated[bool, Query(description="camera cut: start from a fresh history")] = False,
    shot_model: Annotated[str | None, Query(
        max_length=256,
        description="model 'auto' only: the model already chosen for this frame's shot (e.g. "
        "by another farm chunk of the shot); a frame that starts the shot's history (the "
        "session's first, a cut) takes it instead of choosing, so one shot keeps one model")
    ] = None,
) -> Response:
    """Reads the body and answers with the outcome; `SessionRegistry.denoise_frame` owns the
    frame's journey."""
    session = await sessions.get(session_id)  # 404 before reading a body for nothing
    media_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media_type not in ACCEPTED_FRAME_TYPES:
        raise UnsupportedMediaType(f"send the EXR as {EXR_MEDIA_TYPE} (got {media_type})")
    budget, spec = sessions.admission, session.spec
    # 429 when no slot can be had; 408 when the body is cut for its time (upload_slots.py)
    declared = declared_length(request)
    expected = settings.max_body_bytes if declared is None else declared  # chunked: the limit
    async with sessions.upload_slots.hold(session_id, expected) as upload:
        body, header, reservation = await read_frame(
            request,
            settings,
            (spec.width, spec.height),
            budget,
            lambda h, body_bytes: sessions.frame_need(session, h, body_bytes, cut),
            upload,
        )
    try:
        metrics.bytes_in.inc(len(body))
        outcome = await sessions.denoise_frame(session_id, index, body, cut, header,
                                               shot_model)
    finally:
        reservation.release()
    return _response(outcome, metrics)


def _response(outcome: FrameOutcome, metrics) -> Response:
    """A frame's reply: the EXR (200), or nothing yet (202: a look-ahead session holds it)."""
    reply = outcome.reply
    metrics.bytes_out.inc(len(reply.body))
    headers = {**reply.headers, Header.REPLAYED: "true" if outcome.replayed else "false"}
    if reply.status == status.HTTP_202_ACCEPTED:
        return Response(status_code=reply.status, headers=headers)
    return Response(reply.body, status_code=reply.status, media_type=EXR_MEDIA_TYPE,
                    headers=headers)


@router.post(
    "/{session_id}/frames/{index}/finish",
    response_class=Response,
    summary="Finish a held-back frame (look-ahead sessions)",
    responses={
        200: {
            "content": {EXR_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
            "description": "the denoised EXR of frame `index`",
        },
        **errors(401, 404, 409, 413, 429),
    },
)
async def finish_frame(
    session_id: str,
    index: Annotated[int, Path(ge=0, description="the oldest pending frame")],
    sessions: SessionsDep,
    metrics: MetricsDep,
) -> Response:
    """A session with `lookahead` k > 0 returns frame `index` now, finished with the later
    frames it has received: call it for each frame still pending at the end of a shot or a
    chunk, oldest first. `index` must be the oldest pending frame (409 naming it otherwise); the
    same request again replays the reply (`X-Quietframe-Replayed: true`). The headers describe
    the frame, with `X-Quietframe-Pending` the frames still held back."""
    return _response(await sessions.finish_frame(session_id, index), metrics)
