"""What a frame's path knows of one frame, found once and handed on: to `auto`'s choice
(service/shot_choice.py) and to the processing (service/frame_path.py).

From the header, before the session's lock: the spp the session or the renderer states, which
renderer wrote the frame, and where each buffer is in the file (for `model=auto` every buffer the
file has, since the model is not chosen yet). Where a shot's first frame is decoded for the choice,
its pixels and the buffers that hold nothing usable join it, and the processing denoises those same
pixels. `for_model` narrows it to the buffers of the model that runs.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

from quietframe.client.session_fields import AUTO
from quietframe.runtime import BUFFER_NAMES, ModelInfo
from quietframe.runtime.buffers import FORWARD, SIDE_BUFFERS
from quietframe.runtime.usable_buffers import unusable_buffers
from quietframe.service import frames
from quietframe.service.frame_evidence import renderer_from_header, stated_samples
from quietframe.service.noise_estimate import NoiseLevel
from quietframe.service.session_spec import SessionSpec

Installed = Mapping[str, tuple[Sequence[str], Sequence[str]]]  # model -> required, optional


@dataclass(frozen=True)
class FrameContext:
    header: frames.ExrHeader
    stated: NoiseLevel | None  # the spp the session's options or the header state (else None)
    renderer: str | None  # who wrote the frame, where its header says (OIDN's row order)
    sources: dict[str, frames.Source]  # buffer -> where it is in the file
    decoded: frames.DecodedFrame | None = None  # the pixels, once decoded
    decode_ms: float = 0.0  # what decoding them took
    unusable: tuple[str, ...] = ()  # named buffers that hold nothing (known once decoded)

    @property
    def present(self) -> list[str]:
        """The buffers the frame carries, in the pixels and not just named; an all-zero motion
        counts as present: it is no evidence either way (a locked-off camera, motion blur, a
        first frame), and the chosen model's history follows the aux's evidence frame by frame
        (runtime/motion_evidence.py)."""
        return [b for b in self.sources
                if b not in SIDE_BUFFERS and (b not in self.unusable or b == "motion")]

    def decode(self, body: bytes | bytearray) -> FrameContext:
        """With its pixels (worker pool): every buffer of `sources`; those that hold nothing
        usable are named (runtime.usable_buffers; decode leaves an all-zero motion out)."""
        start = time.perf_counter()
        decoded = frames.decode(body, self.sources)
        dropped = [b for b in self.sources if b not in decoded.buffers]
        return replace(self, decoded=decoded, decode_ms=1e3 * (time.perf_counter() - start),
                       unusable=(*dropped, *unusable_buffers(decoded.buffers)))

    def for_model(self, info: ModelInfo, installed: Installed | None) -> FrameContext:
        """Narrowed to what `info`'s model reads (MissingChannels for an absent required buffer,
        naming the installed models that would take the frame); the other decoded buffers are let
        go before the model runs."""
        sources = frames.for_model(self.sources, self.header.channels, info.required_buffers,
                                   info.optional_buffers, info.name, installed)
        sources |= {b: s for b, s in self.sources.items() if b in SIDE_BUFFERS}  # look-ahead
        decoded = self.decoded
        if decoded is not None:
            decoded = replace(decoded, buffers={b: plane for b, plane in decoded.buffers.items()
                                                if b in sources})
        return replace(self, sources=sources, decoded=decoded)


def frame_context(header: frames.ExrHeader, spec: SessionSpec, info: ModelInfo | None,
                  installed: Installed | None) -> FrameContext:
    """A frame's context from its header alone (no pixel decoded). `info`: the session's model;
    None (model=auto): every canonical buffer the file has, colour required. A look-ahead
    session also reads the frame's motion to the next frame (FORWARD), where it has one.
    MissingChannels where a required buffer is absent."""
    if info is None:
        required, optional = ("color",), tuple(b for b in BUFFER_NAMES if b != "color")
    else:
        required, optional = info.required_buffers, info.optional_buffers
    if spec.lookahead:
        optional = (*optional, FORWARD)
    sources = frames.resolve(
        header.channels,
        required,
        optional,
        spec.channels,
        spec.motion_scale,
        model=info.name if info else AUTO,
        layer=spec.layer,
        installed=installed,
    )
    attributes = header.attributes
    return FrameContext(
        header,
        stated_samples(attributes, spec.layer, spec.model_options),
        renderer_from_header(attributes),
        sources,
    )
