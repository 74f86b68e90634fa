"""`model=auto` against every fixed model, on test sequences mixed in spp and in buffers.

    python -m quietframe.bench.auto_choice [--data ~/.cache/quietframe/data] [--split validation]
        [--threads 2] [--max-frames 8] [--sequences N] [--spp 1,4,16] [--out docs]
        [--model extra.onnx ...] [--buffer-sets all,no-albedo] [--no-absence] [--synthetic]

A test sequence is (rendered sequence, spp level, buffers present); the set is the cross product
of the split's sequences (finished or still rendering: the frames on disk), their spp levels
(the stored 1–8 and any added by `quietframe-render topup`, e.g. 16), and BUFFER_SETS. Every
installed model that accepts a sequence's buffers denoises it through the runtime (absent
optional buffers fed as zeros, as the service does); `auto` makes the service's choice
(service/choice_policy.choose) at the sequence's first frame, once with the spp a Cycles header
would state and once with the reference-free estimate, and its figures are those of the model it
chose on that sequence (plus the estimate's own time). Per sequence: PSNR and ms/frame of each;
the target is auto within 0.3 dB of the best fixed model on every sequence, at ≤ 60 % of the
average ms/frame of the best model (highest mean PSNR). The summary adds an oracle (the cheapest
model within 0.3 dB of each sequence's best): the floor of the ms share any rule can reach.

Run on the validation split (`--split validation --out docs/evaluation/auto_validation`), its
rows are what `bench/model_card.py --stamp --noise-points` stamps as each model's `by_noise` points
(the first frame's noise statistic, the model's PSNR on the sequence); only a test run updates
docs/benchmarks.md.

The buffer-absence table (`absence` in the JSON, docs/benchmarks.md): each model with each
buffer absent, fed as zeros (what a dropout-trained model saw in training), PSNR and TRMAE, next
to OIDN given the same buffers; `absent_db` (PSNR change per absent buffer) is what
bench/model_card.py --stamp --absent writes into a model's metadata.

--synthetic: tiny generated sequences instead (proves the harness; the figures mean nothing).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.baselines import OIDNDenoiser
from quietframe.bench.evaluate import AUX
from quietframe.bench.harness import (
    Frames,
    ImageMethod,
    Method,
    RuntimeMethod,
    planar_frames,
    score_sequence,
)
from quietframe.runtime import Denoiser, default_model_path, installed_models
from quietframe.scenes.exr_io import color_layer, load_frame, read_meta
from quietframe.scenes.stored_sequence import TOPUP_KEY
from quietframe.service.choice_policy import choose
from quietframe.service.model_profiles import ModelProfile, profile_of
from quietframe.service.noise_estimate import (
    NoiseLevel,
    estimate_spp,
    load_calibration,
    log2_statistic,
    noise_statistic,
)

BUFFER_SETS: dict[str, tuple[str, ...]] = {
    "all": ("color", *AUX),
    "no-motion": ("color", "albedo", "normal", "depth"),
    "no-albedo": ("color", "normal", "depth", "motion"),
    "colour-only": ("color",),
}
ABSENT = ("albedo", "normal", "depth", "motion")
# auto's acceptance target: within 0.3 dB of the best fixed model at <= 60% of its time
TOLERANCE_DB, SPEED_SHARE = 0.3, 0.6

# (buffers as (H, W, C) images, reference, reset): what the loaders give; planar_frames converts
ImageFrames = list[tuple[dict[str, np.ndarray], np.ndarray, bool]]


@dataclass
class Run:
    psnr: float
    trmae: float
    ms: float  # mean per frame


def load_frames(folder: Path, spp: int, max_frames: int) -> ImageFrames:
    frames = []
    for path in sorted(folder.glob("frame_*.exr"))[:max_frames]:
        layers = load_frame(path, [color_layer(spp), "reference", *AUX])
        buffers = {"color": layers[color_layer(spp)], **{k: layers[k] for k in AUX}}
        frames.append((buffers, layers["reference"], bool(read_meta(path).get("reset"))))
    return frames


def synthetic_frames(seed: int, spp: int, count: int = 3, size: int = 48) -> ImageFrames:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    albedo = np.repeat(rng.uniform(0.2, 0.9, (size, size, 1)), 3, -1).astype(np.float32)
    normal = np.dstack([np.zeros((size, size, 2)), np.ones((size, size))]).astype(np.float32)
    frames = []
    for t in range(count):
        shading = 0.3 + np.exp(-((xx - 0.3 - 0.05 * t) ** 2 + (yy - 0.5) ** 2) * 6)
        reference = (albedo * shading[..., None]).astype(np.float32)
        noise = rng.gamma(spp / 2, 2 / spp, (size, size, 1))
        buffers = {"color": (reference * noise).astype(np.float32), "albedo": albedo,
                   "normal": normal, "depth": np.full((size, size, 1), 3.0, np.float32),
                   "motion": np.zeros((size, size, 2), np.float32)}
        frames.append((buffers, reference, t == 0))
    return frames


def frame_noise(buffers: dict[str, np.ndarray]) -> dict[str, float | None]:  # planes
    """The first frame's noise statistic (log2), demodulated and of the colour alone: what
    bench/model_card.py --stamp --noise-points stamps as a model's by_noise points."""
    color, albedo = buffers["color"], buffers["albedo"]
    return {"log2_sigma": log2_statistic(noise_statistic(color, albedo)),
            "log2_sigma_colour": log2_statistic(noise_statistic(color, None))}


def run_model(method: Method, frames: Frames, present: tuple[str, ...]) -> Run:
    """One sequence through the harness's loop, the method given only the `present` buffers."""
    score = score_sequence(method, frames,
                           inputs=lambda planes: {k: v for k, v in planes.items() if k in present})
    return Run(score.mean("psnr"), score.trmae, float(np.mean(score.ms)))


def runtime_call(denoiser: Denoiser, zeros_for_required: bool = False) -> RuntimeMethod:
    """The runtime as a method; `zeros_for_required` feeds zeros for absent required buffers
    too (the absence table: what the model would see without them)."""
    return RuntimeMethod(denoiser, zeros_for_required=zeros_for_required)


def oidn_call(present: tuple[str, ...], threads: int) -> ImageMethod:
    """OIDN (balanced) given the same buffers: colour, + albedo, + normal (OIDN takes a normal
    only together with an albedo)."""
    aux = ("albedo", "normal") if {"albedo", "normal"} <= set(present) else (
        ("albedo",) if "albedo" in present else ())
    oidn = OIDNDenoiser("balanced", num_threads=threads, aux=aux)
    return ImageMethod(oidn, fill={"albedo": np.zeros_like, "normal": np.zeros_like,
                                   "depth": lambda c: np.ones_like(c[..., :1]),
                                   "motion": lambda c: np.zeros_like(c[..., :2])})


def parse_args(argv: list[str] | None) -> tuple[argparse.Namespace, dict[str, Path]]:
    """The arguments, and the models to run by name (installed, --model, cut to --only)."""
    parser = argparse.ArgumentParser(prog="auto_choice", description=__doc__.split("\n")[0])
    cli_args.add_data(parser)
    cli_args.add_split(parser)
    cli_args.add_threads(parser)
    parser.add_argument("--max-frames", type=int, default=8)
    parser.add_argument("--sequences", type=int, default=0,
                        help="the split's first N sequences only (0: all)")
    parser.add_argument("--spp", default="", help="spp levels to use, e.g. 1,4,16 (default: all)")
    parser.add_argument("--model", type=Path, action="append", default=[])
    parser.add_argument("--quality", default="balanced")
    parser.add_argument("--synthetic", action="store_true")
    parser.add_argument("--no-absence", action="store_true", help="skip the absence table")
    parser.add_argument("--buffer-sets", default=",".join(BUFFER_SETS),
                        help=f"comma list of {list(BUFFER_SETS)}")
    parser.add_argument("--only", default="",
                        help="comma list: run only these models (to measure a new model's "
                             "tables for bench/model_card.py --stamp; auto then chooses among "
                             "them)")
    parser.add_argument("--out", type=Path, default=Path("docs"))
    args = parser.parse_args(argv)
    unknown = [name for name in args.buffer_sets.split(",") if name not in BUFFER_SETS]
    if unknown:
        parser.error(f"--buffer-sets: unknown {unknown[0]!r}")
    paths = {p.stem: p for p in (*installed_models(), *args.model)}
    if args.only:
        unknown = sorted(set(args.only.split(",")) - set(paths))
        if unknown:
            parser.error(f"--only: no model {unknown}; known: {sorted(paths)}")
        paths = {name: paths[name] for name in args.only.split(",")}
    return args, paths


Source = tuple[str, list[int], object]  # (sequence name, spp levels, its folder or seed)


def sequence_sources(args: argparse.Namespace) -> tuple[list[Source], str]:
    """The test sequences' sources and the line that describes them in the results."""
    if args.synthetic:
        return ([(f"synthetic-{s}", [1, 4, 16], s) for s in (1, 2)],
                "synthetic sequences (48×48, 3 frames): proves the harness, no more")
    sources: list[Source] = []
    root = args.data.expanduser()
    folders = sorted(p.parent for p in root.glob(f"*/{args.split}/*/manifest.json"))
    wanted = {int(v) for v in args.spp.split(",")} if args.spp else None
    for folder in folders[:args.sequences or None]:
        manifest = json.loads((folder / "manifest.json").read_text())
        if any(folder.glob("frame_*.exr")):  # stored levels + topped-up ones (16 spp)
            levels = sorted(spp for spp in {*manifest["config"]["spp_levels"],
                                            *manifest.get(TOPUP_KEY, [])}
                            if wanted is None or spp in wanted)
            sources.append((folder.name, levels, folder))
    frames_used = sum(min(len(list(f.glob("frame_*.exr"))), args.max_frames)
                      for _, _, f in sources)
    levels = sorted({spp for _, spps, _ in sources for spp in spps})
    return sources, (f"rendered {args.data}/*/{args.split}: {len(sources)} sequences, "
                     f"{frames_used} frames in all (at most {args.max_frames} per sequence), "
                     f"each at every spp level of its sequence ({levels})")


@dataclass
class Chooser:
    """What `auto` chooses from, as the service has it."""

    denoisers: dict[str, Denoiser]
    profiles: list[ModelProfile]
    default: str  # the service's fallback for 'auto'
    calibration: dict | None
    quality: str


def choice_row(name: str, spp: int, frames: Frames, set_name: str, present: tuple[str, ...],
               looks: dict, chooser: Chooser) -> dict:
    """Every fixed model that accepts `present` on one sequence, and auto's choice with the
    spp a header states and with the estimate (its figures: its choice's, plus its time)."""
    fixed = {m: run_model(runtime_call(d), frames, present)
             for m, d in chooser.denoisers.items()
             if set(d.info.required_buffers) <= set(present)}
    row = {"sequence": name, "spp": spp, "buffers": set_name, "noise": looks,
           "fixed": {m: vars(r) for m, r in fixed.items()}}
    for mode in ("header", "estimate"):
        start = time.perf_counter()  # the service measures the statistic either way
        first = frames[0][0]
        albedo = first["albedo"] if "albedo" in present else None
        stated = NoiseLevel(spp, "header") if mode == "header" else None
        noise = estimate_spp(first["color"], albedo, chooser.calibration, header=stated)
        pick = choose(present, noise, chooser.profiles, chooser.default,
                      quality=chooser.quality,
                      pixels=frames[0][1].shape[0] * frames[0][1].shape[1])
        overhead = 1e3 * (time.perf_counter() - start) / len(frames)
        chosen = fixed.get(pick.model)
        row[f"auto_{mode}"] = {
            "model": pick.model, "spp": noise.spp, "reason": pick.reason,
            "psnr": chosen.psnr if chosen else None,
            "ms": chosen.ms + overhead if chosen else None,
        }
    print(json.dumps({k: row[k] for k in ("sequence", "spp", "buffers")}),
          {m: round(r.psnr, 2) for m, r in fixed.items()},
          row["auto_header"]["model"], row["auto_estimate"]["model"], flush=True)
    return row


def absence_entries(name: str, spp: int, frames: Frames, denoisers: dict[str, Denoiser],
                    threads: int) -> list[dict]:
    """Each model, and OIDN given the same buffers, with each buffer absent (fed as zeros)."""
    entries = []
    for missing in ("none", *ABSENT, "all-aux"):
        gone = set(ABSENT) if missing == "all-aux" else {missing}
        present = tuple(b for b in ("color", *ABSENT) if b not in gone)
        entry = {"sequence": name, "spp": spp, "absent": missing}
        for m, d in denoisers.items():
            entry[m] = vars(run_model(runtime_call(d, True), frames, present))
        entry["oidn-balanced"] = vars(run_model(oidn_call(present, threads), frames, present))
        entries.append(entry)
    return entries


def write_results(result: dict, models: list[str], args: argparse.Namespace) -> None:
    """auto_choice.json and .md under --out; a test-split run also docs/benchmarks.md's
    section."""
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "auto_choice.json").write_text(json.dumps(result, indent=1) + "\n")
    (args.out / "auto_choice.md").write_text(report(result, models))
    if not args.synthetic and args.split == "test":  # reported figures: the test split only
        update_section(args.out / "benchmarks.md", section(result, models))


def main(argv: list[str] | None = None) -> int:
    args, paths = parse_args(argv)
    buffer_sets = {name: BUFFER_SETS[name] for name in args.buffer_sets.split(",")}
    denoisers = {name: Denoiser(p, threads=args.threads) for name, p in paths.items()}
    chooser = Chooser(denoisers, [profile_of(n, d) for n, d in denoisers.items()],
                      default_model_path().stem, load_calibration(), args.quality)
    sources, data_note = sequence_sources(args)
    rows, absence = [], []
    for name, levels, where in sources:
        for spp in levels:
            frames = planar_frames(
                synthetic_frames(where, spp) if args.synthetic  # type: ignore[arg-type]
                else load_frames(where, spp, args.max_frames))  # type: ignore[arg-type]
            looks = frame_noise(frames[0][0])
            rows += [choice_row(name, spp, frames, set_name, present, looks, chooser)
                     for set_name, present in buffer_sets.items()]
            if not args.no_absence:
                absence += absence_entries(name, spp, frames, denoisers, args.threads)
    summary = summarise(rows, list(denoisers))
    absent_db = {
        m: {b: round(float(np.mean([e[m]["psnr"] for e in absence if e["absent"] == b]) -
                           np.mean([e[m]["psnr"] for e in absence if e["absent"] == "none"])), 3)
            for b in ABSENT}
        for m in denoisers} if absence else {}
    result = {"meta": {"data": data_note, "threads": args.threads, "quality": args.quality,
                       "calibration": (chooser.calibration or {}).get("source"),
                       "command": "python -m quietframe.bench.auto_choice "
                                  + " ".join(argv if argv is not None else sys.argv[1:])},
              "summary": summary, "rows": rows, "absence": absence, "absent_db": absent_db}
    write_results(result, list(denoisers), args)
    print(json.dumps(summary, indent=1))
    return 0


def summarise(rows: list[dict], models: list[str]) -> dict:
    """Best model = the highest mean PSNR over the sequences every model runs on."""
    common = [r for r in rows if len(r["fixed"]) == len(models)]
    out: dict = {"sequences": len(rows), "sequences_all_models_run": len(common)}
    if not common:
        return out
    mean = {m: float(np.mean([r["fixed"][m]["psnr"] for r in common])) for m in models}
    best = max(mean, key=mean.__getitem__)
    best_ms = float(np.mean([r["fixed"][best]["ms"] for r in common]))
    out.update(best_model=best, best_model_ms=round(best_ms, 2))
    # When the best model on this data is a cheap one, auto matching it cannot also run at
    # 60 % of its time: the share of the slowest (quality-tier) model is reported beside it.
    ms_of = {m: float(np.mean([r["fixed"][m]["ms"] for r in common])) for m in models}
    out["ms_by_model"] = {m: round(v, 2) for m, v in ms_of.items()}
    # What a choice that knew every sequence's PSNRs would reach: the cheapest model within the
    # tolerance of each row's best. If this misses the speed target, no rule can meet it with
    # these models.
    oracle = [min((f["ms"] for f in r["fixed"].values()
                   if f["psnr"] >= max(g["psnr"] for g in r["fixed"].values()) - TOLERANCE_DB),
                  default=float("nan")) for r in common]
    out["oracle"] = {"ms": round(float(np.mean(oracle)), 2),
                     "ms_share_of_best": round(float(np.mean(oracle)) / best_ms, 3)}
    for mode in ("header", "estimate"):
        runnable = [r for r in rows if r[f"auto_{mode}"]["psnr"] is not None]
        gaps = [max(f["psnr"] for f in r["fixed"].values()) - r[f"auto_{mode}"]["psnr"]
                for r in runnable]
        auto_ms = float(np.mean([r[f"auto_{mode}"]["ms"] for r in common]))
        out[mode] = {
            "worst_gap_db": round(max(gaps), 3) if gaps else None,
            "sequences_within_tolerance": sum(g <= TOLERANCE_DB + 1e-9 for g in gaps),
            "sequences_runnable": len(runnable),
            "ms": round(auto_ms, 2), "ms_share_of_best": round(auto_ms / best_ms, 3),
            "ms_share_of_slowest": round(auto_ms / max(ms_of.values()), 3),
            "meets_target": bool(gaps) and max(gaps) <= TOLERANCE_DB
            and auto_ms <= SPEED_SHARE * best_ms,
        }
    return out


MARK_BEGIN, MARK_END = "<!-- auto_choice: begin -->", "<!-- auto_choice: end -->"


def update_section(path: Path, text: str) -> None:
    """Put `text` between the markers of docs/benchmarks.md (appended when absent: quietframe-eval
    rewrites that file, so run this after it)."""
    old = path.read_text() if path.exists() else ""
    block = f"{MARK_BEGIN}\n{text}{MARK_END}\n"
    if MARK_BEGIN in old and MARK_END in old:
        head, rest = old.split(MARK_BEGIN, 1)
        new = head + block + rest.split(MARK_END, 1)[1].lstrip("\n")
    else:
        new = old.rstrip("\n") + "\n\n" + block
    path.write_text(new)


def section(result: dict, models: list[str]) -> str:
    summary, meta = result["summary"], result["meta"]
    lines = ["## model=auto and missing buffers (bench/auto_choice.py)", "",
             f"Data: {meta['data']}; {meta['threads']} threads; quality {meta['quality']}. "
             f"Command: `{meta['command']}`. Per-sequence figures and the choices: "
             "[auto_choice.md](auto_choice.md).", ""]
    if "oracle" in summary:
        lines.append(f"- an oracle (the cheapest model within {TOLERANCE_DB} dB of each "
                     f"sequence's best, knowing the PSNRs): {summary['oracle']['ms']} ms/frame = "
                     f"{summary['oracle']['ms_share_of_best']:.0%} of the best model: the "
                     "floor any choice rule has with these models")
    for mode in ("header", "estimate"):
        if mode in summary:
            s = summary[mode]
            lines.append(
                f"- auto, spp from {'the Cycles header' if mode == 'header' else 'the estimate'}:"
                f" within {TOLERANCE_DB} dB of the best fixed model on "
                f"{s['sequences_within_tolerance']} of {s['sequences_runnable']} runnable "
                f"sequences (worst gap {s['worst_gap_db']} dB); {s['ms']} ms/frame = "
                f"{s['ms_share_of_best']:.0%} of the best model ({summary['best_model']}), "
                f"{s['ms_share_of_slowest']:.0%} of the slowest; target met: "
                f"{s['meets_target']}")
    lines += ["", *absence_table(result, models)]
    return "\n".join(lines) + "\n"


def absence_table(result: dict, models: list[str]) -> list[str]:
    if not result["absence"]:
        return []
    columns = [*models, "oidn-balanced"]
    lines = ["Each buffer absent, fed as zeros (OIDN balanced given the same buffers: it takes a "
             "normal only with an albedo, and no depth or motion); PSNR / TRMAE, mean over the "
             "sequences and spp levels. A model that lists a buffer as required was not trained "
             "without it: its row shows the cost of zeros it never saw (buffer dropout, "
             "docs/training.md, is what lowers it).", "",
             "| absent | " + " | ".join(columns) + " |", "|---|" + "---|" * len(columns)]
    for missing in ("none", *ABSENT, "all-aux"):
        entries = [e for e in result["absence"] if e["absent"] == missing]
        cells = []
        for m in columns:
            psnr = np.mean([e[m]["psnr"] for e in entries])
            finite = [e[m]["trmae"] for e in entries if np.isfinite(e[m]["trmae"])]
            trmae = np.mean(finite) if finite else float("nan")
            cells.append(f"{psnr:.2f} / {trmae:.3f}")
        lines.append(f"| {missing} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def report(result: dict, models: list[str]) -> str:
    lines = [f"# model=auto vs fixed models\n\nData: {result['meta']['data']}. "
             f"Command: `{result['meta']['command']}`.\n",
             "| sequence | spp | buffers | " + " | ".join(f"{m} dB / ms" for m in models)
             + " | auto (header) | auto (estimate) |",
             "|---|---|---|" + "---|" * (len(models) + 2)]
    for r in result["rows"]:
        cells = [f"{r['fixed'][m]['psnr']:.2f} / {r['fixed'][m]['ms']:.0f}" if m in r["fixed"]
                 else "—" for m in models]
        autos = []
        for mode in ("header", "estimate"):
            a = r[f"auto_{mode}"]
            autos.append(f"{a['model']} @{a['spp']:g} spp: " + (
                f"{a['psnr']:.2f} / {a['ms']:.0f}" if a["psnr"] is not None else "cannot run"))
        lines.append(f"| {r['sequence']} | {r['spp']} | {r['buffers']} | "
                     + " | ".join(cells + autos) + " |")
    lines += ["", "Summary: `" + json.dumps(result["summary"]) + "`", ""]
    if result["absence"]:
        lines += ["## Each buffer absent", "", *absence_table(result, models)]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
