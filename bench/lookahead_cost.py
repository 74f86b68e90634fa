"""What a look-ahead of k frames costs beside the quality tier's frame, timed interleaved in one
run (runtime/lookahead.py; docs/service.md, "Look-ahead").

    python -m quietframe.bench.lookahead_cost [--model oidn-history-cleanaux] [--k 1,2,4]
        [--size 720p] [--rounds 3]

Each round times one frame of the model through the runtime's per-sequence step (its history
carried, OIDN's filters kept: a session's frame), then per k the look-ahead's own work for one
frame: its push (the previous frame's forward motion inverted from this frame's backward
motion, as where the renderer writes none; `push` alone where it does) and the pop of a frame
with k later frames pending (every hop carried, checked and fetched, whatever is trusted: the
work does not depend on the content). Synthetic buffers of --size (bench/synthetic.py) moving
1.2 px a frame. The figure is the median over rounds of the look-ahead's time over the frame's
in the same round (wall and CPU); on a shared machine read the ratios, not the milliseconds.
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.synthetic import frame_buffers
from quietframe.bench.timing import interleaved_rounds
from quietframe.runtime import Denoiser, find_model
from quietframe.runtime.buffers import FORWARD
from quietframe.runtime.lookahead import frame_pieces, pop, push
from quietframe.runtime.stream import Stream

SIZES = {"720p": (720, 1280), "1080p": (1080, 1920)}


def pieces_of(stream: Stream, count: int, height: int, width: int) -> list[dict]:
    """`count` consecutive frames' window pieces from real causal steps (a history run)."""
    out, state = [], None
    architecture = stream.info.card.architecture
    for t in range(count):
        planes = frame_buffers(height, width, seed=t)
        planes["motion"] = np.full((2, height, width), -1.2, np.float32)
        planes[FORWARD] = np.full((2, height, width), 1.2, np.float32)
        step = stream.step(planes, state, 4.0)
        state = step.state
        out.append(frame_pieces(step, planes, architecture))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="quietframe-lookahead-cost",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--model", default="oidn-history-cleanaux",
                        help="the quality tier (default oidn-history-cleanaux)")
    parser.add_argument("--k", type=cli_args.spp_levels, default="1,2,4",
                        help="look-ahead depths (comma list)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=2, help="timed calls per round")
    parser.add_argument("--size", choices=sorted(SIZES), default="720p")
    cli_args.add_threads(parser)
    args = parser.parse_args(argv)
    height, width = SIZES[args.size]
    ks = sorted(args.k)
    stream = Stream(Denoiser(find_model(args.model), threads=args.threads))
    frames = pieces_of(stream, max(ks) + 2, height, width)
    planes = frame_buffers(height, width, seed=99)
    planes["motion"] = np.full((2, height, width), -1.2, np.float32)
    state = stream.step(planes, stream.step(planes, None, 4.0).state, 4.0).state
    windows = {}
    for k in ks:  # k later frames pending behind the one that leaves
        window: dict = {}
        for t, pieces in enumerate(frames[:k + 1]):
            window = push(window, pieces, t, t == 0)
        windows[k] = window
    last = {name: p for name, p in frames[-1].items() if name != FORWARD}
    before: dict = {}
    for t, pieces in enumerate(frames[:2]):
        before = push(before, {n: p for n, p in pieces.items() if n != FORWARD}, t, t == 0)
    runs = {"frame": lambda: stream.step(planes, state, 4.0),
            "push (inverted forward)": lambda: push(before, last, 2, False),
            "push (rendered forward)": lambda: push(windows[1], frames[2], 2, False)}
    runs |= {f"pop, k = {k}": lambda k=k: pop(windows[k]) for k in ks}
    wall, cpu = interleaved_rounds(runs, args.rounds, args.repeats)
    print(f"\n{width}×{height}, {args.model}, {args.threads} threads, {args.rounds} interleaved "
          "rounds; per frame: a push, and the pop of a frame with k later frames")
    print("| | median ms | median CPU ms | ÷ the frame (wall) | ÷ the frame (CPU) |")
    print("|---|---:|---:|---:|---:|")
    for name in runs:
        share = [a / f for a, f in zip(wall[name], wall["frame"], strict=True)]
        share_cpu = [a / f for a, f in zip(cpu[name], cpu["frame"], strict=True)]
        print(f"| {name} | {statistics.median(wall[name]):.0f} | "
              f"{statistics.median(cpu[name]):.0f} | {statistics.median(share):.3f} | "
              f"{statistics.median(share_cpu):.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
