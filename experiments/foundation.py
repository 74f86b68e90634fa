"""Foundation benchmark: GuideNet and whole-model speed at 1280×720 on this machine.

python -m quietframe.experiments.foundation [--threads 2] [--out docs/bench-foundation.md]

Prints ms per frame (median, bench/timing.py) for
- GuideNet forward alone (PyTorch and onnxruntime) with achieved conv GFLOP/s vs the machine's
  AVX2-FMA peak (cores × clock × 2 FMA pipes × 8 float lanes × 2 FLOP),
- the whole exported model per frame through the shipped runtime (quietframe.runtime.Denoiser),
  for 1 and 3 grids, GuideNet widths 8, 16 and 20, and the 7-layer net,
- splat+slice through the custom ops and PyTorch (quietframe.experiments.grid_ops).
Untrained weights: speed does not depend on the weights' values.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
from pathlib import Path

import torch

from quietframe.bench import cli_args
from quietframe.bench.synthetic import cpu_peak_gflops, frame_buffers
from quietframe.bench.timing import time_ms
from quietframe.experiments import grid_ops
from quietframe.export.onnx_export import export_nbg
from quietframe.model.nbg import GUIDE_INPUT_CHANNELS, VARIANTS, GuideNet, NBGDenoiser
from quietframe.runtime import Denoiser
from quietframe.runtime.denoiser import make_session

HEIGHT, WIDTH = 720, 1280


def conv_gflop(net: GuideNet, height: int, width: int) -> float:
    """FLOPs of all convolutions (2 per multiply-add) for one frame, in GFLOP."""
    total = 0
    for conv in net.modules():
        if isinstance(conv, torch.nn.Conv2d):
            k = conv.kernel_size[0] * conv.kernel_size[1]
            total += 2 * conv.in_channels * conv.out_channels * k * height * width
    return total / 1e9


def bench_guidenet(config, threads: int, workdir: Path) -> dict[str, float]:
    net = GuideNet(config).eval()
    features = torch.rand(1, GUIDE_INPUT_CHANNELS, HEIGHT, WIDTH)
    with torch.no_grad():
        torch_ms = time_ms(lambda: net(features), warmup=1, repeats=5).median_ms
    path = workdir / f"guidenet-{config.layers}-{config.width}.onnx"
    torch.onnx.export(net, (features,), str(path), dynamo=True, opset_version=18,
                      input_names=["features"], verbose=False)
    session = make_session(path, threads)
    feeds = {"features": features.numpy()}
    ort_ms = time_ms(lambda: session.run(None, feeds), warmup=1, repeats=5).median_ms
    return {"gflop": conv_gflop(net, HEIGHT, WIDTH), "torch_ms": torch_ms, "ort_ms": ort_ms}


def bench_model(config, threads: int, workdir: Path) -> float:
    torch.manual_seed(0)
    path = export_nbg(NBGDenoiser(config), workdir / f"{config.name}-w{config.width}.onnx")
    runtime = Denoiser(path, threads=threads)
    buffers = frame_buffers()
    state = runtime.denoise(buffers, None).state
    return time_ms(lambda: runtime.denoise(buffers, state),
                   warmup=1, repeats=5).median_ms


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_threads(parser)
    parser.add_argument("--out", type=Path, help="also write the report (markdown) here")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    peak, machine = cpu_peak_gflops(args.threads)
    lines = [f"# Foundation benchmark, {WIDTH}×{HEIGHT}", "", f"Machine: {machine}; "
             f"AVX2-FMA peak {peak:.0f} GFLOP/s. Median ms per frame (bench/timing.py).", ""]

    # Width 16 next to 8 and 20: onnxruntime's blocked (NCHWc) convolutions work on groups of 8
    # channels, so 20 costs as much as 24 while 16 runs near the speed of 8.
    variants = [("nbg-2l-1g", 8), ("nbg-2l-1g", 16), ("nbg-2l-1g", 20), ("nbg-2l-3g", 8),
                ("nbg-2l-3g", 16), ("nbg-2l-3g", 20), ("nbg-7l-3g", 20)]
    lines += ["## GuideNet forward alone", "",
              "| GuideNet | GFLOP/frame | PyTorch ms | ORT ms | ORT GFLOP/s | % of peak |",
              "|---|---|---|---|---|---|"]
    rows = ["", "## Whole exported model per frame (runtime: numpy + onnxruntime + custom ops)",
            "", "| model | GuideNet width | ms/frame |", "|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        for name, width in variants:
            config = dataclasses.replace(VARIANTS[name], width=width)
            if name != "nbg-2l-1g":  # GuideNet of 1 and 3 grids differ only in the last layer
                g = bench_guidenet(config, args.threads, workdir)
                rate = g["gflop"] / (g["ort_ms"] / 1e3)
                lines.append(f"| {config.layers} layers, width {width}, {config.grids} grids | "
                             f"{g['gflop']:.1f} | {g['torch_ms']:.0f} | {g['ort_ms']:.0f} | "
                             f"{rate:.0f} | {100 * rate / peak:.0f}% |")
                print(lines[-1], flush=True)
            rows.append(f"| {name} | {width} | {bench_model(config, args.threads, workdir):.0f} |")
            print(rows[-1], flush=True)
    lines += rows
    try:
        lines += ["", "## Splat + slice", "", grid_ops.report(threads=args.threads)]
    except (ImportError, AttributeError) as error:
        lines += ["", f"(grid op benchmark unavailable: {error})"]
    report = "\n".join(lines) + "\n"
    print(report)
    if args.out:
        args.out.write_text(report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
