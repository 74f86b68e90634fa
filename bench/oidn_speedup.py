"""Speed of model files against per-frame OIDN-high at 1280×720, timed interleaved in one run.

    python -m quietframe.bench.oidn_speedup models/nbg-2l-3g.onnx /tmp/candidate.onnx \
        [--rounds 5] [--threads 2]

Each round times plain OIDN-high (pyoidn's RT filter on colour, albedo and normal, quality high,
its filter committed once and kept, as an application that calls OIDN itself runs it), then
OIDN-high through quietframe (`models/oidn-frame.onnx`, the baseline the cards' "× faster than
OIDN-high" reads), then every model (bench/timing.py, median of `--repeats` calls), each model
through the runtime's per-sequence step (runtime/stream.py: state carried, OIDN filters kept,
as the service runs a session), so all of them see the same load. The figures per model are
medians over rounds of its time over the baseline's and over plain OIDN's in that round. On a
shared machine read the ratios, not the milliseconds. `--json PATH` also writes each row's
median time over plain OIDN-high's (keys: `oidn-high`, `oidn-fast` for plain OIDN at fast
quality, timed in each round too, and the model files' stems), what bench/learned_report.py's
speed-versus-error plot reads.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.synthetic import frame_buffers
from quietframe.bench.timing import time_ms
from quietframe.runtime import Denoiser
from quietframe.runtime.stream import Stream

BASELINE = Path(__file__).resolve().parents[1] / "models" / "oidn-frame.onnx"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="quietframe-oidn-speedup",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("models", type=Path, nargs="+")
    parser.add_argument("--baseline", type=Path, default=BASELINE,
                        help="the OIDN-high model file (default models/oidn-frame.onnx)")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per model and round")
    parser.add_argument("--json", type=Path, help="write each row's time / plain OIDN-high here")
    cli_args.add_threads(parser)
    args = parser.parse_args(argv)
    buffers = frame_buffers()
    paths = [args.baseline, *args.models]
    runners = [plain_oidn(buffers, args.threads)]
    for path in paths:
        stream = Stream(Denoiser(path, threads=args.threads))
        state = stream.step(buffers, None).state  # a history, as in a running sequence
        runners.append(lambda s=stream, st=state: s.step(buffers, st))
    runners.append(plain_oidn(buffers, args.threads, quality="fast"))
    names = ["plain OIDN-high", *(p.name for p in paths), "plain OIDN-fast"]
    ms: list[list[float]] = [[] for _ in runners]
    for r in range(args.rounds):
        for i, run in enumerate(runners):
            ms[i].append(time_ms(run, warmup=1, repeats=args.repeats).median_ms)
        print(f"round {r + 1}: " + ", ".join(f"{n} {t[-1]:.0f} ms"
                                             for n, t in zip(names, ms, strict=True)), flush=True)
    print(f"\n1280×720, {args.threads} threads, {args.rounds} interleaved rounds (medians over "
          "rounds of the ratio in the same round; min–max in brackets)")
    print("| model | median ms | × faster than OIDN-high through quietframe | "
          "time / plain OIDN-high |\n|---|---:|---:|---:|")
    for i, (name, times) in enumerate(zip(names, ms, strict=True)):
        faster = [base / t for base, t in zip(ms[1], times, strict=True)]
        over_plain = [t / plain for plain, t in zip(ms[0], times, strict=True)]
        label = f"{name} (baseline)" if i == 1 else name
        print(f"| {label} | {statistics.median(times):.0f} | {_spread(faster)} | "
              f"{_spread(over_plain)} |")
    if args.json:
        keys = ["oidn-high", *(p.stem for p in paths), "oidn-fast"]
        args.json.write_text(json.dumps({
            key: round(statistics.median(t / plain for plain, t in zip(ms[0], times,
                                                                        strict=True)), 4)
            for key, times in zip(keys, ms, strict=True)}, indent=1))
    return 0


def _spread(ratios: list[float]) -> str:
    return f"{statistics.median(ratios):.2f} ({min(ratios):.2f}–{max(ratios):.2f})"


def plain_oidn(buffers: dict[str, np.ndarray], threads: int, quality: str = "high"):
    """A call of pyoidn's RT filter (HDR, albedo and normal; quality high or fast), committed
    once."""
    import pyoidn as oidn

    device = oidn.Device(oidn.OIDN_DEVICE_TYPE_CPU)
    device.set_int("numThreads", threads)
    device.commit()
    images = {name: np.ascontiguousarray(buffers[name].transpose(1, 2, 0))
              for name in ("color", "albedo", "normal")}
    images["output"] = np.zeros_like(images["color"])
    flt = oidn.Filter(device, oidn.OIDN_FILTER_TYPE_RT)
    for name, image in images.items():
        flt.set_image(name, image, oidn.OIDN_FORMAT_FLOAT3)
    flt.set_quality({"high": oidn.OIDN_QUALITY_HIGH, "fast": oidn.OIDN_QUALITY_FAST}[quality])
    flt.set_bool("hdr", True)
    flt.commit()
    # the arrays and device live as long as the closure (pyoidn binds memory without a ref)
    return lambda keep=(device, images): flt.execute()


if __name__ == "__main__":
    raise SystemExit(main())
