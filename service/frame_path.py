"""A frame's heavy part, on a worker thread: decode (unless the choice did), denoise, encode, and
the reply's headers. Touches no session: the registry commits the result (service/sessions.py)."""

from __future__ import annotations

import time

import numpy as np

from quietframe.runtime import lookahead
from quietframe.runtime.stream import Step, Stream
from quietframe.service import frames, lookahead_queue, state_codec
from quietframe.service.below_input import below_input_warning
from quietframe.service.choice_policy import Choice
from quietframe.service.frame_context import FrameContext
from quietframe.service.noise_estimate import ESTIMATE
from quietframe.service.session import ProcessedFrame, Session
from quietframe.service.session_spec import SessionSpec
from quietframe.service.session_store import Reply, request_digest
from quietframe.service.shot_choice import choice_header
from quietframe.wire.protocol import (
    Header,
    Reset,
    format_counts,
    format_estimated_motion,
    format_timings,
    join_list,
)


def process_frame(
    stream: Stream,
    spec: SessionSpec,
    index: int,
    body: bytes | bytearray,
    context: FrameContext,
    reset: Reset,
    state: dict[str, np.ndarray] | None,
    choice: Choice | None = None,
    window: dict[str, np.ndarray] | None = None,
    shot_spp: float | None = None,
) -> ProcessedFrame:
    """Decode, denoise, encode one frame. `stream`: the session's sequence on the model that
    runs (runtime/stream.py: options, spp, the motion-evidence gate, the history, OIDN's
    filters); `context`: the frame as found for that model (FrameContext.for_model), its pixels
    too where the choice decoded them; `state` is None when the history starts afresh;
    `choice` (model=auto) is said in a header; a model asked for by name at an spp where it is
    below its own noisy input gets X-Quietframe-Warning (service/below_input.py). A look-ahead
    session (`spec.lookahead`) queues the frame in its `window` instead and replies with the
    oldest pending one, once more than `lookahead` are pending (`_held_back`). `shot_spp`: a
    named model's estimate of the shot's spp, where it reads one and none is stated
    (Stream.wants_estimate); said in X-Quietframe-Samples and kept with the session."""
    if context.decoded is None:
        context = context.decode(body)
    frame, sources = context.decoded, context.sources
    assert frame is not None
    decoded = time.perf_counter()
    stated = context.stated.spp if context.stated is not None else None
    step = stream.step(frame.buffers, state, stated, choice.spp if choice else shot_spp,
                       context.renderer)
    # A temporal model reads its history only where the motion is evidence (motion_evidence):
    # a frame without vectors whose aux moved starts afresh, as after a cut.
    verdict = step.history_verdict
    if verdict is not None:
        reset = Reset.DETECTED_CUT if verdict == "cut" else Reset.NO_MOTION
    denoised = time.perf_counter()
    info = stream.info
    model = f"{info.name} {info.version}"
    extra = {"quietframe.model": model, "quietframe.frame": str(index)}
    # auto's own choice leaves such a model out (choice_policy.not_below_input), and a shot's
    # kept model is auto's too: only a model the session names is warned of
    # Only a stated spp is judged: the shot's estimate reads 1-spp frames as ~6 spp and 64-spp
    # ones as ~14 (docs/service.md), which would warn wrongly at the low end of the range.
    warning = (below_input_warning(info.name, stream.denoiser, stated, context.renderer)
               if choice is None else None)
    if spec.lookahead:
        return _held_back(stream, spec, index, body, context, reset, choice, window or {},
                          step, extra, 1e3 * (denoised - decoded), warning, shot_spp)
    body_out, clamped = frames.encode_denoised(
        step.color,
        frame,
        sources["color"].channels,
        spec.precision,
        extra,
        spec.compression,
        spec.denoised_layer,
    )
    done = time.perf_counter()
    decode_ms = context.decode_ms  # the choice's decode, where it decoded the frame
    timings = {
        "decode": decode_ms,
        "denoise": 1e3 * (denoised - decoded),
        "encode": 1e3 * (done - denoised),
        "total": decode_ms + 1e3 * (done - decoded),
    }
    sanitized = {k: v for k, v in step.sanitized.items() if v}
    if clamped:
        sanitized["denoised"] = sanitized.get("denoised", 0) + clamped
    headers = frame_headers(index, reset, model, sanitized, timings, step, choice, warning,
                            shot_spp)
    # Where the colour is a state plane, a store keeps how to write the reply, not its bytes
    dtypes = frames.output_dtypes(frame, spec.precision)
    recipe = state_codec.reply_recipe(step.color, step.state, dtypes, sources["color"].channels,
                                      spec.precision, spec.compression, spec.denoised_layer, extra)
    return ProcessedFrame(
        reply=Reply(index, body_out, headers, len(body), request_digest(body), recipe=recipe),
        state=step.state,
        reset=reset,
        sources={b: list(s.channels) for b, s in sources.items()},
        missing=list(step.missing),
        sanitized=sanitized,
        timings_ms=timings,
        info=info,
        choice=choice,
        shot_spp=shot_spp,
    )


def frame_headers(index: int, reset: Reset, model: str, sanitized: dict[str, int],
                  timings: dict[str, float], step: Step, choice: Choice | None,
                  warning: str | None = None, shot_spp: float | None = None
                  ) -> dict[str, str]:
    """The headers that describe a denoised frame (`warning`: below_input_warning's;
    `shot_spp`: a named model's estimate of the shot's spp)."""
    headers = {
        Header.FRAME: str(index),
        Header.RESET: reset.value,
        Header.MODEL: model,
        Header.SANITIZED: str(sum(sanitized.values())),
        Header.SERVER_TIMING: format_timings(timings),
    }
    if sanitized:
        headers[Header.SANITIZED_BUFFERS] = format_counts(sanitized)
    if step.missing:
        headers[Header.MISSING] = join_list(step.missing)
    if step.gate is not None and step.gate.evidence is not None:
        headers[Header.MOTION] = motion_header(step)
    if choice is not None:
        headers[Header.CHOICE] = choice_header(choice)
    if shot_spp is not None:
        headers[Header.SAMPLES] = f"{shot_spp:g}; source={ESTIMATE}"
    if warning:
        headers[Header.WARNING] = warning
    return headers


def _held_back(stream: Stream, spec: SessionSpec, index: int, body: bytes | bytearray,
               context: FrameContext, reset: Reset, choice: Choice | None,
               window: dict[str, np.ndarray], step: Step, extra: dict[str, str],
               denoise_ms: float, warning: str | None,
               shot_spp: float | None = None) -> ProcessedFrame:
    """A look-ahead session's frame: queued with its headers and how to write its reply, and
    the reply to this request: the oldest pending frame finished (200) once more than
    `spec.lookahead` are pending, else 202 (docs/service.md, "Look-ahead")."""
    frame, sources = context.decoded, context.sources
    assert frame is not None
    info = stream.info
    timings = {"decode": context.decode_ms, "denoise": denoise_ms, "encode": 0.0,
               "total": context.decode_ms + denoise_ms}
    sanitized = {k: v for k, v in step.sanitized.items() if v}
    headers = frame_headers(index, reset, extra["quietframe.model"], sanitized, timings, step,
                            choice, warning, shot_spp)
    dtypes = tuple(np.dtype(d).name for d in frames.output_dtypes(frame, spec.precision))
    recipe = state_codec.ReplyRecipe("", 0, dtypes, tuple(sources["color"].channels),
                                     spec.precision, spec.compression, spec.denoised_layer,
                                     extra)
    start = time.perf_counter()
    window = lookahead_queue.hold(window, step, frame.buffers, info.card.architecture, index,
                                  body, headers, timings, sanitized, recipe)
    held = lookahead.pending(window)
    if len(held) > spec.lookahead:
        released = lookahead_queue.release(window)
        window, reply_body, status = released.window, released.body, 200
        reply_headers, held = released.headers, held[1:]
    else:
        reply_body, status = b"", 202
        reply_headers = {Header.PENDING: str(len(held))}
    encode_ms = 1e3 * (time.perf_counter() - start)  # queueing, and the reply's blend and write
    now = {"decode": context.decode_ms, "denoise": denoise_ms, "encode": encode_ms,
           "total": context.decode_ms + denoise_ms + encode_ms}
    return ProcessedFrame(
        reply=Reply(index, reply_body, reply_headers, len(body), request_digest(body),
                    status=status),
        state=lookahead_queue.join(step.state, window),
        reset=reset,
        sources={b: list(s.channels) for b, s in sources.items()},
        missing=list(step.missing),
        sanitized=sanitized,
        timings_ms=now,
        info=info,
        choice=choice,
        pending=held,
        shot_spp=shot_spp,
    )


def finish_frame(session: Session) -> ProcessedFrame:
    """A look-ahead session's oldest pending frame finished now with the later frames it has
    (POST .../frames/{index}/finish): its reply, and the session's state without it."""
    history, window = lookahead_queue.split(session.state)
    start = time.perf_counter()
    released = lookahead_queue.release(window)
    total = 1e3 * (time.perf_counter() - start)
    return ProcessedFrame(
        reply=Reply(released.index, released.body, released.headers, 0, request_digest(b""),
                    finish=True),
        state=lookahead_queue.join(history, released.window),
        reset=Reset.NONE,
        sources=session.sources,
        missing=session.missing,
        sanitized={},
        timings_ms={"decode": 0.0, "denoise": 0.0, "encode": total, "total": total},
        info=session.info,
        pending=lookahead.pending(released.window),
        finish=True,
    )


def motion_header(step: Step) -> str:
    """X-Quietframe-Motion of a temporal model's frame without motion vectors: what its aux
    showed, whether motion was estimated from them, and whether (or where) the history was
    used."""
    gate = step.gate
    assert gate is not None and gate.evidence is not None
    if step.estimated is not None:
        return format_estimated_motion(gate.evidence.describe(), step.estimated.share)
    used = "history not used" if gate.state is None else "history used"
    return f"{gate.evidence.describe()}; {used}"
