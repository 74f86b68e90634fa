"""Model cards: a markdown file next to each shipped .onnx, written from its ModelCard.

    python -m quietframe.bench.model_card models/*.onnx [--evaluation RUN.json] [--measure]
    python -m quietframe.bench.model_card --stamp --evaluation VALIDATION.json [--renderer R]
        [--static-evaluation S.json] [--timing T.json] [--absent A.json]
        [--noise-points P.json] [--measured-as METHOD] [--no-card] models/*.onnx
    python -m quietframe.bench.model_card --zoo zoo.json --no-card models/*.onnx
    python -m quietframe.bench.model_card models/*.onnx --input-margin zoo1.json zoo3.json

The markdown repeats what the file's card says (runtime/card.py: architecture, composition,
tiling, training, measured tables per renderer) and adds the speed measured on this machine
through the shipped runtime, so the markdown and the file can never disagree. `--stamp` first
writes the measured tables `model=auto` reads into the files (bench/model_metrics.py), `--zoo`
how each model held on the validation zoo (bench/zoo_stamp.py), `--input-margin` how it compared
with its own noisy input there (bench/input_margin_stamp.py); `--no-card` stops there. Without
`--measure` the markdown quotes the cards' speed: re-writing it measures nothing.
"""

from __future__ import annotations

import argparse
import json
from functools import partial
from pathlib import Path

from quietframe.bench import cli_args
from quietframe.bench.input_margin_stamp import stamp_input_margin
from quietframe.bench.model_metrics import RunProblem, TableRuns, card_of, stamp_tables
from quietframe.bench.oidn_temporal import measure as time_stages
from quietframe.bench.synthetic import cpu_peak_gflops, frame_buffers
from quietframe.bench.timing import time_ms
from quietframe.bench.zoo_stamp import stamp_zoo
from quietframe.runtime import Denoiser
from quietframe.runtime.card import (
    GraphStage,
    Measurements,
    ModelCard,
    OIDNStage,
    worse_than_input_from,
)
from quietframe.scenes.corpus_shots import corpus_dir
from quietframe.scenes.layout import RENDERERS, split_dir


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


def data_lines(training: dict, previous: list[str] = (), metrics: dict | None = None
               ) -> list[str]:
    """The training data's splits as on disk, one line per split and source the run read (the
    `renderers` of its config, and the Cycles training corpus with `corpus`); a split not on
    this machine keeps the line an earlier card (`previous`, its lines) wrote where the data
    was. `metrics`: the run's notes; a run that validated on nothing (`val_sequences` 0) says so
    instead of naming a split it never saw, and one that picked `best.pt` on shots (the zoo's
    or the corpus's validation shots, `selected_on`) says which and what they scored."""
    if "data" not in training:
        return []
    data = Path(training["data"]).expanduser()
    renderers = [r.strip() for r in str(training.get("renderers", "mitsuba")).split(",")
                 if r.strip()]
    sources = [(r, partial(split_dir, data, renderer=r)) for r in renderers]
    if training.get("corpus"):
        sources.append(("corpus", partial(corpus_dir, data)))
    metrics = metrics or {}
    unvalidated = metrics.get("val_sequences") == 0 and "selected_on" not in metrics
    lines = ["## Data", ""]
    picks = "" if "selected_on" in metrics else "; picks `best.pt`"
    for split, note in (("train", " (as on disk when this card was written; a run started "
                                  "while the split was still rendering saw fewer)"),
                        ("validation", f" (never trained on{picks})")):
        if split == "validation" and unvalidated:
            lines.append("- validation: none on the machine during the run, so `best.pt` is its "
                         "last step (nothing was selected)")
            continue
        for source, root_of in sources:
            name = f"- {split}" + (f", {source}" if len(sources) > 1 else "")
            root = root_of(split)
            kept = [line for line in previous if line.startswith((name + " ", name + ":"))]
            present = any(root.glob("*/manifest.json"))
            lines.append(f"{name}{note}: {describe_split(root)}" if present or not kept
                         else kept[0])
    if "selected_on" in metrics:
        lines.append(f"- `best.pt` (step {metrics.get('step', '?')}) was picked on the "
                     f"{metrics['selected_on']} validation shots through the runtime's stream "
                     f"(model/zoo_selection.py): mean PSNR {metrics.get('zoo_psnr', '?')} dB over "
                     f"{metrics.get('zoo_sequences', '?')} (shot, spp) sequences")
    return [*lines, ""]


def prepass_lines(runtime: Denoiser, threads: int, measure: bool) -> list[str]:
    """For a composition (an OIDN stage): what runs first, and (measured) the 720p time
    split."""
    settings = runtime.card.prepass
    if settings is None:
        return []
    first = [s.file for s in runtime.card.stages if isinstance(s, GraphStage) and s.file]
    source = (f"on the output of `{first[0]}` (run first, with its own state)"
              if first else "on the frame")
    graph = ("then the graph on its output" if "reset" in runtime.input_names
             else "and returns its output (no learned stage)")
    line = (f"Runs Open Image Denoise {source} (quality {settings.quality}, prefiltered "
            f"aux {settings.prefilter_aux}; needs pyoidn), {graph}")
    if not measure:
        return [line + ".", ""]
    t = time_stages(runtime.info.path, threads, repeats=3)
    return [f"{line}: OIDN {t['oidn'].median_ms:.0f} ms, quietframe's part (the graphs) "
            f"{t['stage'].median_ms:.0f} ms "
            f"({100 * t['stage'].median_ms / t['oidn'].median_ms:.0f}% of OIDN), median of 3 "
            "(bench/oidn_temporal.py).", ""]


def speed_lines(runtime: Denoiser, threads: int, measure: bool) -> list[str]:
    """The 720p time: the card's (the evaluation run that measured the table `auto` reads)
    unless `measure` or the card has none; then measured now on this machine."""
    table = runtime.card.measured()
    if not measure and table.ms_720p is not None:
        run = table.measured
        where = ", ".join(f"{k} {run[k]}" for k in ("split", "threads", "machine") if k in run)
        return [f"{table.ms_720p:.0f} ms per 1280×720 frame through quietframe.runtime: the "
                f"card's figure, from the `quietframe-eval` run of its table ({where}).", "",
                *prepass_lines(runtime, threads, measure=False)]
    ms = measure_720p_ms(runtime)
    return [f"{ms:.0f} ms per 1280×720 frame through quietframe.runtime with {threads} threads "
            f"on {cpu_peak_gflops(threads)[1]}, median of 5 (bench/timing.py).", "",
            *prepass_lines(runtime, threads, measure=True)]


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
        reach = "".join(f" + its reach by {name} ({r} px)" for name, table in tiling.reach.items()
                        for r in [", ".join(f"{v}: {x}" for v, x in table.items())])
        stats = ", ".join(f"{s.name} ({s.how})" for s in tiling.statistics) or "none"
        lines += [f"Tiles: receptive radius {tiling.radius} px{reach}, origins on multiples "
                  f"of {tiling.align} px, "
                  f"{'overlap + max |motion| + 1 (warps history)' if tiling.motion else 'no warp'}"
                  "; frame-wide "
                  f"statistics: {stats}; graph working set ~{tiling.bytes_per_pixel} B/px "
                  "(a tile holds max_memory_mb / (that + its own inputs, state and output), "
                  "runtime/tiling.py).", ""]
    for renderer, table in card.measurements.items():
        if table.complete:
            rows = ", ".join(f"{r.spp:g} spp {r.psnr:.2f} dB"
                             + (f" (locked-off flicker {r.flicker:.4f})" if r.flicker else "")
                             for r in table.by_spp)
            lines += [f"Measured on {renderer} frames (what `auto` reads): {rows}; "
                      f"{table.ms_720p} ms at 720p.", ""]
        if table.zoo:
            rows = ", ".join(f"{r.spp:g} spp {r.gap_db:+.2f} dB (worst shot {r.worst_gap_db:+.2f})"
                             for r in table.zoo)
            short = ", ".join(f"{r.spp:g} spp {r.shortfall_db:+.2f}" for r in table.zoo
                              if r.shortfall_db < 0) or "none"
            worst = ", ".join(f"{r.spp:g} spp {r.worst_vs_denoise_db:+.2f}" for r in table.zoo
                              if r.worst_vs_denoise_db is not None)
            lines += [f"On the validation zoo ({renderer} shots from outside the scene "
                      f"generator, docs/zoo.md) against per-frame OIDN-high in the same run: "
                      f"{rows}. Taken off the table above by `auto` (shortfall against it): "
                      f"{short}."
                      + (f" Its worst shot against Blender's own denoise (what `auto` weighs "
                         f"so that no shot loses to it): {worst}." if worst else ""), ""]
        lines += input_margin_lines(table)
    return lines


def worth_using(table: Measurements) -> str:
    """Where the model is worth using against its own noisy input, one clause; "" where that
    was not measured."""
    rows = table.input_margin
    if not rows:
        return ""
    worse = worse_than_input_from(rows)
    span = f"{rows[0].spp:g}-{rows[-1].spp:g} spp"
    if worse is None:
        return (f"never worse than its noisy input on the validation zoo's worst shot over "
                f"{span}")
    return (f"worse than its noisy input from {worse:g} spp on the validation zoo's worst shot "
            f"(measured over {span}), so `auto` does not choose it from there")


def input_margin_lines(table: Measurements) -> list[str]:
    """The card's `input_margin`: per spp the worst shot's and the mean (model − noisy input)
    PSNR, and from which spp the model is worse than its input."""
    if not table.input_margin:
        return []
    rows = ", ".join(f"{r.spp:g} spp {r.worst_db:+.2f} dB (worst shot"
                     f"{' ' + r.worst_shot if r.worst_shot else ''}; mean {r.mean_db:+.2f})"
                     for r in table.input_margin)
    shots = ", ".join(table.input_margin_measured.get("shots") or ())
    return [f"Against its own noisy input on the validation zoo (output PSNR less the input's, "
            f"same frames{'; shots ' + shots if shots else ''}): {rows}. "
            f"It is {worth_using(table)}.", ""]


def role_lines(path: Path, card: ModelCard) -> list[str]:
    """What a learned tier (no OIDN stage) is for, in plain words, with its speed against
    per-frame OIDN-high (`oidn-frame` beside it) and its zoo figures."""
    if card.prepass is not None:
        return []
    table = card.measured("cycles")
    baseline = path.with_name("oidn-frame.onnx")
    speed = ""
    if baseline.is_file() and table.ms_720p:
        oidn = card_of(baseline).measured("cycles").ms_720p
        if oidn:
            ratio = oidn / table.ms_720p
            speed = (f", about {ratio:.1f}× faster than OIDN-high at 720p" if ratio >= 1
                     else f" (about {1 / ratio:.1f}× slower than OIDN-high at 720p)")
    worst = min((r.worst_gap_db for r in table.zoo), default=None)
    mean = [r.gap_db for r in table.zoo]
    fall = (f" It falls short on content unlike the scene generator's: on the validation zoo "
            f"it is {max(mean):+.1f} to {min(mean):+.1f} dB against per-frame OIDN-high over "
            f"1-64 spp, {worst:+.1f} dB on its worst shot, so `auto` does not choose it for "
            f"final frames." if mean else "")
    worth = worth_using(table)
    corpus = " and its Cycles training corpus" if card.training.get("corpus") else ""
    kind = (f"a learned tier trained on quietframe's scene generator{corpus}"
            if card.training.get("trained", True)
            else "no network, the temporal accumulation of the noisy frames alone")
    return ["## What it is for", "",
            f"Previews{speed}: {kind}.{fall}"
            f"{f' It is {worth}.' if worth else ''} "
            "For final frames use the OIDN tiers (or `auto`).", ""]


def quality_section(previous: list[str]) -> list[str]:
    """An earlier card's quality table (its `## Quality` section to the end), if it had one."""
    start = next((i for i, line in enumerate(previous) if line.startswith("## Quality")), None)
    if start is None or not any(line.startswith("| spp |") for line in previous[start:]):
        return []
    return previous[start:]


def write_model_card(path: Path, evaluation: list[dict] | None = None, threads: int = 2,
                     split: str = "", measure: bool = False, renderer: str = "",
                     source: str = "") -> Path:
    """Write <model>.md beside `path`; `evaluation` = rows of quietframe-eval for this model,
    measured on `split` (named in the card: test figures are reported, validation ones chose;
    none given: an earlier card's quality table is kept);
    `measure`: time the model now instead of quoting the card's measured 720p time;
    `renderer`: whose frames the split is (named in the card when given);
    `source`: the evaluation file the rows come from (cited in the card)."""
    runtime = Denoiser(path, threads=threads)
    info = runtime.info
    card = path.with_suffix(".md")
    previous = card.read_text().splitlines() if card.is_file() else []
    lines = [
        f"# {info.name} (version {info.version})", "",
        f"File: `{path.name}` ({path.stat().st_size / 1024:.0f} KiB). "
        f"Needs buffers {list(info.required_buffers)}; optional {list(info.optional_buffers)}"
        " (missing motion = static camera).", "",
        "## Architecture", "", "```json",
        json.dumps(dict(runtime.card.architecture), indent=1),
        "```", "", *role_lines(path, runtime.card), *card_lines(runtime.card),
        "## Training", "", "```json", json.dumps(info.training, indent=1), "```", "",
        *data_lines(info.training, previous, info.metrics),
        "## Speed", "", *speed_lines(runtime, threads, measure),
        f"## Quality ({' '.join(filter(None, (renderer, split)))} split)" if split
        else "## Quality", "",
    ]
    rows = evaluation or []
    if rows:
        lines += ["| spp | PSNR | SSIM | SMAPE | relMSE | TRMAE |", "|---|---|---|---|---|---|"]
        lines += [f"| {r['spp']} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['smape']:.4f} | "
                  f"{r['relmse']:.4f} | {r['trmae']:.4f} |" for r in rows]
        on = " ".join(filter(None, (renderer, split)))
        lines += ["", f"From `quietframe-eval`{f' on the {on} split' if split else ''}"
                  f"{f' ({source})' if source else ''}."]
    elif kept := quality_section(previous):  # re-written after a stamp: its table stays
        lines = lines[:-2] + kept
    else:
        lines.append(f"Metadata metrics: `{json.dumps(info.metrics)}` (no evaluation run given).")
    card.write_text("\n".join(lines) + "\n")
    return card


STAMP_RUNS = ("renderer", "static_evaluation", "timing", "absent", "noise_points")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="model_card", description=__doc__.split("\n")[0])
    parser.add_argument("models", type=Path, nargs="+")
    parser.add_argument("--evaluation", type=Path,
                        help="quietframe-eval JSON: the card's quality rows (with --stamp, the "
                             "measured table's too)")
    parser.add_argument("--measure", action="store_true",
                        help="time each model now instead of quoting its card's 720p time")
    cli_args.add_threads(parser)
    parser.add_argument("--measured-as", metavar="METHOD",
                        help="the method name the runs measured the (one) model under: a "
                             "candidate installed under the shipped name")
    parser.add_argument("--no-card", action="store_true",
                        help="stamp only: leave the markdown cards as they are")
    stamping = parser.add_argument_group(
        "stamping", "measured tables written into the model files before the cards (what "
        "`model=auto` reads; bench/model_metrics.py, bench/zoo_stamp.py)")
    stamping.add_argument("--stamp", action="store_true",
                          help="stamp --evaluation's rows into each model's table")
    stamping.add_argument("--renderer", choices=RENDERERS,
                          help="whose frames the runs measured, the table stamped (default: "
                               "the renderer --evaluation ran on; every run must agree)")
    stamping.add_argument("--static-evaluation", type=Path,
                          help="benchmarks.json of a run on locked-off shots: flicker per spp")
    stamping.add_argument("--timing", type=Path,
                          help="benchmarks.json whose ms_720p is stamped instead of the "
                               "evaluation's (a quiet timing run)")
    stamping.add_argument("--absent", type=Path,
                          help="auto_choice.json: per-model PSNR change with each buffer absent")
    stamping.add_argument("--noise-points", type=Path,
                          help="auto_choice.json of a validation run: by_noise points per model")
    stamping.add_argument("--zoo", type=Path,
                          help="zoo.json of bench/zoo_eval.py --split validation: each model's "
                               "zoo rows, after --stamp (give oidn-frame.onnx too)")
    stamping.add_argument("--input-margin", type=Path, nargs="+", action="extend",
                          metavar="RUN.json",
                          help="zoo.json runs of bench/zoo_eval.py --split validation with the "
                               "`noisy` method: each model's margin over its own input, the "
                               "runs joined by shot (give the models before this flag)")
    args = parser.parse_args(argv)
    onnx_runs = [str(p) for p in args.input_margin or () if p.suffix == ".onnx"]
    if onnx_runs:
        parser.error(f"--input-margin takes zoo.json runs, got {', '.join(onnx_runs)}: give the "
                     "models before --input-margin (or after `--`)")
    if args.measured_as and len(args.models) != 1:
        parser.error("--measured-as names one model's rows: give exactly one model")
    if args.stamp and not args.evaluation:
        parser.error("--stamp stamps --evaluation's rows: give --evaluation")
    given = [f"--{k.replace('_', '-')}" for k in STAMP_RUNS if getattr(args, k)]
    if given and not args.stamp:
        parser.error(f"{', '.join(given)}: only with --stamp")
    if args.no_card and not (args.stamp or args.zoo or args.input_margin):
        parser.error("--no-card: nothing to do without --stamp, --zoo or --input-margin")
    return args


def stamp_models(args: argparse.Namespace) -> None:
    """The stamping the flags ask for, before the cards: the tables, then the zoo rows (whose
    shortfall is measured against the tables). Nothing is written where a run cannot make its
    table (RunProblem)."""
    if args.stamp:
        runs = TableRuns(args.evaluation, args.static_evaluation, args.timing, args.absent,
                         args.noise_points)
        print("\n".join(stamp_tables(args.models, runs, args.renderer, args.measured_as)))
    if args.zoo:
        print("\n".join(stamp_zoo(args.zoo, args.models)))
    if args.input_margin:
        print("\n".join(stamp_input_margin(args.input_margin, args.models)))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        stamp_models(args)
    except RunProblem as problem:
        raise SystemExit(f"model_card: error: {problem}") from None
    if args.no_card:
        return 0
    evaluation = json.loads(args.evaluation.read_text()) if args.evaluation else {}
    meta = evaluation.get("meta", {})
    for path in args.models:
        method = args.measured_as or path.stem
        rows = sorted((r for r in evaluation.get("rows", []) if r["method"] == method),
                      key=lambda r: r["spp"])
        card = write_model_card(path, rows, args.threads, meta.get("split", ""), args.measure,
                                meta.get("renderer", ""),
                                str(args.evaluation) if args.evaluation else "")
        print(f"wrote {card}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
