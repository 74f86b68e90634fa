"""HTTP clients of the quietframe service: sync `Client`, async `AsyncClient`.

Both are thin I/O shells over client/core.py, which builds the requests, decides the retries
and parses the replies; each method here only sends a core Call (and awaits, for the async one).
"""

from __future__ import annotations

import asyncio
import time

import httpx

from quietframe.client import core
from quietframe.client.core import Call, FrameResult, QuietframeError, RetryPolicy
from quietframe.client.job import Job
from quietframe.client.sequence import arun_sequence, run_sequence


class _ClientBase:
    """Connection settings shared by both clients; `_http_class` is httpx's sync or async one."""

    _http_class: type = httpx.Client

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        timeout_s: float = 300.0,
        retry: RetryPolicy | None = None,
        transport: httpx.BaseTransport | httpx.AsyncBaseTransport | None = None,
        on_retry=None,
    ) -> None:
        """`on_retry(core.Retry)`: told before each retry's wait (the CLI prints it)."""
        self.retry = retry or RetryPolicy()
        self.on_retry = on_retry
        self.url = core.base_url(base_url)
        self._http = self._http_class(
            base_url=self.url,
            headers=core.auth_headers(token),
            timeout=timeout_s,
            transport=transport,
        )


class Client(_ClientBase):
    """Synchronous client. `Client("http://farm-denoise:8000")`, use as a context manager."""

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *_) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _send(self, call: Call) -> httpx.Response:
        attempts = core.Attempts(self.retry, call, self.on_retry)
        while (delay := attempts.after(self._try(call))) is not None:
            time.sleep(delay)
        return attempts.response

    def _try(self, call: Call) -> httpx.Response | httpx.TransportError:
        try:
            return self._http.request(call.method, call.path, **call.options)
        except httpx.TransportError as exc:
            return exc

    def models(self) -> dict:
        return self._send(core.models_call()).json()

    def ready(self) -> bool:
        try:
            return self._http.get("/readyz").status_code == 200
        except httpx.TransportError:
            return False

    def create_session(self, width: int, height: int, model: str = "auto", **options) -> dict:
        """Start a sequence; options are core.SessionRequest's (channels, precision,
        motion_scale, compression, layer, denoised_layer, quality, latency_ms, model_options
        such as {"kernel_size": 9}), the API's SessionCreate fields."""
        return self._send(core.SessionRequest.of(width, height, model, **options).call()).json()

    def session(self, session_id: str) -> dict:
        return self._send(core.session_call(session_id)).json()

    def delete_session(self, session_id: str, missing_ok: bool = True) -> None:
        try:
            self._send(core.delete_session_call(session_id))
        except QuietframeError as exc:
            if not (missing_ok and exc.status == 404):
                raise

    def send_frame(self, session_id: str, index: int, exr: bytes, cut: bool = False,
                   shot_model: str | None = None) -> FrameResult | None:
        """`shot_model` (model=auto): the model already chosen for the frame's shot. The result
        is the frame the reply carries: frame `index`, or in a look-ahead session (`lookahead`
        k > 0) the frame k before it (`result.index`); None while the session holds the frame
        back (202: nothing to write yet)."""
        response = self._send(core.frame_call(session_id, index, exr, cut, shot_model))
        return core.parse_frame(index, response)

    def finish_frame(self, session_id: str, index: int) -> FrameResult:
        """A look-ahead session's oldest pending frame `index`, finished now with the later
        frames it has: call it for each frame still pending at the end of a shot or chunk."""
        return core.parse_finished(index, self._send(core.finish_call(session_id, index)))

    def denoise_sequence(self, source, out_dir, frames: tuple[int, ...] | None = None,
                         pre_roll: int = 0, post_roll: int = 0, cuts: tuple[int, ...] = (),
                         **options) -> str | None:
        """Stream a folder, glob or frame pattern of EXR frames through one session into
        `out_dir` (same names), resuming an earlier run: `frames` (frame numbers, e.g.
        range(1001, 1013)) limits it to a chunk, sent after its `pre_roll` frames and before
        its `post_roll` ones (for `lookahead`; neither written), `cuts` starts a fresh history
        at those frames; options of `sequence.run_sequence` (model, precision, compression,
        warmup, on_progress, layers, and session fields such as channels or lookahead).
        Returns the session id, None if nothing was left."""
        job = Job.plan(source, out_dir, _frames(frames), pre_roll, tuple(cuts),
                       post_roll=post_roll)
        return run_sequence(self, job, str(self._http.base_url), **options)


class AsyncClient(_ClientBase):
    """The same API for asyncio (several sequences from one process, one task per sequence)."""

    _http_class = httpx.AsyncClient

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *_) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _send(self, call: Call) -> httpx.Response:
        attempts = core.Attempts(self.retry, call, self.on_retry)
        while (delay := attempts.after(await self._try(call))) is not None:
            await asyncio.sleep(delay)
        return attempts.response

    async def _try(self, call: Call) -> httpx.Response | httpx.TransportError:
        try:
            return await self._http.request(call.method, call.path, **call.options)
        except httpx.TransportError as exc:
            return exc

    async def models(self) -> dict:
        return (await self._send(core.models_call())).json()

    async def create_session(
        self, width: int, height: int, model: str = "auto", **options
    ) -> dict:
        """Start a sequence; options as for Client.create_session."""
        call = core.SessionRequest.of(width, height, model, **options).call()
        return (await self._send(call)).json()

    async def session(self, session_id: str) -> dict:
        return (await self._send(core.session_call(session_id))).json()

    async def delete_session(self, session_id: str, missing_ok: bool = True) -> None:
        try:
            await self._send(core.delete_session_call(session_id))
        except QuietframeError as exc:
            if not (missing_ok and exc.status == 404):
                raise

    async def send_frame(
        self, session_id: str, index: int, exr: bytes, cut: bool = False,
        shot_model: str | None = None,
    ) -> FrameResult | None:
        response = await self._send(core.frame_call(session_id, index, exr, cut, shot_model))
        return core.parse_frame(index, response)

    async def finish_frame(self, session_id: str, index: int) -> FrameResult:
        response = await self._send(core.finish_call(session_id, index))
        return core.parse_finished(index, response)

    async def denoise_sequence(self, source, out_dir, frames: tuple[int, ...] | None = None,
                               pre_roll: int = 0, post_roll: int = 0,
                               cuts: tuple[int, ...] = (), **options) -> str | None:
        """`Client.denoise_sequence` for asyncio (one task per sequence)."""
        job = Job.plan(source, out_dir, _frames(frames), pre_roll, tuple(cuts),
                       post_roll=post_roll)
        return await arun_sequence(self, job, str(self._http.base_url), **options)


def _frames(frames) -> tuple[int, ...] | None:
    """Frame numbers as Job.plan takes them: ascending, without repeats."""
    return None if frames is None else tuple(sorted(set(frames)))
