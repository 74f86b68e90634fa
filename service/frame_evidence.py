"""What a frame's EXR header says before any pixel is decoded: the renderer that wrote it and
the samples per pixel it states, and the spp a session states instead (`model_options.spp`)."""

from __future__ import annotations

import math
from collections.abc import Mapping

from quietframe.runtime.card import SAMPLES_INPUT
from quietframe.runtime.stream import chosen_samples
from quietframe.service.noise_estimate import NoiseLevel
from quietframe.wire.exr_layout import attribute_number

# Header attributes that state a frame's samples per pixel, by renderer. Only Cycles is known to
# write one (`cycles.<view layer>.samples`, a string, tests/fixtures/blender/README.md). Arnold,
# RenderMan and V-Ray write none we are confident of (V-Ray's `vrayInfo/*` carries no sample
# count): their frames use the estimate.
CYCLES_PREFIX, CYCLES_SUFFIX = "cycles.", ".samples"
# The renderers whose headers state the spp (`renderer_from_header` names them)
RENDERERS_STATING_SPP = ("cycles",)
# A NoiseLevel's source where the session set the spp (model_options)
SESSION_SAMPLES = f"model_options.{SAMPLES_INPUT}"


def samples_from_header(
    attributes: Mapping[str, tuple[str, bytes]], layer: str | None = None
) -> NoiseLevel | None:
    """The renderer's samples per pixel from EXR header attributes (kind, raw bytes), or None.
    With several view layers and none chosen, the fewest samples (the noisiest layer) count."""
    found: dict[str, float] = {}
    for name, (kind, value) in attributes.items():
        if name.startswith(CYCLES_PREFIX) and name.endswith(CYCLES_SUFFIX):
            view = name[len(CYCLES_PREFIX) : -len(CYCLES_SUFFIX)]
            number = attribute_number(name, kind, value)
            if number is not None and math.isfinite(number) and number >= 1:
                found[view] = number
    if layer is not None and layer in found:
        return NoiseLevel(found[layer], f"{CYCLES_PREFIX}{layer}{CYCLES_SUFFIX}")
    if not found:
        return None
    view = min(found, key=found.__getitem__)
    return NoiseLevel(found[view], f"{CYCLES_PREFIX}{view}{CYCLES_SUFFIX}")


def stated_samples(
    attributes: Mapping[str, tuple[str, bytes]], layer: str | None,
    model_options: Mapping[str, float | int],
) -> NoiseLevel | None:
    """The spp stated for a frame, or None (estimate it): the session's `model_options.spp`
    where set, else the renderer's header, by the rule the model's input follows
    (runtime/stream.chosen_samples), so the choice plans for the spp the chosen model is
    given."""
    header = samples_from_header(attributes, layer)
    chosen = chosen_samples(model_options, header.spp if header is not None else None)
    if chosen is None:
        return None
    spp, source = chosen
    return NoiseLevel(spp, SESSION_SAMPLES if source == "session" else header.source)


def renderer_from_header(attributes: Mapping[str, tuple[str, bytes]]) -> str | None:
    """Which renderer wrote a frame, where its header says so: Cycles writes
    `cycles.<view layer>.samples` (tests/fixtures/blender/README.md). None: unknown, and
    `auto` uses the default renderer's tables (runtime/card.py ModelCard.measured)."""
    if any(n.startswith(CYCLES_PREFIX) and n.endswith(CYCLES_SUFFIX) for n in attributes):
        return "cycles"
    return None
