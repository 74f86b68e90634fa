"""The run-time options a model is given for one frame: of a session's options, those the model
declares, and the frame's spp for a model that takes it. One rule for the service and the
evaluation, so that every figure is measured with the inputs the service gives."""

from __future__ import annotations

import math
from collections.abc import Mapping

from quietframe.runtime.card import SAMPLES_INPUT
from quietframe.runtime.denoiser import ModelInfo


def options_for(info: ModelInfo, options: Mapping[str, float | int],
                samples: float | None = None) -> dict[str, float | int]:
    """The options `info`'s model takes: those of `options` it declares (model=auto switches
    between models, and one without an option ignores it). A model that takes the frame's spp
    (SAMPLES_INPUT) gets `samples` (the header's count or auto's estimate, at least 1) unless
    `options` set it."""
    names = {spec.name for spec in info.inputs}
    chosen = {name: value for name, value in options.items() if name in names}
    if SAMPLES_INPUT in names and SAMPLES_INPUT not in chosen and samples is not None \
            and math.isfinite(samples):
        chosen[SAMPLES_INPUT] = max(1.0, float(samples))
    return chosen
