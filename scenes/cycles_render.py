"""Render g2 sequences with Blender Cycles, writing the EXRs a Blender farm writes.

Runs inside Blender's Python module (the `cycles` extra: bpy 4.5 LTS, Python 3.11, its own
venv). Per sequence, under <data>/g2-cycles/<split>/<seed>/:

    manifest.json                      scene description, exposure, config, per-frame timings
    spp0001/frame_0001.exr  ...        one Blender render per spp level and frame (multilayer
    spp0064/frame_0008.exr             EXR: Combined = Blender's own denoise (OIDN, Accurate
                                       prefilter, High quality), Noisy Image = the raw beauty,
                                       Denoising Albedo/Normal/Depth, Depth, Vector)
    reference_a/frame_0001.exr         the reference in two independent halves (Combined, no
    reference_b/frame_0001.exr         denoise; adaptive sampling, path guiding): their mean is
                                       the reference, their difference measures its noise on
                                       every frame at no extra cost. A locked-off sequence
                                       renders its (constant) reference once, at frame 1.

Every spp level is its own render with its own seed (a farm renders N spp in one go; Cycles'
sampling pattern is not the mean of N one-sample renders), with Cycles' animated seed so the
noise changes per frame. Frames carry Blender's frame numbers (1, 2, ...). Finished files are
skipped, so a killed render resumes; EXRs are written under a temporary name and renamed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import bpy  # only in the Cycles venv
import numpy as np

from quietframe.model.metrics import psnr

from . import cycles_scene, preview
from .generator import (
    GENERATOR_VERSION,
    LOCKED_OFF_REFERENCE_SCALE,
    generate,
    locked_off,
    summary,
)
from .layout import DATA_DIR, is_locked_off, split_dir, split_seeds
from .manifest import MANIFEST, open_sequence, write_json

LUMA = preview.LUMA
REFERENCE_HALVES = {"reference_a": 1_000_003, "reference_b": 2_000_003}  # dir -> seed salt


@dataclass
class CyclesConfig:
    width: int = 192
    height: int = 192
    frames: tuple[int, int] = (8, 8)
    spp_levels: tuple[int, ...] = (1, 2, 4, 8, 16, 64)
    reference_spp: int = 1024  # the most samples a reference pixel gets, both halves together
    reference_threshold: float = 0.002  # Cycles' adaptive noise threshold for references
    reference_min_spp: int = 64  # both halves together
    guiding: bool = True  # path guiding for references (CPU only, unbiased)
    max_bounces: int = 8
    threads: int = 2
    locked_off: bool = False  # static camera and scene over every frame (flicker shots)
    extra: dict = field(default_factory=dict)

    def key(self) -> dict:
        d = asdict(self)
        d.pop("threads")  # how fast, not what: a resume may use another thread count
        d["frames"], d["spp_levels"] = list(self.frames), list(self.spp_levels)
        return d


def level_dir(spp: int) -> str:
    return f"spp{spp:04d}"


def frame_file(t: int) -> str:
    return f"frame_{cycles_scene.blender_frame(t):04d}.exr"


def _seed(*parts: int) -> int:
    return int(np.random.SeedSequence(list(parts)).generate_state(1)[0] & 0x7FFFFFFF)


# ---------------------------------------------------------------------------------------------
# Render settings


def configure(scene: bpy.types.Scene, cfg: CyclesConfig) -> None:
    """Cycles on the CPU with Blender's defaults but for path length (the Mitsuba renderer's),
    every pass a farm turns on for denoising, and multilayer EXR output."""
    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y, r.resolution_percentage = cfg.width, cfg.height, 100
    r.threads_mode, r.threads = "FIXED", cfg.threads
    r.use_persistent_data = True  # one BVH per sequence: frames and levels re-use it
    c = scene.cycles
    c.device = "CPU"
    c.use_animated_seed = True
    c.max_bounces = cfg.max_bounces
    c.diffuse_bounces = c.glossy_bounces = c.transmission_bounces = cfg.max_bounces
    c.denoiser = "OPENIMAGEDENOISE"
    c.denoising_prefilter = "ACCURATE"
    c.denoising_quality = "HIGH"
    c.denoising_input_passes = "RGB_ALBEDO_NORMAL"
    c.denoising_use_gpu = False
    layer = scene.view_layers[0]
    layer.use_pass_combined = layer.use_pass_z = layer.use_pass_vector = True
    layer.cycles.denoising_store_passes = True
    layer.cycles.use_denoising = True
    settings = r.image_settings
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_mode = "RGBA"
    settings.exr_codec = "ZIP"
    scene.view_settings.view_transform = "Standard"


def _set_input_level(scene: bpy.types.Scene, spp: int, seed: int) -> None:
    c = scene.cycles
    c.samples, c.seed = spp, seed
    c.use_adaptive_sampling = False  # exactly `spp` samples in every pixel
    c.use_denoising = True  # Combined = Blender's denoise, Noisy Image = the input
    c.use_guiding = False
    scene.render.image_settings.color_depth = "16"  # half, as farms write beauty passes


def reference_scale(cfg: CyclesConfig) -> int:
    """Samples multiplier of a locked-off sequence's one reference (its frames share it)."""
    return LOCKED_OFF_REFERENCE_SCALE if cfg.locked_off else 1


def _set_reference_half(scene: bpy.types.Scene, cfg: CyclesConfig, seed: int) -> None:
    c = scene.cycles
    c.samples = cfg.reference_spp * reference_scale(cfg) // 2
    c.seed = seed
    c.use_adaptive_sampling = True
    c.adaptive_threshold = cfg.reference_threshold
    c.adaptive_min_samples = cfg.reference_min_spp * reference_scale(cfg) // 2
    c.use_denoising = False
    c.use_guiding = cfg.guiding
    if cfg.guiding:
        c.use_surface_guiding, c.use_volume_guiding = True, False
    scene.render.image_settings.color_depth = "32"


def render_to(scene: bpy.types.Scene, frame: int, path: Path) -> float:
    """Render scene frame `frame` into `path` (atomically); returns the wall seconds."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".partial.exr")
    scene.frame_set(frame)
    scene.render.filepath = str(tmp)
    t0 = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    seconds = time.perf_counter() - t0
    os.replace(tmp, path)
    return seconds


def read_layer(path: Path, layer: str) -> np.ndarray:
    """(H, W, C) float32 of one Blender pass (`Combined`, `Depth`, ...) of a multilayer EXR."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        chans = f.channels()
        names = sorted(n for n in chans if n.split(".")[-2:-1] == [layer])
        order = {"R": 0, "G": 1, "B": 2, "A": 3, "X": 0, "Y": 1, "Z": 2, "W": 3, "V": 0}
        names.sort(key=lambda n: order.get(n.rsplit(".", 1)[-1], 9))
        return np.stack([np.asarray(chans[n].pixels, np.float32) for n in names], -1)


# ---------------------------------------------------------------------------------------------
# Scene choice and exposure (the Mitsuba renderer's rule, with Cycles previews)


def choose_scene(seed: int, n_frames: int, cfg: CyclesConfig, work: Path, tries: int = 8):
    """Generate the description, rejecting scenes whose shots start blocked (> 20% of pixels
    nearer than 0.25 m) or near black (< 20% of pixels with any light in an 8-spp preview);
    the exposure maps the preview's mean luminance (clipped at its 99th percentile) to a
    seeded 0.15-0.6, and `direct_fraction` is the share of it that direct light explains."""
    made: dict = {}

    def shot_previews(attempt: int):
        desc = generate(seed, n_frames, attempt)
        if cfg.locked_off:
            desc = locked_off(desc)
        scene = cycles_scene.build_scene(desc, 1.0)
        configure(scene, cfg)
        made.update(desc=desc, scene=scene)
        c = scene.cycles
        c.samples, c.seed = preview.PREVIEW_SPP, 99
        c.use_adaptive_sampling = c.use_denoising = False
        for shot in desc["shots"]:
            path = work / f"preview_{attempt}_{shot['first_frame']}.exr"
            render_to(scene, cycles_scene.blender_frame(shot["first_frame"]), path)
            rad = read_layer(path, "Combined")[..., :3] @ LUMA
            depth = read_layer(path, "Depth")[..., 0]  # 1e10 where no ray hit
            path.unlink()
            yield rad, depth

    attempt, lum = preview.first_acceptable(seed, tries, shot_previews)
    desc, scene = made["desc"], made["scene"]
    c = scene.cycles
    exposure, clip = preview.exposure(lum, seed)
    c.max_bounces = 0  # direct light only: emitters seen directly or after one bounce
    path = work / "preview_direct.exr"
    render_to(scene, cycles_scene.blender_frame(desc["shots"][-1]["first_frame"]), path)
    direct = read_layer(path, "Combined")[..., :3] @ LUMA
    path.unlink()
    stats = preview.lighting_stats(direct, lum[-1], clip, np.mean(lum[-1] <= 0))
    return desc, attempt, exposure, stats


# ---------------------------------------------------------------------------------------------
# One sequence


def _frame_count(seed: int, cfg: CyclesConfig) -> int:
    lo, hi = cfg.frames
    return int(np.random.default_rng([seed, 1]).integers(lo, hi + 1))


def reference_frame(t: int, cfg: CyclesConfig) -> int:
    """The frame whose reference frame t uses (a locked-off shot has one)."""
    return 0 if cfg.locked_off else t


def _todo(out: Path, cfg: CyclesConfig, n_frames: int) -> list[tuple[int, str]]:
    todo = [(t, level_dir(s)) for t in range(n_frames) for s in cfg.spp_levels]
    todo += [(reference_frame(t, cfg), d) for t in range(n_frames) for d in REFERENCE_HALVES]
    return sorted({(t, d) for t, d in todo if not (out / d / frame_file(t)).exists()})


def render_sequence(seed: int, out: Path, cfg: CyclesConfig, log=print) -> dict:
    """Render (or finish) sequence `seed` into `out`; returns the manifest."""
    mpath = out / MANIFEST
    manifest = open_sequence(out, cfg.key())
    n_frames = _frame_count(seed, cfg)
    todo = _todo(out, cfg, n_frames)
    if manifest and not todo:
        return manifest
    t0, cpu0 = time.perf_counter(), time.process_time()
    if manifest is None:
        desc, attempt, exposure, stats = choose_scene(seed, n_frames, cfg, out)
        manifest = {
            "generator": GENERATOR_VERSION,
            "renderer": "cycles",
            "blender": bpy.app.version_string,
            "seed": seed,
            "attempt": attempt,
            "config": cfg.key(),
            "frame_count": n_frames,
            "exposure": exposure,  # every emitter is scaled by it before rendering
            "summary": summary(desc),
            "lighting_stats": stats,
            "cuts": desc["cuts"],
            "scene_setup_s": round(time.perf_counter() - t0, 2),
            "scene_setup_cpu_s": round(time.process_time() - cpu0, 2),
            "frames": [],
            "scene": desc,
        }
        write_json(mpath, manifest)
    desc = manifest["scene"]
    scene = cycles_scene.build_scene(desc, manifest["exposure"])
    configure(scene, cfg)
    render_missing(scene, seed, out, cfg, manifest, todo, {0, *desc["cuts"]}, log)
    return manifest


def render_missing(scene: bpy.types.Scene, seed: int, out: Path, cfg: CyclesConfig,
                   manifest: dict, todo: list[tuple[int, str]], resets: set[int],
                   log=print) -> None:
    """Render the frames `todo` names (every missing spp level and reference half of each),
    recording seconds and CPU seconds per level in the manifest after every frame."""
    mpath = out / MANIFEST
    records = {f["index"]: f for f in manifest["frames"]}
    for t in sorted({t for t, _ in todo}):
        rec = records.setdefault(t, {"index": t, "file": frame_file(t), "reset": t in resets,
                                     "seconds": {}, "cpu_s": {}})
        frame = cycles_scene.blender_frame(t)
        for spp in cfg.spp_levels:
            path = out / level_dir(spp) / frame_file(t)
            if path.exists():
                continue
            cpu = time.process_time()
            _set_input_level(scene, spp, _seed(seed, spp))
            rec["seconds"][level_dir(spp)] = round(render_to(scene, frame, path), 2)
            rec["cpu_s"][level_dir(spp)] = round(time.process_time() - cpu, 2)
        for half, salt in REFERENCE_HALVES.items():
            path = out / half / frame_file(t)
            if reference_frame(t, cfg) != t or path.exists():
                continue
            cpu = time.process_time()
            _set_reference_half(scene, cfg, _seed(seed, salt))
            rec["seconds"][half] = round(render_to(scene, frame, path), 2)
            rec["cpu_s"][half] = round(time.process_time() - cpu, 2)
        manifest["frames"] = sorted(records.values(), key=lambda f: f["index"])
        write_json(mpath, manifest)
        log(f"sequence {seed} frame {t}: {json.dumps(rec['seconds'])}")


def reference_noise(seq_dir: Path, t: int, eps: float = 0.01) -> tuple[float, float]:
    """Noise of frame t's reference from its two halves a, b, and the PSNR ceiling it implies.

    Noise as docs/data.md measures it (the median over pixels of |a - b| / ((a + b)/2 + eps)
    on luminance, exposed units, for two independent references of the reference's spp): the
    halves' figure over sqrt(2), since each half has half the samples. Ceiling: the PSNR a
    perfect denoiser would score against this reference, whose error is half of each half's:
    MSE(a, b) = 4 MSE(reference, truth) for independent halves, so PSNR(a, b) + 6.02 dB."""
    a, b = (read_layer(seq_dir / h / frame_file(t), "Combined")[..., :3]
            for h in REFERENCE_HALVES)
    la, lb = a @ LUMA, b @ LUMA
    noise = float(np.median(np.abs(la - lb) / ((la + lb) / 2 + eps)) / np.sqrt(2))
    return noise, psnr(a, b) + 10 * float(np.log10(4))


# ---------------------------------------------------------------------------------------------
# A split


def split_summary(root: Path, cfg: CyclesConfig, seeds: list[int]) -> dict:
    """<split>/split.json: seeds, config, frames done, CPU-hours summed from the manifests (per
    spp level and reference half), and the reference noise of every finished frame."""
    path = root / "split.json"
    seqs = [json.loads((root / str(s) / MANIFEST).read_text()) for s in seeds
            if (root / str(s) / MANIFEST).exists()]
    per_frame = {
        f"{m['seed']}/{f['index']}": reference_noise(root / str(m["seed"]), f["index"])
        for m in seqs
        for f in m["frames"]
        if reference_frame(f["index"], cfg) == f["index"]
        and all((root / str(m["seed"]) / h / frame_file(f["index"])).exists()
                for h in REFERENCE_HALVES)
    }
    noise = {
        "median_relative_difference": float(np.median([n for n, _ in per_frame.values()]))
        if per_frame else None,
        "psnr_ceiling_db_median": float(np.median([c for _, c in per_frame.values()]))
        if per_frame else None,
        "definition": "per frame: median over pixels of |a-b| / ((a+b)/2 + eps), luminance, "
        "eps 0.01, for two independent references of the reference's spp (from its two "
        "halves: their figure / sqrt 2); the split's figure is the median over frames. "
        "Ceiling: PSNR of a perfect denoiser against the reference (halves' PSNR + 6.02 dB)",
        "per_frame": {k: {"noise": round(n, 4), "psnr_ceiling_db": round(c, 2)}
                      for k, (n, c) in per_frame.items()},
    }
    frames = [f for m in seqs for f in m["frames"]]
    cpu = sum(m.get("scene_setup_cpu_s", 0) for m in seqs) + sum(
        sum(f["cpu_s"].values()) for f in frames
    )
    by_level: dict[str, float] = {}
    for f in frames:
        for k, v in f["cpu_s"].items():
            by_level[k] = by_level.get(k, 0.0) + v
    summary_ = {
        "renderer": "cycles",
        "blender": bpy.app.version_string,
        "command": " ".join(sys.argv),
        "seeds": seeds,
        "config": cfg.key(),
        "sequences_done": sum(not _todo(root / str(m["seed"]), cfg, m["frame_count"])
                              for m in seqs),
        "frames_done": sum(len(m["frames"]) for m in seqs),
        "cpu_s": round(cpu, 1),
        "cpu_hours": round(cpu / 3600, 3),
        "cpu_s_by_level": {k: round(v, 1) for k, v in sorted(by_level.items())},
        "reference_noise": noise,
        "lighting": {
            "indirect_sequences": sum(m["lighting_stats"]["direct_fraction"] < 0.5 for m in seqs),
            "locked_off": cfg.locked_off,
        },
    }
    write_json(path, summary_)
    return summary_


CYCLES_SPLITS = ("train", "validation", "test", "test-static", "validation-static")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--split", required=True, choices=CYCLES_SPLITS)
    p.add_argument("--sequences", type=int, required=True)
    p.add_argument("--start", type=int, default=0)
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--size", default="192x192")
    p.add_argument("--spp", default="1,2,4,8,16,64")
    p.add_argument("--reference-spp", type=int, default=1024, help="both halves together")
    p.add_argument("--reference-threshold", type=float, default=0.002)
    p.add_argument("--reference-min-spp", type=int, default=64)
    p.add_argument("--no-guiding", action="store_true")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, default=DATA_DIR)
    args = p.parse_args(argv)
    w, h = (int(x) for x in args.size.lower().split("x"))
    cfg = CyclesConfig(
        width=w, height=h, frames=(args.frames, args.frames),
        spp_levels=tuple(int(s) for s in args.spp.split(",")),
        reference_spp=args.reference_spp, reference_threshold=args.reference_threshold,
        reference_min_spp=args.reference_min_spp, guiding=not args.no_guiding,
        threads=args.threads, locked_off=is_locked_off(args.split),
    )
    root = split_dir(args.out, args.split, renderer="cycles")
    seeds = split_seeds(args.split, args.sequences, args.start, renderer="cycles")
    print(f"cycles {args.split}: {len(seeds)} sequences -> {root}", flush=True)
    failed = 0
    for seed in seeds:
        try:
            render_sequence(seed, root / str(seed), cfg, log=lambda s: print(s, flush=True))
        except Exception as e:  # noqa: BLE001 - one bad scene must not stop a night-long render
            failed += 1
            print(f"sequence {seed}: failed: {e!r}", flush=True)
    s = split_summary(root, cfg, seeds)
    print(json.dumps({k: s[k] for k in ("sequences_done", "frames_done", "cpu_hours",
                                         "reference_noise")}), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
