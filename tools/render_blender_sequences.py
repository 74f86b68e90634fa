"""Render two short Cycles sequences into tests/fixtures/blender_sequences/: the motion-evidence
fixtures (a temporal model's history on frames whose `Vector` is all zero).

    make cycles     # .venv-cycles: bpy 4.5 LTS (the `cycles` extra)
    nice -n 10 .venv-cycles/bin/python tools/render_blender_sequences.py [--out DIR]

- `motion_blur.000{1..6}.exr`: motion blur on while the camera pans ~3 px a frame, so Blender
  writes an all-zero `Vector` over a moving image (a history reprojected with it ghosts);
- `locked_off.000{1..6}.exr`: a locked-off camera (Blender writes a `Vector` of float noise,
  ~1e-5 px; the tests also strip it, for a locked-off shot without vectors).

Both at 4 spp with Cycles' animated seed (the noise changes per frame), half float, ZIP, every
pass a farm sends, Blender's denoise on (`Combined`; the raw beauty is `Noisy Image`). Beside
them `*_reference.000N.exr` (Combined only, float): 512 spp adaptive, no denoise; the locked-off
shot has one reference (frame 1) for all its frames. The set is built from the zoo's parts
(scenes/zoo_parts.py, procedural textures only: no downloaded asset), 128×72, one CPU thread,
fixed seeds, so the pixels are reproducible. `manifest.json` records the Blender version and
settings.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import bpy  # only in the bpy venv: never imported by the package or its tests
import numpy as np

from quietframe.scenes import zoo_parts, zoo_scene
from quietframe.scenes.zoo_shots import Shot

WIDTH, HEIGHT, FRAMES, SPP, REFERENCE_SPP = 128, 72, 6, 4, 512
SEED = 11


def build(shot: Shot) -> bpy.types.Scene:
    """A brick wall, a checker floor, a fabric box, a chrome ball and a monkey under a sun and
    a uniform sky: structure in every buffer at this size, and no outside asset."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    floor = zoo_parts.Material("floor")
    floor.set(**{"Base Color": floor.procedural("checker", 2.0, Color1=(0.7, 0.7, 0.65, 1),
                                                Color2=(0.2, 0.2, 0.22, 1), Scale=1.0),
                 "Roughness": 0.4})
    zoo_parts.quad("floor", (-10, -10, 0), (20, 0, 0), (0, 20, 0), floor.mat)
    zoo_parts.box("wall", (-4, 3, 0), (4, 3.3, 2.5),
                  zoo_parts.brick_wall("bricks", (0.65, 0.32, 0.2), brick_m=0.3))
    zoo_parts.box("crate", (-1.6, 1.0, 0), (-0.8, 1.8, 0.8),
                  zoo_parts.fabric("cloth", (0.2, 0.35, 0.6), 0.05))
    zoo_parts.sphere("ball", (0.6, 1.2, 0.4), 0.4, zoo_parts.metal("chrome", (0.9,) * 3, 0.1))
    zoo_parts.suzanne("monkey", (1.8, 1.6, 0.5), 0.8, 200.0,
                      zoo_parts.plain("clay", (0.75, 0.5, 0.35), 0.5))
    zoo_parts.sun(40.0, 30.0, 3.0)
    world = bpy.data.worlds.new("sky")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.4, 0.55, 0.8, 1.0)
    scene.world = world
    anchor = ((0.0, -4.0, 1.4), (0.0, 2.0, 0.8), 50.0)
    scene.camera = zoo_scene.add_camera("camera", shot, anchor, np.random.default_rng(SEED))
    scene.render.use_motion_blur = shot.motion_blur
    scene.frame_start, scene.frame_end = 1, FRAMES
    r, c = scene.render, scene.cycles
    r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage = "CYCLES", WIDTH, HEIGHT, 100
    r.threads_mode, r.threads = "FIXED", 1
    c.device, c.use_animated_seed, c.max_bounces = "CPU", True, 6
    c.denoiser, c.denoising_prefilter, c.denoising_quality = "OPENIMAGEDENOISE", "ACCURATE", "HIGH"
    c.denoising_input_passes, c.denoising_use_gpu = "RGB_ALBEDO_NORMAL", False
    layer = scene.view_layers[0]
    layer.use_pass_combined = layer.use_pass_z = layer.use_pass_vector = True
    layer.cycles.denoising_store_passes = True
    s = r.image_settings
    s.file_format, s.color_mode, s.exr_codec = "OPEN_EXR_MULTILAYER", "RGBA", "ZIP"
    scene.view_settings.view_transform = "Standard"
    return scene


def render(scene: bpy.types.Scene, frame: int, path: Path, reference: bool) -> None:
    c = scene.cycles
    c.seed = SEED + (1000 if reference else 0)
    c.samples = REFERENCE_SPP if reference else SPP
    c.use_adaptive_sampling = reference
    c.adaptive_threshold, c.adaptive_min_samples = 0.002, 64
    c.use_denoising = not reference
    layer = scene.view_layers[0]
    layer.cycles.denoising_store_passes = not reference
    layer.use_pass_z = layer.use_pass_vector = not reference
    scene.render.image_settings.color_depth = "32" if reference else "16"
    scene.frame_set(frame)
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


SEQUENCES = {
    # ~3 px a frame at this lens and width: a slow pan, well within what a history must follow
    "motion_blur": Shot("motion_blur", "fixture", "fixture", "pan", (), seed=SEED, frames=FRAMES,
                        size=(WIDTH, HEIGHT), speed=3.0, motion_blur=True),
    "locked_off": Shot("locked_off", "fixture", "fixture", "locked", (), seed=SEED,
                       frames=FRAMES, size=(WIDTH, HEIGHT)),
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path,
                   default=Path(__file__).resolve().parents[1] / "tests/fixtures/blender_sequences")
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name, shot in SEQUENCES.items():
        scene = build(shot)
        for frame in range(1, FRAMES + 1):
            render(scene, frame, args.out / f"{name}.{frame:04d}.exr", reference=False)
            if not shot.locked_off or frame == 1:
                render(scene, frame, args.out / f"{name}_reference.{frame:04d}.exr", True)
    manifest = {
        "blender": bpy.app.version_string, "size": [WIDTH, HEIGHT], "frames": FRAMES,
        "spp": SPP, "reference_spp": REFERENCE_SPP, "reference": "adaptive 0.002, min 64",
        "seed": SEED, "pan_px_per_frame": SEQUENCES["motion_blur"].speed,
        "fov_deg": 50.0, "sequences": {k: v.record() for k, v in SEQUENCES.items()},
        "locked_off_reference": "frame 1 only", "degrees_per_px": math.degrees(
            zoo_scene._pixel_angle(50.0, WIDTH)),
    }
    (args.out / "manifest.json").write_text(json.dumps(manifest, indent=1))


if __name__ == "__main__":
    main()
