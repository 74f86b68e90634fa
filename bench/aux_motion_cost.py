"""What motion estimated from the aux costs beside the quality tier's frame, at 1080p, timed
interleaved in one run.

    python -m quietframe.bench.aux_motion_cost [--model oidn-history-cleanaux] [--rounds 3]
        [--size 1080p]

Each round times one frame of the model through the runtime's per-sequence step (its history
carried, OIDN's filters kept: a session's frame) and the estimate of that frame's motion from
its aux and depth and the previous frame's (runtime/aux_motion.estimate on the probes the gate
keeps: a fixed number of fitting steps, so its cost does not depend on the content), on
synthetic buffers of --size (1920×1080 by default; bench/synthetic.py). The figure is the
median over rounds of the estimate's time over the frame's in the same round (wall and CPU);
on a shared machine read the ratios, not the milliseconds.
"""

from __future__ import annotations

import argparse
import statistics

from quietframe.bench import cli_args
from quietframe.bench.synthetic import frame_buffers
from quietframe.bench.timing import interleaved_rounds
from quietframe.runtime import Denoiser, aux_motion, find_model
from quietframe.runtime.motion_evidence import probe
from quietframe.runtime.stream import Stream

SIZES = {"720p": (720, 1280), "1080p": (1080, 1920), "4k": (2160, 3840)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="quietframe-aux-motion-cost",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="oidn-history-cleanaux",
                        help="the quality tier (default oidn-history-cleanaux)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=2, help="timed calls per round")
    parser.add_argument("--size", choices=sorted(SIZES), default="1080p",
                        help="frame size (the cost target is at 1080p; at 720p and below the "
                             "fit also runs on the probe's finest level)")
    cli_args.add_threads(parser)
    args = parser.parse_args(argv)
    height, width = SIZES[args.size]
    previous, current = (frame_buffers(height, width, seed=s) for s in (0, 1))
    stream = Stream(Denoiser(find_model(args.model), threads=args.threads))
    state = stream.step(previous, None).state
    probes = probe(previous), probe(current)
    previous_depth = aux_motion.depth_probe(previous["depth"])  # its forward-backward check
    runs = {"frame": lambda: stream.step(current, state),
            "estimate": lambda: aux_motion.estimate(*probes, height, width, current["depth"],
                                                    previous_depth)}
    wall, cpu = interleaved_rounds(runs, args.rounds, args.repeats)
    share = [e / f for e, f in zip(wall["estimate"], wall["frame"], strict=True)]
    share_cpu = [e / f for e, f in zip(cpu["estimate"], cpu["frame"], strict=True)]
    print(f"\n{width}×{height}, {args.threads} threads, {args.rounds} interleaved rounds")
    print("| | median ms | median CPU ms |\n|---|---:|---:|")
    for name in runs:
        print(f"| {name} | {statistics.median(wall[name]):.0f} | "
              f"{statistics.median(cpu[name]):.0f} |")
    print(f"\nestimate / {args.model} frame: {statistics.median(share):.3f} wall "
          f"({min(share):.3f}–{max(share):.3f}), {statistics.median(share_cpu):.3f} CPU")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
