"""Score the methods on the validation zoo (scenes/zoo_shots.py), per shot and spp.

    python -m quietframe.bench.zoo_eval --split validation --out docs/evaluation/zoo-validation

Per shot, per spp, per method: mean PSNR (tone-mapped, as everywhere in quietframe), TRMAE, and
on a locked-off shot its flicker; for a runtime model also the frames whose history the motion
evidence dropped, and for `auto` the model it chose. Methods: Blender's denoise (stored beside
each input), per-frame OIDN-high with plain and with prefiltered aux, every installed OIDN tier
and learned tier, each history tier's per-frame stage (`<tier>/frame`), `auto`, and the SID
add-on's temporal mode; by name also a tier with a look-ahead of k frames
(`<tier>/lookahead-<k>`, bench/lookahead_method.py: a session's `lookahead`). Cuts are not
flagged to the methods: Blender writes nothing into a frame that says "cut", so a farm sends a
shot with a camera switch as one sequence (`--flag-cuts` tells the methods, as a farm using
`quietframe denoise --cut` would).

`--zoo corpus --split validation` scores the training corpus's validation shots instead (the
zoo's layout; scenes/corpus_shots.py), none of which a learned tier trains on; `--extra-models`
adds .onnx files by stem (a candidate export beside the installed models).

Writes <out>/zoo.json (every row, per shot) and <out>/README.md (tables per shot type).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.evaluate import (
    Scores,
    build_methods,
    give_header_spp,
    load_sequence,
    run_sequence,
)
from quietframe.bench.harness import planar_frames
from quietframe.bench.lookahead_method import LookaheadMethod, lookahead_methods
from quietframe.runtime.oidn_prepass import PrepassUnavailable
from quietframe.scenes import cycles_io
from quietframe.scenes.corpus_shots import corpus_dir
from quietframe.scenes.zoo_shots import ZOO_VERSION, zoo_dir

HISTORY_TIERS = ("oidn-history", "oidn-fast-history", "oidn-history-cleanaux")
LEARNED = ("nbg-2l-3g", "affinity-h16-k5gc")
METHODS = ("blender-denoise", "oidn-high", "oidn-high-cleanaux", "oidn-frame", *HISTORY_TIERS,
           *(f"{t}/frame" for t in HISTORY_TIERS), *LEARNED, "auto", "sid-temporal")


CORPUS = "corpus"  # --zoo corpus: the training corpus's shots (validation only: train trains)


def shot_folders(data: Path, split: str, spp_levels: tuple[int, ...],
                 zoo: str = ZOO_VERSION) -> list[Path]:
    if zoo == CORPUS and split != "validation":
        raise SystemExit("--zoo corpus: only its validation split is for scoring (the corpus "
                         "has no test split, and its train split is what the tiers learn from)")
    root = corpus_dir(data, split) if zoo == CORPUS else zoo_dir(data, split, zoo)
    return [p.parent for p in sorted(root.glob("*/manifest.json"))
            if cycles_io.finished(p.parent, spp_levels)]


def shot_info(folder: Path) -> dict:
    """The shot's name, camera work and tags: a zoo shot's `zoo` record, or a corpus shot's
    `shot` record with its manifest's tags."""
    manifest = json.loads((folder / "manifest.json").read_text())
    if "zoo" in manifest:
        return manifest["zoo"]
    return {**manifest["shot"], "tags": manifest["tags"]}


def evaluate(folders: list[Path], spp_levels: tuple[int, ...], methods: dict,
             flag_cuts: bool, log=print, header_spp: bool = True) -> list[dict]:
    """`header_spp` False: score the frames as a renderer whose files state no spp would send
    them (a model that reads the spp gets the shot's estimate, as RuntimeMethod does; auto its
    own)."""
    rows = []
    for folder in folders:
        info = shot_info(folder)
        locked = info["camera"] == "locked"
        for spp in spp_levels:
            frames = planar_frames(load_sequence(folder, spp, forward=True))
            if not flag_cuts:
                frames = [(p, r, i == 0) for i, (p, r, _) in enumerate(frames)]
            for name, factory in list(methods.items()):
                try:
                    method = factory()
                except PrepassUnavailable as exc:
                    log(f"skipping {name}: {exc}")
                    del methods[name]
                    continue
                if header_spp:
                    give_header_spp(method, "cycles", spp)
                scores = Scores()
                run_sequence(method, frames, scores, None, locked)
                summary = scores.summary()
                row = {"shot": info["name"], "tags": info["tags"], "camera": info["camera"],
                       "spp": spp, "method": name,
                       **{k: round(v, 4) for k, v in summary.items() if k != "ms"},
                       "psnr_per_frame": [round(v, 3) for v in scores.per_frame["psnr"]]}
                chosen = getattr(method, "choices", None)
                if chosen:
                    row["chosen"] = dict(chosen)
                if getattr(method, "shot_spp", None) is not None:  # no spp stated: estimated
                    row["estimated_spp"] = method.shot_spp
                current = getattr(method, "current", method)
                if hasattr(current, "dropped"):
                    row["history_dropped"] = current.dropped
                    row["motion_estimated"] = current.estimated
                if isinstance(method, LookaheadMethod):  # frames blended, pixels trusted
                    row["lookahead_blended"] = method.blended
                    row["lookahead_trusted"] = (round(float(np.mean(method.trusted)), 4)
                                                if method.trusted else None)
                rows.append(row)
                log(json.dumps(row))
    return rows


def _cell(rows: dict, method: str, key: str, against: str | None = None) -> str:
    row = rows.get(method)
    if row is None or not np.isfinite(row.get(key, np.nan)):
        return "–"
    value = row[key]
    if against is not None and against in rows:
        return f"{value - rows[against][key]:+.2f}"
    return f"{value:.3f}" if key != "psnr" else f"{value:.2f}"


def per_frame_gaps(by: dict) -> list[str]:
    """Per shot, spp and history tier: the gap to its per-frame stage at each frame index (a
    loss that builds up over a long shot shows as a falling row)."""
    lines = ["", "## History tiers against their own stage, per frame index (dB)", "",
             "Frame 1 is the stage itself (no history yet).", ""]
    for (shot, spp), row in sorted(by.items()):
        for tier in HISTORY_TIERS:
            ours, stage = row.get(tier, {}), row.get(f"{tier}/frame", {})
            a, b = ours.get("psnr_per_frame"), stage.get("psnr_per_frame")
            if not a or not b or len(a) != len(b):
                continue
            gaps = " ".join(f"{x - y:+.2f}" for x, y in zip(a, b, strict=True))
            lines.append(f"- {shot}, {spp} spp, {tier}: {gaps} (worst "
                         f"{min(x - y for x, y in zip(a[1:], b[1:], strict=True)):+.2f})"
                         if len(a) > 1 else f"- {shot}, {spp} spp, {tier}: {gaps}")
    return lines


def report(rows: list[dict], meta: dict) -> str:
    """README.md: per shot and spp, PSNR of Blender's denoise and every method against it,
    the history tiers against their per-frame stage, and the locked-off flicker ratios."""
    by = {}
    for r in rows:
        by.setdefault((r["shot"], r["spp"]), {})[r["method"]] = r
    methods = [m for m in METHODS if any(m in v for v in by.values())]
    methods += sorted({r["method"] for r in rows} - set(METHODS))  # asked for by name
    lines = [f"# Validation zoo ({meta['split']}): per shot and spp", "",
             f"`{meta['command']}` ({meta['zoo']}, {meta['threads']} threads). "
             "PSNR (dB, tone-mapped) of Blender's denoise, and every other method's difference "
             "to it; cuts are " + ("flagged" if meta["flag_cuts"] else "not flagged") + ".", "",
             "| shot | tags | spp | Blender | " + " | ".join(
                 m for m in methods if m != "blender-denoise") + " | auto chose |",
             "|---|---|---|---|" + "---|" * (len(methods) - 1) + "---|"]
    for (shot, spp), row in sorted(by.items(), key=lambda kv: (kv[0][0], kv[0][1])):
        tags = ", ".join(next(iter(row.values()))["tags"])
        cells = [_cell(row, m, "psnr", "blender-denoise") for m in methods
                 if m != "blender-denoise"]
        chose = ", ".join(row.get("auto", {}).get("chosen", {}))
        lines.append(f"| {shot} | {tags} | {spp} | {_cell(row, 'blender-denoise', 'psnr')} | "
                     + " | ".join(cells) + f" | {chose} |")
    lines += ["", "## History tiers against their own per-frame stage (dB)", "",
              "| shot | spp | " + " | ".join(HISTORY_TIERS) + " | frames without history |",
              "|---|---|" + "---|" * len(HISTORY_TIERS) + "---|"]
    for (shot, spp), row in sorted(by.items()):
        cells = [_cell(row, t, "psnr", f"{t}/frame") for t in HISTORY_TIERS]
        dropped = ", ".join(str(row[t].get("history_dropped", "–")) for t in HISTORY_TIERS
                            if t in row)
        lines.append(f"| {shot} | {spp} | " + " | ".join(cells) + f" | {dropped} |")
    lines += per_frame_gaps(by)
    lines += ["", "## TRMAE (temporal error against the reference's own change; lower is steadier)",
              "", "| shot | spp | " + " | ".join(methods) + " |",
              "|---|---|" + "---|" * len(methods)]
    for (shot, spp), row in sorted(by.items()):
        lines.append(f"| {shot} | {spp} | " + " | ".join(_cell(row, m, "trmae") for m in methods)
                     + " |")
    locked = sorted(k for k, row in by.items() if np.isfinite(
        row.get("blender-denoise", {}).get("flicker", np.nan)))
    if locked:
        lines += ["", "## Locked-off flicker ÷ Blender's denoise's", "",
                  "| shot | spp | " + " | ".join(m for m in methods if m != "blender-denoise")
                  + " |", "|---|---|" + "---|" * (len(methods) - 1)]
        for key in locked:
            row = by[key]
            base = row["blender-denoise"]["flicker"]
            cells = [f"{row[m]['flicker'] / base:.2f}" if m in row else "–"
                     for m in methods if m != "blender-denoise"]
            lines.append(f"| {key[0]} | {key[1]} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_zoo_shots(p, also=(CORPUS,))
    p.add_argument("--spp", type=cli_args.spp_levels, default="1,2,4,8,16,64")
    p.add_argument("--extra-models", type=Path, nargs="+", default=[],
                   help="more .onnx models, each a method named by its file stem")
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--flag-cuts", action="store_true")
    p.add_argument("--no-header-spp", action="store_true",
                   help="score as frames whose header states no spp (Mitsuba, Arnold): a model "
                        "that reads the spp is given the shot's estimate, as the service gives "
                        "a session naming it, and auto chooses at its estimate")
    cli_args.add_threads(p)
    p.add_argument("--merge", type=Path, nargs="+", default=[],
                   help="instead of evaluating: join these runs' zoo.json (shots evaluated one "
                        "by one as their renders finished) into one report")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    if args.merge:
        return write(args.out, *merge([json.loads(f.read_text()) for f in args.merge]))
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    spp_levels = args.spp
    folders = [f for f in shot_folders(args.data, args.split, spp_levels, args.zoo)
               if not args.shots or f.name in args.shots]
    if not folders:
        raise SystemExit(f"no finished zoo {args.split} shots under {args.data} "
                         "(render them: scenes/render_zoo.sh)")
    wanted = args.methods.split(",")
    everything = build_methods(args.threads, args.extra_models, single_frame=HISTORY_TIERS,
                               renderer="cycles", rendered_only=HISTORY_TIERS)
    everything |= lookahead_methods(everything, wanted)  # <tier>/lookahead-<k>
    methods = {m: everything[m] for m in wanted if m in everything}
    rows = evaluate(folders, spp_levels, methods, args.flag_cuts,
                    header_spp=not args.no_header_spp)
    meta = {"split": args.split, "zoo": args.zoo, "threads": args.threads,
            "flag_cuts": args.flag_cuts, "header_spp": not args.no_header_spp,
            "shots": [f.name for f in folders],
            "command": "python -m quietframe.bench.zoo_eval " + " ".join(
                sys.argv[1:] if argv is None else argv)}
    return write(args.out, meta, rows)


def merge(runs: list[dict]) -> tuple[dict, list[dict]]:
    """One run of several (each shot from one of them: the later run's rows win), refusing
    runs of different splits, zoo versions or cut handling."""
    keys = {(r["meta"]["split"], r["meta"]["zoo"], r["meta"]["flag_cuts"]) for r in runs}
    if len(keys) != 1:
        raise SystemExit(f"--merge: runs of different splits or settings {sorted(keys)}")
    rows: dict[tuple, dict] = {}
    for run in runs:
        for row in run["rows"]:
            rows[(row["shot"], row["spp"], row["method"])] = row
    meta = {**runs[-1]["meta"], "shots": sorted({r["shot"] for r in rows.values()}),
            "command": " ; ".join(dict.fromkeys(r["meta"]["command"] for r in runs))}
    return meta, list(rows.values())


def write(out: Path, meta: dict, rows: list[dict]) -> int:
    out.mkdir(parents=True, exist_ok=True)
    (out / "zoo.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    (out / "README.md").write_text(report(rows, meta))
    print(f"wrote {out / 'README.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
