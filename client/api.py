"""HTTP clients of the quietframe service (sync `Client`, async `AsyncClient`), with retries.

Retries with exponential backoff (and the server's Retry-After) on 429, 5xx and connection
errors. Frames are idempotent by index on the server (the same index again returns the same
bytes without advancing history), so a frame whose response was lost is simply sent again.
Creating a session is retried only when the server surely did not create it (429/502/503/504,
or the connection was never made).
"""

from __future__ import annotations

import asyncio
import random
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import httpx

EXR = "image/x-exr"
_RETRY_STATUS = frozenset({429, 500, 502, 503, 504})
_RETRY_STATUS_CREATE = frozenset({429, 502, 503, 504})


class QuietframeError(Exception):
    """A request failed for good: `status` (0 for connection errors), `code`, `detail`."""

    def __init__(self, status: int, code: str, detail: str) -> None:
        super().__init__(f"{status} {code}: {detail}" if status else f"{code}: {detail}")
        self.status, self.code, self.detail = status, code, detail


@dataclass
class FrameResult:
    index: int
    exr: bytes  # the denoised EXR
    reset: str  # "none", "first-frame", "cut", "gap"
    sanitized: int  # input values replaced by the server's sanitising rule
    missing: tuple[str, ...]  # optional buffers the frame lacked (filled by the model)
    replayed: bool  # answered from the server's stored reply (a retry)
    timings_ms: dict[str, float] = field(default_factory=dict)


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


def _error(response: httpx.Response) -> QuietframeError:
    try:
        body = response.json()
        return QuietframeError(response.status_code, body["error"], body["detail"])
    except Exception:
        return QuietframeError(response.status_code, "http_error", response.text[:500])


def _frame_result(index: int, response: httpx.Response) -> FrameResult:
    h = response.headers
    timings = {}
    for part in h.get("server-timing", "").split(","):
        name, _, dur = part.strip().partition(";dur=")
        if name and dur:
            timings[name] = float(dur)
    missing = tuple(m.strip() for m in h.get("x-quietframe-missing", "").split(",") if m.strip())
    return FrameResult(
        index=index,
        exr=response.content,
        reset=h.get("x-quietframe-reset", "none"),
        sanitized=int(h.get("x-quietframe-sanitized", "0")),
        missing=missing,
        replayed=h.get("x-quietframe-replayed") == "true",
        timings_ms=timings,
    )


def _session_body(width, height, model, channels, precision, motion_scale, compression) -> dict:
    body: dict = {"width": width, "height": height, "model": model, "precision": precision}
    if compression != "input":
        body["compression"] = compression
    if channels:
        body["channels"] = dict(channels)
    if motion_scale is not None:
        body["motion_scale"] = list(motion_scale)
    return body


def _headers(token: str | None) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"} if token else {}


class Client:
    """Synchronous client. `Client("http://farm-denoise:8000")`, use as a context manager."""

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        timeout_s: float = 300.0,
        retry: RetryPolicy | None = None,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.retry = retry or RetryPolicy()
        self._http = httpx.Client(
            base_url=base_url.rstrip("/"),
            headers=_headers(token),
            timeout=timeout_s,
            transport=transport,
        )

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *_) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _request(self, method: str, path: str, *, create: bool = False, **kw) -> httpx.Response:
        attempt = 0
        while True:
            try:
                outcome: httpx.Response | Exception = self._http.request(method, path, **kw)
            except httpx.TransportError as exc:
                outcome = exc
            if isinstance(outcome, httpx.Response) and outcome.status_code < 400:
                return outcome
            if not self.retry.should_retry(attempt, outcome, create):
                if isinstance(outcome, httpx.Response):
                    raise _error(outcome)
                raise QuietframeError(0, "connection_error", f"{type(outcome).__name__}: {outcome}")
            retry_after = (
                outcome.headers.get("retry-after") if isinstance(outcome, httpx.Response) else None
            )
            time.sleep(self.retry.delay(attempt, retry_after))
            attempt += 1

    def models(self) -> dict:
        return self._request("GET", "/v1/models").json()

    def ready(self) -> bool:
        try:
            return self._http.get("/readyz").status_code == 200
        except httpx.TransportError:
            return False

    def create_session(
        self,
        width: int,
        height: int,
        model: str = "auto",
        channels: Mapping[str, str | Sequence[str]] | None = None,
        precision: str = "input",
        motion_scale: tuple[float, float] | None = None,
        compression: str = "input",
    ) -> dict:
        """Start a sequence; see the API's SessionCreate for the fields."""
        body = _session_body(width, height, model, channels, precision, motion_scale, compression)
        return self._request("POST", "/v1/sessions", json=body, create=True).json()

    def session(self, session_id: str) -> dict:
        return self._request("GET", f"/v1/sessions/{session_id}").json()

    def delete_session(self, session_id: str, missing_ok: bool = True) -> None:
        try:
            self._request("DELETE", f"/v1/sessions/{session_id}")
        except QuietframeError as exc:
            if not (missing_ok and exc.status == 404):
                raise

    def send_frame(self, session_id: str, index: int, exr: bytes, cut: bool = False) -> FrameResult:
        params = {"cut": "true"} if cut else None
        response = self._request(
            "POST",
            f"/v1/sessions/{session_id}/frames/{index}",
            content=exr,
            headers={"Content-Type": EXR},
            params=params,
        )
        return _frame_result(index, response)

    def denoise_sequence(self, source, out_dir, **options) -> str | None:
        """Stream a folder or glob of EXR frames through one session into `out_dir` (same
        names), resuming an earlier run; options of `sequence.run_sequence` (model, precision,
        compression, warmup, on_progress). Returns the session id, None if nothing was left."""
        from quietframe.client.sequence import Job, run_sequence

        job = Job.plan(source, out_dir)
        return run_sequence(self, job, str(self._http.base_url), **options)


class AsyncClient:
    """The same API for asyncio (several sequences from one process, one task per sequence)."""

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        timeout_s: float = 300.0,
        retry: RetryPolicy | None = None,
        transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        self.retry = retry or RetryPolicy()
        self._http = httpx.AsyncClient(
            base_url=base_url.rstrip("/"),
            headers=_headers(token),
            timeout=timeout_s,
            transport=transport,
        )

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *_) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _request(self, method: str, path: str, *, create: bool = False, **kw):
        attempt = 0
        while True:
            try:
                outcome: httpx.Response | Exception = await self._http.request(method, path, **kw)
            except httpx.TransportError as exc:
                outcome = exc
            if isinstance(outcome, httpx.Response) and outcome.status_code < 400:
                return outcome
            if not self.retry.should_retry(attempt, outcome, create):
                if isinstance(outcome, httpx.Response):
                    raise _error(outcome)
                raise QuietframeError(0, "connection_error", f"{type(outcome).__name__}: {outcome}")
            retry_after = (
                outcome.headers.get("retry-after") if isinstance(outcome, httpx.Response) else None
            )
            await asyncio.sleep(self.retry.delay(attempt, retry_after))
            attempt += 1

    async def models(self) -> dict:
        return (await self._request("GET", "/v1/models")).json()

    async def create_session(
        self,
        width: int,
        height: int,
        model: str = "auto",
        channels: Mapping[str, str | Sequence[str]] | None = None,
        precision: str = "input",
        motion_scale: tuple[float, float] | None = None,
        compression: str = "input",
    ) -> dict:
        """Start a sequence; see the API's SessionCreate for the fields."""
        body = _session_body(width, height, model, channels, precision, motion_scale, compression)
        return (await self._request("POST", "/v1/sessions", json=body, create=True)).json()

    async def session(self, session_id: str) -> dict:
        return (await self._request("GET", f"/v1/sessions/{session_id}")).json()

    async def delete_session(self, session_id: str, missing_ok: bool = True) -> None:
        try:
            await self._request("DELETE", f"/v1/sessions/{session_id}")
        except QuietframeError as exc:
            if not (missing_ok and exc.status == 404):
                raise

    async def send_frame(
        self, session_id: str, index: int, exr: bytes, cut: bool = False
    ) -> FrameResult:
        params = {"cut": "true"} if cut else None
        response = await self._request(
            "POST",
            f"/v1/sessions/{session_id}/frames/{index}",
            content=exr,
            headers={"Content-Type": EXR},
            params=params,
        )
        return _frame_result(index, response)

    async def denoise_sequence(self, source, out_dir, **options) -> str | None:
        """`Client.denoise_sequence` for asyncio (one task per sequence)."""
        from quietframe.client.sequence import Job, arun_sequence

        job = Job.plan(source, out_dir)
        return await arun_sequence(self, job, str(self._http.base_url), **options)
