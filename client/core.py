"""The client's logic without I/O, shared by the sync and the async client: building requests,
deciding retries, parsing replies.

Retries with exponential backoff (and the server's Retry-After) on 429, 5xx and connection
errors. Frames are idempotent by index on the server (the same index again returns the same
bytes without advancing history), so a frame whose response was lost is simply sent again.
Creating a session is retried only when the server surely did not create it (429/502/503/504,
or the connection was never made).

A look-ahead session (session field `lookahead` k > 0) holds frames back: the reply to a frame
carries an earlier one (X-Quietframe-Frame), or nothing yet (202: `parse_frame` gives None), and
`finish_call` asks for a pending frame at the end of a shot or chunk. A retried frame or finish
gets the stored reply, the same frame.
"""

from __future__ import annotations

import random
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import httpx

from quietframe.client.session_fields import SessionFields
from quietframe.wire.protocol import (
    CUT_QUERY,
    EXR_MEDIA_TYPE,
    SHOT_MODEL_QUERY,
    Header,
    parse_counts,
    parse_timings,
    split_list,
)

_RETRY_STATUS = frozenset({429, 500, 502, 503, 504})
_RETRY_STATUS_CREATE = frozenset({429, 502, 503, 504})


class QuietframeError(Exception):
    """A request failed for good: `status` (0 for connection errors), `code`, `detail`."""

    def __init__(self, status: int, code: str, detail: str) -> None:
        super().__init__(f"{status} {code}: {detail}" if status else f"{code}: {detail}")
        self.status, self.code, self.detail = status, code, detail


@dataclass
class FrameResult:
    index: int  # the frame it carries: the one sent, or with look-ahead an earlier one
    exr: bytes  # the denoised EXR
    reset: str  # a protocol.Reset value: "none", "first-frame", "cut", "gap"
    sanitized: int  # input values replaced by the server's sanitising rule
    missing: tuple[str, ...]  # optional buffers the frame lacked (filled by the model)
    replayed: bool  # answered from the server's stored reply (a retry)
    timings_ms: dict[str, float] = field(default_factory=dict)
    sanitized_buffers: dict[str, int] = field(default_factory=dict)  # per buffer: depth=678
    model: str = ""  # "<name> <version>" of the model that ran
    choice: str = ""  # model=auto: the X-Quietframe-Choice header
    # a temporal model's frame without usable motion vectors: what its aux showed
    # (X-Quietframe-Motion, e.g. "moving (64% of 120 tiles moved); history not used")
    motion: str = ""
    # look-ahead sessions: the frames the session holds back after this reply
    # (X-Quietframe-Pending); None where the server does not say (no look-ahead)
    pending: int | None = None
    # a model asked for by name at an spp where its card says it is below its own noisy input
    # (X-Quietframe-Warning); the frame was denoised as asked
    warning: str = ""
    # a model asked for by name that reads the frame's spp, none stated by the header or the
    # session's options: the shot's estimated spp it was given (X-Quietframe-Samples,
    # "<spp>; source=estimate")
    samples: str = ""


@dataclass(frozen=True)
class RetryPolicy:
    retries: int = 5
    backoff_s: float = 0.5
    max_backoff_s: float = 30.0

    def delay(self, attempt: int, retry_after: str | None = None) -> float:
        """Seconds before retry number `attempt` (0-based): the server's Retry-After when it
        gives one, else exponential backoff with jitter; never more than max_backoff_s."""
        if retry_after is not None:
            try:
                return min(self.max_backoff_s, max(0.0, float(retry_after)))
            except ValueError:
                pass
        base = min(self.max_backoff_s, self.backoff_s * 2**attempt)
        return base * random.uniform(0.5, 1.0)

    def should_retry(self, attempt: int, outcome: httpx.Response | Exception, create: bool) -> bool:
        if attempt >= self.retries:
            return False
        if isinstance(outcome, httpx.Response):
            return outcome.status_code in (_RETRY_STATUS_CREATE if create else _RETRY_STATUS)
        if create:  # the request may have reached the server: only retry if it surely did not
            return isinstance(outcome, httpx.ConnectError | httpx.ConnectTimeout)
        return isinstance(outcome, httpx.TransportError)


@dataclass(frozen=True)
class Call:
    """One API request, as both clients send it."""

    method: str
    path: str
    create: bool = False  # creates a session: retried only when it surely was not created
    options: dict[str, Any] = field(default_factory=dict)  # httpx request keyword arguments


class Attempts:
    """The retry loop's decisions for one Call: `after(outcome)` is None when the response is
    the answer, else the seconds to wait before sending again; it raises QuietframeError when
    the call has failed for good."""

    def __init__(self, policy: RetryPolicy, call: Call, on_retry=None) -> None:
        self.policy, self.call, self.attempt = policy, call, 0
        self.on_retry = on_retry  # (Retry) -> None: told before each wait, e.g. to print it
        self.response: httpx.Response | None = None  # the answer, once `after` returned None

    def after(self, outcome: httpx.Response | Exception) -> float | None:
        if isinstance(outcome, httpx.Response) and outcome.status_code < 400:
            self.response = outcome
            return None
        if not self.policy.should_retry(self.attempt, outcome, self.call.create):
            if isinstance(outcome, httpx.Response):
                raise parse_error(outcome)
            raise QuietframeError(0, "connection_error", f"{type(outcome).__name__}: {outcome}")
        retry_after = (
            outcome.headers.get("retry-after") if isinstance(outcome, httpx.Response) else None
        )
        delay = self.policy.delay(self.attempt, retry_after)
        self.attempt += 1
        if self.on_retry is not None:
            self.on_retry(Retry(self.call, self.attempt, self.policy.retries, delay, outcome))
        return delay


@dataclass(frozen=True)
class Retry:
    """One retry about to happen: which call, its number (1-based) of `of`, the wait."""

    call: Call
    number: int
    of: int
    delay_s: float
    outcome: httpx.Response | Exception

    def describe(self) -> str:
        if isinstance(self.outcome, httpx.Response):
            why = f"{self.outcome.status_code} {parse_error(self.outcome).code}"
        else:
            why = f"{type(self.outcome).__name__}: {self.outcome}"
        return f"{why}; retry {self.number} of {self.of} in {self.delay_s:.1f} s"


def parse_error(response: httpx.Response) -> QuietframeError:
    try:
        body = response.json()
        return QuietframeError(response.status_code, body["error"], body["detail"])
    except Exception:
        return QuietframeError(response.status_code, "http_error", response.text[:500])


def parse_frame(index: int, response: httpx.Response) -> FrameResult | None:
    """The frame a reply to frame `index` carries: that frame, or where the session looks ahead
    the earlier frame X-Quietframe-Frame names; None for 202 (the session holds the frame back:
    nothing to write yet)."""
    if response.status_code == 202:
        return None
    h = response.headers
    pending = h.get(Header.PENDING)
    return FrameResult(
        index=_frame_number(h.get(Header.FRAME), index),
        exr=response.content,
        reset=h.get(Header.RESET, "none"),
        sanitized=int(h.get(Header.SANITIZED, "0")),
        missing=split_list(h.get(Header.MISSING, "")),
        replayed=h.get(Header.REPLAYED) == "true",
        timings_ms=parse_timings(h.get(Header.SERVER_TIMING, "")),
        sanitized_buffers=parse_counts(h.get(Header.SANITIZED_BUFFERS, "")),
        model=h.get(Header.MODEL, ""),
        choice=h.get(Header.CHOICE, ""),
        motion=h.get(Header.MOTION, ""),
        pending=int(pending) if pending is not None and pending.isdigit() else None,
        warning=h.get(Header.WARNING, ""),
        samples=h.get(Header.SAMPLES, ""),
    )


def _frame_number(value: str | None, sent: int) -> int:
    """X-Quietframe-Frame's index; the frame sent where the header is absent (or not a number)."""
    return int(value) if value is not None and value.isdigit() else sent


class SyncClient(Protocol):
    """What a sequence run asks of a client (api.Client): its session and frame calls."""

    def create_session(self, width: int, height: int, model: str = "auto",
                       **fields: Any) -> dict: ...

    def session(self, session_id: str) -> dict: ...

    def delete_session(self, session_id: str, missing_ok: bool = True) -> None: ...

    def send_frame(self, session_id: str, index: int, exr: bytes, cut: bool = False,
                   shot_model: str | None = None) -> FrameResult | None: ...

    def finish_frame(self, session_id: str, index: int) -> FrameResult: ...


class AsyncClient(Protocol):
    """SyncClient's calls awaited (api.AsyncClient): what the sequence protocol is written for."""

    async def create_session(self, width: int, height: int, model: str = "auto",
                             **fields: Any) -> dict: ...

    async def session(self, session_id: str) -> dict: ...

    async def delete_session(self, session_id: str, missing_ok: bool = True) -> None: ...

    async def send_frame(self, session_id: str, index: int, exr: bytes, cut: bool = False,
                         shot_model: str | None = None) -> FrameResult | None: ...

    async def finish_frame(self, session_id: str, index: int) -> FrameResult: ...


def base_url(url: str) -> str:
    """The server's root URL: a trailing `/v1` (the API prefix, which every call adds) is
    dropped, so `--server http://denoise:8000/v1` works; ValueError without http(s)://."""
    url = url.strip().rstrip("/")
    if not url.startswith(("http://", "https://")):
        raise ValueError(f"server URL {url!r} must start with http:// or https://")
    if url.endswith("/v1"):
        url = url[: -len("/v1")]
    return url


def auth_headers(token: str | None) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"} if token else {}


def models_call() -> Call:
    return Call("GET", "/v1/models")


# Sent whatever their value; every other field only where it differs from the server's default
ALWAYS_SENT = frozenset({"width", "height", "model", "precision"})


class SessionRequest(SessionFields):
    """The body of POST /v1/sessions (the API's SessionCreate). Built unchecked (`of`): the server
    judges the values, and a farm's server may be newer than its clients (a codec or a quality
    this client's copy of the fields would refuse)."""

    @classmethod
    def of(cls, width: int, height: int, model: str = "auto", **fields: Any) -> SessionRequest:
        """TypeError for a name that is no session field; a None value leaves a field out."""
        unknown = sorted(set(fields) - set(cls.model_fields))
        if unknown:
            raise TypeError(f"no session field {', '.join(unknown)}; the fields: "
                            f"{', '.join(cls.model_fields)}")
        given = {name: value for name, value in fields.items() if value is not None}
        return cls.model_construct(width=width, height=height, model=model, **given)

    def body(self) -> dict[str, Any]:
        body: dict[str, Any] = {}
        for name, info in type(self).model_fields.items():
            value = getattr(self, name)
            unset = value in (None, {}) or value == info.get_default(call_default_factory=True)
            if name in ALWAYS_SENT or not unset:
                body[name] = _json_value(value)
        return body

    def call(self) -> Call:
        return Call("POST", "/v1/sessions", create=True, options={"json": self.body()})


def _json_value(value: Any) -> Any:
    """A field's value as JSON takes it (a mapping of channel lists given as tuples, say)."""
    if isinstance(value, Mapping):
        return {k: _json_value(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_json_value(v) for v in value]
    return value


def session_call(session_id: str) -> Call:
    return Call("GET", f"/v1/sessions/{session_id}")


def delete_session_call(session_id: str) -> Call:
    return Call("DELETE", f"/v1/sessions/{session_id}")


def frame_call(session_id: str, index: int, exr: bytes, cut: bool = False,
               shot_model: str | None = None) -> Call:
    """`shot_model` (model=auto): the model already chosen for the frame's shot, which the
    server takes where the shot's history starts instead of choosing (client/shots.py)."""
    options: dict[str, Any] = {"content": exr, "headers": {"Content-Type": EXR_MEDIA_TYPE}}
    params = {}
    if cut:
        params[CUT_QUERY] = "true"
    if shot_model:
        params[SHOT_MODEL_QUERY] = shot_model
    if params:
        options["params"] = params
    return Call("POST", f"/v1/sessions/{session_id}/frames/{index}", options=options)


def finish_call(session_id: str, index: int) -> Call:
    """A look-ahead session's pending frame `index` now, finished with the later frames it has
    (it must be the oldest pending: else 409)."""
    return Call("POST", f"/v1/sessions/{session_id}/frames/{index}/finish")


def parse_finished(index: int, response: httpx.Response) -> FrameResult:
    """A finish reply: frame `index` itself; QuietframeError where the server says otherwise."""
    result = parse_frame(index, response)
    if result is None or result.index != index:
        got = "nothing (202)" if result is None else f"frame {result.index}"
        raise QuietframeError(response.status_code, "unexpected_reply",
                              f"finishing frame {index} returned {got}")
    return result
