"""Render tiny Cycles frames into tests/fixtures/blender/ (multilayer EXRs written by Blender).

Regenerate (one command; needs Blender as a Python module in its own venv, not the project's):

    make cycles     # .venv-cycles: bpy 4.5 LTS (the `cycles` extra)
    nice -n 10 .venv-cycles/bin/python tools/render_blender_fixtures.py [--out DIR]

The scene is built in code (no downloaded assets): a floor, a cube, a sphere and a cylinder with
different materials, a sun, a coloured sky in the top part of the frame, and a camera that pans
right and tilts up over frames 1-3, so every surface moves by a known amount in the image (Cycles
writes no motion for the sky: tests/fixtures/blender/README.md).
Each variant is one point of the matrix of what Blender writes for a farm (passes, view layers,
motion blur, Blender's denoiser, half/float, ZIP/PIZ/DWAA). Seeds are fixed and Cycles runs on
one CPU thread so the pixels are reproducible; `manifest.json` records the Blender version and
every setting.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import bpy  # only in the bpy venv: this script is never imported by the package or its tests

WIDTH, HEIGHT = 64, 36
SEED = 7
# Camera: yaw to the right and pitch up per frame, so image content moves left and down from
# frame t-1 to frame t (x by ~2.9 px, y by ~1.9 px at this lens); frame 1 is the start pose.
YAW_DEG_PER_FRAME = -1.8  # rotation about world Z; negative turns the camera to its right
PITCH_DEG_PER_FRAME = 1.2  # positive tilts the view up
LENS_MM, SENSOR_MM = 50.0, 36.0


@dataclass
class Variant:
    """One fixture: a combination of the matrix, written as <name>.<frame:04d>.exr."""

    name: str
    frames: tuple[int, ...] = (2,)
    multilayer: bool = True
    depth: str = "16"  # "16" half, "32" float
    codec: str = "ZIP"
    samples: int = 4
    denoising_data: bool = True  # Denoising Albedo / Normal / Depth passes
    vector: bool = True
    z: bool = True
    motion_blur: bool = False
    blender_denoiser: bool = False
    transparent: bool = False  # film transparent: alpha 0 on the sky
    second_view_layer: bool = False
    note: str = ""
    extra: dict = field(default_factory=dict)


VARIANTS = (
    Variant(
        "passes_float_zip",
        frames=(1, 2, 3),
        depth="32",
        samples=8,
        note="all AOVs, one view layer, float, ZIP; three frames for the motion-sign check",
    ),
    Variant("passes_half_piz", codec="PIZ", note="all AOVs, half, PIZ"),
    Variant("passes_half_dwaa", codec="DWAA", note="all AOVs, half, DWAA (lossy)"),
    Variant(
        "two_view_layers",
        second_view_layer=True,
        note="view layers 'ViewLayer' and 'Objects' (sky and floor excluded), same passes",
    ),
    Variant(
        "motion_blur",
        frames=(2, 3),
        motion_blur=True,
        note="motion blur on: Blender still writes a Vector pass, all zeros",
    ),
    Variant(
        "blender_denoised",
        blender_denoiser=True,
        note="Blender's denoiser (OIDN) on: Combined is denoised, Noisy Image is the raw beauty",
    ),
    Variant(
        "no_vector",
        vector=False,
        z=False,
        note="Denoising Data but no Vector and no Depth pass",
    ),
    Variant(
        "transparent",
        transparent=True,
        note="film transparent: Combined.A is 0 on the sky",
    ),
    Variant(
        "plain_rgba",
        multilayer=False,
        denoising_data=False,
        vector=False,
        z=False,
        note="single-layer OpenEXR: R, G, B, A only, no AOVs",
    ),
)


def material(name: str, color, metallic=0.0, roughness=0.5, transmission=0.0, emission=0.0):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Transmission Weight"].default_value = transmission
    if emission:
        bsdf.inputs["Emission Color"].default_value = (*color, 1.0)
        bsdf.inputs["Emission Strength"].default_value = emission
    return mat


def add(obj_op, mat, collection, **kw):
    obj_op(**kw)
    obj = bpy.context.active_object
    obj.data.materials.append(mat)
    for c in obj.users_collection:
        c.objects.unlink(obj)
    collection.objects.link(obj)
    return obj


def build_scene() -> bpy.types.Scene:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    ground = bpy.data.collections.new("Ground")
    objects = bpy.data.collections.new("Objects")
    scene.collection.children.link(ground)
    scene.collection.children.link(objects)
    mesh = bpy.ops.mesh
    add(mesh.primitive_plane_add, material("floor", (0.5, 0.45, 0.4)), ground, size=40)
    add(
        mesh.primitive_cube_add,
        material("red", (0.8, 0.1, 0.05)),
        objects,
        size=1.6,
        location=(-1.6, 4.0, 0.8),
        rotation=(0, 0, 0.5),
    )
    add(
        mesh.primitive_uv_sphere_add,
        material("metal", (0.9, 0.9, 0.95), metallic=1.0, roughness=0.2),
        objects,
        radius=0.9,
        location=(0.9, 5.5, 0.9),
        segments=24,
        ring_count=12,
    )
    add(
        mesh.primitive_cylinder_add,
        material("glass", (0.7, 0.9, 1.0), roughness=0.05, transmission=1.0),
        objects,
        radius=0.5,
        depth=2.2,
        location=(2.6, 3.2, 1.1),
    )
    add(
        mesh.primitive_ico_sphere_add,
        material("lamp", (1.0, 0.6, 0.2), emission=4.0),
        objects,
        radius=0.3,
        location=(-0.2, 2.6, 0.3),
    )

    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(50), 0.0, math.radians(30))
    scene.collection.objects.link(sun)

    world = bpy.data.worlds.new("sky")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.35, 0.55, 0.9, 1.0)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 1.0
    scene.world = world

    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    cam.data.lens, cam.data.sensor_width, cam.data.sensor_fit = LENS_MM, SENSOR_MM, "HORIZONTAL"
    cam.location = (0.0, -3.0, 1.6)
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.rotation_mode = "XYZ"
    for frame in (1, 2, 3):
        # Rotation X = 90 deg looks along +Y; the start pitch leaves the sky in the top rows.
        cam.rotation_euler = (
            math.radians(84.0 + PITCH_DEG_PER_FRAME * (frame - 1)),
            0.0,
            math.radians(YAW_DEG_PER_FRAME * (frame - 1)),
        )
        cam.keyframe_insert("rotation_euler", frame=frame)
    for curve in cam.animation_data.action.fcurves:  # constant speed: frame t-1 -> t is one step
        for key in curve.keyframe_points:
            key.interpolation = "LINEAR"

    scene.frame_start, scene.frame_end = 1, 3
    render = scene.render
    render.engine = "CYCLES"
    render.resolution_x, render.resolution_y, render.resolution_percentage = WIDTH, HEIGHT, 100
    render.threads_mode, render.threads = "FIXED", 1  # one thread: reproducible, and polite
    render.use_persistent_data = False
    scene.cycles.device = "CPU"
    scene.cycles.seed = SEED
    scene.cycles.use_animated_seed = False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.max_bounces = 4
    scene.view_settings.view_transform = "Standard"  # EXR is scene-linear either way
    return scene


def configure(scene: bpy.types.Scene, v: Variant) -> None:
    scene.cycles.samples = v.samples
    scene.cycles.use_denoising = v.blender_denoiser
    scene.cycles.denoiser = "OPENIMAGEDENOISE"
    scene.render.use_motion_blur = v.motion_blur
    scene.render.film_transparent = v.transparent
    while len(scene.view_layers) > 1:
        scene.view_layers.remove(scene.view_layers[-1])
    layers = [scene.view_layers[0]]
    if v.second_view_layer:
        second = scene.view_layers.new("Objects")
        second.layer_collection.children["Ground"].exclude = True
        layers.append(second)
    for layer in layers:
        layer.use_pass_combined = True
        layer.use_pass_z = v.z
        layer.use_pass_vector = v.vector
        layer.cycles.denoising_store_passes = v.denoising_data
        layer.cycles.use_denoising = True  # per-layer switch; the scene switch decides
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR_MULTILAYER" if v.multilayer else "OPEN_EXR"
    settings.color_mode = "RGBA"
    settings.color_depth = v.depth
    settings.exr_codec = v.codec


def render(scene: bpy.types.Scene, v: Variant, out: Path) -> list[str]:
    configure(scene, v)
    names = []
    for frame in v.frames:
        scene.frame_set(frame)
        path = out / f"{v.name}.{frame:04d}.exr"
        scene.render.filepath = str(path)
        bpy.ops.render.render(write_still=True)
        names.append(path.name)
    return names


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "blender"
    parser.add_argument("--out", type=Path, default=default)
    parser.add_argument("--only", nargs="*", help="variant names (default: all)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    scene = build_scene()
    manifest = {
        "blender": bpy.app.version_string,
        "build_hash": bpy.app.build_hash.decode(),
        "command": "<bpy venv>/bin/python tools/render_blender_fixtures.py",
        "resolution": [WIDTH, HEIGHT],
        "seed": SEED,
        "device": "CPU, 1 thread",
        "camera": {
            "lens_mm": LENS_MM,
            "sensor_width_mm": SENSOR_MM,
            "yaw_deg_per_frame": YAW_DEG_PER_FRAME,
            "pitch_deg_per_frame": PITCH_DEG_PER_FRAME,
            "expected_image_motion": "content moves left and down from frame t-1 to t",
        },
        "variants": {},
    }
    for v in VARIANTS:
        if args.only and v.name not in args.only:
            continue
        files = render(scene, v, args.out)
        manifest["variants"][v.name] = {**asdict(v), "files": files}
    path = args.out / "manifest.json"
    if args.only and path.exists():  # a partial run updates the variants it rendered
        old = json.loads(path.read_text())
        old["variants"].update(manifest["variants"])
        manifest["variants"] = old["variants"]
    path.write_text(json.dumps(manifest, indent=1) + "\n")


if __name__ == "__main__":
    main()
