"""Render the Cycles training corpus (scenes/corpus_shots.py) in the zoo's layout, which the
training reader (model/data.py) reads as Cycles sequences:

    <data>/corpus-cycles/<split>/<shot>/manifest.json, spp0001/frame_0001.exr, ...,
                                        reference_a/frame_0001.exr, reference_b/...

Inputs at 1/4/16/64 spp with Blender's own denoise beside each, the reference in two
independent adaptive halves (a locked-off shot renders one, 4x the samples), as
scenes/cycles_render.py renders every Cycles split. A shot's scene is drawn from its seed,
redrawn (attempt + 1) when its first frame's preview is blocked or near black, exposed by the g2
rule, and stored in its manifest, which also gets the CPU time and the reference's noise once
the shot is whole. Resumable: finished files are skipped. Runs in the Cycles venv:

    .venv-cycles/bin/python -m quietframe.scenes.corpus_render --split train --start 0 --count 6
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

import bpy  # only in the Cycles venv
import numpy as np

from . import corpus_scene, preview
from .corpus_shots import (
    CORPUS_VERSION,
    REFERENCE_MIN_SPP,
    SPLIT_COUNT,
    CorpusShot,
    corpus_dir,
    corpus_shots,
    describe,
)
from .cycles_render import (
    CyclesConfig,
    _todo,
    configure,
    read_layer,
    reference_frame,
    reference_noise,
    render_missing,
    render_to,
)
from .layout import DATA_DIR
from .manifest import MANIFEST, open_sequence, write_json

NOISE_DEFINITION = ("per frame: median over pixels of |a-b| / ((a+b)/2 + 0.01) on luminance "
                    "of the two reference halves, over sqrt 2 (the figure of two independent "
                    "references of the reference's spp; scenes/cycles_render.reference_noise); "
                    "ceiling: PSNR of a perfect denoiser against the reference")


def shot_config(shot: CorpusShot, threads: int, reference_spp: int = 0) -> CyclesConfig:
    w, h = shot.size
    reference_spp = reference_spp or shot.reference_spp
    return CyclesConfig(width=w, height=h, frames=(shot.frames, shot.frames),
                        spp_levels=shot.spp_levels, reference_spp=reference_spp,
                        reference_min_spp=min(REFERENCE_MIN_SPP, reference_spp), threads=threads,
                        locked_off=shot.locked_off, extra={"corpus": CORPUS_VERSION})


def choose_scene(shot: CorpusShot, cfg: CyclesConfig, work: Path, tries: int = 8):
    """The first attempt whose previews (8 spp, each camera's first frame) are neither blocked
    nor near black (preview.first_acceptable), its exposure and how direct its light is."""
    made: dict = {}

    def shot_previews(attempt: int):
        desc = describe(shot, attempt)
        scene = corpus_scene.build(shot, desc, 1.0)
        configure(scene, cfg)
        made.update(desc=desc, scene=scene)
        c = scene.cycles
        c.samples, c.seed = preview.PREVIEW_SPP, 99
        c.use_adaptive_sampling = c.use_denoising = False
        for t in (0, *(() if shot.cut_at is None else (shot.cut_at,))):
            path = work / f"preview_{attempt}_{t}.exr"
            render_to(scene, t + 1, path)
            rad = read_layer(path, "Combined")[..., :3] @ preview.LUMA
            depth = read_layer(path, "Depth")[..., 0]  # 1e10 where no ray hit
            path.unlink()
            yield rad, depth

    attempt, lum = preview.first_acceptable(shot.seed, tries, shot_previews)
    desc, scene = made["desc"], made["scene"]
    exposure, clip = preview.exposure(lum, shot.seed)
    scene.cycles.max_bounces = 0  # direct light only
    path = work / "preview_direct.exr"
    render_to(scene, 1 + (shot.cut_at or 0), path)
    direct = read_layer(path, "Combined")[..., :3] @ preview.LUMA
    path.unlink()
    return desc, exposure, preview.lighting_stats(direct, lum[-1], clip, np.mean(lum[-1] <= 0))


def render_shot(shot: CorpusShot, out: Path, cfg: CyclesConfig, log=print) -> dict:
    """Render (or finish) one shot into `out`; returns its manifest."""
    manifest = open_sequence(out, cfg.key())
    todo = _todo(out, cfg, shot.frames)
    if manifest is None:
        t0, cpu0 = time.perf_counter(), time.process_time()
        desc, exposure, stats = choose_scene(shot, cfg, out)
        manifest = {
            "generator": CORPUS_VERSION, "renderer": "cycles", "blender": bpy.app.version_string,
            "seed": shot.seed, "attempt": desc["attempt"], "config": cfg.key(),
            "frame_count": shot.frames, "exposure": exposure, "shot": shot.record(),
            "tags": desc["tags"], "lighting_stats": stats,
            "cuts": [] if shot.cut_at is None else [shot.cut_at],
            "scene_setup_s": round(time.perf_counter() - t0, 2),
            "scene_setup_cpu_s": round(time.process_time() - cpu0, 2), "frames": [],
            "scene": desc,
        }
        write_json(out / MANIFEST, manifest)
    if todo:
        scene = corpus_scene.build(shot, manifest["scene"], manifest["exposure"])
        configure(scene, cfg)
        render_missing(scene, shot.seed, out, cfg, manifest, todo, {0, *manifest["cuts"]}, log)
    if "cpu_s" not in manifest or todo:
        record_totals(out, manifest, cfg)
    return manifest


def record_totals(out: Path, manifest: dict, cfg: CyclesConfig) -> None:
    """The shot's CPU time (set-up, inputs, reference halves) and its reference's noise and
    PSNR ceiling per reference frame and as the median, into its manifest."""
    frames = manifest["frames"]
    inputs = sum(v for f in frames for k, v in f["cpu_s"].items() if k.startswith("spp"))
    refs = sum(v for f in frames for k, v in f["cpu_s"].items() if k.startswith("reference"))
    per_frame = {}
    for f in frames:
        t = f["index"]
        if reference_frame(t, cfg) == t and not _todo(out, cfg, manifest["frame_count"]):
            noise, ceiling = reference_noise(out, t)
            per_frame[str(t)] = {"noise": round(noise, 4), "psnr_ceiling_db": round(ceiling, 2)}
    manifest["cpu_s"] = round(manifest["scene_setup_cpu_s"] + inputs + refs, 1)
    manifest["cpu_s_by_kind"] = {"setup": manifest["scene_setup_cpu_s"],
                                 "inputs": round(inputs, 1), "reference": round(refs, 1)}
    manifest["reference"] = {
        "spp": cfg.reference_spp, "min_spp": cfg.reference_min_spp, "halves": 2,
        "threshold": cfg.reference_threshold, "locked_off_scale": 4 if cfg.locked_off else 1,
        "noise_median": round(float(np.median([v["noise"] for v in per_frame.values()])), 4)
        if per_frame else None,
        "psnr_ceiling_db_median": round(float(np.median(
            [v["psnr_ceiling_db"] for v in per_frame.values()])), 2) if per_frame else None,
        "per_frame": per_frame, "definition": NOISE_DEFINITION,
    }
    write_json(out / MANIFEST, manifest)


def summarize(root: Path, split: str) -> dict:
    """<split>/split.json: shots and frames done, CPU-hours (and per finished shot), the
    projected total for the whole split, reference noise, and what the finished shots cover."""
    manifests = [json.loads(p.read_text()) for p in sorted(root.glob(f"*/{MANIFEST}"))]
    done = [m for m in manifests if m.get("reference", {}).get("noise_median") is not None]
    cpu = sum(m.get("cpu_s", 0.0) for m in manifests)
    per_shot = [m["cpu_s"] for m in done]
    mean = float(np.mean(per_shot)) if per_shot else None
    noise = [m["reference"]["noise_median"] for m in done]
    ceiling = [m["reference"]["psnr_ceiling_db_median"] for m in done]
    summary = {
        "corpus": CORPUS_VERSION, "split": split, "renderer": "cycles",
        "blender": bpy.app.version_string, "command": " ".join(sys.argv),
        "shots_planned": SPLIT_COUNT[split], "shots_done": len(done),
        "shots_started": len(manifests), "frames_done": sum(len(m["frames"]) for m in manifests),
        "cpu_hours": round(cpu / 3600, 3),
        "cpu_s_per_shot_mean": round(mean, 1) if mean else None,
        "cpu_s_per_shot_by_kind": {
            k: round(float(np.mean([m["cpu_s_by_kind"][k] for m in done])), 1)
            for k in ("setup", "inputs", "reference")} if done else None,
        "projected_cpu_hours": round(mean * SPLIT_COUNT[split] / 3600, 2) if mean else None,
        "reference_noise_median": float(np.median(noise)) if noise else None,
        "psnr_ceiling_db_median": float(np.median(ceiling)) if ceiling else None,
        "noise_definition": NOISE_DEFINITION,
        "tags": dict(Counter(t for m in done for t in m["tags"]).most_common()),
        "shots": {m["shot"]["name"]: {"cpu_s": m.get("cpu_s"), "frames_done": len(m["frames"]),
                                      "reference_noise": m.get("reference", {}).get("noise_median"),
                                      "attempt": m["attempt"]} for m in manifests},
    }
    write_json(root / "split.json", summary)
    return summary


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give WxH, e.g. 160x160") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: width and height must be positive")
    return w, h


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--split", required=True, choices=sorted(SPLIT_COUNT))
    p.add_argument("--start", type=int, default=0, help="first shot (index in the split)")
    p.add_argument("--count", type=int, default=0, help="shots from --start (0: to the end)")
    p.add_argument("--shots", default="", help="comma list of shot names (default: all)")
    p.add_argument("--frames", type=int, default=0, help="frames a shot (0: the corpus's)")
    p.add_argument("--size", type=_size, default=None, help="WxH (default: the corpus's)")
    p.add_argument("--spp", default="", help="comma list of input levels (default: the corpus's)")
    p.add_argument("--reference-spp", type=int, default=0, help="both halves (0: the corpus's)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, default=DATA_DIR)
    args = p.parse_args(argv)
    selected = corpus_shots(args.split)
    end = args.start + args.count if args.count else len(selected)
    selected = [s for s in selected[args.start:end]
                if not args.shots or s.name in args.shots.split(",")]
    overrides = {}
    if args.frames:
        overrides["frames"] = args.frames
    if args.size:
        overrides["size"] = args.size
    if args.spp:
        overrides["spp_levels"] = tuple(int(s) for s in args.spp.split(","))
    root = corpus_dir(args.out, args.split)
    print(f"corpus {args.split}: {len(selected)} shots -> {root}", flush=True)
    failed = 0
    for s in selected:
        if overrides:  # a smaller render of the same scene (tests, budget measurements)
            s = replace(s, **overrides)
            if s.cut_at is not None and s.cut_at >= s.frames:
                s = replace(s, cut_at=None)
        try:
            render_shot(s, root / s.name, shot_config(s, args.threads, args.reference_spp),
                        log=lambda m, n=s.name: print(f"{n}: {m}", flush=True))
        except Exception as e:  # noqa: BLE001 - one bad shot must not stop the night's render
            failed += 1
            print(f"shot {s.name}: failed: {e!r}", flush=True)
    summary = summarize(root, args.split)
    print(json.dumps({k: summary[k] for k in ("shots_done", "frames_done", "cpu_hours",
                                               "cpu_s_per_shot_mean", "projected_cpu_hours",
                                               "reference_noise_median")}), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
