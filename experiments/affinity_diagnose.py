"""Why an affinity checkpoint scores what it scores on the validation split (docs/affinity.md).

    python -m quietframe.experiments.affinity_diagnose RUN/best.pt [--sequences 12] [--spp 1 8] \
        [--against models/nbg-2l-3g.onnx]

Through the PyTorch model (quietframe-train's unroll, whole sequences, training's validation
metric: τ-mapped PSNR), per spp:
- PSNR per frame index (does the history help; does the recurrence drift),
- output energy: mean(output) / mean(reference) of each sequence's last frame, next to the noisy
  input's (a denoiser should keep the frame's energy; the input is unbiased),
- last-frame PSNR per run-time kernel size,
- last-frame PSNR with the output's energy restored per block (output × blur(accumulated
  input) / blur(output), luminance, block means upsampled bilinearly): how much of the gap to
  the reference is a low-frequency bias rather than noise left or detail lost;
- with --against, the same per-frame PSNR and energy for exported models (e.g. the shipped NBG)
  run through quietframe.runtime on the same batches: a comparison measured in one run.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from quietframe.bench import cli_args
from quietframe.model import affinity, families, metrics
from quietframe.model import train as qt
from quietframe.model.nbg import demodulation_divisor, luminance
from quietframe.runtime import Denoiser


def restore_energy(output: torch.Tensor, accumulated: torch.Tensor, albedo: torch.Tensor,
                   block: int) -> torch.Tensor:
    """output × (block mean of the accumulated radiance) / (block mean of the output), both in
    demodulated luminance; bilinear between block centres."""
    divisor = demodulation_divisor(albedo)

    def smooth(x: torch.Tensor) -> torch.Tensor:
        means = F.avg_pool2d(luminance(x), block, ceil_mode=True)
        return F.interpolate(means, size=x.shape[-2:], mode="bilinear", align_corners=False)

    return output * (smooth(accumulated) + 1e-4) / (smooth(output / divisor) + 1e-4)


def run(model: affinity.AffinityDenoiser, batch: dict, kernel_size: int, block: int = 0
        ) -> list[torch.Tensor]:
    """Outputs of one whole sequence, optionally energy-restored per `block`."""
    state = model.initial_state(*batch["color"].shape[:1], *batch["color"].shape[-2:])
    outputs = []
    with torch.no_grad():
        for t in range(batch["color"].shape[1]):
            frame = [batch[k][:, t] for k in ("color", "albedo", "normal", "depth", "motion")]
            out, state = model(*frame, batch["reset"][:, t], state, kernel_size=kernel_size)
            if block:
                accumulated = state[0][:, affinity.STATE_SLICES["radiance"]]
                out = restore_energy(out, accumulated, frame[1], block)
            outputs.append(out)
    return outputs


def run_exported(denoiser, batch: dict) -> list[torch.Tensor]:
    """Outputs of one whole sequence through quietframe.runtime (state carried, reset honoured)."""
    state, outputs = None, []
    for t in range(batch["color"].shape[1]):
        planes = {k: batch[k][0, t].numpy() for k in ("color", "albedo", "normal", "depth",
                                                      "motion")}
        result = denoiser.denoise(planes, None if batch["reset"][0, t] else state)
        state = result.state
        outputs.append(torch.from_numpy(result.color)[None])
    return outputs


def psnr(pred: torch.Tensor, ref: torch.Tensor) -> float:
    return metrics.psnr(pred[0].permute(1, 2, 0).numpy(), ref[0].permute(1, 2, 0).numpy())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--sequences", type=int, default=12)
    parser.add_argument("--spp", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--kernel-sizes", type=int, nargs="+", default=[5, 9, 13])
    parser.add_argument("--blocks", type=int, nargs="+", default=[16, 32])
    cli_args.add_threads(parser)
    parser.add_argument("--against", type=Path, nargs="*", default=[],
                        help="exported .onnx models to measure on the same batches")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    model, checkpoint = families.load_checkpoint(str(args.checkpoint))
    model.eval()
    fields = {f.name for f in dataclasses.fields(qt.TrainConfig)}
    cfg = qt.TrainConfig(**{k: v for k, v in checkpoint["training"].items() if k in fields})
    default = model.config.kernel_size
    print(f"{args.checkpoint} (step {checkpoint['step']}, default kernel size {default})")
    for spp in args.spp:
        batches = qt.validation_batches(cfg, spp)[: args.sequences]
        frames = max(b["color"].shape[1] for b in batches)
        per_frame = [[] for _ in range(frames)]
        energy, noisy_energy, last = [], [], {}
        for batch in batches:
            outputs = run(model, batch, default)
            refs = batch["reference"]
            for t, out in enumerate(outputs):
                per_frame[t].append(psnr(out, refs[:, t]))
            energy.append(float(outputs[-1].mean() / refs[:, -1].mean()))
            noisy_energy.append(float(batch["color"][:, -1].mean() / refs[:, -1].mean()))
            for k in args.kernel_sizes:
                out = outputs[-1] if k == default else run(model, batch, k)[-1]
                last.setdefault(f"k={k}", []).append(psnr(out, refs[:, -1]))
            for block in args.blocks:
                out = run(model, batch, default, block)[-1]
                last.setdefault(f"k={default}, energy restored per {block}²",
                                []).append(psnr(out, refs[:, -1]))
        print(f"\n{spp} spp, {len(batches)} sequences")
        for path in args.against:
            report_exported(path, batches, args.threads)
        print("  PSNR per frame index: " + " ".join(f"{np.mean(v):.2f}" for v in per_frame if v))
        print(f"  energy out/ref (last frame): {np.round(energy, 2).tolist()}, mean "
              f"{np.mean(energy):.3f}; noisy input/ref: mean {np.mean(noisy_energy):.3f}")
        for name, values in last.items():
            print(f"  last-frame PSNR, {name}: {np.mean(values):.2f}")
    return 0


def report_exported(path: Path, batches: list[dict], threads: int) -> None:
    denoiser = Denoiser(path, threads=threads)
    per_frame: list[list[float]] = []
    energy = []
    for batch in batches:
        outputs = run_exported(denoiser, batch)
        for t, out in enumerate(outputs):
            if len(per_frame) <= t:
                per_frame.append([])
            per_frame[t].append(psnr(out, batch["reference"][:, t]))
        energy.append(float(outputs[-1].mean() / batch["reference"][:, -1].mean()))
    print(f"  {path.stem}: PSNR per frame index: "
          + " ".join(f"{np.mean(v):.2f}" for v in per_frame)
          + f"; last frame {np.mean(per_frame[-1]):.2f}; energy out/ref {np.mean(energy):.3f}")


if __name__ == "__main__":
    raise SystemExit(main())
