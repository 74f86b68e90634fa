"""A stand-in server for the look-ahead protocol (docs/service.md, "Look-ahead"), written from the
protocol alone, for the client's tests: sessions that hold `lookahead` frames back, the 202 and
the reply carrying the oldest pending frame (X-Quietframe-Frame, X-Quietframe-Pending), the
finish route (409 out of order), replay of the last frame or finish request, and DELETE.

Each frame is "denoised" as itself: a reply's body is the upload of the frame it carries, so a
test sees exactly which frame an output was made from. Every request is logged, and a request
can be made to fail once (`fail_once`: its status without processing it, as a busy server does)
or to lose its reply once (`lose_reply_once`: processed, then 500, as a reply lost on the way).
"""

from __future__ import annotations

import json
import secrets
import threading
from collections import deque
from dataclasses import dataclass, field

from conftest import ThreadedServer
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from quietframe.wire.protocol import EXR_MEDIA_TYPE, Header

MAX_LOOKAHEAD = 4


@dataclass
class FakeSession:
    id: str
    width: int
    height: int
    lookahead: int
    model: str
    layer: str | None
    pending: deque = field(default_factory=deque)  # (index, body), oldest first
    last_index: int | None = None
    last_request: tuple[str, int] | None = None  # ("frame" | "finish", index)
    last_reply: Response | None = None


class LookaheadFake:
    """The app (`app`) and what it saw (`log`: (kind, session, index) per request)."""

    def __init__(self) -> None:
        self.sessions: dict[str, FakeSession] = {}
        self.log: list[tuple[str, str, int | None]] = []
        self.fail_once: dict[tuple[str, int], int] = {}
        self.lose_reply_once: set[tuple[str, int]] = set()
        self.lock = threading.Lock()
        self.app = Starlette(routes=[
            Route("/v1/models", self.models, methods=["GET"]),
            Route("/v1/sessions", self.create, methods=["POST"]),
            Route("/v1/sessions/{sid}", self.view, methods=["GET"]),
            Route("/v1/sessions/{sid}", self.delete, methods=["DELETE"]),
            Route("/v1/sessions/{sid}/frames/{index:int}", self.frame, methods=["POST"]),
            Route("/v1/sessions/{sid}/frames/{index:int}/finish", self.finish,
                  methods=["POST"]),
        ])

    def sent(self, kind: str = "frame") -> list[int | None]:
        """The indices of the requests of one kind ("frame", "finish", "create", "delete")."""
        return [index for k, _, index in self.log if k == kind]

    # ---- routes -------------------------------------------------------------------------

    async def models(self, request: Request) -> Response:
        return JSONResponse({"models": [{"name": "fake", "options": []}], "default": "fake"})

    async def create(self, request: Request) -> Response:
        body = json.loads(await request.body())
        lookahead = body.get("lookahead", 0)
        if isinstance(lookahead, bool) or not isinstance(lookahead, int) or not (
                0 <= lookahead <= MAX_LOOKAHEAD):
            return _error(422, "invalid_request",
                          f"lookahead: an integer from 0 to {MAX_LOOKAHEAD}, got {lookahead!r}")
        session = FakeSession(secrets.token_hex(8), body["width"], body["height"], lookahead,
                              body.get("model", "auto"), body.get("layer"))
        self.sessions[session.id] = session
        self.log.append(("create", session.id, None))
        return JSONResponse(self._public(session))

    async def view(self, request: Request) -> Response:
        session = self.sessions.get(request.path_params["sid"])
        if session is None:
            return _error(404, "not_found", "no such session")
        return JSONResponse(self._public(session))

    async def delete(self, request: Request) -> Response:
        self.log.append(("delete", request.path_params["sid"], None))
        if self.sessions.pop(request.path_params["sid"], None) is None:
            return _error(404, "not_found", "no such session")
        return Response(status_code=204)

    async def frame(self, request: Request) -> Response:
        body = await request.body()
        return self._answer(request, "frame", lambda s, t: self._take_frame(s, t, body))

    async def finish(self, request: Request) -> Response:
        return self._answer(request, "finish", self._take_finish)

    # ---- the protocol ---------------------------------------------------------------------

    def _answer(self, request: Request, kind: str, step) -> Response:
        sid, index = request.path_params["sid"], request.path_params["index"]
        with self.lock:
            self.log.append((kind, sid, index))
            if (kind, index) in self.fail_once:
                return _error(self.fail_once.pop((kind, index)), "busy", "try again later")
            session = self.sessions.get(sid)
            if session is None:
                return _error(404, "not_found", "no such session")
            if session.last_request == (kind, index) and session.last_reply is not None:
                replayed = session.last_reply
                replayed.headers[Header.REPLAYED] = "true"
                return replayed
            reply = step(session, index)
            if reply.status_code < 400:
                session.last_request, session.last_reply = (kind, index), reply
            if (kind, index) in self.lose_reply_once:
                self.lose_reply_once.discard((kind, index))
                return _error(500, "internal_error", "the reply was lost")
            return reply

    def _take_frame(self, session: FakeSession, index: int, body: bytes) -> Response:
        if session.last_index is not None and index <= session.last_index:
            return _error(409, "frame_out_of_order",
                          f"frame {index} is older than the last frame {session.last_index}")
        session.pending.append((index, body))
        session.last_index = index
        if len(session.pending) > session.lookahead:
            return self._carry(session)
        return Response(status_code=202,
                        headers={Header.PENDING: str(len(session.pending))})

    def _take_finish(self, session: FakeSession, index: int) -> Response:
        if not session.pending:
            return _error(409, "frame_conflict", f"frame {index}: no frame is pending")
        oldest = session.pending[0][0]
        if oldest != index:
            return _error(409, "frame_conflict",
                          f"frame {index} is not the oldest pending frame; that is {oldest}")
        return self._carry(session)

    def _carry(self, session: FakeSession) -> Response:
        index, body = session.pending.popleft()
        headers = {Header.FRAME: str(index), Header.RESET: "none",
                   Header.MODEL: f"{session.model} 1", Header.SERVER_TIMING: "total;dur=1.0"}
        if session.lookahead:
            headers[Header.PENDING] = str(len(session.pending))
        return Response(body, media_type=EXR_MEDIA_TYPE, headers=headers)

    def _public(self, session: FakeSession) -> dict:
        return {"id": session.id, "width": session.width, "height": session.height,
                "lookahead": session.lookahead, "layer": session.layer,
                "model": {"name": session.model, "version": "1"}, "requested_model":
                session.model, "choice": None, "last_index": session.last_index}


def _error(status: int, code: str, detail: str) -> Response:
    return JSONResponse({"error": code, "detail": detail}, status_code=status)


class FakeServer(ThreadedServer):
    """The fake on 127.0.0.1 in a background thread (uvicorn), as conftest.LiveServer."""

    start_timeout_s = 30

    def __init__(self) -> None:
        self.fake = LookaheadFake()
        super().__init__(self.fake.app)
