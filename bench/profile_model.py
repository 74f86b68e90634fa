"""Where a shipped model's time goes: onnxruntime's node profile per op type at 1280×720, per
graph stage (a staged model's other files too), the OIDN stages' wall time, and each of the
OIDN stage's filters alone (aux prefilters, main filter).

    python -m quietframe.bench.profile_model models/affinity-h16-k5gc.onnx [--option kernel_size=5]

Runs the model through quietframe.runtime with its history carried, on a session built like the
runtime's (same threads, optimisation level, custom ops) but with profiling on, and prints per
op type the summed node time per frame and its share. On a shared machine read the shares, not
the milliseconds.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import onnxruntime as ort

from quietframe.bench import cli_args
from quietframe.bench.synthetic import frame_buffers
from quietframe.runtime import Denoiser
from quietframe.runtime.denoiser import GraphRunner
from quietframe.runtime.oidn_prepass import OIDNPrepass, _FilterSet, usable_aux
from quietframe.runtime.ops_library import ops_library_path


def profiling_session(path: Path, threads: int, prefix: Path) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.register_custom_ops_library(str(ops_library_path()))
    options.enable_profiling = True
    options.profile_file_prefix = str(prefix)
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def node_ms_by_op(trace: list[dict]) -> dict[str, float]:
    """Summed 'Node' event durations per op type, in ms per run, leaving out the session's
    first run (allocations, first-touch)."""
    runs = sorted(e["ts"] for e in trace if e.get("name") == "model_run")
    if len(runs) < 2:
        raise ValueError("the profile needs at least two runs")
    totals: dict[str, float] = defaultdict(float)
    for event in trace:
        if (event.get("cat") == "Node" and event.get("name", "").endswith("_kernel_time")
                and event["ts"] >= runs[1]):
            totals[event["args"]["op_name"]] += event["dur"] / 1e3 / (len(runs) - 1)
    return dict(sorted(totals.items(), key=lambda kv: -kv[1]))


def parse_option(text: str) -> tuple[str, int | float]:
    name, _, value = text.partition("=")
    if not name or not value:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    number = float(value)
    return name, int(number) if number.is_integer() else number


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="quietframe-profile", description=__doc__.split("\n")[0])
    parser.add_argument("model", type=Path)
    cli_args.add_threads(parser)
    parser.add_argument("--frames", type=int, default=3, help="profiled frames (after a warm-up)")
    parser.add_argument("--option", type=parse_option, action="append", default=[],
                        help="a run-time input, e.g. kernel_size=5; repeatable")
    parser.add_argument("--out", type=Path, default=Path("/tmp/quietframe-profile"))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    denoiser = Denoiser(args.model, threads=args.threads, options=dict(args.option))
    buffers = frame_buffers()
    state = denoiser.denoise(buffers, None).state  # a history, as in a running sequence
    # Every graph stage (a staged model's other files too) gets a profiling session; the OIDN
    # stages are timed by wall clock as the frame's rest.
    graphs = [s for s in denoiser.stages if isinstance(s, GraphRunner)]
    for index, graph in enumerate(graphs):
        graph.session = profiling_session(graph.path, args.threads,
                                          args.out / f"{args.model.stem}-{index}")
    state = denoiser.denoise(buffers, state).state  # left out (node_ms_by_op)
    started = time.perf_counter()
    for _ in range(args.frames):
        state = denoiser.denoise(buffers, state).state
    frame_ms = (time.perf_counter() - started) * 1e3 / args.frames
    print(f"{args.model.name} at 1280×720, {args.threads} threads, options {dict(args.option)}: "
          f"{frame_ms:.0f} ms a frame (wall)")
    graph_total = 0.0
    for graph in graphs:
        totals = node_ms_by_op(json.loads(Path(graph.session.end_profiling()).read_text()))
        total = sum(totals.values())
        graph_total += total
        print(f"{graph.path.name}: {total:.0f} ms of node time per frame")
        for op, ms in totals.items():
            print(f"  {op:28s} {ms:8.1f} ms  {100 * ms / total:5.1f}%")
    if len(graphs) < len(denoiser.stages):
        print(f"OIDN and the rest (wall less graph node time): {frame_ms - graph_total:.0f} ms")
    if denoiser.prepass is not None:
        for name, ms in oidn_filter_ms(denoiser.prepass, buffers):
            print(f"  OIDN {name:23s} {ms:8.0f} ms (median of 3)")
    return 0


def oidn_filter_ms(prepass: OIDNPrepass, planes: dict) -> list[tuple[str, float]]:
    """Each of the OIDN stage's filters timed alone on `planes` (its aux prefilters, then the
    main filter), as the runtime builds them (runtime/oidn_prepass.py), median of 3 runs."""
    _, height, width = planes["color"].shape
    aux = usable_aux(prepass.settings.aux, planes)
    filters = _FilterSet(prepass._oidn, prepass._device().device, prepass.settings,
                         (height, width), aux, prepass.max_memory_mb)
    try:
        for name in filters.inputs:
            np.copyto(filters.bound[name], planes[name].transpose(1, 2, 0))
        settings = prepass.settings
        names = ([f"{a} prefilter ({settings.aux_quality or settings.quality})" for a in aux]
                 if settings.prefilter_aux else [])
        names.append(f"main ({settings.quality}{', cleanAux' if settings.prefilter_aux else ''})")
        out = []
        for name, flt in zip(names, filters.filters, strict=True):
            flt.execute()  # first run: scratch pages
            times = []
            for _ in range(3):
                started = time.perf_counter()
                flt.execute()
                times.append((time.perf_counter() - started) * 1e3)
            out.append((name, float(np.median(times))))
        return out
    finally:
        filters.close()


if __name__ == "__main__":
    raise SystemExit(main())
