"""A look-ahead session's held-back frames (session field `lookahead` k > 0; docs/service.md,
"Look-ahead"): the service's side of runtime/lookahead.py.

Each frame is denoised causally as in any session and queued in the runtime's window with what
its reply needs later: the request's EXR (`body`: the reply is that file with the finished
colour written in, as for any frame) and the reply's headers and recipe (`reply`, JSON). Once
more than k frames are pending, the oldest leaves, finished with the later frames of its history
run, as the reply to the frame just sent; `finish` lets one leave at the end of a shot or chunk.

The window is part of the session's state, its arrays under PREFIX beside the model's history:
it is kept, counted, evicted, stored (service/session_store.record: the planes exactly as
float32, the 1-D pieces as their bytes), failed over and dropped (DELETE) with the rest of it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from quietframe.runtime import lookahead
from quietframe.runtime.stream import Step
from quietframe.service import frames
from quietframe.service.session_store import ANY_LENGTH
from quietframe.service.state_codec import ReplyRecipe
from quietframe.wire.protocol import Header, format_counts, format_timings

PREFIX = "lookahead."  # the window's arrays among a session's state
BODY, REPLY = "body", "reply"  # the service's pieces of a pending frame (1-D uint8)


def split(state: Mapping[str, np.ndarray] | None
          ) -> tuple[dict[str, np.ndarray] | None, dict[str, np.ndarray]]:
    """(the model's history and the stream's probes, or None where there is none; the window)."""
    if not state:
        return None, {}
    history = {k: v for k, v in state.items() if not k.startswith(PREFIX)}
    window = {k[len(PREFIX):]: v for k, v in state.items() if k.startswith(PREFIX)}
    return history or None, window


def join(history: Mapping[str, np.ndarray] | None,
         window: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A session's state from its history and its window."""
    return {**(history or {}), **{PREFIX + k: v for k, v in window.items()}}


def pending(state: Mapping[str, np.ndarray] | None) -> list[int]:
    """The indices of the frames a session's state holds back, oldest first."""
    return lookahead.pending(split(state)[1])


def shapes(k: int, height: int, width: int) -> dict[str, tuple[int, ...]]:
    """Every window array a session with look-ahead `k` may store, and its shape."""
    held = {f"{slot}.{name}": ANY_LENGTH for slot in range(k + 1) if k for name in (BODY, REPLY)}
    return {PREFIX + name: shape
            for name, shape in (lookahead.window_shapes(k, height, width) | held).items()}


def reserve_bytes(k: int, height: int, width: int, body_bytes: int) -> int:
    """What k pending frames of bodies of `body_bytes` hold between frames."""
    return k * (lookahead.frame_nbytes(height, width) + body_bytes + (1 << 12))


def frame_need(k: int, height: int, width: int, body_bytes: int) -> int:
    """What a look-ahead frame holds in flight beyond any frame's: its pieces before the oldest
    leaves (k + 1 pending for a moment), its body's copy, the blend's working set and the
    leaving frame's colour decoded again."""
    if not k:
        return 0
    return (lookahead.frame_nbytes(height, width) + body_bytes
            + lookahead.working_set_bytes(height, width) + 3 * 4 * height * width)


def finish_need(state: Mapping[str, np.ndarray] | None, spec) -> int:
    """What finishing the oldest pending frame holds in flight: the blend's working set, its
    request decoded again (its colour) and its reply written (at most twice the request)."""
    window = split(state)[1]
    body = window.get(f"0.{BODY}")
    body_bytes = 0 if body is None else body.size
    h, w = spec.height, spec.width
    return lookahead.working_set_bytes(h, w) + 2 * 3 * 4 * h * w + 2 * body_bytes


@dataclass(frozen=True)
class Released:
    """A pending frame finished: its reply's body and headers, and the window without it."""

    index: int
    body: bytes
    headers: dict[str, str]
    window: dict[str, np.ndarray]
    blend_ms: float


def hold(window: Mapping[str, np.ndarray], step: Step, planes: Mapping[str, np.ndarray],
         architecture: Mapping, index: int, body: bytes | bytearray, headers: Mapping[str, str],
         timings: Mapping[str, float], sanitized: Mapping[str, int],
         recipe: ReplyRecipe) -> dict[str, np.ndarray]:
    """The window with frame `index`'s causal step queued: the runtime's pieces (`planes`: the
    frame's buffers as decoded, FORWARD too) and what its reply needs (`headers` and `timings`
    of its processing, the input values `sanitized`, how to write it: `recipe`)."""
    reply = {"headers": dict(headers), "timings": dict(timings), "sanitized": dict(sanitized),
             "recipe": recipe.to_dict()}
    pieces = lookahead.frame_pieces(step, planes, architecture) | {
        BODY: np.frombuffer(bytes(body), np.uint8),
        REPLY: np.frombuffer(json.dumps(reply).encode(), np.uint8),
    }
    return lookahead.push(window, pieces, index, not step.history_used)


def release(window: Mapping[str, np.ndarray]) -> Released:
    """The oldest pending frame finished with the later frames the window holds, its reply
    written from its request (ValueError where nothing is pending or its pieces are not a
    reply's: a damaged record)."""
    start = time.perf_counter()
    done = lookahead.pop(window)
    blended = time.perf_counter()
    try:
        reply = json.loads(done.pieces[REPLY].tobytes())
        recipe = ReplyRecipe.from_dict(reply["recipe"])
        headers = {str(k): str(v) for k, v in reply["headers"].items()}
        timings = {str(k): float(v) for k, v in reply["timings"].items()}
        sanitized = {str(k): int(v) for k, v in reply["sanitized"].items()}
        body = done.pieces[BODY].tobytes()
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ValueError(f"pending frame {done.index}: its stored reply is damaged ({exc})"
                         ) from exc
    frame = frames.decode(body, {"color": frames.Source(recipe.color_channels, "held")})
    out, clamped = frames.encode_denoised(done.color, frame, recipe.color_channels,
                                          recipe.precision, recipe.extra, recipe.compression,
                                          recipe.denoised_layer)
    if clamped:
        sanitized["denoised"] = sanitized.get("denoised", 0) + clamped
    done_ms = time.perf_counter()
    # The frame's own processing and what finishing it took now (the blend and writing it)
    timings.pop("total", None)
    timings |= {"lookahead": 1e3 * (blended - start), "encode": 1e3 * (done_ms - blended)}
    timings["total"] = sum(timings.values())
    headers[Header.SANITIZED] = str(sum(sanitized.values()))
    headers.pop(Header.SANITIZED_BUFFERS, None)
    if sanitized:
        headers[Header.SANITIZED_BUFFERS] = format_counts(sanitized)
    headers[Header.SERVER_TIMING] = format_timings(timings)
    headers[Header.PENDING] = str(len(lookahead.pending(done.window)))
    return Released(done.index, out, headers, done.window, 1e3 * (blended - start))
