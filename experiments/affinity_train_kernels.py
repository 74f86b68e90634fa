"""Training step time of the affinity denoiser with the reference and the native kernels.

    python -m quietframe.experiments.affinity_train_kernels [--sizes 5,13] [--threads 1]
        [--repeats 3]

One forward + backward of the model (unrolled over the frames, the training loss, eq. 13's
penalty) per step, as quietframe-train runs it, on a synthetic batch; first with the PyTorch
reference kernels (model/affinity_kernels.py), then with the native ones
(QUIETFRAME_TRAIN_KERNELS=native, model/affinity_native.py), in one run. The kernels' share is
the time of the step's kernel calls alone (captured from one step, replayed forward + backward)
over the step time. Prints the median over the repeats, after one warm-up step.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from quietframe.bench import cli_args
from quietframe.bench.synthetic import frame_buffers
from quietframe.model import affinity_native
from quietframe.model import train as qt

KERNEL_OPS = ("quietframe::affinity_filter", "quietframe::affinity_temporal_filter")


def synthetic_batch(batch: int, frames: int, crop: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """A (B, T, C, h, w) batch shaped like TrainingBatches' (reference: another noise draw)."""
    def stacked(name: str, offset: int = 0) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.stack([
            frame_buffers(crop, crop, seed + 1000 * b + t + offset)[name] for t in range(frames)])
            for b in range(batch)]))

    out = {name: stacked(name) for name in ("color", "albedo", "normal", "depth", "motion")}
    out["motion"] = out["motion"] * 0.5
    out["reference"] = stacked("color", offset=500)
    out["reset"] = torch.zeros(batch, frames)
    return out


def step(cfg: qt.TrainConfig, model: torch.nn.Module, batch: dict[str, torch.Tensor]) -> None:
    """One training step's forward + backward (the optimizer update left out)."""
    model.zero_grad(set_to_none=True)
    loss = qt.batch_loss(cfg, model, batch)
    loss.backward()


class _KernelCalls(TorchDispatchMode):
    """Records the affinity kernel calls (op, args) of what runs under it."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func._schema.name in KERNEL_OPS:
            self.calls.append((func, tuple(a.detach().clone() if isinstance(a, torch.Tensor)
                                           else a for a in args)))
        return func(*args, **(kwargs or {}))


def kernel_calls(model: torch.nn.Module, batch: dict[str, torch.Tensor]) -> list[tuple]:
    recorder = _KernelCalls()
    with torch.no_grad(), recorder:
        qt.unroll(model, batch)
    return recorder.calls


def kernels_seconds(calls: list[tuple]) -> float:
    """Forward + backward of every recorded kernel call (temporal_on gets no gradient)."""
    start = time.perf_counter()
    for func, args in calls:
        inputs = [a.detach().requires_grad_(i < 7) if isinstance(a, torch.Tensor) else a
                  for i, a in enumerate(args)]
        out = func(*inputs)
        out.backward(torch.ones_like(out))
    return time.perf_counter() - start


def measure(cfg: qt.TrainConfig, batch: dict[str, torch.Tensor], kernels: str,
            repeats: int) -> tuple[float, float]:
    """(median step seconds, median kernel seconds) with QUIETFRAME_TRAIN_KERNELS = kernels."""
    os.environ[affinity_native.KERNELS_ENV] = kernels
    torch.manual_seed(cfg.seed)
    model = qt.build_model(cfg)
    calls = kernel_calls(model, batch)
    step(cfg, model, batch)  # warm-up
    steps, kernel = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        step(cfg, model, batch)
        steps.append(time.perf_counter() - start)
        kernel.append(kernels_seconds(calls))
    return statistics.median(steps), statistics.median(kernel)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="quietframe-bench-affinity-train",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--variant", default="affinity-h24")
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--crop", type=int, default=128)
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--sizes", default="5,13", help="spatial kernel sizes, comma-separated")
    cli_args.add_threads(parser)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    reason = affinity_native.unavailable_reason()
    if reason is not None:
        parser.error(f"the native kernels cannot run: {reason}")
    torch.set_num_threads(args.threads)
    batch = synthetic_batch(args.batch, args.frames, args.crop)
    previous = os.environ.get(affinity_native.KERNELS_ENV)
    print(f"{args.variant}, batch {args.batch} × {args.crop}² × {args.frames} frames, "
          f"{args.threads} thread(s), torch {torch.__version__}: seconds per forward + backward")
    print(f"{'k':>3} {'kernels':10} {'step s':>8} {'kernel s':>9} {'share':>6} {'speed-up':>9}")
    try:
        for size in (int(s) for s in args.sizes.split(",")):
            cfg = qt.TrainConfig(variant=args.variant, crop=args.crop, frames=args.frames,
                                 batch=args.batch, threads=args.threads, kernel_size=size)
            results = {k: measure(cfg, batch, k, args.repeats) for k in ("reference", "native")}
            for kernels, (seconds, kernel) in results.items():
                speedup = results["reference"][0] / seconds
                print(f"{size:>3} {kernels:10} {seconds:8.3f} {kernel:9.3f} "
                      f"{100 * kernel / seconds:5.0f}% {speedup:8.2f}×")
    finally:
        if previous is None:
            os.environ.pop(affinity_native.KERNELS_ENV, None)
        else:
            os.environ[affinity_native.KERNELS_ENV] = previous
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
