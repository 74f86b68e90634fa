"""What the shot's spp estimate buys a session that names a learned tier on frames whose header
states no spp: the same frames (the Cycles corpus's validation shots, the header's spp
withheld), each tier given the shot's estimate (service/shot_choice.estimate_for_shot, as
bench/harness.RuntimeMethod runs it) against the same tier at its default 4 (what such a
session got before), and how far the estimate is from the true spp.

    python -m quietframe.experiments.named_spp_estimate \
        --out docs/evaluation/learned-noise/estimated-spp-corpus-validation/default-vs-estimate.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args, zoo_eval
from quietframe.bench.harness import RuntimeMethod
from quietframe.runtime import find_model
from quietframe.runtime.card import SAMPLES_INPUT

TIERS = ("nbg-2l-3g", "affinity-h16-k5gc")
SPP_LEVELS = (1, 4, 16, 64)
DEFAULT = "@default"  # the suffix of a tier run at its default spp


def methods(threads: int) -> dict:
    out = {}
    for name in TIERS:
        path = find_model(name)
        default = next(i.default for i in RuntimeMethod(path, 1).denoiser.info.inputs
                       if i.name == SAMPLES_INPUT)
        out[name + DEFAULT] = lambda p=path, d=default: RuntimeMethod(p, threads,
                                                                      {SAMPLES_INPUT: d})
        out[name] = lambda p=path: RuntimeMethod(p, threads)
    return out


def summary(rows: list[dict]) -> list[str]:
    psnr = {(r["shot"], r["spp"], r["method"]): r["psnr"] for r in rows}
    shots = sorted({r["shot"] for r in rows})
    lines = []
    for name in TIERS:
        for spp in SPP_LEVELS:
            gain = [psnr[(s, spp, name)] - psnr[(s, spp, name + DEFAULT)] for s in shots]
            stops = [np.log2(r["estimated_spp"] / spp) for r in rows
                     if r["method"] == name and r["spp"] == spp]
            lines.append(f"{name} {spp:>2} spp: estimate - default {np.mean(gain):+.2f} dB mean, "
                         f"{min(gain):+.2f} worst, {max(gain):+.2f} best; estimated spp "
                         f"{np.mean(stops):+.2f} stops off on the mean (rms "
                         f"{np.sqrt(np.mean(np.square(stops))):.2f})")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    cli_args.add_data(p)
    cli_args.add_threads(p)
    p.add_argument("--out", type=Path, help="write the rows and the summary here (JSON)")
    args = p.parse_args(argv)
    folders = zoo_eval.shot_folders(args.data, "validation", SPP_LEVELS, zoo_eval.CORPUS)
    if not folders:
        raise SystemExit(f"no finished corpus validation shots under {args.data} "
                         "(scenes/render_corpus.sh)")
    rows = zoo_eval.evaluate(folders, SPP_LEVELS, methods(args.threads), False,
                             log=lambda *_: None, header_spp=False)
    lines = summary(rows)
    print("\n".join(lines))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        command = "python -m quietframe.experiments.named_spp_estimate --out " + str(args.out)
        args.out.write_text(json.dumps({"meta": {"command": command, "zoo": "corpus",
                                                 "split": "validation",
                                                 "shots": [f.name for f in folders]},
                                        "summary": lines, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
