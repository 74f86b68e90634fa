"""The oidn-temporal tiers' time split at 720p: OIDN's share and the temporal stage's share.

`measure(model, threads, repeats)` runs one model through the shipped runtime (`Denoiser`,
prepass + onnxruntime + custom ops) on one 1280×720 frame with history carried: `oidn` times
the prepass alone (Denoiser.prepass), `stage` the exported temporal graph alone on OIDN's
output (session.run), `total` the whole `Denoiser.denoise` (sanitising, both, copies).
quietframe-eval and the model cards report the split from it; the sweep over untrained
variants and kernel sizes that set the tier's shape is experiments/oidn_temporal_speed.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from quietframe.bench.synthetic import frame_buffers
from quietframe.bench.timing import Timing, time_ms
from quietframe.runtime import Denoiser
from quietframe.runtime.oidn_prepass import PREPASS_BUFFERS


def measure(path: Path, threads: int, repeats: int,
            size: tuple[int, int] = (720, 1280)) -> dict[str, Timing]:
    """oidn / stage / total timings of one model on a (height, width) frame (720p), history
    carried; the stage is everything but OIDN (the graph, and a prepass's color_from model)."""
    runtime = Denoiser(path, threads=threads)
    planes = frame_buffers(*size)
    state = runtime.denoise(planes, None).state
    oidn = runtime.prepass({b: planes[b] for b in PREPASS_BUFFERS})
    feeds = {"oidn": oidn, **{b: planes[b][None] for b in ("albedo", "normal", "depth",
                                                           "motion")},
             "reset": np.zeros(1, np.float32),
             **{f"state_in.{k}": v for k, v in state.items()}, **runtime.option_feeds}
    feeds = {k: v for k, v in feeds.items() if k in runtime.input_names}
    first = runtime.color_stage  # a graph stage before OIDN: quietframe's time too
    first_feeds = {name: plane[None] for name, plane in planes.items()}
    _, height, width = planes["color"].shape

    def stage() -> None:
        if first is not None:
            first.run(first_feeds, state, height, width)  # reads its namespace of `state`
        runtime.session.run(None, feeds)

    return {
        "oidn": time_ms(lambda: runtime.prepass(planes), warmup=1, repeats=repeats),
        "stage": time_ms(stage, warmup=1, repeats=repeats),
        "total": time_ms(lambda: runtime.denoise(planes, state), warmup=1, repeats=repeats),
    }
