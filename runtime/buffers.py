"""The canonical frame buffers: the one definition of their names, channel counts, what an absent
one becomes, and which sanitising rule each gets (the rules themselves: `sanitize.py`).

Torch-free and serving-free: the service, the runtime, the exporter, training, evaluation and the
benchmarks all read the buffer vocabulary from here. Buffers travel as planar float32 arrays
(C, H, W), the layout of both EXR channels and the NCHW graph inputs.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import Enum

import numpy as np


class Rule(str, Enum):
    """How bad input values of a buffer are replaced (sanitize.py implements each)."""

    RADIANCE = "radiance"  # NaN/±Inf/negative -> 0; above 65504 (half max) -> 65504
    DIRECTION = "direction"  # NaN/±Inf -> 0 (no orientation / no motion)
    DISTANCE = "distance"  # NaN/±Inf/negative -> the farthest finite depth of the frame


@dataclass(frozen=True)
class Buffer:
    name: str
    channels: int
    rule: Rule
    absent: str  # what the runtime feeds when an optional buffer is missing (always zeros)


BUFFERS: dict[str, Buffer] = {
    b.name: b
    for b in (
        Buffer("color", 3, Rule.RADIANCE, "zeros"),
        Buffer("albedo", 3, Rule.RADIANCE, "zeros"),
        Buffer("normal", 3, Rule.DIRECTION, "zeros (no orientation)"),
        Buffer("depth", 1, Rule.DISTANCE, "zeros"),
        Buffer("motion", 2, Rule.DIRECTION, "zeros (a static camera)"),
    )
}
BUFFER_NAMES: tuple[str, ...] = tuple(BUFFERS)
# Read beside a model's buffers for the runtime itself, never given to a model: `forward`, the
# motion to the next frame (XY in pixels, x right and y down: frame t + 1 shows p's surface at
# p + forward), for a look-ahead session (runtime/lookahead.py). Absent: left out, not zeros.
FORWARD = "forward"
SIDE_BUFFERS: dict[str, Buffer] = {
    FORWARD: Buffer(FORWARD, 2, Rule.DIRECTION, "left out (no look-ahead along it)"),
}
BUFFER_CHANNELS: dict[str, int] = {name: b.channels
                                   for name, b in (BUFFERS | SIDE_BUFFERS).items()}


class BufferError(ValueError):
    """A frame's buffers do not fit the model: wrong shape, mismatched sizes, unknown name."""


class MissingBuffers(BufferError):
    """Required buffers are absent: the one check, for the service and every other caller."""

    def __init__(self, model: str, missing: list[str], present: list[str], optional: list[str]):
        self.model, self.missing, self.present, self.optional = model, missing, present, optional
        super().__init__(
            f"missing required buffers {missing}; model {model} needs them, the frame has "
            f"{present} (optional: {optional})"
        )


def check_buffers(
    model: str, required: Iterable[str], optional: Iterable[str], present: Iterable[str]
) -> tuple[str, ...]:
    """The optional buffers that are absent (fed as zeros); MissingBuffers if a required one is."""
    have = set(present)
    required, optional = list(required), list(optional)
    missing = [b for b in required if b not in have]
    if missing:
        raise MissingBuffers(model, missing, sorted(have), optional)
    return tuple(b for b in optional if b not in have)


def check_plane(name: str, plane: np.ndarray, height: int, width: int) -> None:
    """A buffer must be (C, H, W) with the buffer's channel count and the frame's size."""
    expected = (BUFFERS[name].channels, height, width)
    if np.shape(plane) != expected:
        raise BufferError(f"buffer {name!r} has shape {np.shape(plane)}; expected {expected}")


def planes_from_hwc(buffers: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """(H, W, C) or (H, W) images (datasets, OIDN-style callers) -> contiguous (C, H, W) planes
    holding each buffer's first `channels` channels."""
    planes = {}
    for name, image in buffers.items():
        image = np.asarray(image, np.float32)
        if image.ndim == 2:
            image = image[:, :, None]
        count = BUFFERS[name].channels if name in BUFFERS else image.shape[2]
        planes[name] = np.ascontiguousarray(image[:, :, :count].transpose(2, 0, 1))
    return planes
