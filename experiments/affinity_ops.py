"""Micro-benchmark: the affinity-kernel ops at 1280×720, ms per frame.

python -m quietframe.experiments.affinity_ops [--threads 1 2] [--repeats 5] [--dilation 4]
                                        [--torch-kernel 13] [--no-torch]

- ai.quietframe::AffinityFilter with kernel sizes 5, 7, 9, 11, 13 (the paper's §5.5.3 knob),
  d = 8 features, 3 radiance channels, at each thread count;
- ai.quietframe::AffinityTemporalFilter with a 13×13 spatial kernel and temporal windows 5 and 13
  (temporal_on = 1, so the temporal term is computed);
- the PyTorch reference (quietframe.model.affinity_kernels.spatial_math, no autograd) for one
  kernel size, at the largest thread count.
One frame per call, one session per op with inputs and output bound once (no copies in the loop),
intra_op_num_threads = threads; the kernel size is fed as an input, as a session would at run time.
Figures are medians (bench/timing.py), with the process CPU time per call beside them: on a shared
machine, wall time well above CPU time / threads means the run waited for a core. The load
average before and after is printed with the table.
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.timing import Timing, time_ms
from quietframe.runtime.ops_library import OPS_DOMAIN, ops_library_path

HEIGHT, WIDTH = 720, 1280
FEATURES = 8
KERNEL_SIZES = (5, 7, 9, 11, 13)
TEMPORAL_WINDOWS = (5, 13)
SPATIAL_INPUTS = ("radiance", "features", "bandwidth", "center")
TEMPORAL_INPUTS = ("prev_output", "prev_features", "temporal_bandwidth", "temporal_on")


def make_inputs(height: int = HEIGHT, width: int = WIDTH, seed: int = 0) -> dict[str, np.ndarray]:
    """Plausible inputs: noisy HDR radiance, smooth-ish features, bandwidths that keep a good
    share of the weights above the exp cut-off (the op's work does not depend on the values)."""
    rng = np.random.default_rng(seed)
    f32 = np.float32
    yy, xx = np.mgrid[0:height, 0:width] / max(height, width)
    smooth = np.stack([np.sin((k + 1) * xx + (k % 3) * yy) for k in range(FEATURES)])[None]
    return {
        "radiance": rng.lognormal(0.0, 0.7, (1, 3, height, width)).astype(f32),
        "features": (smooth + 0.1 * rng.standard_normal(smooth.shape)).astype(f32),
        "bandwidth": rng.uniform(0.5, 4.0, (1, 1, height, width)).astype(f32),
        "center": rng.uniform(0.0, 1.0, (1, 1, height, width)).astype(f32),
        "prev_output": rng.lognormal(0.0, 0.3, (1, 3, height, width)).astype(f32),
        "prev_features": (smooth + 0.1 * rng.standard_normal(smooth.shape)).astype(f32),
        "temporal_bandwidth": rng.uniform(0.5, 4.0, (1, 1, height, width)).astype(f32),
        "temporal_on": np.ones(1, f32),
    }


def op_graph(op: str, dilation: int) -> bytes:
    """One-node model of `op` with its kernel sizes as int64 graph inputs."""
    from onnx import TensorProto, helper

    floats = SPATIAL_INPUTS + (TEMPORAL_INPUTS if op == "AffinityTemporalFilter" else ())
    ints = ("kernel_size",) + (("temporal_kernel_size",) if op == "AffinityTemporalFilter"
                               else ())
    inputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in floats]
    inputs += [helper.make_tensor_value_info(n, TensorProto.INT64, []) for n in ints]
    output = helper.make_tensor_value_info("output", TensorProto.FLOAT, None)
    node = helper.make_node(op, [*floats, *ints], ["output"], domain=OPS_DOMAIN,
                            dilation=dilation)
    graph = helper.make_graph([node], op, inputs, [output])
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid(OPS_DOMAIN, 1)]
    return helper.make_model(graph, opset_imports=opsets, ir_version=9).SerializeToString()


def ort_runner(op: str, data: dict[str, np.ndarray], sizes: dict[str, int], threads: int,
               dilation: int):
    """A no-argument callable that runs `op` once on `data` with the kernel sizes `sizes`."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.register_custom_ops_library(str(ops_library_path()))
    session = ort.InferenceSession(op_graph(op, dilation), options,
                                   providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    values = {n: ort.OrtValue.ortvalue_from_numpy(data[n]) for n in names if n in data}
    values |= {n: ort.OrtValue.ortvalue_from_numpy(np.array(v, np.int64))
               for n, v in sizes.items()}
    values["output"] = ort.OrtValue.ortvalue_from_numpy(np.empty_like(data["radiance"]))
    binding = session.io_binding()
    for name, value in values.items():
        if name == "output":
            binding.bind_ortvalue_output(name, value)
        else:
            binding.bind_ortvalue_input(name, value)
    return lambda: (values, session.run_with_iobinding(binding))


def torch_runner(data: dict[str, np.ndarray], kernel_size: int, threads: int, dilation: int):
    import torch

    from quietframe.model.affinity_kernels import spatial_math

    torch.set_num_threads(threads)
    tensors = [torch.from_numpy(data[n]) for n in SPATIAL_INPUTS]

    def run():
        with torch.no_grad():
            return spatial_math(*tensors, kernel_size, dilation)

    return run


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_threads(parser, sweep=True)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dilation", type=int, default=4)
    parser.add_argument("--torch-kernel", type=int, default=13)
    parser.add_argument("--no-torch", action="store_true")
    args = parser.parse_args(argv)

    data = make_inputs()
    load_before = os.getloadavg()
    rows: list[tuple[str, int, Timing]] = []
    for threads in args.threads:
        for k in KERNEL_SIZES:
            run = ort_runner("AffinityFilter", data, {"kernel_size": k}, threads, args.dilation)
            rows.append((f"AffinityFilter {k}×{k}", threads, time_ms(run, repeats=args.repeats)))
        for kt in TEMPORAL_WINDOWS:
            run = ort_runner("AffinityTemporalFilter", data,
                             {"kernel_size": 13, "temporal_kernel_size": kt}, threads,
                             args.dilation)
            rows.append((f"AffinityTemporalFilter 13×13 + temporal {kt}×{kt}", threads,
                         time_ms(run, repeats=args.repeats)))
    if not args.no_torch:
        threads = max(args.threads)
        k = args.torch_kernel
        run = torch_runner(data, k, threads, args.dilation)
        rows.append((f"PyTorch reference spatial_math {k}×{k}", threads,
                     time_ms(run, warmup=1, repeats=max(2, args.repeats // 2))))
    load_after = os.getloadavg()

    print(f"{WIDTH}×{HEIGHT}, d = {FEATURES}, C = 3, dilation {args.dilation}; "
          f"{os.cpu_count()} CPUs; load average (1/5/15 min) before "
          f"{'/'.join(f'{v:.2f}' for v in load_before)}, after "
          f"{'/'.join(f'{v:.2f}' for v in load_after)}")
    print()
    print("| case | threads | ms per frame (median) | min | CPU ms per call |")
    print("|---|---:|---:|---:|---:|")
    for name, threads, t in rows:
        print(f"| {name} | {threads} | {t.median_ms:.1f} | {t.min_ms:.1f} | {t.cpu_ms:.1f} |")


if __name__ == "__main__":
    main()
