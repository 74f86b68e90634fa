"""Ablation: history kept in output space on top of per-frame OIDN, next to
per-frame OIDN and the shipped accumulation tier, scored in one run.

    python -m quietframe.experiments.output_history --renderer cycles --split test-static
        [--spp 1,2,4,8,16,64] [--sequences N] [--json rows.json]

The shipped `*-acc` tiers reproject the noisy accumulation and run OIDN on it; the question
is whether reprojecting OIDN's per-frame output instead, and only where that stays sharp, can
keep per-frame OIDN's detail and still be steadier. Each candidate is `OutputHistory` over
`oidn-frame` (the shipped per-frame model, run by the runtime), or with `acc+` over the
shipped `oidn-acc` (OIDN on the accumulation), so both kinds of history stack:

- `out-history`: the previous output reprojected to the nearest pixel and blended with this
  frame's OIDN output where the surface test passes (`model/temporal.history_valid`), with the
  accumulation's weights (1/n, floored at MIN_CURRENT_WEIGHT);
- `+clamp`: the reprojected output clipped to the 3×3 min/max of this frame's OIDN output
  first (the obvious fix);
- `+sharp`: history only where the motion vector is a whole number of pixels (a locked-off or
  pixel-aligned pixel), where nearest reprojection is exact, so resampling never blurs.

And the accumulation itself restricted the same way (`accumulated_oidn`): `acc-torch` is
`oidn-acc` rebuilt from the PyTorch pre-stage (its row checks the composition), `aligned-acc`
keeps history only under pixel-aligned motion, `aligned-acc+out-history` adds the sharp output
history on top. `acc-nearest` is the same accumulation through `OutputHistory` over the noisy
colour (demodulated) then OIDN, which should equal `acc-torch`; `acc-bicubic` fetches that
history bicubically instead (resampling that does not blur), and
`out-history+bicubic` (`+clamp`) does the same to OIDN's output. `out-history+hybrid` takes
the exact pixel where the motion is pixel-aligned and the clamped bicubic fetch elsewhere, and
`aligned-acc+hybrid` puts that over the pixel-aligned accumulation.

Rows per spp: PSNR, TRMAE (meaningless on locked-off splits: their reference is one frame's,
so ∂t r = 0 and TRMAE is |∂t p| / ε), and on locked-off splits (`*-static`) flicker
(`metrics.flicker`), each also as a ratio to `oidn-frame`'s (the temporal tiers' targets: PSNR at
least oidn-frame's and Blender's denoise; flicker ≤ 0.5×; TRMAE ≤ 0.7×). The candidates'
extra cost is a few elementwise passes over the frame (no second OIDN pass).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch

from quietframe.bench import cli_args
from quietframe.bench.evaluate import (
    Noisy,
    Scores,
    build_methods,
    give_header_spp,
    load_sequence,
    run_sequence,
    sequence_dirs,
    time_720p,
)
from quietframe.bench.harness import Method, Planes, RuntimeMethod, planar_frames
from quietframe.model.nbg import AccumulationDenoiser, demodulation_divisor
from quietframe.model.output_history import OutputHistory as ShippedOutputHistory
from quietframe.model.output_history import OutputHistoryConfig, clamp_to_neighbourhood
from quietframe.model.temporal import (
    HISTORY_LENGTH,
    RADIANCE,
    backward_warp,
    history_weights,
    pixel_aligned,
    reproject_history,
)
from quietframe.runtime import find_model
from quietframe.runtime.oidn_prepass import OIDNPrepass, OIDNSettings
from quietframe.runtime.sanitize import sanitize_buffer

BASELINES = ("oidn-frame", "oidn-acc", "blender-denoise")
# name: (base model, clamp, sharp only)
CANDIDATES = {"out-history": ("oidn-frame", False, False),
              "out-history+clamp": ("oidn-frame", True, False),
              "out-history+sharp": ("oidn-frame", False, True),
              "acc+out-history": ("oidn-acc", False, False)}


def resample_bicubic(image: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """image(t-1) at p + motion(p), bicubic (BackwardWarp's bicubic mode), negatives cut to 0."""
    return backward_warp(image, motion, mode="bicubic")[0].clamp_min(0)


class OutputHistory:
    """`base`'s output blended with its own reprojected previous output (module docstring).
    `resample`: how the previous output is fetched ("nearest"; "bicubic"; "hybrid": the
    nearest pixel, unclamped, where the motion is pixel-aligned, else bicubic clamped to the
    current 3×3 neighbourhood; the surface test always reads the nearest pixel's depth and
    normal). `demodulate`: blend albedo-divided values and multiply the current albedo back
    (the shipped accumulation's way, so texture does not go through the history)."""

    def __init__(self, base: Method, clamp: bool = False, sharp_only: bool = False,
                 resample: str = "nearest", demodulate: bool = False) -> None:
        self.base, self.clamp, self.sharp_only = base, clamp, sharp_only
        self.resample, self.demodulate = resample, demodulate
        self.state: torch.Tensor | None = None  # (1, 8, H, W): output, depth, normal, count

    def reset(self) -> None:
        self.base.reset()
        self.state = None

    def __call__(self, planes: Planes) -> np.ndarray:
        current = torch.from_numpy(np.asarray(self.base(planes), np.float32))[None]
        divisor = torch.ones(())
        if self.demodulate:
            divisor = demodulation_divisor(torch.from_numpy(planes["albedo"])[None])
            current = current / divisor
        depth = torch.from_numpy(planes["depth"])[None]
        normal = torch.from_numpy(planes["normal"])[None]
        motion = torch.from_numpy(planes.get("motion", np.zeros_like(planes["color"][:2])))[None]
        count = torch.ones_like(depth)
        out = current
        if self.state is not None:
            warped, keep = reproject_history(self.state, motion, depth, normal, torch.zeros(1))
            if self.sharp_only:
                keep = keep * pixel_aligned(motion).to(keep.dtype)
            previous = warped[:, RADIANCE]
            if self.resample in ("bicubic", "hybrid"):
                fetched = resample_bicubic(self.state[:, RADIANCE], motion)
                if self.clamp or self.resample == "hybrid":
                    fetched = clamp_to_neighbourhood(fetched, current)
                # hybrid: the exact pixel, unclamped, where the motion is pixel-aligned
                previous = (torch.where(pixel_aligned(motion), previous, fetched)
                            if self.resample == "hybrid" else fetched)
            elif self.clamp:
                previous = clamp_to_neighbourhood(previous, current)
            alpha, count = history_weights(keep, warped[:, HISTORY_LENGTH])
            out = alpha * current + (1 - alpha) * previous
        self.state = torch.cat((out, depth, normal, count), dim=1)
        return (out * divisor)[0].numpy()


RUNTIME_BUFFERS = ("color", "albedo", "normal", "depth", "motion")


class ThenOIDN:
    """OIDN-high (plain aux) on what `first` makes of the sanitised frame (what the runtime
    feeds its graphs): a history of the noisy colour, then OIDN, as the `*-acc` tiers
    compose it."""

    def __init__(self, first: Method, threads: int) -> None:
        self.first = first
        self.oidn = OIDNPrepass(OIDNSettings("high", False), threads)

    def reset(self) -> None:
        self.first.reset()

    def __call__(self, planes: Planes) -> np.ndarray:
        clean = {k: sanitize_buffer(k, planes[k])[0] for k in RUNTIME_BUFFERS}
        color = np.ascontiguousarray(self.first(clean), np.float32)
        return self.oidn({**clean, "color": color})[0]


class PreStage:
    """The shipped accumulation (`model/nbg.AccumulationDenoiser`) on planes. With
    `aligned_only` the history is dropped wherever the motion is not pixel-aligned (the
    `aligned-accumulation` model): the accumulation then never resamples, at the price of no
    history under sub-pixel motion."""

    def __init__(self, aligned_only: bool) -> None:
        self.accumulation = AccumulationDenoiser(aligned_history=aligned_only)
        self.state: torch.Tensor | None = None

    def reset(self) -> None:
        self.state = None

    def __call__(self, planes: Planes) -> np.ndarray:
        t = {k: torch.from_numpy(np.ascontiguousarray(planes[k]))[None] for k in RUNTIME_BUFFERS}
        reset = torch.tensor([1.0 if self.state is None else 0.0])
        if self.state is None:
            self.state = self.accumulation.initial_state(1, *t["color"].shape[-2:])
        with torch.no_grad():
            acc, self.state = self.accumulation(t["color"], t["albedo"], t["normal"], t["depth"],
                                                t["motion"], reset, self.state)
        return acc[0].numpy()


def accumulated_oidn(aligned_only: bool, threads: int) -> ThenOIDN:
    """`oidn-acc` rebuilt from the PyTorch pre-stage (or its pixel-aligned-only variant)."""
    return ThenOIDN(PreStage(aligned_only), threads)


class ShippedStage:
    """The shipped history stage (model/output_history.OutputHistory, `config`) over `base`'s
    output: its rows measure the graph's own code (and variants of its config). `stage`: a
    module with the same interface instead (model/learned_blend.LearnedBlendHistory)."""

    def __init__(self, base: Method, config=None, stage: torch.nn.Module | None = None) -> None:
        self.base = base
        self.stage = stage if stage is not None else ShippedOutputHistory(config)
        self.state: torch.Tensor | None = None
        self.header_spp: float | None = None  # the frame's spp, as the service gives it

    def reset(self) -> None:
        self.base.reset()
        self.state = None

    def __call__(self, planes: Planes) -> np.ndarray:
        t = {k: torch.from_numpy(np.ascontiguousarray(planes[k]))[None]
             for k in ("albedo", "normal", "depth", "motion")}
        current = torch.from_numpy(np.asarray(self.base(planes), np.float32))[None]
        reset = torch.tensor([1.0 if self.state is None else 0.0])
        if self.state is None:
            self.state = self.stage.initial_state(1, *current.shape[-2:])
        with torch.no_grad():
            spp = None if self.header_spp is None else torch.tensor([float(self.header_spp)])
            out, self.state = self.stage(current, t["albedo"], t["normal"], t["depth"],
                                         t["motion"], reset, self.state, spp)
        return out[0].numpy()


def candidate_methods(threads: int, renderer: str, resampled_weights: str) -> dict:
    """Every row's method factory, baselines first, in the tables' order."""
    known = build_methods(threads, renderer=renderer)
    methods = {name: known[name] for name in BASELINES if name in known}
    for name, (model, clamp, sharp) in CANDIDATES.items():
        path = find_model(model)
        methods[name] = lambda m=path, c=clamp, s=sharp: OutputHistory(
            RuntimeMethod(m, threads), clamp=c, sharp_only=s)
    methods["acc-torch"] = lambda: accumulated_oidn(False, threads)  # = oidn-acc
    for resample in ("nearest", "bicubic"):  # acc-nearest: oidn-acc by OutputHistory's code
        methods[f"acc-{resample}"] = lambda r=resample: ThenOIDN(OutputHistory(
            Noisy(), resample=r, demodulate=True), threads)
    methods["out-history+bicubic"] = lambda: OutputHistory(
        RuntimeMethod(find_model("oidn-frame"), threads), resample="bicubic")
    methods["out-history+bicubic+clamp"] = lambda: OutputHistory(
        RuntimeMethod(find_model("oidn-frame"), threads), clamp=True, resample="bicubic")
    methods["out-history+hybrid"] = lambda: OutputHistory(
        RuntimeMethod(find_model("oidn-frame"), threads), resample="hybrid")
    methods["aligned-acc+hybrid"] = lambda: OutputHistory(
        accumulated_oidn(True, threads), resample="hybrid")
    methods["aligned-acc"] = lambda: accumulated_oidn(True, threads)
    methods["aligned-acc+out-history"] = lambda: OutputHistory(
        accumulated_oidn(True, threads), sharp_only=True)
    for weight in filter(None, resampled_weights.split(",")):  # constant floors
        config = OutputHistoryConfig(resampled_weight=float(weight),
                                     resampled_weight_per_doubling=0.0)
        methods[f"aligned-acc+stage@w{weight}"] = lambda c=config: ShippedStage(
            accumulated_oidn(True, threads), c)
    # the shipped floor, w(spp) from the frame's spp (given where the renderer states it)
    methods["aligned-acc+stage@w(spp)"] = lambda: ShippedStage(
        accumulated_oidn(True, threads), OutputHistoryConfig())
    return methods


def print_rows(rows: list[dict], title: str, locked_off: bool) -> None:
    """One markdown table, each figure with its ratio (or difference) to oidn-frame's."""
    base = {r["spp"]: r for r in rows if r["method"] == "oidn-frame"}
    print(f"{title}; ratios to oidn-frame in brackets\n")
    flick = " flicker (×) |" if locked_off else ""
    print(f"| method | spp | PSNR (Δ dB) | TRMAE (×) |{flick}")
    print("|---|---|---|---|" + ("---|" if locked_off else ""))
    for r in rows:
        b = base[r["spp"]]
        line = (f"| {r['method']} | {r['spp']} | {r['psnr']:.2f} ({r['psnr'] - b['psnr']:+.2f}) "
                f"| {r['trmae']:.3f} ({r['trmae'] / b['trmae']:.2f}) |")
        if locked_off:
            line += f" {r['flicker']:.4f} ({r['flicker'] / b['flicker']:.2f}) |"
        print(line)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    cli_args.add_sequences(p, spp="1,2,4,8,16,64")
    p.add_argument("--sequences", type=int, default=0, help="limit (0 = all)")
    cli_args.add_threads(p)
    cli_args.add_json(p)
    p.add_argument("--resampled-weights", default="",
                   help="comma list: also rows aligned-acc+stage@w<W>, the shipped stage with "
                        "that current-frame weight floor where the history is resampled")
    p.add_argument("--only", default="", help="comma list: only these rows (and baselines)")
    p.add_argument("--timing", action="store_true",
                   help="also ms per 1280x720 frame of each method (evaluate.time_720p), "
                        "in one run, and its ratio to oidn-frame's")
    args = p.parse_args(argv)
    folders = sequence_dirs(args.data.expanduser(), args.split, args.renderer, args.spp)
    folders = folders[: args.sequences] if args.sequences else folders
    if not folders:
        print(f"no finished {args.renderer} {args.split} sequences under {args.data}",
              file=sys.stderr)
        return 1
    locked_off = args.split.endswith("-static")
    methods = candidate_methods(args.threads, args.renderer, args.resampled_weights)
    if args.only:
        keep = {*BASELINES, *args.only.split(",")}
        methods = {k: v for k, v in methods.items() if k in keep}
    if args.timing:
        ms = {name: time_720p(factory, args.threads) for name, factory in methods.items()}
        print("| method | ms per 720p frame | ÷ oidn-frame |\n|---|---|---|")
        for name, value in ms.items():
            print(f"| {name} | {value:.0f} | {value / ms['oidn-frame']:.2f} |")
        print()
    rows = []
    for spp in args.spp:
        sequences = [planar_frames(load_sequence(f, spp)) for f in folders]
        for name, factory in methods.items():
            method, scores = factory(), Scores()
            give_header_spp(method, args.renderer, spp)
            for frames in sequences:
                run_sequence(method, frames, scores, None, locked_off)
            rows.append({"method": name, "spp": spp, **scores.summary()})
    print_rows(rows, f"{args.renderer} {args.split}: {len(folders)} sequence(s) "
                     f"({', '.join(f.name for f in folders)})", locked_off)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0

if __name__ == "__main__":
    raise SystemExit(main())
