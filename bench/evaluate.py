"""quietframe-eval: every method on the validation sequences through the same loader.

    quietframe-eval [--split validation] [--spp 1,2,4,8] [--threads 2] [--out docs]
    quietframe-eval --compare RUN.json [--static STATIC.json] [--against a,b] [--wide]

Methods: the noisy input, temporal accumulation alone (models/accumulation.onnx: the NBG
pre-stage), an SVGF-style à-trous filter, Open Image Denoise (fast/balanced/high, high with
prefiltered aux), and every shipped model through the runtime (onnxruntime + custom ops): NBG,
the affinity model, and the oidn-temporal tier (OIDN prepass + temporal graph; its 720p time is
also split into OIDN's share and the temporal stage's, bench/oidn_temporal.py). A model the
runtime cannot run here (oidn-temporal without pyoidn) is skipped with a line.
`--kernel-sizes 5,9,13` adds rows `<model>@k<size>` for models with a run-time kernel size (the
affinity tier); `--single-frame <model>` adds `<model>/frame`, its history cleared every frame.
Per method and spp: PSNR, SSIM, SMAPE, relMSE (mean over frames), TRMAE (mean over sequences),
ms/frame at the evaluation resolution and at 1280×720 — one run, same machine, same threads.
Writes <out>/benchmarks.md, <out>/psnr_vs_ms.png and <out>/crops.png. `--compare` evaluates
nothing: it prints the temporal tiers' targets table of earlier runs (bench/compare_table.py).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from quietframe.bench import baselines, cli_args, compare_table
from quietframe.bench.auto_method import AutoMethod
from quietframe.bench.harness import (
    FRAME_METRICS,
    Frames,
    ImageMethod,
    RuntimeMethod,
    SequenceScore,
    planar_frames,
    score_sequence,
)
from quietframe.bench.oidn_temporal import measure
from quietframe.bench.sid_temporal import SIDTemporal
from quietframe.bench.synthetic import cpu_peak_gflops, frame_buffers
from quietframe.bench.timing import time_ms
from quietframe.model import metrics
from quietframe.runtime import Denoiser, installed_models
from quietframe.runtime.buffers import FORWARD
from quietframe.runtime.oidn_prepass import PrepassUnavailable
from quietframe.scenes import cycles_io
from quietframe.scenes.exr_io import color_layer, load_frame, read_meta
from quietframe.scenes.layout import split_dir
from quietframe.service.frame_evidence import RENDERERS_STATING_SPP as HEADER_STATES_SPP

AUX = ("albedo", "normal", "depth", "motion")
STORED_BLENDER = "blender_denoise"  # a stored output in a Cycles frame's buffers, not an input


def give_header_spp(method, renderer: str, spp: float) -> None:
    """Tell a method that takes the frame's spp (auto, oidn-history*: `header_spp`) the spp the
    header states, as the service would, where `renderer`'s headers state one."""
    if hasattr(method, "header_spp") and renderer in HEADER_STATES_SPP:
        method.header_spp = spp


def model_variants(path: Path, threads: int, kernel_sizes: tuple[int, ...],
                   single_frame: bool, renderer: str | None = None,
                   rendered_only: bool = False) -> dict[str, Callable[[], object]]:
    """Extra methods of one model: `<name>@k<size>` per requested kernel size the model accepts
    other than its default (models without a kernel_size input get none), and for a model
    that keeps state `<name>/frame` (history cleared every frame) when `single_frame` and
    `<name>/rendered-only` (no motion estimated from the aux: a moving frame without vectors
    starts the history afresh, the session field `motion: rendered-only`) and
    `<name>/estimated` (the shot's vectors withheld: its history follows motion estimated from
    the aux, as on a motion-blurred shot) when `rendered_only`."""
    info = Denoiser(path, threads=1).info
    spec = next((i for i in info.inputs if i.name == "kernel_size"), None)
    methods: dict[str, Callable[[], object]] = {}
    if spec is not None:
        for k in kernel_sizes:
            if k != spec.default and (spec.allowed is None or k in spec.allowed):
                methods[f"{path.stem}@k{k}"] = lambda k=k: RuntimeMethod(
                    path, threads, {"kernel_size": k}, renderer=renderer)
    if single_frame and info.state_specs:
        methods[f"{path.stem}/frame"] = lambda: RuntimeMethod(path, threads, single_frame=True,
                                                              renderer=renderer)
    if rendered_only and info.state_specs:
        methods[f"{path.stem}/rendered-only"] = lambda: RuntimeMethod(
            path, threads, renderer=renderer, motion="rendered-only")
        methods[f"{path.stem}/estimated"] = lambda: RuntimeMethod(
            path, threads, renderer=renderer, withhold_vectors=True)
    return methods


class Noisy:
    """The input itself: the floor every method is measured against."""

    def reset(self) -> None:
        pass

    def __call__(self, planes: dict[str, np.ndarray]) -> np.ndarray:
        return planes["color"]


class BlenderDenoise:
    """What a Blender user gets by ticking Denoise: Cycles' own OIDN pass (Accurate prefilter,
    High quality) of the same render, stored with the Cycles splits (scenes/cycles_render.py).
    Its time is Blender's, not measured here."""

    reads_stored = True

    def reset(self) -> None:
        pass

    def __call__(self, planes: dict[str, np.ndarray]) -> np.ndarray:
        return planes[STORED_BLENDER]


def build_methods(threads: int, extra: list[Path] = (), kernel_sizes: tuple[int, ...] = (),
                  single_frame: tuple[str, ...] = (), renderer: str = "mitsuba",
                  rendered_only: tuple[str, ...] = ()) -> dict[str, Callable[[], object]]:
    """Method name -> factory (each sequence gets fresh state through reset()). `extra`: more
    .onnx files (e.g. fresh training runs), named by file stem. `kernel_sizes`,
    `single_frame` and `rendered_only` (model names) add model_variants. Cycles data adds
    Blender's denoise. Every OIDN call sees the rows in `renderer`'s order, as the service's
    does for its frames."""
    models = {p.stem: p for p in (*installed_models(), *extra)}
    methods: dict[str, Callable[[], object]] = {"noisy": Noisy}
    if renderer == "cycles":
        methods["blender-denoise"] = BlenderDenoise
    if "accumulation" in models:
        methods["accumulation"] = lambda: RuntimeMethod(models["accumulation"], threads,
                                                        renderer=renderer)
    methods["svgf"] = lambda: ImageMethod(baselines.SVGFStyleFilter(num_threads=threads))
    for quality in ("fast", "balanced", "high"):
        methods[f"oidn-{quality}"] = (
            lambda q=quality: ImageMethod(baselines.OIDNDenoiser(q, num_threads=threads,
                                                                 renderer=renderer)))
    methods["oidn-high-cleanaux"] = lambda: ImageMethod(baselines.OIDNDenoiser(
        "high", prefilter_aux=True, num_threads=threads, renderer=renderer))
    for aux_quality in ("fast", "balanced"):  # a cheaper prefilter of the aux alone
        methods[f"oidn-high-cleanaux-{aux_quality}"] = lambda q=aux_quality: ImageMethod(
            baselines.OIDNDenoiser("high", prefilter_aux=True, num_threads=threads,
                                   aux_quality=q, renderer=renderer))
    # the SID add-on's temporal mode: its defaults (fake motion blur on), and without the blur
    methods["sid-temporal-default"] = lambda: SIDTemporal(num_threads=threads, renderer=renderer)
    methods["sid-temporal"] = lambda: SIDTemporal(motion_blur=False, num_threads=threads,
                                                  renderer=renderer)
    if models:  # the service's choice among the installed models (bench/auto_method.py)
        installed = {p.stem: p for p in installed_models()}
        methods["auto"] = lambda: AutoMethod(installed, threads, renderer)
    for name, path in models.items():
        if name != "accumulation":
            methods[name] = lambda p=path: RuntimeMethod(p, threads, renderer=renderer)
        if kernel_sizes or name in single_frame or name in rendered_only:
            methods |= model_variants(path, threads, kernel_sizes, name in single_frame,
                                      renderer, name in rendered_only)
    return methods


def sequence_dirs(data: Path, split: str, renderer: str = "mitsuba",
                  spp_levels: tuple[int, ...] = ()) -> list[Path]:
    """Sequence folders of a split; of a Cycles split only those finished at `spp_levels`."""
    root = split_dir(data, split, renderer)
    folders = sorted(p.parent for p in root.glob("*/manifest.json"))
    if renderer == "cycles":
        folders = [f for f in folders if cycles_io.finished(f, spp_levels)]
    return folders


def load_sequence(folder: Path, spp: int, forward: bool = False
                  ) -> list[tuple[dict, np.ndarray, bool]]:
    """[(buffers, reference, reset)] for every frame of a sequence at `spp`. A Cycles frame's
    buffers also hold Blender's own denoise of it (STORED_BLENDER) and with `forward` its motion
    to the next frame (FORWARD, where the renderer wrote one: only a look-ahead reads it)."""
    if cycles_io.is_cycles_sequence(folder):
        resets = cycles_io.frame_resets(folder)
        frames = []
        for t, reset in enumerate(resets):
            f = cycles_io.load_frame(folder, t, spp)
            buffers = {k: f[k] for k in ("color", *AUX, STORED_BLENDER)}
            if forward and (motion := cycles_io.load_forward(folder, t, spp)) is not None:
                buffers[FORWARD] = motion
            frames.append((buffers, f["reference"], reset))
        return frames
    frames = []
    for path in sorted(folder.glob("frame_*.exr")):
        layers = load_frame(path, [color_layer(spp), "reference", *AUX])
        buffers = {"color": layers[color_layer(spp)], **{k: layers[k] for k in AUX}}
        frames.append((buffers, layers["reference"], bool(read_meta(path).get("reset"))))
    return frames


@dataclass
class Scores:
    """One method's sequences at one spp, gathered for its row."""

    per_frame: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    trmae: list[float] = field(default_factory=list)
    flicker: list[float] = field(default_factory=list)
    ms: list[float] = field(default_factory=list)

    def add(self, sequence: SequenceScore) -> None:
        for name, values in sequence.per_frame.items():
            self.per_frame[name] += values
        self.trmae.append(sequence.trmae)
        if sequence.flicker is not None:
            self.flicker.append(sequence.flicker)
        self.ms += sequence.ms

    def summary(self) -> dict[str, float]:
        out = {k: float(np.mean(v)) for k, v in self.per_frame.items()}
        out["trmae"] = float(np.mean(self.trmae)) if self.trmae else float("nan")
        out["flicker"] = float(np.mean(self.flicker)) if self.flicker else float("nan")
        out["ms"] = float(np.median(self.ms))
        return out


def run_sequence(method, frames: Frames, scores: Scores, keep: list | None = None,
                 locked_off: bool = False) -> None:
    """Score `method` over one sequence of planar frames (harness.score_sequence, every frame
    metric); `locked_off` (a static shot) also scores flicker. Only a method that reads a
    stored output (Blender's denoise) is given it."""
    inputs = None if getattr(method, "reads_stored", False) else _inputs
    if getattr(method, "reads_forward", False):  # a look-ahead (bench/lookahead_method.py)
        inputs = _inputs_with_forward
    if hasattr(method, "look_ahead"):  # non-causal (sid_temporal.py): frame t+1 rides with t
        frames = method.look_ahead(frames)
    sequence = score_sequence(method, frames, tuple(FRAME_METRICS), locked_off, inputs)
    scores.add(sequence)
    if keep is not None:
        keep.append(sequence.outputs[-1])


def _inputs(planes: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: v for k, v in planes.items() if k not in (STORED_BLENDER, FORWARD)}


def _inputs_with_forward(planes: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: v for k, v in planes.items() if k != STORED_BLENDER}


def prepass_shares(method, threads: int) -> dict[str, float]:
    """For a composition (prepass + graph): 720p ms of OIDN alone and of the graph alone."""
    denoiser = getattr(method, "denoiser", None)
    if denoiser is None or denoiser.prepass is None:
        return {}
    timings = measure(denoiser.info.path, threads, repeats=3)
    return {"ms_720p_oidn": timings["oidn"].median_ms,
            "ms_720p_stage": timings["stage"].median_ms}


def time_720p(factory, threads: int) -> float:
    """ms/frame at 1280×720 on synthetic buffers, state carried like a real sequence (nan for
    a stored output, whose time is the renderer's, and for auto, whose time is its choice's)."""
    method = factory()
    if getattr(method, "reads_stored", False) or getattr(method, "chooses", False):
        return float("nan")
    buffers = frame_buffers()  # (C, H, W) planes
    method.reset()
    method(buffers)
    return time_ms(lambda: method(buffers), warmup=1, repeats=3).median_ms


def scatter_plot(rows: list[dict], path: Path, split: str = "validation") -> None:
    """PSNR against 720p ms per method and spp; methods that cost nothing (the noisy input)
    are left out: on the log axis they would squeeze every denoiser into one corner."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    markers = "os^vD<>pP*hX"
    rows = [r for r in rows if r["ms_720p"] >= 1]
    for i, name in enumerate(sorted({r["method"] for r in rows})):
        mine = [r for r in rows if r["method"] == name]
        ax.scatter([r["ms_720p"] for r in mine], [r["psnr"] for r in mine],
                   marker=markers[i % len(markers)], label=name)
        for r in mine:
            ax.annotate(f"{r['spp']}", (r["ms_720p"], r["psnr"]), fontsize=7,
                        xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("ms per 1280×720 frame (log scale; this machine)")
    ax.set_ylabel(f"PSNR dB on τ-mapped images ({split} split)")
    ax.set_title("Speed vs error (label = spp)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def crop_sheet(crops: dict[str, list[np.ndarray]], columns: list[str], path: Path,
               size: int = 96) -> None:
    """One row per sequence: the centre crop of the last frame of each method (τ-mapped)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = len(crops[columns[0]])
    fig, axes = plt.subplots(rows, len(columns), figsize=(1.8 * len(columns), 1.9 * rows),
                             squeeze=False)
    for r in range(rows):
        for c, name in enumerate(columns):
            image = crops[name][r]
            h, w = image.shape[:2]
            y, x = max(0, h // 2 - size // 2), max(0, w // 2 - size // 2)
            axes[r][c].imshow(np.clip(metrics.tonemap_tau(image[y:y + size, x:x + size]), 0, 1))
            axes[r][c].set_xticks([])
            axes[r][c].set_yticks([])
            if r == 0:
                axes[r][c].set_title(name, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _figure(value: float, spec: str) -> str:
    """A table cell: the figure, or a dash where it does not apply (nan)."""
    return "–" if np.isnan(value) else format(value, spec)


def write_report(rows: list[dict], meta: dict, path: Path) -> None:
    lines = ["# quietframe evaluation", "",
             f"Data: {meta['sequences']} {meta.get('renderer', 'mitsuba')} {meta['split']} "
             f"sequences ({meta['resolution']}), "
             f"{meta['frames']} frames each spp level; machine: {meta['machine']}. "
             f"Command: `{meta['command']}`.",
             "PSNR on τ(x) = (x/(1+x))^(1/2.4); TRMAE per Işık et al. eq. 16; ms = median "
             "per frame.", "",
             "| method | spp | PSNR | SSIM | SMAPE | relMSE | TRMAE | flicker | "
             "ms/frame (eval) | ms/frame 720p |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['spp']} | {r['psnr']:.2f} | {r['ssim']:.4f} | "
                     f"{r['smape']:.4f} | {r['relmse']:.4f} | {r['trmae']:.4f} | "
                     f"{_figure(r.get('flicker', np.nan), '.4f')} | {r['ms']:.1f} | "
                     f"{_figure(r['ms_720p'], '.0f')} |")
    shares = {r["method"]: r for r in rows if "ms_720p_oidn" in r}
    if shares:
        lines += ["", "720p time of the compositions (OIDN prepass + temporal graph):", "",
                  "| method | OIDN ms | temporal stage ms | stage / OIDN |", "|---|---|---|---|"]
        lines += [f"| {m} | {r['ms_720p_oidn']:.0f} | {r['ms_720p_stage']:.0f} | "
                  f"{100 * r['ms_720p_stage'] / r['ms_720p_oidn']:.1f}% |"
                  for m, r in shares.items()]
    lines += ["", "![PSNR vs ms](psnr_vs_ms.png)", "", "![crops](crops.png)", ""]
    path.write_text("\n".join(lines))


def parse_args(argv: list[str] | None) -> tuple[argparse.ArgumentParser, argparse.Namespace]:
    parser = argparse.ArgumentParser(prog="quietframe-eval", description=__doc__.split("\n")[0])
    cli_args.add_data(parser)
    cli_args.add_split(parser, help="train, validation or test, or the locked-off "
                                    "validation-static and test-static (flicker is scored)")
    cli_args.add_renderer(parser)
    parser.add_argument("--spp", default="", help="comma list (default: Mitsuba 1,2,4,8; "
                                                  "Cycles 1,2,4,8,16,64)")
    cli_args.add_threads(parser)
    parser.add_argument("--sequences", type=int, default=0, help="limit (0 = all)")
    parser.add_argument("--methods", default="", help="comma list (default: all)")
    parser.add_argument("--model", type=Path, action="append", default=[],
                        help="also evaluate this .onnx (named by its file stem); repeatable")
    parser.add_argument("--kernel-sizes", default="",
                        help="comma list: also rows <model>@k<size> for models with a run-time "
                             "kernel size (the affinity tier)")
    parser.add_argument("--single-frame", default="",
                        help="comma list of models: also rows <model>/frame, history cleared "
                             "every frame")
    parser.add_argument("--no-timing", action="store_true",
                        help="skip the 720p timing of each method (quality figures only; the "
                             "table shows – for ms/frame 720p)")
    parser.add_argument("--out", type=Path, default=Path("docs"))
    comparing = parser.add_argument_group(
        "compare", "instead of evaluating: the targets table of earlier runs' JSON, printed "
        "(bench/compare_table.py; --methods: the rows, default every method of the run)")
    comparing.add_argument("--compare", type=Path, metavar="RUN.json",
                           help="benchmarks.json of moving shots: each method against the "
                                "run's per-frame baselines")
    comparing.add_argument("--static", type=Path, metavar="STATIC.json",
                           help="benchmarks.json of locked-off shots: flicker against the "
                                "first baseline's")
    comparing.add_argument("--against", default=",".join(compare_table.DEFAULT_AGAINST),
                           help="the baselines, comma list (default %(default)s)")
    comparing.add_argument("--trmae", type=float, default=compare_table.TRMAE_TARGET,
                           help="TRMAE target, × the first baseline's (default %(default)s)")
    comparing.add_argument("--flicker", type=float, default=compare_table.FLICKER_TARGET,
                           help="flicker target, × the first baseline's (default %(default)s)")
    comparing.add_argument("--wide", action="store_true",
                           help="only PSNR by spp, one row per method, difference to the "
                                "first baseline")
    args = parser.parse_args(argv)
    if (args.static or args.wide) and not args.compare:
        parser.error("--static and --wide read an earlier run: give --compare RUN.json")
    return parser, args


def print_comparison(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """`--compare`: the targets table of earlier runs, nothing evaluated."""
    methods = [m for m in args.methods.split(",") if m]
    try:
        print(compare_table.table_text(args.compare, args.static, methods,
                                       args.against.split(","), args.trmae, args.flicker,
                                       args.wide))
    except ValueError as exc:
        parser.error(str(exc))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser, args = parse_args(argv)
    if args.compare:
        return print_comparison(parser, args)
    missing = [str(p) for p in args.model if not p.is_file()]
    if missing:
        raise SystemExit(f"--model: no such file {missing}")
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    spp_levels = tuple(int(s) for s in (
        args.spp or ("1,2,4,8,16,64" if args.renderer == "cycles" else "1,2,4,8")).split(","))
    folders = sequence_dirs(args.data.expanduser(), args.split, args.renderer, spp_levels)
    if args.sequences:
        folders = folders[: args.sequences]
    if not folders:
        raise SystemExit(f"no finished {args.renderer} {args.split} sequences under "
                         f"{args.data} (render them: docs/data.md)")
    locked_off = args.split.endswith("-static")
    kernel_sizes = tuple(int(k) for k in args.kernel_sizes.split(",") if k)
    single_frame = tuple(m for m in args.single_frame.split(",") if m)
    methods = build_methods(args.threads, args.model, kernel_sizes, single_frame, args.renderer)
    if args.methods:  # a listed model keeps its @k / /frame rows
        wanted = args.methods.split(",")
        methods = {k: v for k, v in methods.items() if re.split("[@/]", k)[0] in wanted}
    rows, crops, ms_720p = [], defaultdict(list), {}
    crop_spp = spp_levels[0]
    for spp in spp_levels:
        sequences = [planar_frames(load_sequence(f, spp)) for f in folders]
        for name, factory in list(methods.items()):
            try:
                method, scores = factory(), Scores()
            except PrepassUnavailable as exc:
                print(f"skipping {name}: {exc}", flush=True)
                del methods[name]
                continue
            give_header_spp(method, args.renderer, spp)
            for i, frames in enumerate(sequences):
                keep = crops[name] if spp == crop_spp and i < 3 else None
                run_sequence(method, frames, scores, keep, locked_off)
            if spp == crop_spp:
                crops["reference"] = [s[-1][1] for s in sequences[:3]]
            row = {"method": name, "spp": spp, **scores.summary()}
            if hasattr(method, "choices"):  # auto: the models it chose, shots each
                row["chosen"] = dict(method.choices)
            if name not in ms_720p and args.no_timing:
                ms_720p[name] = {"ms_720p": float("nan")}
            elif name not in ms_720p:  # speed does not depend on the spp: time once per method
                ms_720p[name] = {"ms_720p": time_720p(factory, args.threads),
                                 **prepass_shares(method, args.threads)}
            row |= ms_720p[name]
            rows.append(row)
            print(json.dumps({k: round(v, 4) if isinstance(v, float) else v
                              for k, v in row.items()}), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    first = sequences[0][0][1]
    meta = {"sequences": len(folders), "split": args.split, "renderer": args.renderer,
            "threads": args.threads,
            "resolution": f"{first.shape[1]}×{first.shape[0]}",
            "frames": sum(len(s) for s in sequences), "machine": cpu_peak_gflops(args.threads)[1],
            "command": "quietframe-eval " + " ".join(sys.argv[1:] if argv is None else argv)}
    (args.out / "benchmarks.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    write_report(rows, meta, args.out / "benchmarks.md")
    scatter_plot([r for r in rows if np.isfinite(r["ms_720p"])], args.out / "psnr_vs_ms.png",
                 f"{args.renderer} {args.split}")
    columns = [c for c in ("noisy", "accumulation", "svgf", "oidn-high", "blender-denoise",
                           *sorted(
        m for m in methods if m.startswith(("nbg", "affinity", "oidn-temporal"))
        and not re.search("[@/]", m)),
        "reference") if c in crops]
    crop_sheet(crops, columns, args.out / "crops.png")
    print(f"wrote {args.out / 'benchmarks.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
