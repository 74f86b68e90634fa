"""Render the validation zoo (scenes/zoo_shots.py) with Blender Cycles, in the layout of the
Cycles splits (scenes/cycles_render.py), so every evaluation tool reads a zoo shot as it reads
a g2 sequence:

    <data>/<zoo round>-cycles/<split>/<shot>/manifest.json, spp0001/frame_0001.exr, ...,
                                      reference_a/frame_0001.exr, reference_b/...

Inputs at 1-64 spp with Blender's own denoise (OIDN, Accurate prefilter, High) stored beside
each, references in two independent adaptive halves (a locked-off shot renders one, 4x the
samples). Resumable: finished files are skipped. Runs in the Cycles venv:

    .venv-cycles/bin/python -m quietframe.scenes.zoo_render --split validation
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import bpy  # only in the Cycles venv
import numpy as np

from . import preview, zoo_scene
from .cycles_render import (
    REFERENCE_HALVES,
    CyclesConfig,
    _todo,
    configure,
    frame_file,
    read_layer,
    reference_frame,
    reference_noise,
    render_missing,
    render_to,
)
from .layout import DATA_DIR
from .manifest import MANIFEST, open_sequence, write_json
from .zoo_shots import ZOO_ROUNDS, ZOO_SPLITS, ZOO_VERSION, Shot, shots, zoo_dir


def shot_config(shot: Shot, reference_spp: int, threads: int) -> CyclesConfig:
    w, h = shot.size
    return CyclesConfig(width=w, height=h, frames=(shot.frames, shot.frames),
                        spp_levels=shot.spp_levels, reference_spp=reference_spp,
                        threads=threads, locked_off=shot.locked_off, extra={"zoo": shot.zoo})


def choose_exposure(shot: Shot, cfg: CyclesConfig, work: Path) -> float:
    """The g2 rule (preview.exposure): an 8-spp preview of each camera's first frame at
    exposure 1, its clipped mean luminance mapped to a seeded 0.15-0.6."""
    scene = zoo_scene.build(shot, 1.0)
    configure(scene, cfg)
    c = scene.cycles
    c.samples, c.seed = preview.PREVIEW_SPP, 99
    c.use_adaptive_sampling = c.use_denoising = False
    lum = []
    for t in (0, *(() if shot.cut_at is None else (shot.cut_at,))):
        path = work / f"preview_{t}.exr"
        render_to(scene, t + 1, path)
        lum.append(read_layer(path, "Combined")[..., :3] @ preview.LUMA)
        path.unlink()
    return preview.exposure(lum, shot.seed)[0]


def render_shot(shot: Shot, out: Path, cfg: CyclesConfig, log=print) -> dict:
    manifest = open_sequence(out, cfg.key())
    todo = _todo(out, cfg, shot.frames)
    if manifest and not todo:
        return manifest
    if manifest is None:
        t0, cpu0 = time.perf_counter(), time.process_time()
        exposure = choose_exposure(shot, cfg, out)
        manifest = {
            "generator": shot.zoo, "renderer": "cycles", "blender": bpy.app.version_string,
            "seed": shot.seed, "config": cfg.key(), "frame_count": shot.frames,
            "exposure": exposure, "zoo": shot.record(),
            "cuts": [] if shot.cut_at is None else [shot.cut_at],
            "scene_setup_s": round(time.perf_counter() - t0, 2),
            "scene_setup_cpu_s": round(time.process_time() - cpu0, 2), "frames": [],
        }
        write_json(out / MANIFEST, manifest)
    scene = zoo_scene.build(shot, manifest["exposure"])
    configure(scene, cfg)
    render_missing(scene, shot.seed, out, cfg, manifest, todo, {0, *manifest["cuts"]}, log)
    return manifest


def motion_stats(out: Path, n_frames: int) -> dict:
    """What the renderer wrote as motion: mean |Vector| in pixels per frame at 1 spp (Vector
    is noise-free), so the report can say which frames carry none."""
    mean = []
    for t in range(n_frames):
        v = read_layer(out / "spp0001" / frame_file(t), "Vector")[..., :2]
        mean.append(round(float(np.abs(v).sum(-1).mean()), 3))
    return {"mean_abs_vector_px": mean}


def summarize(root: Path, selected: list[Shot], zoo: str = ZOO_VERSION) -> dict:
    """<split>/split.json: per shot, CPU-hours, reference noise and PSNR ceiling (median over
    its reference frames) and the motion the renderer wrote; the split's medians."""
    per_shot, noise, ceiling, cpu = {}, [], [], 0.0
    for s in selected:
        path = root / s.name / MANIFEST
        if not path.exists():
            continue
        m = json.loads(path.read_text())
        done = [f["index"] for f in m["frames"]
                if reference_frame(f["index"], CyclesConfig(locked_off=s.locked_off))
                == f["index"] and all((root / s.name / h / frame_file(f["index"])).exists()
                                      for h in REFERENCE_HALVES)]
        nc = [reference_noise(root / s.name, t) for t in done]
        shot_cpu = m["scene_setup_cpu_s"] + sum(sum(f["cpu_s"].values()) for f in m["frames"])
        cpu += shot_cpu
        noise += [n for n, _ in nc]
        ceiling += [c for _, c in nc]
        per_shot[s.name] = {
            "tags": list(s.tags), "frames_done": len(m["frames"]),
            "cpu_hours": round(shot_cpu / 3600, 3),
            "reference_noise": round(float(np.median([n for n, _ in nc])), 4) if nc else None,
            "psnr_ceiling_db": round(float(np.median([c for _, c in nc])), 2) if nc else None,
            **(motion_stats(root / s.name, len(m["frames"])) if m["frames"] else {}),
        }
    summary = {
        "zoo": zoo, "renderer": "cycles", "blender": bpy.app.version_string,
        "command": " ".join(sys.argv), "cpu_hours": round(cpu / 3600, 3),
        "reference_noise_median": float(np.median(noise)) if noise else None,
        "psnr_ceiling_db_median": float(np.median(ceiling)) if ceiling else None,
        "noise_definition": "as scenes/cycles_render.reference_noise (docs/data.md)",
        "shots": per_shot,
    }
    write_json(root / "split.json", summary)
    return summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--split", required=True, choices=ZOO_SPLITS)
    p.add_argument("--zoo", default=ZOO_VERSION, choices=ZOO_ROUNDS, help="the round")
    p.add_argument("--shots", default="", help="comma list of shot names (default: the split's)")
    p.add_argument("--reference-spp", type=int, default=0,
                   help="both halves together (default: the shot's)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, default=DATA_DIR)
    args = p.parse_args(argv)
    selected = [s for s in shots(args.split, args.zoo)
                if not args.shots or s.name in args.shots.split(",")]
    root = zoo_dir(args.out, args.split, args.zoo)
    print(f"zoo {args.split}: {len(selected)} shots -> {root}", flush=True)
    failed = 0
    for s in selected:
        try:
            cfg = shot_config(s, args.reference_spp or s.reference_spp, args.threads)
            render_shot(s, root / s.name, cfg,
                        log=lambda m, n=s.name: print(f"{n}: {m}", flush=True))
        except Exception as e:  # noqa: BLE001 - one bad shot must not stop the night's render
            failed += 1
            print(f"shot {s.name}: failed: {e!r}", flush=True)
    summary = summarize(root, shots(args.split, args.zoo), args.zoo)
    print(json.dumps({k: summary[k] for k in ("cpu_hours", "reference_noise_median",
                                               "psnr_ceiling_db_median")}), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
