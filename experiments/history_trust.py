"""Experiment: which pixels may an `oidn-history` tier's history be trusted at? Each
candidate rule is scored against the tier's own per-frame stage (OIDN on the frame alone) per
shot, spp and frame index, on the zoo (scenes/zoo_shots.py; round 2 holds the shots the
history finds hard).

    python -m quietframe.experiments.history_trust --zoo zoo2 --split validation \
        [--shots fence-truck] [--spp 1,4,16,64] [--model oidn-history-cleanaux] [--json out]

The tier is OIDN on the pixel-aligned accumulation (its first graph and OIDN stage, run here
through the shipped runtime pieces, once per frame), then the output history
(model/output_history.OutputHistory). Only the last step differs between candidates, so it runs
in PyTorch on the cached OIDN outputs: each candidate is an OutputHistoryConfig (the shipped
one, and the per-pixel trust tests `edge_depth`, `edge_motion`, `shading_change`,
`resampling_detail`). The exported graph computes the same
(tests/experiments/test_output_history.py); the zoo figures of the shipped models come from
bench/zoo_eval, not from here.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch

from quietframe.bench import cli_args
from quietframe.bench.evaluate import AUX, STORED_BLENDER
from quietframe.bench.harness import planar_frames
from quietframe.model import metrics
from quietframe.model.output_history import VARIANTS, OutputHistory, OutputHistoryConfig
from quietframe.runtime import Denoiser, find_model
from quietframe.runtime.card import OIDNStage
from quietframe.runtime.motion_evidence import has_motion
from quietframe.runtime.oidn_prepass import PREPASS_BUFFERS, OIDNPrepass
from quietframe.runtime.stream import options_for
from quietframe.scenes import cycles_io
from quietframe.scenes.zoo_shots import shots, zoo_dir

# name -> changes to the shipped config (version 4: edge_depth 0.05, edge_motion 0.25,
# exact_edge_motion 0.25, shading_change 0.06 with power 0.75, resampling_detail 0.04 with
# power 1.5, still_radius 16 with the looser surface test there)
OFF = {"edge_depth": 0.0, "edge_motion": 0.0, "exact_edge_motion": 0.0, "shading_change": 0.0,
       "resampling_detail": 0.0, "still_radius": 0}
U_SPP = {"untrusted_weight": 0.5, "untrusted_weight_per_doubling": 0.25}
STAGE_INPUT = "stage input"  # a candidate's key that is not a config field: "frame" or not
CANDIDATES: dict[str, dict] = {
    "shipped": {},
    "version 2": OFF,  # no per-pixel trust
    "depth-edge": {**OFF, "edge_depth": 0.1},
    "motion-edge": {**OFF, "edge_motion": 0.5},
    "depth+motion": {"edge_depth": 0.1, "edge_motion": 0.5},
    "tight u(spp)": U_SPP,  # an untrusted pixel keeps some history at low spp
    "d+m u(spp)": {"edge_depth": 0.1, "edge_motion": 0.5, **U_SPP},
    # the motion test at exactly fetched pixels too
    "tight (v3 without the exact pixels' test)": {"exact_edge_motion": 0.0},
    "exact-motion 0.5": {"exact_edge_motion": 0.5},
    # a resampled history weighs less as the spp rise: the stage alone from 16 / 64 spp
    "w16": {"resampled_weight_per_doubling": 0.1625, "resampled_weight_max": 1.0},
    "w64": {"resampled_weight_per_doubling": 0.11, "resampled_weight_max": 1.0},
    # the resampled history clipped to the 3×3 mean ± γ·std of the stage (variance clipping)
    "clip 1σ": {"clip_sigma": 1.0},
    "clip 1.5σ": {"clip_sigma": 1.5},
    "clip 2σ": {"clip_sigma": 2.0},
    # the shading test: off (version 3's rule), other thresholds θ(16 spp) and powers
    "no shading test": {"shading_change": 0.0},
    "shading 0.03": {"shading_change": 0.03},
    "shading 0.12": {"shading_change": 0.12},
    "shading power 0.5": {"shading_change_power": 0.5},
    "shading power 1": {"shading_change_power": 1.0},
    # the detail test: off, other bounds θ_r(16 spp) and powers
    "no detail test": {"resampling_detail": 0.0},
    "detail 0.02 power 1": {"resampling_detail": 0.02, "resampling_detail_power": 1.0},
    "detail 0.08 power 2": {"resampling_detail": 0.08, "resampling_detail_power": 2.0},
    # the surface test at still pixels: as strict as elsewhere, or looser still
    "no still test": {"still_radius": 0},
    "still cos 0": {"still_normal_min_dot": 0.0, "still_depth_tolerance": 0.5},
    # the output history over OIDN on the frame alone, not on the aligned accumulation: Cycles'
    # 1-spp frames of a still pixel share their primary hit (the aux are equal frame to frame),
    # so the accumulation converged to an aliased image (docs/zoo.md "Repeated samples")
    "no accumulation": {STAGE_INPUT: "frame"},
}


def stage_outputs(denoiser: Denoiser, frames, spp: float,
                  prepass: OIDNPrepass | None = None) -> tuple[list, list]:
    """(D_t: OIDN on the tier's pixel-aligned accumulation, S_t: OIDN on the frame alone) per
    frame, through the shipped stages before the output history (Denoiser.denoise's loop,
    stopped before its last graph); `prepass`: another OIDN stage in place of the model's."""
    prepass = prepass or denoiser.prepass
    first, oidn, last = denoiser.stages
    assert isinstance(oidn, OIDNStage) and last is denoiser.graph
    options = options_for(denoiser.info, {}, spp)
    state, outputs, stages = None, [], []
    for planes, _, reset in frames:
        feeds, _, missing, (h, w) = denoiser._feeds(planes)
        feeds |= denoiser._options(denoiser.option_feeds, options)
        aux = {n: feeds[n][0] for n in PREPASS_BUFFERS[1:] if n not in missing}
        if reset:
            state = None
        accumulated, new = first.run(feeds, state, h, w)
        state = {first.stage.state_key(k): v for k, v in new.items()}
        outputs.append(prepass({"color": accumulated[0], **aux}, "cycles")[0])
        stages.append(prepass({"color": feeds["color"][0], **aux}, "cycles")[0])
    return outputs, stages


def history_run(config: OutputHistoryConfig, outputs, frames, spp: float) -> list[np.ndarray]:
    model = OutputHistory(config)
    state = None
    result = []
    with torch.no_grad():
        for d, (planes, _, reset) in zip(outputs, frames, strict=True):
            h, w = d.shape[-2:]
            t = {k: torch.from_numpy(np.ascontiguousarray(planes[k]))[None]
                 for k in ("albedo", "normal", "depth")}
            motion = planes.get("motion") if has_motion(planes) else None
            m = (torch.zeros(1, 2, h, w) if motion is None
                 else torch.from_numpy(np.nan_to_num(motion[:2]).astype(np.float32))[None])
            if state is None or reset:
                state, r = model.initial_state(1, h, w), torch.ones(1)
            else:
                r = torch.zeros(1)
            out, state = model(torch.from_numpy(d)[None], t["albedo"], t["normal"], t["depth"],
                               m, r, state, torch.full((1,), float(spp)))
            result.append(out[0].numpy())
    return result


def rendered_frames(folder: Path, spp: int) -> list:
    """The frames of a shot rendered so far (a render in progress: its manifest's frames),
    as bench.evaluate.load_sequence gives them."""
    manifest = json.loads((folder / "manifest.json").read_text())
    done = sorted(f["index"] for f in manifest["frames"])
    done = done[: next((i for i, t in enumerate(done) if t != i), len(done))]  # no gaps
    resets = cycles_io.frame_resets(folder)
    frames = []
    for t in done:
        reference = cycles_io.frame_file(cycles_io.reference_frame(folder, t))
        if not (folder / "reference_b" / reference).exists():
            break
        f = cycles_io.load_frame(folder, t, spp)
        frames.append(({k: f[k] for k in ("color", *AUX, STORED_BLENDER)}, f["reference"],
                       resets[t]))
    return frames


def _psnr(pred: np.ndarray, ref: np.ndarray) -> float:
    return metrics.psnr(pred.transpose(1, 2, 0), ref)  # planar prediction, (H, W, 3) reference


def worst_frame_gap(row: dict, stage: dict) -> float:
    """The lowest per-frame PSNR difference to the stage (frame 0 is the stage itself)."""
    return min(a - b for a, b in zip(row["per_frame"][1:], stage["per_frame"][1:], strict=True))


def run_shot(folder: Path, model: str, spps: list[int], aux_quality: str = "",
             candidates: tuple[str, ...] = tuple(CANDIDATES)) -> list[dict]:
    denoiser = Denoiser(find_model(model))
    prepass = None
    if aux_quality:  # the same tier with its aux prefiltered at another quality
        assert denoiser.card.prepass is not None
        prepass = OIDNPrepass(dataclasses.replace(denoiser.card.prepass, prefilter_aux=True,
                                                  aux_quality=aux_quality), num_threads=2)
    base = VARIANTS[model]
    rows = []
    for spp in spps:
        frames = planar_frames(rendered_frames(folder, spp))
        outputs, stages = stage_outputs(denoiser, frames, spp, prepass)
        refs = [ref for _, ref, _ in frames]
        # "accumulated": OIDN on the aligned accumulation, before the output history
        scored = {"stage": stages, "accumulated": outputs,
                  "blender": [p[STORED_BLENDER] for p, _, _ in frames]}
        for name in candidates:
            change = dict(CANDIDATES[name])
            stage_input = stages if change.pop(STAGE_INPUT, "") == "frame" else outputs
            scored[name] = history_run(dataclasses.replace(base, **change), stage_input, frames,
                                       spp)
        for method, preds in scored.items():
            per_frame = [_psnr(p, r) for p, r in zip(preds, refs, strict=True)]
            rows.append({"shot": folder.name, "spp": spp, "method": method,
                         "psnr": float(np.mean(per_frame)), "per_frame": per_frame})
        stage = {r["method"]: r for r in rows if r["spp"] == spp and r["shot"] == folder.name}
        line = "  ".join(f"{m} {stage[m]['psnr'] - stage['stage']['psnr']:+.2f}"
                         f" (worst frame {worst_frame_gap(stage[m], stage['stage']):+.2f})"
                         for m in scored if m != "stage")
        print(f"{folder.name} {spp:>3} spp, {len(frames)} frames: stage "
              f"{stage['stage']['psnr']:.2f} dB; {line}", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_zoo_shots(p, zoo="zoo2")
    p.add_argument("--spp", type=cli_args.spp_levels, default="1,4,16,64")
    p.add_argument("--model", default="oidn-history-cleanaux", choices=sorted(VARIANTS))
    p.add_argument("--aux-quality", default="", choices=("", "fast", "balanced", "high"),
                   help="prefilter the aux at this quality instead of the model's")
    p.add_argument("--candidates", type=lambda v: tuple(c.strip() for c in v.split(",")),
                   default=tuple(CANDIDATES),
                   help=f"comma-separated, of: {', '.join(CANDIDATES)} (default: all)")
    cli_args.add_json(p)
    args = p.parse_args(argv)
    if unknown := [c for c in args.candidates if c not in CANDIDATES]:
        p.error(f"unknown candidates {unknown}; choose from {list(CANDIDATES)}")
    root = zoo_dir(args.data, args.split, args.zoo)
    names = [s.name for s in shots(args.split, args.zoo)
             if not args.shots or s.name in args.shots]
    rows = []
    for name in names:
        folder = root / name
        if not (folder / "manifest.json").exists():
            print(f"{name}: not rendered", file=sys.stderr)
            continue
        rows += run_shot(folder, args.model, list(args.spp), args.aux_quality, args.candidates)
    if args.json:
        args.json.write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
