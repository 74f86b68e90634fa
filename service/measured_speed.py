"""How fast each model denoises on this replica, measured: the denoise stage's time of the last
frames (Server-Timing `denoise`) per model and frame size. A session's `choice` says the median
at its own size beside the tables' `expected_ms` (a 720p timing from the machine that made the
tables, scaled by pixels; often several times off on the machine that serves), so a farm plans
with what this server does. It informs; it does not change what `auto` chooses.

Bounded: the last FRAMES_PER_SIZE frames of each (model, height, width), at most MAX_SIZES keys,
the least recently measured let go first. In memory, per replica: a restart measures afresh."""

from __future__ import annotations

import statistics
import threading
from collections import OrderedDict, deque
from dataclasses import dataclass

FRAMES_PER_SIZE = 32  # enough for a stable median, short enough to follow a change of load
MAX_SIZES = 64  # (model, height, width) keys: a few models at a few sizes on a farm


@dataclass(frozen=True)
class Measured:
    """This server's median denoise time per frame of one model at one size, over `frames`."""

    ms: float
    frames: int
    width: int
    height: int


class MeasuredSpeeds:
    def __init__(self, frames_per_size: int = FRAMES_PER_SIZE,
                 max_sizes: int = MAX_SIZES) -> None:
        self.frames_per_size, self.max_sizes = frames_per_size, max_sizes
        self._times: OrderedDict[tuple[str, int, int], deque[float]] = OrderedDict()
        self._lock = threading.Lock()  # recorded on the event loop, read by any route

    def record(self, model: str, height: int, width: int, ms: float) -> None:
        key = (model, height, width)
        with self._lock:
            times = self._times.get(key)
            if times is None:
                times = self._times[key] = deque(maxlen=self.frames_per_size)
            times.append(ms)
            self._times.move_to_end(key)
            while len(self._times) > self.max_sizes:
                self._times.popitem(last=False)

    def at(self, model: str, height: int, width: int) -> Measured | None:
        """The median of the last frames of `model` at this size; None before the first."""
        with self._lock:
            times = list(self._times.get((model, height, width), ()))
        if not times:
            return None
        return Measured(round(statistics.median(times), 1), len(times), width, height)

    def __len__(self) -> int:
        return len(self._times)
