"""Model cards: a markdown file next to each shipped .onnx, written from its ModelCard.

The markdown repeats what the file's card says (runtime/card.py: architecture, composition,
tiling, training, measured tables per renderer) and adds the speed measured on this machine
through the shipped runtime, so the markdown and the file can never disagree.
"""

from __future__ import annotations

import json
from pathlib import Path

from quietframe.bench.synthetic import cpu_peak_gflops, frame_buffers
from quietframe.bench.timing import time_ms
from quietframe.runtime import Denoiser
from quietframe.runtime.card import GraphStage, ModelCard, OIDNStage


def measure_720p_ms(runtime: Denoiser) -> float:
    """Median ms per 1280×720 frame through the runtime, history carried (bench/timing.py)."""
    buffers = frame_buffers()
    state = runtime.denoise(buffers, None).state
    return time_ms(lambda: runtime.denoise(buffers, state),
                   warmup=1, repeats=5).median_ms


def describe_split(root: Path) -> str:
    """One line on a rendered split, read from its manifests (docs/data.md)."""
    manifests = [json.loads(p.read_text()) for p in sorted(root.glob("*/manifest.json"))]
    if not manifests:
        return f"`{root}`: not present on the machine that wrote this card"
    frames = sum(m["frame_count"] for m in manifests)
    sizes = sorted({f"{m['config']['width']}×{m['config']['height']}" for m in manifests})
    levels = sorted({s for m in manifests for s in m["config"]["spp_levels"]})
    refs = sorted({m["config"]["reference_spp"] for m in manifests})
    seeds = [m["seed"] for m in manifests]
    return (f"{len(manifests)} sequences (seeds {min(seeds)}–{max(seeds)}, generator "
            f"{manifests[0].get('generator', '?')}), {frames} frames, {', '.join(sizes)}, inputs "
            f"at {levels} spp, references at {refs} spp")


def data_lines(training: dict) -> list[str]:
    if "data" not in training:
        return []
    from quietframe.scenes.layout import split_dir

    data = Path(training["data"]).expanduser()
    return ["## Data", "",
            f"- train (as on disk when this card was written; a run started while the split "
            f"was still rendering saw fewer): {describe_split(split_dir(data, 'train'))}",
            f"- validation (never trained on; picks `best.pt`): "
            f"{describe_split(split_dir(data, 'validation'))}", ""]


def prepass_lines(runtime: Denoiser, threads: int) -> list[str]:
    """For a composition (an OIDN stage): what runs first, and the 720p time split."""
    settings = runtime.card.prepass
    if settings is None:
        return []
    from quietframe.bench.oidn_temporal import measure

    t = measure(runtime.info.path, threads, repeats=3)
    first = [s.file for s in runtime.card.stages if isinstance(s, GraphStage) and s.file]
    source = (f"on the output of `{first[0]}` (run first, with its own state)"
              if first else "on the frame")
    graph = ("then the graph on its output" if "reset" in runtime.input_names
             else "and returns its output (no learned stage)")
    return [f"Runs Open Image Denoise {source} (quality {settings.quality}, prefiltered "
            f"aux {settings.prefilter_aux}; needs pyoidn), {graph}: OIDN "
            f"{t['oidn'].median_ms:.0f} ms, quietframe's part (the `color_from` model and the "
            f"graph) {t['stage'].median_ms:.0f} ms "
            f"({100 * t['stage'].median_ms / t['oidn'].median_ms:.0f}% of OIDN), median of 3 "
            "(bench/oidn_temporal.py).", ""]


def stage_text(stage: GraphStage | OIDNStage) -> str:
    if isinstance(stage, OIDNStage):
        return (f"OIDN ({stage.quality}, prefiltered aux {stage.prefilter_aux}) -> graph input "
                f"`{stage.input}`")
    if not stage.file:
        return "this file's graph"
    return f"`{stage.file}` (state under `{stage.namespace}.`)"


def card_lines(card: ModelCard) -> list[str]:
    """Composition, tiling and the measured tables per renderer, from the card."""
    lines = ["## Composition and tiling", "",
             f"Stages: {' -> '.join(stage_text(s) for s in card.stages)}. "
             f"State: {[f'{s.name} ({s.channels} ch, 1/{s.scale})' for s in card.state]}.", ""]
    tiling = card.tiling
    if tiling is None:
        lines += ["No tiling rule knows this graph: frames run whole.", ""]
    else:
        reach = "".join(f"; + {r} px by {name}" for name, table in tiling.reach.items()
                        for r in [", ".join(f"{v}: {x}" for v, x in table.items())])
        stats = ", ".join(f"{s.name} ({s.how})" for s in tiling.statistics) or "none"
        lines += [f"Tiles: receptive radius {tiling.radius} px{reach}, origins on multiples "
                  f"of {tiling.align} px, overlap + max |motion| + 1 "
                  f"{'(warps history)' if tiling.motion else '(no warp)'}; frame-wide "
                  f"statistics: {stats}; ~{tiling.bytes_per_pixel} B per tile pixel "
                  "(tile size = max_memory_mb / that, runtime/tiling.py).", ""]
    for renderer, table in card.measurements.items():
        if table.complete:
            rows = ", ".join(f"{r.spp:g} spp {r.psnr:.2f} dB" for r in table.by_spp)
            lines += [f"Measured on {renderer} frames (what `auto` reads): {rows}; "
                      f"{table.ms_720p} ms at 720p.", ""]
    return lines


def write_model_card(path: Path, evaluation: dict | None = None, threads: int = 2,
                     split: str = "") -> Path:
    """Write <model>.md beside `path`; `evaluation` = rows of quietframe-eval for this model,
    measured on `split` (named in the card: test figures are reported, validation ones chose)."""
    runtime = Denoiser(path, threads=threads)
    info = runtime.info
    ms = measure_720p_ms(runtime)
    lines = [
        f"# {info.name} (version {info.version})", "",
        f"File: `{path.name}` ({path.stat().st_size / 1024:.0f} KiB). "
        f"Needs buffers {list(info.required_buffers)}; optional {list(info.optional_buffers)}"
        " (missing motion = static camera).", "",
        "## Architecture", "", "```json",
        json.dumps(dict(runtime.card.architecture), indent=1),
        "```", "", *card_lines(runtime.card),
        "## Training", "", "```json", json.dumps(info.training, indent=1), "```", "",
        *data_lines(info.training),
        "## Speed", "",
        f"{ms:.0f} ms per 1280×720 frame through quietframe.runtime with {threads} threads on "
        f"{cpu_peak_gflops(threads)[1]}, median of 5 (bench/timing.py).", "",
        *prepass_lines(runtime, threads),
        f"## Quality ({split} split)" if split else "## Quality", "",
    ]
    rows = evaluation or []
    if rows:
        lines += ["| spp | PSNR | SSIM | SMAPE | relMSE | TRMAE |", "|---|---|---|---|---|---|"]
        lines += [f"| {r['spp']} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['smape']:.4f} | "
                  f"{r['relmse']:.4f} | {r['trmae']:.4f} |" for r in rows]
        lines += ["", f"From `quietframe-eval`{f' on the {split} split' if split else ''} "
                  "(docs/benchmarks.md)."]
    else:
        lines.append(f"Metadata metrics: `{json.dumps(info.metrics)}` (no evaluation run given).")
    card = path.with_suffix(".md")
    card.write_text("\n".join(lines) + "\n")
    return card
