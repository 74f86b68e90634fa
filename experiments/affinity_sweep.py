"""Width sweep of the affinity denoiser for a 2-core CPU (docs/affinity.md).

python -m quietframe.experiments.affinity_sweep [--threads 2] [--variants affinity-h8 …]
       [--kernel-sizes 5 9 13] [--runs DIR] [--out FILE]

For each variant (model/affinity.py VARIANTS): parameters, network GFLOP per 1280×720 frame
(embedding + U-Net convolutions, 2 FLOP per multiply-add; the kernel filtering is in the ms),
and ms per 720p frame through the exported ONNX and quietframe.runtime (history carried, kernel
size fed as the run-time input) at each kernel size, with the process CPU time per frame beside
it. Validation PSNR comes from `<runs>/<variant>/best.pt` metrics when such a run exists.
Untrained weights: speed does not depend on the weights' values. The load average before and
after is printed: the machine may be shared.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import torch

from quietframe.bench import cli_args
from quietframe.bench.synthetic import cpu_peak_gflops, frame_buffers
from quietframe.bench.timing import Timing, time_ms
from quietframe.export.affinity_export import export_affinity
from quietframe.model.affinity import VARIANTS, AffinityDenoiser
from quietframe.runtime import Denoiser

HEIGHT, WIDTH = 720, 1280
DEFAULT_VARIANTS = ("affinity-h8", "affinity-h16", "affinity-h24", "affinity-h32",
                    "affinity-f16")


def network_gflop(model: AffinityDenoiser) -> float:
    """Convolution GFLOP of one 720p frame: counted on a 72×128 frame (1/100 of the pixels,
    every pooling level exact) and scaled by 100."""
    macs = 0

    def count(module: torch.nn.Conv2d, _inputs, output: torch.Tensor) -> None:
        nonlocal macs
        k = module.kernel_size[0] * module.kernel_size[1]
        macs += module.in_channels * module.out_channels * k * output.shape[-2] * output.shape[-1]

    hooks = [m.register_forward_hook(count) for m in model.modules()
             if isinstance(m, torch.nn.Conv2d)]
    buffers = {k: torch.from_numpy(v)[None] for k, v in frame_buffers(72, 128).items()}
    with torch.no_grad():
        model(buffers["color"], buffers["albedo"], buffers["normal"], buffers["depth"],
              buffers["motion"], torch.ones(1), model.initial_state(1, 72, 128), kernel_size=3)
    for hook in hooks:
        hook.remove()
    return 2 * macs * 100 / 1e9


def time_runtime(runtime: Denoiser, kernel_size: int, repeats: int) -> Timing:
    buffers = frame_buffers(HEIGHT, WIDTH)
    options = {"kernel_size": kernel_size}
    state = runtime.denoise(buffers, None, options).state
    return time_ms(lambda: runtime.denoise(buffers, state, options), warmup=1, repeats=repeats)


def validation_psnr(runs: Path | None, name: str) -> str:
    best = runs / name / "best.pt" if runs else None
    if best is None or not best.exists():
        return "–"
    metrics = torch.load(best, map_location="cpu", weights_only=False).get("metrics", {})
    value = metrics.get("val_psnr_1spp_last_frame")
    return f"{value:.2f}" if value is not None else "–"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_threads(parser)
    parser.add_argument("--variants", nargs="+", default=list(DEFAULT_VARIANTS))
    parser.add_argument("--kernel-sizes", nargs="+", type=int, default=[5, 9, 13])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--runs", type=Path, help="training runs: <runs>/<variant>/best.pt")
    parser.add_argument("--out", type=Path, help="also write the table (markdown) here")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()[0]
    _, machine = cpu_peak_gflops(args.threads)
    sizes = args.kernel_sizes
    lines = [f"Machine: {machine}; load average {load_before:.1f} at the start.",
             f"Per {WIDTH}×{HEIGHT} frame through quietframe.runtime: median / min wall ms of "
             f"{args.repeats}, then median CPU ms (all threads; on a shared machine the steadier "
             "figure).", "",
             "| variant | U-Net widths | U-Net res | params | net GFLOP/frame | "
             + " | ".join(f"ms k={k}" for k in sizes) + " | val PSNR |",
             "|---|---|---|---|---|" + "---|" * len(sizes) + "---|"]
    print("\n".join(lines), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.variants:
            torch.manual_seed(0)
            model = AffinityDenoiser(VARIANTS[name]).eval()
            params = sum(p.numel() for p in model.parameters())
            gflop = network_gflop(model)
            runtime = Denoiser(export_affinity(model, Path(tmp) / f"{name}.onnx"),
                               threads=args.threads)
            cells = []
            for k in sizes:
                t = time_runtime(runtime, k, args.repeats)
                cells.append(f"{t.median_ms:.0f} / {t.min_ms:.0f} / {t.cpu_ms:.0f}")
            config = model.config
            res = "full" if config.unet_scale == 1 else f"1/{config.unet_scale}"
            lines.append(f"| {name} | {'/'.join(map(str, config.widths))} | {res} | {params:,} | "
                         f"{gflop:.1f} | " + " | ".join(cells) +
                         f" | {validation_psnr(args.runs, name)} |")
            print(lines[-1], flush=True)
    lines += ["", f"Load average {os.getloadavg()[0]:.1f} at the end."]
    print(lines[-1])
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
