"""`<tier>/lookahead-<k>`: a shipped model with a look-ahead of k frames (runtime/lookahead.py)
as a session with `lookahead: k` runs it: every frame's causal step as today, pushed into the
window, and frame t popped once t + k is in (fewer at the end of the sequence, as the service's
finish), finished with the later frames of its history run. k = 0 is the model itself.

The harness scores frame t's output against frame t's reference at call t, so the later frames
ride with it: `look_ahead` (evaluate.run_sequence applies it, as for sid_temporal) gives each
frame the sequence and its place in it; call t runs the causal steps up to t + k that have not
run yet (each frame's once, in order; a frame flagged as a cut resets the history first) and
pops t. The per-frame time is a causal step plus a blend, as on the server.
"""

from __future__ import annotations

import numpy as np

from quietframe.bench.harness import Frames, Planes, RuntimeMethod
from quietframe.client.session_fields import MAX_LOOKAHEAD
from quietframe.runtime.buffers import FORWARD
from quietframe.runtime.lookahead import frame_pieces, pending, pop, push

SEQUENCE = "_lookahead_sequence"  # planes key: (the sequence's frames, this frame's index)
SUFFIX = "/lookahead-"  # <tier>/lookahead-<k>


class LookaheadMethod:
    reads_forward = True  # evaluate.run_sequence gives it the frames' forward motion

    def __init__(self, inner: RuntimeMethod, k: int) -> None:
        if not 0 <= k <= MAX_LOOKAHEAD:
            raise ValueError(f"look-ahead k must be 0..{MAX_LOOKAHEAD}, got {k}")
        self.inner, self.k = inner, k
        self.window: dict[str, np.ndarray] = {}
        self.pushed = 0  # frames of the sequence whose causal step has run
        self.blended = 0  # frames finished with at least one later frame
        self.trusted: list[float] = []  # per blended frame, the share of later pixels trusted

    @property
    def current(self) -> RuntimeMethod:
        """The causal method (zoo_eval reads its dropped / estimated counts)."""
        return self.inner

    @property
    def header_spp(self) -> float | None:
        return self.inner.header_spp

    @header_spp.setter
    def header_spp(self, spp: float | None) -> None:
        self.inner.header_spp = spp

    def look_ahead(self, frames: Frames) -> Frames:
        """Each frame with the whole sequence and its index beside its planes."""
        sequence = [(planes, reset) for planes, _, reset in frames]
        return [({**planes, SEQUENCE: (sequence, t)}, reference, reset)  # type: ignore[dict-item]
                for t, (planes, reference, reset) in enumerate(frames)]

    def reset(self) -> None:
        """Nothing: the cuts ride with the frames (`look_ahead`), which may run ahead of it."""

    def __call__(self, planes: Planes) -> np.ndarray:
        sequence, t = planes[SEQUENCE]  # type: ignore[misc]
        if t == 0:  # a new sequence
            self.window, self.pushed = {}, 0
        architecture = self.inner.denoiser.info.card.architecture
        while self.pushed <= min(t + self.k, len(sequence) - 1):
            given, reset = sequence[self.pushed]
            if reset:
                self.inner.reset()
            if self.inner.withhold_vectors:
                given = {name: plane for name, plane in given.items() if name != FORWARD}
            self.inner(given)
            step = self.inner.last_step
            assert step is not None
            self.window = push(self.window, frame_pieces(step, given, architecture),
                               self.pushed, not step.history_used)
            self.pushed += 1
        assert pending(self.window)[0] == t, (pending(self.window), t)
        done = pop(self.window)
        self.window = done.window
        if done.trusted is not None:
            self.blended += 1
            self.trusted.append(done.trusted)
        return done.color


def lookahead_methods(base: dict, names) -> dict:
    """Factories of the `<tier>/lookahead-<k>` names among `names` whose tier `base` has (a
    RuntimeMethod factory)."""
    methods = {}
    for name in names:
        tier, sep, k = name.rpartition(SUFFIX)
        if sep and tier in base and k.isdigit():
            methods[name] = lambda tier=tier, k=int(k): LookaheadMethod(base[tier](), k)
    return methods
