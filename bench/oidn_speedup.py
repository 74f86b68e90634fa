"""Speed-up of model files over per-frame OIDN-high at 1280×720, timed interleaved in one run.

    python -m quietframe.bench.oidn_speedup models/nbg-2l-3g.onnx /tmp/candidate.onnx \
        [--rounds 5] [--threads 2]

Each round times OIDN-high (`models/oidn-frame.onnx`, the baseline the cards' "× faster than
OIDN-high" reads) and then every model (bench/timing.py, median of `--repeats` calls, state
carried as in a sequence), so all of them see the same load; the figure per model is the median
over rounds of its time over OIDN-high's in that round. On a shared machine read the ratios, not
the milliseconds.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from quietframe.bench import cli_args
from quietframe.bench.synthetic import frame_buffers
from quietframe.bench.timing import time_ms
from quietframe.runtime import Denoiser

BASELINE = Path(__file__).resolve().parents[1] / "models" / "oidn-frame.onnx"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="quietframe-oidn-speedup",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("models", type=Path, nargs="+")
    parser.add_argument("--baseline", type=Path, default=BASELINE,
                        help="the OIDN-high model file (default models/oidn-frame.onnx)")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per model and round")
    cli_args.add_threads(parser)
    args = parser.parse_args(argv)
    buffers = frame_buffers()
    paths = [args.baseline, *args.models]
    runners = []
    for path in paths:
        denoiser = Denoiser(path, threads=args.threads)
        state = denoiser.denoise(buffers, None).state  # a history, as in a running sequence
        runners.append(lambda d=denoiser, s=state: d.denoise(buffers, s))
    ms: list[list[float]] = [[] for _ in paths]
    for r in range(args.rounds):
        for i, run in enumerate(runners):
            ms[i].append(time_ms(run, warmup=1, repeats=args.repeats).median_ms)
        print(f"round {r + 1}: " + ", ".join(f"{p.name} {t[-1]:.0f} ms"
                                             for p, t in zip(paths, ms, strict=True)), flush=True)
    print(f"\n1280×720, {args.threads} threads, {args.rounds} interleaved rounds "
          f"(median over rounds of OIDN-high ms / model ms in the same round)")
    print("| model | median ms | × faster than OIDN-high (min–max over rounds) |\n|---|---:|---:|")
    print(f"| {args.baseline} (OIDN-high) | {statistics.median(ms[0]):.0f} | 1.00 |")
    for path, times in zip(args.models, ms[1:], strict=True):
        ratios = [base / t for base, t in zip(ms[0], times, strict=True)]
        print(f"| {path} | {statistics.median(times):.0f} | {statistics.median(ratios):.2f} "
              f"({min(ratios):.2f}–{max(ratios):.2f}) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
