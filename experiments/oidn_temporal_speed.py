"""Speed of the oidn-temporal tier at 720p: OIDN's share and the temporal stage's share.

    python -m quietframe.experiments.oidn_temporal_speed
        [--variants oidn-temporal-high,oidn-temporal-fast] [--kernels 3x3,5x3,5x5]
        [--widths 16] [--threads 2] [--repeats 5] [--model a.onnx ...]

Each case is timed by bench/oidn_temporal.measure (the shipped runtime on one 1280×720 frame,
history carried: `oidn`, `stage`, `total`). Without --model the cases are exported from
untrained variants (speed does not depend on the weights; needs torch). The tier's target:
stage ≤ 15% of oidn.

    python -m quietframe.experiments.oidn_temporal_speed
        --prefilter ~/.cache/quietframe/data/g2/test

instead compares OIDN with and without prefiltered aux (Blender's "accurate" mode) on every
finished frame under that folder: PSNR / SSIM against the reference per spp level and quality,
and the time each costs at 720p — the measurement behind the variants' `prefilter_aux`.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.oidn_temporal import measure
from quietframe.bench.synthetic import cpu_peak_gflops, frame_buffers
from quietframe.bench.timing import Timing, time_ms
from quietframe.model import metrics
from quietframe.model.oidn_cache import oidn_output
from quietframe.models import MODELS_DIR
from quietframe.runtime.oidn_prepass import OIDNPrepass, OIDNSettings
from quietframe.scenes.exr_io import color_layer, load_frame


def export_cases(variants: list[str], kernels: list[tuple[int, int]], widths: list[int],
                 folder: Path) -> list[Path]:
    """Untrained exports of every variant × kernel sizes × width (seeded)."""
    import torch

    from quietframe.export.onnx_export import export_nbg
    from quietframe.model.oidn_temporal import VARIANTS, OIDNTemporal

    paths = []
    for variant in variants:
        for k, kt in kernels:
            for width in widths or [VARIANTS[variant].width]:
                config = dataclasses.replace(VARIANTS[variant], kernel_size=k,
                                             temporal_kernel_size=kt, width=width)
                torch.manual_seed(0)
                name = f"{variant}-k{k}-t{kt}-w{width}"
                paths.append(export_nbg(OIDNTemporal(config), folder / f"{name}.onnx"))
                if config.color_from:  # the model it composes, installed next to it
                    shutil.copy(MODELS_DIR / config.color_from, folder / config.color_from)
    return paths


def compare_prefilter(folder: Path, qualities: list[str], threads: int) -> str:
    """PSNR/SSIM of OIDN without and with prefiltered aux on the frames under `folder`."""
    frames = sorted(folder.glob("*/frame_*.exr"))
    if not frames:
        raise SystemExit(f"--prefilter: no frames under {folder}")
    lines = [f"{len(frames)} frames under {folder}; PSNR / SSIM vs the reference (mean)", "",
             "| quality | prefilter aux | spp | PSNR | SSIM |", "|---|---|---:|---:|---:|"]
    timing_lines = []
    for quality in qualities:
        for prefilter in (False, True):
            settings = OIDNSettings(quality, prefilter)
            levels: dict[int, list[tuple[float, float]]] = {}
            for path in frames:
                names = ["albedo", "normal", "reference"]
                layers = load_frame(path, names + [color_layer(s) for s in (1, 2, 4, 8)])
                for spp in (1, 2, 4, 8):
                    if color_layer(spp) not in layers:
                        continue
                    out = oidn_output(layers[color_layer(spp)], layers["albedo"],
                                      layers["normal"], settings)
                    ref = layers["reference"]
                    levels.setdefault(spp, []).append((metrics.psnr(out, ref),
                                                       metrics.ssim(out, ref)))
            for spp, scores in sorted(levels.items()):
                psnr, ssim = np.mean(scores, axis=0)
                lines.append(f"| {quality} | {prefilter} | {spp} | {psnr:.2f} | {ssim:.4f} |")
            prepass, planes = OIDNPrepass(settings, threads), frame_buffers()
            t = time_ms(lambda p=prepass, x=planes: p(x), warmup=1, repeats=3)
            timing_lines.append(f"- {quality}, prefilter aux {prefilter}: {t} at 720p")
            prepass.close()
    return "\n".join(lines + ["", *timing_lines])


def report(rows: list[tuple[str, dict[str, Timing]]], threads: int) -> str:
    lines = [f"720p, {cpu_peak_gflops(threads)[1]}, load average "
             f"{os.getloadavg()[0]:.1f} at the end; median ms (CPU ms per call in brackets)", "",
             "| model | OIDN ms | temporal stage ms | stage / OIDN | total ms |",
             "|---|---:|---:|---:|---:|"]
    for name, t in rows:
        share = t["stage"].median_ms / t["oidn"].median_ms
        cpu_share = t["stage"].cpu_ms / t["oidn"].cpu_ms
        lines.append(f"| {name} | {t['oidn'].median_ms:.0f} ({t['oidn'].cpu_ms:.0f}) | "
                     f"{t['stage'].median_ms:.0f} ({t['stage'].cpu_ms:.0f}) | "
                     f"{100 * share:.1f}% ({100 * cpu_share:.1f}% CPU) | "
                     f"{t['total'].median_ms:.0f} |")
    return "\n".join(lines)


def parse_kernels(text: str) -> list[tuple[int, int]]:
    return [(int(a), int(b)) for a, b in (item.split("x") for item in text.split(","))]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--variants", default="oidn-temporal-high,oidn-temporal-fast")
    parser.add_argument("--kernels", default="3x3", help="spatial x temporal sizes, comma list")
    parser.add_argument("--widths", default="", help="CNN widths, comma list (default: variant)")
    parser.add_argument("--model", type=Path, action="append", default=[],
                        help="time these exported models instead")
    cli_args.add_threads(parser)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--prefilter", type=Path,
                        help="compare OIDN without/with prefiltered aux on frames under this")
    parser.add_argument("--qualities", default="high,fast", help="for --prefilter")
    args = parser.parse_args(argv)
    if args.prefilter:
        print(compare_prefilter(args.prefilter.expanduser(), args.qualities.split(","),
                                args.threads))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        paths = args.model or export_cases(
            args.variants.split(","), parse_kernels(args.kernels),
            [int(w) for w in args.widths.split(",") if w], Path(tmp))
        rows = [(p.stem, measure(p, args.threads, args.repeats)) for p in paths]
    print(report(rows, args.threads))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
