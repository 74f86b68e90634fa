"""One camera sequence through one model: the frame's step, the one the service and the
evaluation both run, so a reported figure is a figure of the shipped path.

A `Stream` owns what lives as long as a shot on one model: the run-time options it is given and
which spp wins (`samples_for`), the motion-evidence gate and its probe (motion_evidence.py: a
history is read only where the motion is evidence), the history's per-pixel trust (inside the
model's graphs) and the OIDN filters, kept between frames (oidn_prepass.OIDNFilters). The caller
keeps the state between frames: the service stores it per session (on disk or in Redis, so a
replica can take the session over), the evaluation in memory; `step` takes the previous state
and returns the next. A stream's frames run one at a time (the service's session lock), on any
thread.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from quietframe.runtime import aux_motion
from quietframe.runtime.aux_motion import EstimatedMotion
from quietframe.runtime.card import SAMPLES_INPUT
from quietframe.runtime.denoiser import Denoiser, ModelInfo
from quietframe.runtime.motion_evidence import (
    DEPTH_STATE,
    PROBE_STATE,
    STREAM_STATES,
    HistoryGate,
    gate_history,
    judge_cut,
    keep_probe,
)

MOTIONS = ("estimated", "rendered-only")  # a session's `motion`


def chosen_samples(options: Mapping[str, float | int], stated: float | None,
                   estimate: float | None = None) -> tuple[float, str] | None:
    """The one rule for a frame's spp as a model is given it, with where it came from: the
    session's `spp` option (`session`), else the count the renderer's header states
    (`header`), else the estimate of the shot's noise (`estimate`), else None (the
    model's default). At least 1."""
    for source, value in zip(("session", "header", "estimate"),
                             (options.get(SAMPLES_INPUT), stated, estimate), strict=True):
        if value is not None and math.isfinite(float(value)):
            return max(1.0, float(value)), source
    return None


def samples_for(options: Mapping[str, float | int], stated: float | None,
                estimate: float | None = None) -> float | None:
    """chosen_samples' spp."""
    chosen = chosen_samples(options, stated, estimate)
    return None if chosen is None else chosen[0]


def options_for(info: ModelInfo, options: Mapping[str, float | int],
                samples: float | None = None) -> dict[str, float | int]:
    """The options `info`'s model takes: those of `options` it declares (model=auto switches
    between models, and one without an option ignores it), and `samples` (samples_for) for a
    model that takes the frame's spp (SAMPLES_INPUT) where `options` do not set it."""
    names = {spec.name for spec in info.inputs}
    chosen = {name: value for name, value in options.items() if name in names}
    if SAMPLES_INPUT in names and SAMPLES_INPUT not in chosen and samples is not None:
        chosen[SAMPLES_INPUT] = samples
    return chosen


@dataclass(frozen=True)
class Step:
    """One frame through a stream. `gate`: a temporal model's reading of the aux (None for a
    model without history): `gate.dropped` says the history existed and was not used, and
    `gate.evidence` why (a cut the aux show, or a move without motion vectors)."""

    color: np.ndarray  # (3, H, W) float32, finite
    state: dict[str, np.ndarray]  # to give the next step (the gate's probe with the model's)
    sanitized: dict[str, int] = field(default_factory=dict)  # buffer -> values replaced
    missing: tuple[str, ...] = ()  # optional buffers the frame lacked
    gate: HistoryGate | None = None
    estimated: EstimatedMotion | None = None  # motion estimated from the aux, where it was
    # What a look-ahead reads of the frame (runtime/lookahead.py): the last OIDN stage's output
    # D (None without one), the backward motion the model was given (None: zero motion), and
    # the spp it was given (None: the model's default or no spp input).
    oidn: np.ndarray | None = None
    motion: np.ndarray | None = None
    spp: float | None = None

    @property
    def history_used(self) -> bool:
        """Whether the frame continued a history (else it starts a new run: first frame, cut,
        gap, a dropped history, a model without one)."""
        return self.gate is not None and self.gate.state is not None

    @property
    def history_verdict(self) -> str | None:
        """`cut` or `moving` where the gate dropped an existing history, else None."""
        if self.gate is None or not self.gate.dropped or self.gate.evidence is None:
            return None
        return self.gate.evidence.verdict


class Stream:
    """A camera sequence on `denoiser`'s model. `camera`: the session's (`auto`: judged frame
    by frame; `locked`: zero motion trusted, motion_evidence.gate_history); `options`: the
    session's run-time options (those the model declares are given); `renderer`: the frames'
    (an OIDN stage gives OIDN the rows in its order)."""

    def __init__(self, denoiser: Denoiser, camera: str = "auto",
                 options: Mapping[str, float | int] | None = None,
                 renderer: str | None = None, motion: str = "estimated") -> None:
        if motion not in MOTIONS:
            raise ValueError(f"motion must be one of {MOTIONS}, got {motion!r}")
        self.denoiser, self.camera, self.motion = denoiser, camera, motion
        self.options = dict(options or {})
        self.renderer = renderer
        prepass = denoiser.prepass
        self.oidn = prepass.filters() if prepass is not None else None

    @property
    def info(self) -> ModelInfo:
        return self.denoiser.info

    def wants_estimate(self, stated_spp: float | None) -> bool:
        """Whether the model would run at its default spp without an estimate: it reads the
        frame's spp (SAMPLES_INPUT) and neither the session's options nor the header state one.
        Its session then estimates the shot's spp (service/shot_choice.estimate_for_shot)."""
        takes = any(spec.name == SAMPLES_INPUT for spec in self.denoiser.info.inputs)
        return takes and chosen_samples(self.options, stated_spp) is None

    def step(self, planes: Mapping[str, np.ndarray], state: Mapping[str, np.ndarray] | None,
             stated_spp: float | None = None, estimated_spp: float | None = None,
             renderer: str | None = None) -> Step:
        """Denoise one frame of (C, H, W) float32 planes from the previous step's `state`
        (None: a fresh history: first frame, a cut, a gap). `stated_spp`: the renderer's
        header's count; `estimated_spp`: the shot's estimate (auto's, or a named model's where
        `wants_estimate`; samples_for);
        `renderer`: this frame's, where it differs from the stream's."""
        info = self.denoiser.info
        options = options_for(info, self.options,
                              samples_for(self.options, stated_spp, estimated_spp))
        gate = gate_history(planes, state, self.camera) if info.state_specs else None
        estimated = depth = None
        if gate is not None and self._estimates(gate, state):
            assert state is not None
            # A moving frame without vectors: follow the motion the aux show where it is
            # trusted, the per-frame stage elsewhere (aux_motion), instead of a fresh history.
            h, w = planes["color"].shape[-2:]
            estimated = aux_motion.estimate(state[PROBE_STATE], gate.probe, h, w,
                                            planes.get("depth"), state.get(DEPTH_STATE))
            depth = estimated.depth if estimated is not None else None
            # A camera switch moves "everything": the aux along the estimate show it as a cut.
            # Without a depth there is no estimate: a fresh history, as with rendered-only.
            cut = (judge_cut(state[PROBE_STATE], gate.probe, estimated.estimate)
                   if estimated is not None else None)
            if cut is not None:
                gate, estimated = HistoryGate(None, gate.probe, cut, True), None
            elif estimated is not None:
                planes = {**planes, "motion": estimated.motion}
                history = {k: v for k, v in state.items() if k not in STREAM_STATES}
                gate = HistoryGate(history, gate.probe, gate.evidence, False)
        elif gate is not None and self._may_estimate_next(gate):
            depth = aux_motion.depth_probe(planes.get("depth"))
        result = self.denoiser.denoise(planes, gate.state if gate else state, options,
                                       renderer or self.renderer, oidn=self.oidn)
        new_state = keep_probe(result.state, gate.probe, depth) if gate else result.state
        spp = options.get(SAMPLES_INPUT)
        return Step(result.color, new_state, result.sanitized, tuple(result.missing), gate,
                    estimated, result.oidn, planes.get("motion"),
                    None if spp is None else float(spp))

    def _may_estimate_next(self, gate: HistoryGate) -> bool:
        """Whether the next frame may estimate motion against this one (a frame without
        vectors, on a session that allows estimates and whose camera is not locked off: a
        locked camera never estimates): keep this frame's depth for its check."""
        return (self.motion == "estimated" and self.camera != "locked"
                and gate.evidence is not None)

    def _estimates(self, gate: HistoryGate, state: Mapping[str, np.ndarray] | None) -> bool:
        """Whether motion is estimated for this frame: the gate dropped a history because the
        frame moved without vectors (not at a cut), and the session allows it."""
        return (self.motion == "estimated" and gate.dropped and gate.evidence is not None
                and gate.evidence.verdict == "moving" and state is not None
                and state.get(PROBE_STATE) is not None
                and state[PROBE_STATE].shape == gate.probe.shape)

    @property
    def kept_bytes(self) -> int:
        """What the stream holds between frames beside the state: its OIDN filters."""
        return self.oidn.kept_bytes if self.oidn is not None else 0

    def release(self) -> None:
        """Let go of what is kept between frames (rebuilt on the next frame): for a memory
        budget that needs the room. No frame of this stream may be running."""
        if self.oidn is not None:
            self.oidn.release()

    def close(self) -> None:
        if self.oidn is not None:
            self.oidn.close()
