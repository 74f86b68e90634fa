"""A frame's heavy part, on a worker thread: decode (unless the choice did), denoise, encode, and
the reply's headers. Touches no session: the registry commits the result (service/sessions.py)."""

from __future__ import annotations

import time

import numpy as np

from quietframe.runtime import Denoiser
from quietframe.runtime.model_options import options_for
from quietframe.runtime.motion_evidence import HistoryGate, gate_history, keep_probe
from quietframe.service import frames, state_codec
from quietframe.service.choice_policy import Choice
from quietframe.service.frame_context import FrameContext
from quietframe.service.session import ProcessedFrame
from quietframe.service.session_spec import SessionSpec
from quietframe.service.session_store import Reply, request_digest
from quietframe.service.shot_choice import choice_header
from quietframe.wire.protocol import Header, Reset, format_counts, format_timings, join_list


def process_frame(
    denoiser: Denoiser,
    spec: SessionSpec,
    index: int,
    body: bytes | bytearray,
    context: FrameContext,
    reset: Reset,
    state: dict[str, np.ndarray] | None,
    choice: Choice | None = None,
) -> ProcessedFrame:
    """Decode, denoise, encode one frame. `context`: the frame as found for `denoiser`'s model
    (FrameContext.for_model), its pixels too where the choice decoded them; `state` is None
    when the history starts afresh; `choice` (model=auto) is said in a header. A model that
    takes the frame's spp is given it; OIDN sees the rows in the renderer's order."""
    if context.decoded is None:
        context = context.decode(body)
    frame, sources = context.decoded, context.sources
    assert frame is not None
    decoded = time.perf_counter()
    options = options_for(denoiser.info, spec.model_options, context.samples(choice))
    # A temporal model reads its history only where the motion is evidence (motion_evidence):
    # a frame without vectors whose aux moved starts afresh, as after a cut.
    gate = (gate_history(frame.buffers, state, spec.camera) if denoiser.info.state_specs
            else None)
    if gate is not None and gate.dropped:
        assert gate.evidence is not None
        reset = Reset.DETECTED_CUT if gate.evidence.verdict == "cut" else Reset.NO_MOTION
    result = denoiser.denoise(frame.buffers, gate.state if gate else state, options,
                              context.renderer)
    new_state = keep_probe(result.state, gate.probe) if gate else result.state
    denoised = time.perf_counter()
    info = denoiser.info
    model = f"{info.name} {info.version}"
    extra = {"quietframe.model": model, "quietframe.frame": str(index)}
    body_out, clamped = frames.encode_denoised(
        result.color,
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
    sanitized = {k: v for k, v in result.sanitized.items() if v}
    if clamped:
        sanitized["denoised"] = sanitized.get("denoised", 0) + clamped
    headers = {
        Header.FRAME: str(index),
        Header.RESET: reset.value,
        Header.MODEL: model,
        Header.SANITIZED: str(sum(sanitized.values())),
        Header.SERVER_TIMING: format_timings(timings),
    }
    if sanitized:
        headers[Header.SANITIZED_BUFFERS] = format_counts(sanitized)
    if result.missing:
        headers[Header.MISSING] = join_list(result.missing)
    if gate is not None and gate.evidence is not None:
        headers[Header.MOTION] = motion_header(gate)
    if choice is not None:
        headers[Header.CHOICE] = choice_header(choice)
    # Where the colour is a state plane, a store keeps how to write the reply, not its bytes
    dtypes = frames.output_dtypes(frame, spec.precision)
    recipe = state_codec.reply_recipe(result.color, new_state, dtypes, sources["color"].channels,
                                      spec.precision, spec.compression, spec.denoised_layer, extra)
    return ProcessedFrame(
        reply=Reply(index, body_out, headers, len(body), request_digest(body), recipe=recipe),
        state=new_state,
        reset=reset,
        sources={b: list(s.channels) for b, s in sources.items()},
        missing=list(result.missing),
        sanitized=sanitized,
        timings_ms=timings,
        info=info,
        choice=choice,
    )


def motion_header(gate: HistoryGate) -> str:
    """X-Quietframe-Motion of a temporal model's frame without motion vectors: what its aux
    showed and whether the history was used."""
    assert gate.evidence is not None
    used = "history not used" if gate.state is None else "history used"
    return f"{gate.evidence.describe()}; {used}"
