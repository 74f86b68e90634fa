"""The one evaluation harness: every method takes a frame's planes and returns its denoised
planes, and one loop scores a sequence. quietframe-eval (evaluate.py), auto_choice.py and
the experiments that score methods (experiments/oidn_accumulated.py, trmae_floor.py) all run
their methods through `score_sequence`.

A method is the runtime's layout end to end: `reset()` (a new sequence or a camera cut) and
`__call__(planes) -> (3, H, W)`, planes as the runtime takes them ((C, H, W) float32 by
canonical name). Baselines written for (H, W, C) images (SVGF, OIDN) are wrapped by
`ImageMethod`. Frames are `(planes, reference, reset)` (`planar_frames` converts a loader's
(H, W, C) buffers once per sequence); references and the scored outputs are (H, W, 3), the
layout model/metrics computes in, so every figure is the one the metrics have always given.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from quietframe.model import metrics
from quietframe.runtime import Denoiser
from quietframe.runtime.buffers import BUFFER_CHANNELS, FORWARD, planes_from_hwc
from quietframe.runtime.stream import Step, Stream
from quietframe.service.noise_estimate import load_calibration, shot_samples

# The shipped noise fit, read once per process (not at every shot's reset); read-only
_calibration = functools.cache(load_calibration)

Planes = dict[str, np.ndarray]  # canonical name -> (C, H, W) float32
Frames = list[tuple[Planes, np.ndarray, bool]]  # (planes, reference (H, W, 3), reset)
VECTORS = ("motion", FORWARD)  # what a renderer with motion blur on writes none of
FRAME_METRICS: dict[str, Callable[[np.ndarray, np.ndarray], float]] = {
    "psnr": metrics.psnr, "ssim": metrics.ssim, "smape": metrics.smape, "relmse": metrics.relmse,
}


class Method(Protocol):
    def reset(self) -> None: ...

    def __call__(self, planes: Planes) -> np.ndarray: ...  # (3, H, W)


def planar_frames(frames: Iterable[tuple[Mapping[str, np.ndarray], np.ndarray, bool]]) -> Frames:
    """A loader's (H, W, C) frames as the harness takes them (one conversion per sequence)."""
    return [(planes_from_hwc(buffers), reference, reset) for buffers, reference, reset in frames]


class RuntimeMethod:
    """A shipped model through the runtime's per-sequence step (runtime/stream.py), as the
    service runs it: keeps the state between frames, unless `single_frame` (every frame starts
    from an empty history, as after a cut). `options`: the model's run-time inputs
    (kernel_size); `zeros_for_required`: absent required buffers are fed as zeros (what the
    model would see without them: the absence table). `header_spp`: the spp the frame header
    states (set by the evaluation where the renderer writes one). `renderer`: the frames'
    renderer, as the service takes it from the header (an OIDN stage's row order follows it).
    `camera`, `motion`: the session's (`auto` or `locked`; `estimated` or `rendered-only`).
    `withhold_vectors`: the frames' motion vectors are not given (as a renderer with motion blur
    on writes none), so a moving frame follows motion estimated from the aux. A model reading
    the spp with none stated (no header spp, no option) gets the shot's estimate, made at its
    first frame (after each reset), as a session naming the model does
    (service/shot_choice.estimate_for_shot); `shot_spp` holds it."""

    def __init__(self, path: Path | Denoiser, threads: int = 2, options: dict | None = None,
                 single_frame: bool = False, zeros_for_required: bool = False,
                 renderer: str | None = None, camera: str = "auto",
                 motion: str = "estimated", withhold_vectors: bool = False) -> None:
        self.denoiser = path if isinstance(path, Denoiser) else Denoiser(
            path, threads=threads, options=options)
        self.stream = Stream(self.denoiser, camera=camera, options=options, renderer=renderer,
                             motion=motion)
        self.single_frame, self.zeros_for_required = single_frame, zeros_for_required
        self.withhold_vectors = withhold_vectors  # the frames' motion is not given (estimated)
        self.state: dict | None = None
        self.header_spp: float | None = None
        self.shot_spp: float | None = None
        self.dropped = 0  # frames whose history was not used: moved without motion vectors
        self.estimated = 0  # frames that followed motion estimated from the aux
        self.last_step: Step | None = None  # the last frame's (a look-ahead reads it)

    def reset(self) -> None:
        self.state = self.shot_spp = None

    def __call__(self, planes: Planes) -> np.ndarray:
        if self.single_frame:
            self.state = None
        if self.zeros_for_required:
            _, h, w = planes["color"].shape
            planes = {**planes, **{name: np.zeros((BUFFER_CHANNELS[name], h, w), np.float32)
                                   for name in self.denoiser.info.required_buffers
                                   if name not in planes}}
        if self.withhold_vectors:
            planes = {name: plane for name, plane in planes.items() if name not in VECTORS}
        if self.shot_spp is None and self.stream.wants_estimate(self.header_spp):
            self.shot_spp = shot_samples(planes["color"], planes.get("albedo"), _calibration())
        step = self.stream.step(planes, self.state, self.header_spp, self.shot_spp)
        self.last_step = step
        self.dropped += step.gate is not None and step.gate.dropped
        self.estimated += step.estimated is not None
        self.state = step.state
        return step.color


class ImageMethod:
    """A method written for (H, W, C) images (bench/baselines.py) as a planar one; `fill`
    gives the buffers it requires but the frame lacks (name -> (H, W, C) image from the
    colour)."""

    def __init__(self, method,
                 fill: Mapping[str, Callable[[np.ndarray], np.ndarray]] | None = None) -> None:
        self.method, self.fill = method, fill or {}

    def reset(self) -> None:
        self.method.reset()

    def __call__(self, planes: Planes) -> np.ndarray:
        images = {k: np.ascontiguousarray(v.transpose(1, 2, 0)) for k, v in planes.items()}
        for name, make in self.fill.items():
            images.setdefault(name, make(images["color"]))
        return np.asarray(self.method(images), np.float32).transpose(2, 0, 1)


@dataclass
class SequenceScore:
    """One method on one sequence: per-frame metrics, outputs (H, W, 3) and ms per frame;
    TRMAE over the sequence (NaN with one frame), flicker where it was asked for."""

    per_frame: dict[str, list[float]] = field(default_factory=dict)
    outputs: list[np.ndarray] = field(default_factory=list)
    ms: list[float] = field(default_factory=list)
    trmae: float = float("nan")
    flicker: float | None = None

    def mean(self, name: str) -> float:
        return float(np.mean(self.per_frame[name]))


def score_sequence(method: Method, frames: Frames, frame_metrics: Sequence[str] = ("psnr",),
                   locked_off: bool = False,
                   inputs: Callable[[Planes], Planes] | None = None) -> SequenceScore:
    """The one scoring loop: `method` from the sequence's first frame (state reset there and
    at every cut), each frame timed and scored against its reference; `locked_off` (a static
    shot) also scores flicker; `inputs` chooses what the method is given of each frame."""
    score = SequenceScore({name: [] for name in frame_metrics})
    method.reset()
    for planes, reference, reset in frames:
        if reset:
            method.reset()
        given = inputs(planes) if inputs is not None else planes
        start = time.perf_counter()
        pred = np.asarray(method(given), np.float32).transpose(1, 2, 0)  # (H, W, 3)
        score.ms.append(1e3 * (time.perf_counter() - start))
        for name in frame_metrics:
            score.per_frame[name].append(FRAME_METRICS[name](pred, reference))
        score.outputs.append(pred)
    if len(score.outputs) > 1:
        refs = np.stack([reference for _, reference, _ in frames])
        score.trmae = metrics.trmae(np.stack(score.outputs), refs)
        if locked_off:
            score.flicker = metrics.flicker(np.stack(score.outputs))
    return score
