"""The fused blends' time alone: one-node graphs of ai.quietframe::NBGBlend / NBGBlendPass /
NBGBlendNoise (export/ops/nbg_fused.cc) at 1×3×720×1280, for one or more builds of the op
library side by side.

    python -m quietframe.bench.profile_blend_ops /tmp/libquietframe_ops.before.so \\
        build/ops/libquietframe_ops.so [--runs 20] [--threads 2]

Every run of every (library, op) pair is interleaved with the others, so a load that comes and
goes on a shared machine lands on all of them alike; each prints the median of its runs after a
warm-up. An op a library does not have (NBGBlendNoise before it existed) prints as n/a.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import onnxruntime as ort
from onnx import TensorProto, helper

from quietframe.bench import cli_args
from quietframe.runtime.ops_library import OPS_DOMAIN

IMAGES = ["safe_albedo", "sliced0", "sliced1", "sliced2"]
PASS_THROUGH = ["accumulated", "frame"]
NOISE = ["state", "spp", "noise_scale", "noise_shift"]
OPS = {  # op -> its inputs, in order
    "NBGBlend": ["logits", *IMAGES],
    "NBGBlendPass": ["logits", *IMAGES, *PASS_THROUGH],
    "NBGBlendNoise": ["logits", *IMAGES, *PASS_THROUGH, *NOISE],
}


def op_model(op: str) -> bytes:
    """A graph of the one node `op`, every input float32 of any shape."""
    inputs = OPS[op]
    node = helper.make_node(op, inputs, ["denoised"], domain=OPS_DOMAIN)
    graph = helper.make_graph(
        [node], op, [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in inputs],
        [helper.make_tensor_value_info("denoised", TensorProto.FLOAT, None)])
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid(OPS_DOMAIN, 1)]
    return helper.make_model(graph, opset_imports=opsets, ir_version=9).SerializeToString()


def op_inputs(op: str, height: int, width: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Plausible inputs of one image: logits of GuideNet's spread, histories of 1..32 frames."""
    rng = np.random.default_rng(seed)
    candidates = 3 if op == "NBGBlend" else 5

    def planes(channels: int, low: float = 0.0, high: float = 1.0) -> np.ndarray:
        shape = (1, channels, height, width)
        return (low + rng.random(shape, np.float32) * (high - low)).astype(np.float32)

    feeds = {"logits": (rng.standard_normal((1, 3 + candidates, height, width)) * 4)
             .astype(np.float32),
             "safe_albedo": planes(3, 0.01, 1.0)}
    feeds |= {name: planes(3, 0.0, 3.0) for name in IMAGES[1:]}
    feeds |= {name: planes(3, -0.5, 3.5) for name in PASS_THROUGH}
    state = planes(8)
    state[:, 7] = rng.integers(1, 33, (height, width))
    feeds |= {"state": state, "spp": np.array([4.0], np.float32),
              "noise_scale": (rng.standard_normal(5) * 0.5).astype(np.float32),
              "noise_shift": (rng.standard_normal(5) * 2).astype(np.float32)}
    return {name: feeds[name] for name in OPS[op]}


def op_runner(library: Path, op: str, feeds: dict[str, np.ndarray],
              threads: int) -> Callable[[], None] | None:
    """One run of `op` from `library` (inputs bound once, the output left in onnxruntime's
    memory), or None where the library has no such op."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    # Idle pools of the other sessions would spin on the cores this one runs on.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.register_custom_ops_library(str(library))
    try:
        session = ort.InferenceSession(op_model(op), options, providers=["CPUExecutionProvider"])
    except Exception as error:  # onnxruntime raises its own types; only a missing op is expected
        if op not in str(error):
            raise
        return None
    binding = session.io_binding()
    for name, value in feeds.items():
        binding.bind_cpu_input(name, value)
    binding.bind_output("denoised")
    return lambda: session.run_with_iobinding(binding)


def median_ms(runners: dict[tuple[str, str], Callable[[], None]], runs: int,
              warmup: int) -> dict[tuple[str, str], float]:
    """Each runner's median wall time in ms over `runs` rounds, the runners interleaved."""
    times: dict[tuple[str, str], list[float]] = {key: [] for key in runners}
    for round_ in range(warmup + runs):
        for key, run in runners.items():
            start = time.perf_counter()
            run()
            if round_ >= warmup:
                times[key].append((time.perf_counter() - start) * 1e3)
    return {key: statistics.median(values) for key, values in times.items()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("libraries", nargs="+", type=Path, help="builds of libquietframe_ops")
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    cli_args.add_threads(parser, help="onnxruntime intra-op threads")
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--width", type=int, default=1280)
    args = parser.parse_args(argv)
    runners = {}
    for op in OPS:
        feeds = op_inputs(op, args.height, args.width)
        for library in args.libraries:
            runner = op_runner(library, op, feeds, args.threads)
            if runner is not None:
                runners[str(library), op] = runner
    ms = median_ms(runners, args.runs, args.warmup)
    print(f"ms per run, median of {args.runs} at {args.width}x{args.height}, "
          f"{args.threads} threads")
    width = max(len(str(library)) for library in args.libraries)
    print(f"{'library':<{width}}  " + "  ".join(f"{op:>13}" for op in OPS))
    for library in args.libraries:
        cells = (f"{ms[str(library), op]:13.2f}" if (str(library), op) in ms else f"{'n/a':>13}"
                 for op in OPS)
        print(f"{str(library):<{width}}  " + "  ".join(cells))


if __name__ == "__main__":
    main()
