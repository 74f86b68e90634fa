"""What a frame costs outside the model on the service's path: EXR decode, the runtime's work
around session.run (sanitise, layout, output guard) and EXR encode, per frame size.

    python -m quietframe.experiments.frame_path [--sizes 1280x720,3840x2160] [--repeats 5]

Times are this thread's CPU time (time.thread_time), median of `repeats` after one warm-up:
everything measured runs on one thread (the model too, with 1 onnxruntime thread), so other
jobs on the machine do not inflate them; the model's own run is subtracted.
"""

from __future__ import annotations

import argparse
import io
import statistics
import time

import numpy as np

from quietframe.bench.synthetic import frame_buffers
from quietframe.runtime import Denoiser, find_model
from quietframe.service import frames


def farm_exr(planes: dict[str, np.ndarray]) -> bytes:
    """An uncompressed EXR as a farm sends it: half colour/albedo/normal, float depth and motion
    under plain names (uncompressed, so decode time is the layout work, not zlib)."""
    import OpenEXR

    layers = {"color": ("", "RGB"), "albedo": ("albedo.", "RGB"), "normal": ("N.", "XYZ"),
              "depth": ("", "Z"), "motion": ("motion.", "XY")}
    channels = {}
    for name, (prefix, components) in layers.items():
        dtype = np.float16 if name in ("color", "albedo", "normal") else np.float32
        for i, c in enumerate(components):
            channels[prefix + c] = planes[name][i].astype(dtype)
    out = io.BytesIO()
    OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION}, channels).write(out)
    return out.getvalue()


class _TimedSession:
    """The model's onnxruntime session, timing each run (thread CPU ms) to subtract it."""

    def __init__(self, session) -> None:
        self.session, self.ms = session, 0.0

    def run(self, *args, **kwargs):
        start = time.thread_time()
        outputs = self.session.run(*args, **kwargs)
        self.ms = 1e3 * (time.thread_time() - start)
        return outputs

    def __getattr__(self, name: str):
        return getattr(self.session, name)


def measure(denoiser: Denoiser, width: int, height: int, repeats: int) -> dict[str, float]:
    """Median thread-CPU ms of decode, the runtime outside session.run, and encode, over a
    sequence with the state carried (so allocations behave as in a session)."""
    body = farm_exr(frame_buffers(height, width))
    info = denoiser.info
    header = frames.read_header(body, 1 << 16, 1 << 16)
    sources = frames.resolve(header.channels, info.required_buffers, info.optional_buffers)
    timed = denoiser.session = _TimedSession(denoiser.session)
    rows, state = [], None
    for _ in range(repeats + 1):
        t0 = time.thread_time()
        decoded = frames.decode(body, sources)
        t1 = time.thread_time()
        result = denoiser.denoise(decoded.buffers, state)
        state = result.state
        t2 = time.thread_time()
        frames.encode(result.color, decoded.header, sources["color"].channels, "half", {}, "none")
        t3 = time.thread_time()
        rows.append((t1 - t0, t2 - t1 - timed.ms / 1e3, t3 - t2))
    decode, runtime, encode = (1e3 * statistics.median(c) for c in zip(*rows[1:], strict=True))
    return {"decode": decode, "runtime": runtime, "encode": encode,
            "total": decode + runtime + encode}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1280x720,3840x2160")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--model", default="accumulation")
    args = parser.parse_args(argv)
    denoiser = Denoiser(find_model(args.model), threads=1)
    print("| size | decode | runtime outside session.run | encode | total ms |")
    print("|---|---|---|---|---|")
    for size in args.sizes.split(","):
        width, height = (int(v) for v in size.split("x"))
        r = measure(denoiser, width, height, args.repeats)
        print(f"| {width}×{height} | {r['decode']:.1f} | {r['runtime']:.1f} | {r['encode']:.1f} | "
              f"{r['total']:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
