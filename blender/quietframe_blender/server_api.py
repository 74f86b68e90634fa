"""The quietframe server's /v1 API over the standard library (Blender's Python has no httpx):
create a session, send a frame, delete the session, with the retries the service asks for.

- 429 and 503 (busy, or its state store unavailable) and 502/504 (a proxy in front of it) are
  retried after the server's Retry-After, else an exponential backoff; each wait is capped and
  the retries are bounded, and a cancel event ends a wait at once.
- A frame whose connection broke is sent again: the server answers a repeated index with the
  stored reply (idempotent), so the history does not advance twice. A session is created again
  only when the server surely did not create one (a refused connection is reported at once,
  naming the URL: that is a wrong URL or a server that is not running).
- Any other refusal (4xx) is an error carrying the server's own message, which says what to fix.
- A look-ahead session (`lookahead` k > 0) answers a frame with an earlier one (the reply's
  `frame`), or nothing yet (202: None); `finish_frame` asks for a frame it still holds.
"""

from __future__ import annotations

import http.client
import ipaddress
import json
import socket
import threading
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass, field

from .wire import protocol

_RETRY_STATUS = frozenset({429, 502, 503, 504})


class DenoiseError(Exception):
    """A failure to show the user as it is: its message says what went wrong and what to do."""


class Cancelled(Exception):
    """The user cancelled (Esc); the frame in flight was finished or abandoned."""


@dataclass(frozen=True)
class RetryPolicy:
    retries: int = 5
    backoff_s: float = 0.5
    max_wait_s: float = 30.0  # one wait, whatever Retry-After asks

    def delay(self, attempt: int, retry_after: str | None) -> float:
        if retry_after is not None:
            try:
                return min(self.max_wait_s, max(0.0, float(retry_after)))
            except ValueError:  # an HTTP date: fall back to the backoff
                pass
        return min(self.max_wait_s, self.backoff_s * 2**attempt)


@dataclass(frozen=True)
class FrameReply:
    """The denoised EXR and what the server said about it (wire.protocol.Header)."""

    exr: bytes
    reset: str
    model: str
    missing: tuple[str, ...]
    replayed: bool
    choice: str = ""
    frame: int | None = None  # the frame it carries (look-ahead: an earlier one than sent)


@dataclass
class _Outcome:
    status: int  # 0: no response (the exception says why)
    body: bytes = b""
    headers: dict[str, str] = field(default_factory=dict)
    error: Exception | None = None


def base_url(url: str) -> str:
    """The server's root URL from the preference: a trailing `/` or `/v1` is dropped."""
    url = url.strip().rstrip("/")
    if not url.startswith(("http://", "https://")):
        raise DenoiseError(
            f"the quietframe server URL {url!r} must start with http:// or https:// "
            "(Edit > Preferences > Add-ons > quietframe denoise)"
        )
    return url[: -len("/v1")] if url.endswith("/v1") else url


def on_local_network(url: str) -> bool:
    """Whether the server is on this machine or the local network, by its URL alone (no DNS):
    localhost, a loopback, private or link-local address, a single-label host name (`denoise`)
    or an mDNS one (`*.local`). Blender's "Allow Online Access" governs the internet; a farm's
    own server on its network is reached without it."""
    host = urllib.parse.urlsplit(base_url(url)).hostname or ""
    try:
        address = ipaddress.ip_address(host)
    except ValueError:  # a name
        return host == "localhost" or host.endswith(".local") or "." not in host
    return address.is_loopback or address.is_private or address.is_link_local


class ServerApi:
    """One server, its token and retry policy; `cancel` (set by Esc) interrupts retry waits."""

    def __init__(
        self,
        url: str,
        token: str | None = None,
        timeout_s: float = 300.0,
        retry: RetryPolicy | None = None,
        cancel: threading.Event | None = None,
        on_retry=None,
    ) -> None:
        self.url = base_url(url)
        self.token = token or None
        self.timeout_s = timeout_s
        self.retry = retry or RetryPolicy()
        self.cancel = cancel or threading.Event()
        self.on_retry = on_retry  # (message) -> None: told before each wait

    def create_session(self, width: int, height: int, **fields) -> dict:
        """POST /v1/sessions; `fields` are the API's session fields (model, quality, layer...),
        None values left out."""
        body = {"width": width, "height": height}
        body.update({k: v for k, v in fields.items() if v is not None})
        outcome = self._request(
            "POST", "/v1/sessions", json.dumps(body).encode(),
            {"Content-Type": "application/json"}, create=True,
        )
        return json.loads(outcome.body)

    def send_frame(self, session_id: str, index: int, exr: bytes) -> FrameReply | None:
        """The frame the reply carries: frame `index`, or in a look-ahead session an earlier
        one; None while the session holds the frame back (202)."""
        outcome = self._request(
            "POST", f"/v1/sessions/{session_id}/frames/{index}", exr,
            {"Content-Type": protocol.EXR_MEDIA_TYPE},
        )
        return None if outcome.status == 202 else _reply(outcome, index)

    def finish_frame(self, session_id: str, index: int) -> FrameReply:
        """A look-ahead session's oldest held frame `index`, finished with the later frames it
        has (at the end of a shot)."""
        outcome = self._request("POST", f"/v1/sessions/{session_id}/frames/{index}/finish",
                                None, {})
        return _reply(outcome, index)

    def delete_session(self, session_id: str) -> None:
        """Frees the session's history; best effort (an expired session is already gone)."""
        try:
            # also after a cancel: a cancelled job frees its session too
            self._request("DELETE", f"/v1/sessions/{session_id}", None, {}, retries=0,
                          cancellable=False)
        except DenoiseError:
            pass

    # ---- one request with its retries ---------------------------------------------------

    def _request(self, method: str, path: str, body: bytes | None, headers: dict[str, str],
                 create: bool = False, retries: int | None = None,
                 cancellable: bool = True) -> _Outcome:
        limit = self.retry.retries if retries is None else retries
        attempt = 0
        while True:
            if cancellable and self.cancel.is_set():
                raise Cancelled()
            outcome = self._once(method, path, body, headers)
            if 200 <= outcome.status < 300:
                return outcome
            if attempt >= limit or not self._retryable(outcome, create):
                raise self._error(outcome, attempt)
            delay = self.retry.delay(attempt, outcome.headers.get("retry-after"))
            attempt += 1
            if self.on_retry is not None:
                self.on_retry(f"{self._why(outcome)}; retry {attempt} of {limit} in {delay:.1f} s")
            if self.cancel.wait(delay):
                raise Cancelled()

    def _once(self, method: str, path: str, body: bytes | None,
              headers: dict[str, str]) -> _Outcome:
        all_headers = dict(headers)
        if self.token:
            all_headers["Authorization"] = f"Bearer {self.token}"
        request = urllib.request.Request(self.url + path, body, all_headers, method=method)
        try:
            with urllib.request.urlopen(request, timeout=self.timeout_s) as response:
                return _Outcome(response.status, response.read(), _lower(response.headers))
        except urllib.error.HTTPError as exc:
            try:
                return _Outcome(exc.code, exc.read(), _lower(exc.headers))
            finally:
                exc.close()
        except (OSError, http.client.HTTPException) as exc:  # refused, reset, timed out, DNS
            return _Outcome(0, error=exc)

    @staticmethod
    def _retryable(outcome: _Outcome, create: bool) -> bool:
        if outcome.status:
            return outcome.status in _RETRY_STATUS
        if _refused(outcome.error):
            return False  # a wrong URL or no server: say so now, not after a minute of retries
        # A lost connection: a frame is resent safely (idempotent by index); a session may
        # have been created, so creating another could leak one
        return not create

    def _why(self, outcome: _Outcome) -> str:
        if outcome.status:
            return f"{outcome.status} {_error_body(outcome)[0]}"
        return f"no answer from {self.url} ({_reason(outcome.error)})"

    def _error(self, outcome: _Outcome, retried: int) -> DenoiseError:
        if not outcome.status:
            return DenoiseError(
                f"could not reach the quietframe server at {self.url} "
                f"({_reason(outcome.error)}): is it running, and is the URL in the add-on's "
                "preferences right?"
            )
        code, detail = _error_body(outcome)
        verb = "failed" if outcome.status >= 500 else "refused"
        message = f"the quietframe server {verb} ({outcome.status} {code}): {detail}"
        if outcome.status == 401:
            message += " (set the token in the add-on's preferences)"
        elif outcome.status in _RETRY_STATUS:
            message = (f"the quietframe server at {self.url} stayed busy after "
                       f"{retried} retries ({outcome.status} {code}): {detail}")
        return DenoiseError(message)


def _reply(outcome: _Outcome, index: int) -> FrameReply:
    h = outcome.headers
    frame = h.get(protocol.Header.FRAME.lower(), "")
    return FrameReply(
        exr=outcome.body,
        reset=h.get(protocol.Header.RESET.lower(), "none"),
        model=h.get(protocol.Header.MODEL.lower(), ""),
        missing=protocol.split_list(h.get(protocol.Header.MISSING.lower(), "")),
        replayed=h.get(protocol.Header.REPLAYED.lower()) == "true",
        choice=h.get(protocol.Header.CHOICE.lower(), ""),
        frame=int(frame) if frame.isdigit() else index,
    )


def _lower(headers) -> dict[str, str]:
    return {k.lower(): v for k, v in headers.items()} if headers is not None else {}


def _error_body(outcome: _Outcome) -> tuple[str, str]:
    """The service's `{"error": code, "detail": message}`, or what a proxy sent instead."""
    try:
        body = json.loads(outcome.body)
        return str(body["error"]), str(body["detail"])
    except (ValueError, KeyError, TypeError):
        text = outcome.body[:300].decode("utf-8", "replace").strip()
        return "http_error", text or "no detail"


def _refused(error: Exception | None) -> bool:
    reason = error.reason if isinstance(error, urllib.error.URLError) else error
    return isinstance(reason, ConnectionRefusedError | socket.gaierror)


def _reason(error: Exception | None) -> str:
    reason = error.reason if isinstance(error, urllib.error.URLError) else error
    if isinstance(reason, ConnectionRefusedError):
        return "connection refused"
    if isinstance(reason, socket.gaierror):
        return f"unknown host: {reason}"
    if isinstance(reason, TimeoutError | socket.timeout):
        return "timed out"
    return f"{type(reason).__name__}: {reason}"
