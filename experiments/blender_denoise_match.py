"""How close the per-frame OIDN stage comes to Blender's own denoise on Cycles renders.

    python -m quietframe.experiments.blender_denoise_match --split validation \
        --shots garden-blur,study-locked --spp 1,4,16 [--threads 2] [--json out.json]

Blender's denoise (Cycles' OIDN denoiser, prefilter Accurate, quality High, the `Combined` pass
of the zoo's EXRs) makes the same OIDN calls as the runtime's stage with prefiltered aux (the
evaluation's oidn-high-cleanaux): albedo then normal each denoised in place by an RT filter at
the main filter's quality, then the RT filter with hdr, srgb off, cleanAux, quality high, no
inputScale (colour = the sum of the samples: OIDN's auto-exposure makes that scale irrelevant).
The one difference is the orientation: Cycles' render buffers hold the image bottom-up (row 0 is
the image's bottom row), EXRs and the service's decoder top-down, and OIDN's network is not
flip-equivariant. Denoised upside down (`bottom-up`: the stage told the frames are Cycles', as the
service tells it from the header; runtime/oidn_prepass.py rows_bottom_up), the stage reproduces
Blender's `Combined` to the half-float rounding of the stored output (about 92 dB tone-mapped
PSNR; ~48-51 dB as decoded). `flip-ensemble` is the mean of both orientations (twice OIDN's
time).

Per shot and spp: mean over frames of the tone-mapped PSNR (model/metrics, as zoo_eval) of each
method against Blender's `Combined` (the method's output rounded to half, as Blender's is) and
against the reference, and Blender's own PSNR against the reference.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.baselines import OIDNDenoiser
from quietframe.model import metrics
from quietframe.scenes import cycles_io
from quietframe.scenes.zoo_shots import ZOO_SPLITS, zoo_dir

METHODS = ("top-down", "bottom-up", "flip-ensemble")


def denoise(stages: dict, buffers: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The stage's output (H, W, 3) in the stored row order (top-down), in Cycles' (bottom-up),
    and their mean."""
    top, bottom = stages["top-down"](buffers), stages["bottom-up"](buffers)
    return {"top-down": top, "bottom-up": bottom, "flip-ensemble": 0.5 * (top + bottom)}


def _mean_psnr(outputs: list[np.ndarray], targets: list[np.ndarray]) -> float:
    return float(np.mean([metrics.psnr(o, t) for o, t in zip(outputs, targets, strict=True)]))


def score_shot(folder: Path, spp: int, stages: dict) -> dict:
    """One shot at one spp: per method PSNR to Blender's denoise and to the reference."""
    outs: dict[str, list] = {m: [] for m in METHODS}
    blender, reference = [], []
    n = json.loads((folder / cycles_io.MANIFEST).read_text())["frame_count"]
    for t in range(n):
        frame = cycles_io.load_frame(folder, t, spp)
        buffers = {k: frame[k] for k in ("color", "albedo", "normal", "depth", "motion")}
        for name, out in denoise(stages, buffers).items():
            outs[name].append(np.asarray(out, np.float32))
        blender.append(frame["blender_denoise"][..., :3])
        reference.append(frame["reference"][..., :3])
    row = {"shot": folder.name, "spp": spp, "blender_to_ref": _mean_psnr(blender, reference)}
    for name, o in outs.items():
        half = [x.astype(np.float16).astype(np.float32) for x in o]  # as Blender's is stored
        row[name] = {"to_blender": _mean_psnr(half, blender), "to_ref": _mean_psnr(o, reference)}
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_split(p, choices=ZOO_SPLITS)
    cli_args.add_data(p)
    p.add_argument("--shots", default="", help="comma list (default: every shot of the split)")
    p.add_argument("--spp", default="1,4,16")
    cli_args.add_threads(p)
    cli_args.add_json(p)
    args = p.parse_args(argv)
    root = zoo_dir(args.data, args.split)
    folders = [f.parent for f in sorted(root.glob("*/manifest.json"))
               if not args.shots or f.parent.name in args.shots.split(",")]
    if not folders:
        raise SystemExit(f"no zoo shots under {root}")
    stages = {order: OIDNDenoiser("high", prefilter_aux=True, num_threads=args.threads,
                                  renderer=renderer)
              for order, renderer in (("top-down", None), ("bottom-up", "cycles"))}
    rows = []
    print("| shot | spp | Blender→ref | " + " | ".join(
        f"{m} →Blender | {m} →ref (Δ)" for m in METHODS) + " |")
    print("|---|---|---|" + "---|---|" * len(METHODS))
    try:
        for folder in folders:
            for spp in (int(s) for s in args.spp.split(",")):
                row = score_shot(folder, spp, stages)
                rows.append(row)
                b = row["blender_to_ref"]
                cells = [f"{row[m]['to_blender']:.2f} | {row[m]['to_ref']:.2f} "
                         f"({row[m]['to_ref'] - b:+.2f})" for m in METHODS]
                print(f"| {row['shot']} | {spp} | {b:.2f} | " + " | ".join(cells) + " |",
                      flush=True)
    finally:
        for stage in stages.values():
            stage.close()
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
