"""Build a zoo shot (scenes/zoo_shots.py) as a Blender scene: the set, its lights, and the camera
work. Written independently of the g2 generator, from the building blocks of zoo_parts:
Blender primitives and meshes, Blender's procedural textures, the photos of zoo_assets and
Blender's bundled environments.

Blender's world is z up. Every emitter is scaled by `exposure` (chosen from a preview, as the g2
renders are), so the render is already exposed. Sizes are metres.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import bpy  # only in the Cycles venv
import numpy as np
from mathutils import Euler, Vector

from . import zoo_sets2
from .zoo_parts import (
    Material,
    area,
    box,
    brick_wall,
    cylinder,
    fabric,
    glass,
    leaf_material,
    leaves,
    linear_keys,
    link,
    metal,
    photo_material,
    plain,
    quad,
    sphere,
    sun,
    suzanne,
    world_hdri,
    world_sky,
)
from .zoo_shots import Shot

# ---------------------------------------------------------------------------------------------
# Sets: each builds geometry and lights and returns camera anchors {name: (eye, target, fov)}


Anchor = tuple[tuple[float, float, float], tuple[float, float, float], float]


def _room(w: float, d: float, h: float, wall, floor, ceiling, window: tuple | None = None):
    """A closed room x in [0, w], y in [0, d], z in [0, h] seen from inside; `window`
    (x0, x1, z0, z1) cuts an opening into the wall at y = d."""
    quad("floor", (0, 0, 0), (w, 0, 0), (0, d, 0), floor)
    quad("ceiling", (0, 0, h), (0, d, 0), (w, 0, 0), ceiling)
    quad("wall_west", (0, 0, 0), (0, d, 0), (0, 0, h), wall)
    quad("wall_east", (w, 0, 0), (0, 0, h), (0, d, 0), wall)
    quad("wall_south", (0, 0, 0), (0, 0, h), (w, 0, 0), wall)
    if window is None:
        quad("wall_north", (0, d, 0), (w, 0, 0), (0, 0, h), wall)
        return
    x0, x1, z0, z1 = window
    for i, (a, b, c, e) in enumerate(((0, x0, 0, h), (x1, w, 0, h), (x0, x1, 0, z0),
                                      (x0, x1, z1, h))):
        quad(f"wall_north{i}", (a, d, c), (b - a, 0, 0), (0, 0, e - c), wall)


def set_study(rng, v: dict) -> dict[str, Anchor]:
    """A study: a window onto a bundled environment, a ceiling panel, a desk with a printed
    page and a monkey bust, a fabric armchair, a bookshelf of thin spines."""
    plaster = plain("plaster", (0.78, 0.76, 0.72), 0.8)
    wood = Material("wood")
    grain = wood.procedural("wave", 6.0, wave_type="RINGS", Distortion=6.0, Detail=6.0)
    wood.set(**{"Base Color": grain, "Roughness": 0.4})
    oak = photo_material("oak", "gravel", 1.2, tint=(0.55, 0.38, 0.22), roughness=0.5)
    _room(4.0, 5.0, 2.7, plaster, oak, plaster, window=(1.2, 2.8, 0.9, 2.2))
    desk = wood.mat
    box("desk", (1.0, 3.4, 0.72), (3.0, 4.2, 0.76), desk)
    for i, x in enumerate((1.05, 2.9)):
        box(f"desk_leg{i}", (x, 3.45, 0), (x + 0.05, 4.15, 0.72), desk)
    quad("page", (1.5, 3.55, 0.761), (0.42, -0.05, 0), (0.03, 0.21, 0),
         photo_material("page", "page", 1.0, uv=True, roughness=0.9))
    quad("text", (2.2, 3.5, 0.761), (0.45, 0.06, 0), (-0.02, 0.18, 0),
         photo_material("text", "text", 1.0, uv=True, roughness=0.9))
    suzanne("bust", (2.65, 3.9, 0.95), 0.3, 200.0, plain("marble", (0.85, 0.85, 0.82), 0.25))
    chair = fabric("chair_fabric", (0.55, 0.12, 0.1), 0.03)
    box("chair_seat", (0.3, 1.8, 0.0), (1.2, 2.7, 0.45), chair)
    box("chair_back", (0.3, 2.6, 0.45), (1.2, 2.8, 1.05), chair)
    box("shelf", (3.6, 0.6, 0.0), (3.95, 2.6, 2.0), desk)
    for k in range(90):  # book spines: 1-3 cm each, high frequency at the shot's distance
        y0 = 0.62 + k * 0.0215
        shelf_z = 0.05 + 0.48 * (k % 4)
        hue = rng.uniform(0.1, 0.8, 3)
        box(f"book{k}", (3.3, y0, shelf_z), (3.6, y0 + rng.uniform(0.012, 0.02),
                                              shelf_z + rng.uniform(0.28, 0.4)),
            plain(f"spine{k}", hue, 0.6))
    world_hdri(v.get("environment", "courtyard"), 1.5, v.get("yaw", 30.0))
    area("panel", (2.0, 2.0, 2.65), (2.0, 2.0, 0.0), 1.0, 220.0)
    return {"main": ((0.7, 0.5, 1.45), (2.2, 3.8, 0.85), 62.0),
            "close": ((1.9, 2.9, 1.25), (2.0, 3.7, 0.76), 48.0)}


def set_street(rng, v: dict) -> dict[str, Anchor]:
    """A sunlit street: brick facades, a gravel road, grass verges, hedges of leaves, poles,
    a shop sign with text; physical sky and a sun lamp."""
    elevation = v.get("sun_elevation", 35.0)
    quad("road", (-20, -5, 0), (40, 0, 0), (0, 60, 0),
         photo_material("gravel", "gravel", 1.5, tint=(0.45, 0.44, 0.42)))
    for side, x in (("west", -4.0), ("east", 4.0)):
        quad(f"verge_{side}", (x - 1.5 if x < 0 else x, -5, 0.01), (1.5, 0, 0), (0, 60, 0),
             photo_material(f"grass_{side}", "grass", 2.0, tint=(0.35, 0.55, 0.2)))
    brick = photo_material("facade", "brick", 2.5, tint=(0.75, 0.42, 0.3), bump=0.3)
    trim = plain("trim", (0.8, 0.8, 0.78), 0.5)
    glass_mat = plain("window_glass", (0.05, 0.06, 0.07), 0.05, Metallic=0.0)
    for side, sx in (("west", -1), ("east", 1)):
        y = 0.0
        for k in range(6):
            depth = rng.uniform(5, 8)
            height = rng.uniform(6, 12)
            x0 = sx * 5.5
            x1 = x0 + sx * 6
            box(f"house_{side}{k}", (min(x0, x1), y, 0), (max(x0, x1), y + depth, height),
                brick)
            for row in range(int(height // 2.6)):
                for col in range(int(depth // 1.8)):
                    zc, yc = 1.2 + 2.6 * row, y + 0.9 + 1.8 * col
                    quad(f"win_{side}{k}_{row}_{col}", (x0 - sx * 0.02, yc - 0.4, zc),
                         (0, 0.8, 0), (0, 0, 1.3), glass_mat)
            y += depth + 0.15
        leaves(f"hedge_{side}", (sx * 4.6, 20, 0.6), (0.6, 18, 0.6), 6000, 0.09, rng,
               leaf_material(f"leaf_{side}", (0.12, 0.3, 0.06)))
    for k in range(5):
        cylinder(f"pole{k}", (-3.7, 4 + 8 * k, 2.0), 0.06, 4.0, trim)
    quad("sign", (5.45, 6.0, 3.0), (0, 1.8, 0), (0, 0, 0.7),
         photo_material("sign", "text", 1.0, uv=True, roughness=0.4))
    world_sky(elevation, v.get("sun_azimuth", 60.0), 0.25)
    sun(elevation, v.get("sun_azimuth", 60.0), 4.0)
    return {"main": ((0.5, -3.0, 1.6), (0.0, 20.0, 2.5), 60.0),
            "side": ((-2.5, 10.0, 1.7), (6.0, 14.0, 3.0), 55.0)}


def set_gallery(rng, v: dict) -> dict[str, Anchor]:
    """A gallery: a long wall of fine procedural brick hung with photo posters, tiled floor,
    a turning monkey head on a plinth, skylight panels and an interior environment."""
    w, d, h = 14.0, 7.0, 4.0
    tiles = Material("tiles")
    tiles.set(**{"Base Color": tiles.procedural("checker", 4.0, Color1=(0.7, 0.7, 0.68, 1),
                                                Color2=(0.15, 0.15, 0.16, 1), Scale=1.0),
                 "Roughness": 0.25})
    _room(w, d, h, brick_wall("brickwall", (0.62, 0.3, 0.2)), tiles.mat,
          plain("ceiling", (0.8, 0.8, 0.8), 0.9))
    for k, name in enumerate(("astronaut", "coffee", "chelsea", "page", "text", "brick")):
        x = 1.0 + k * 2.1
        aspect = {"coffee": 0.67, "chelsea": 0.67, "page": 0.5, "text": 0.38}.get(name, 1.0)
        quad(f"poster_{name}", (x, d - 0.02, 1.3), (1.5, 0, 0), (0, 0, 1.5 * aspect),
             photo_material(f"poster_{name}", name, 1.0, uv=True, roughness=0.35))
    plinth = plain("plinth", (0.9, 0.9, 0.88), 0.6)
    box("plinth", (6.6, 3.0, 0), (7.4, 3.8, 1.0), plinth)
    head = suzanne("head", (7.0, 3.4, 1.35), 0.6, 0.0, metal("bronze", (0.8, 0.5, 0.3), 0.3))
    head.rotation_mode = "XYZ"
    for t in range(0, 40):  # turns 3 degrees a frame: object motion in the Vector pass
        head.rotation_euler = (0.0, 0.0, math.radians(3.0 * t))
        head.keyframe_insert("rotation_euler", frame=t)
    linear_keys(head)
    sphere("orb", (3.5, 2.5, 0.5), 0.5, glass("glass"))
    for k in range(3):
        area(f"skylight{k}", (2.5 + 4.5 * k, 3.0, h - 0.05), (2.5 + 4.5 * k, 3.5, 0), 1.5,
             500.0)
    world_hdri("interior", 0.5)
    return {"main": ((3.0, 0.6, 1.7), (3.0, 6.0, 1.6), 58.0),
            "wide": ((12.5, 0.6, 2.0), (6.0, 6.0, 1.2), 70.0)}


def set_tabletop(rng, v: dict) -> dict[str, Anchor]:
    """A still life on a table: a fabric cloth, a printed page, a gravel tray, glass, chrome
    and a monkey head; an environment and a softbox."""
    quad("floor", (-5, -5, 0), (10, 0, 0), (0, 10, 0),
         photo_material("floorboards", "gravel", 0.8, tint=(0.4, 0.3, 0.2)))
    box("table", (-0.6, -0.4, 0.70), (0.6, 0.4, 0.74), fabric("cloth", (0.2, 0.3, 0.55), 0.012))
    quad("page", (-0.45, -0.25, 0.741), (0.3, 0.03, 0), (-0.01, 0.15, 0),
         photo_material("page", "page", 1.0, uv=True, roughness=0.85))
    box("tray", (0.05, -0.3, 0.74), (0.4, 0.0, 0.76),
        photo_material("gravel_tray", "gravel", 6.0, tint=(0.7, 0.65, 0.6), bump=0.4))
    sphere("glass_ball", (-0.2, 0.15, 0.82), 0.08, glass("glass"))
    sphere("chrome_ball", (0.3, 0.2, 0.80), 0.06, metal("chrome", (0.9, 0.9, 0.9), 0.05))
    suzanne("head", (0.05, 0.22, 0.86), 0.2, 160.0, plain("clay", (0.7, 0.45, 0.35), 0.55))
    quad("card", (0.12, -0.28, 0.761), (0.22, -0.02, 0), (0.01, 0.09, 0),
         photo_material("card", "text", 1.0, uv=True, roughness=0.8))
    world_hdri(v.get("environment", "studio"), 0.8, v.get("yaw", 0.0))
    area("softbox", (-1.0, -1.0, 1.8), (0, 0, 0.74), 0.8, 90.0)
    return {"main": ((0.0, -0.85, 1.12), (0.0, 0.0, 0.76), 45.0),
            "low": ((0.7, -0.6, 0.9), (-0.05, 0.1, 0.78), 40.0)}


def set_garden(rng, v: dict) -> dict[str, Anchor]:
    """A garden lit by a bundled outdoor environment: lawn, shrubs of leaves, stone spheres,
    a monkey on a plinth, a fabric awning and a brick wall."""
    quad("lawn", (-15, -15, 0), (30, 0, 0), (0, 30, 0),
         photo_material("lawn", "grass", 2.5, tint=(0.3, 0.5, 0.18), bump=0.2))
    box("wall", (-6, 5, 0), (6, 5.3, 2.2), photo_material("wall", "brick", 3.0,
                                                          tint=(0.7, 0.45, 0.35), bump=0.3))
    for k in range(7):
        c = (rng.uniform(-5, 5), rng.uniform(-3, 4.3), rng.uniform(0.4, 0.8))
        leaves(f"shrub{k}", c, (rng.uniform(0.4, 0.9),) * 2 + (c[2],), 3500, 0.07, rng,
               leaf_material(f"leaf{k}", (0.08 + 0.05 * rng.random(), 0.25, 0.05)))
    stone = photo_material("stone", "gravel", 4.0, tint=(0.7, 0.68, 0.62), bump=0.5)
    for k in range(4):
        sphere(f"stone{k}", (-2 + 1.3 * k, -1.5, 0.3), 0.3, stone)
    box("plinth", (-0.3, 0.7, 0), (0.3, 1.3, 0.9), stone)
    suzanne("monkey", (0.0, 1.0, 1.2), 0.5, 180.0, metal("gold", (1.0, 0.75, 0.35), 0.2))
    quad("awning", (-3, 3.0, 2.4), (3.0, 0, 0), (0, 1.6, 0.5),
         fabric("awning", (0.8, 0.75, 0.2), 0.06))
    world_hdri(v.get("environment", "forest"), 1.0, v.get("yaw", 120.0))
    return {"main": ((0.0, -5.0, 1.5), (0.0, 1.0, 0.8), 55.0),
            "close": ((2.8, -3.2, 1.7), (0.0, 1.0, 1.1), 40.0)}


def set_courtyard(rng, v: dict) -> dict[str, Anchor]:
    """A courtyard in daylight: fine procedural brick walls all round, a fountain basin of
    glass-clear water and chrome, printed notices, a tree of leaves; sky and sun lamp."""
    elevation = v.get("sun_elevation", 40.0)
    quad("paving", (-10, -10, 0), (20, 0, 0), (0, 20, 0),
         photo_material("paving", "gravel", 2.0, tint=(0.6, 0.58, 0.55), bump=0.3))
    walls = brick_wall("walls", (0.7, 0.4, 0.28))
    for k, (lo, hi) in enumerate((((-8, 7, 0), (8, 7.5, 7)), ((-8.5, -8, 0), (-8, 7.5, 7)),
                                  ((8, -8, 0), (8.5, 7.5, 7)))):
        box(f"wall{k}", lo, hi, walls)
    for k in range(5):
        quad(f"notice{k}", (-6 + 2.6 * k, 6.98, 1.4), (0.6, 0, 0), (0, 0, 0.3),
             photo_material(f"notice{k}", "text" if k % 2 else "page", 1.0, uv=True,
                            roughness=0.6))
    stone = plain("stone", (0.75, 0.72, 0.66), 0.7)
    cylinder("basin", (0, 2, 0.3), 1.6, 0.6, stone)
    cylinder("water", (0, 2, 0.55), 1.45, 0.05, glass("water"))
    sphere("ornament", (0, 2, 1.1), 0.35, metal("steel", (0.85, 0.85, 0.9), 0.1))
    cylinder("trunk", (4.5, 4.5, 1.5), 0.15, 3.0, plain("bark", (0.25, 0.18, 0.12), 0.9))
    leaves("crown", (4.5, 4.5, 3.6), (1.6, 1.6, 1.2), 9000, 0.08, rng,
           leaf_material("crown", (0.1, 0.28, 0.05)))
    world_sky(elevation, v.get("sun_azimuth", 200.0), 0.3)
    sun(elevation, v.get("sun_azimuth", 200.0), 4.0)
    return {"main": ((-1.0, -7.0, 1.7), (0.0, 2.0, 1.2), 60.0),
            "corner": ((6.5, -6.0, 2.5), (-2.0, 5.0, 1.5), 65.0)}


SETS: dict[str, Callable[[np.random.Generator, dict], dict[str, Anchor]]] = {
    "study": set_study, "street": set_street, "gallery": set_gallery,
    "tabletop": set_tabletop, "garden": set_garden, "courtyard": set_courtyard,
    **zoo_sets2.SETS,
}


# ---------------------------------------------------------------------------------------------
# Camera work


def _pixel_angle(fov_deg: float, width: int) -> float:
    """Radians per pixel at the image centre of a pinhole of horizontal FOV `fov_deg`."""
    return 2 * math.tan(math.radians(fov_deg) / 2) / width


def camera_poses(shot: Shot, anchor: Anchor, rng, frames: range) -> list[tuple[Vector, Euler]]:
    """Pose per frame index t (t = -1 is the frame before the first, keyed so frame 1 carries
    real motion unless the shot wants its first Vector zero)."""
    eye, target, fov = anchor
    eye, target = Vector(eye), Vector(target)
    base = (target - eye).to_track_quat("-Z", "Y")
    forward = (target - eye).normalized()
    per_px = _pixel_angle(fov, shot.size[0])
    # drawn for every shot (the same stream whatever the camera); a truck's speed has a sign
    shake = rng.normal(0.0, abs(shot.speed) * per_px, (len(frames) + 1, 3))
    poses = []
    for i, t in enumerate(frames):
        loc, rot = eye.copy(), base.copy()
        if shot.camera == "dolly":
            loc = eye + forward * shot.speed * t
        elif shot.camera == "truck":  # sideways: near things cross fast, far ones slowly
            loc = eye + forward.cross(Vector((0.0, 0.0, 1.0))).normalized() * shot.speed * t
        elif shot.camera == "pan":
            yaw = Euler((0.0, 0.0, -shot.speed * per_px * t)).to_quaternion()
            rot = yaw @ base
        elif shot.camera == "orbit":
            turn = Euler((0.0, 0.0, math.radians(shot.speed * t))).to_matrix()
            loc = target + turn @ (eye - target)
            rot = (target - loc).to_track_quat("-Z", "Y")
        elif shot.camera == "shake" and t >= 0:  # sub-pixel hand-held jitter around the pose
            rot = rot @ Euler(tuple(shake[i])).to_quaternion()
        poses.append((loc, rot.to_euler()))
    return poses


def add_camera(name: str, shot: Shot, anchor: Anchor, rng) -> bpy.types.Object:
    data = bpy.data.cameras.new(name)
    data.sensor_fit, data.angle, data.clip_start = "HORIZONTAL", math.radians(anchor[2]), 0.01
    if shot.dof:  # focus on the anchor's target, wide open
        data.dof.use_dof = True
        data.dof.focus_distance = (Vector(anchor[1]) - Vector(anchor[0])).length
        data.dof.aperture_fstop = 2.0
    obj = link(bpy.data.objects.new(name, data))
    obj.rotation_mode = "XYZ"
    first = 0 if shot.zero_first_motion or shot.camera == "locked" else -1
    frames = range(first, shot.frames)
    for t, (loc, rot) in zip(frames, camera_poses(shot, anchor, rng, frames), strict=True):
        obj.location, obj.rotation_euler = loc, rot
        obj.keyframe_insert("location", frame=t + 1)
        obj.keyframe_insert("rotation_euler", frame=t + 1)
    linear_keys(obj)
    if shot.zero_first_motion:  # hold before frame 1: the renderer sees no motion there
        for curve in obj.animation_data.action.fcurves:
            curve.extrapolation = "CONSTANT"
    return obj


def build(shot: Shot, exposure: float = 1.0) -> bpy.types.Scene:
    """An empty Blender with `shot`'s set, lights scaled by `exposure` and camera(s); a cut
    switches camera at frame `cut_at` through timeline markers, as an editor would."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    rng = np.random.default_rng(shot.seed)
    anchors = SETS[shot.set](rng, shot.variant)
    for light in bpy.data.lights:
        light.energy *= exposure
    if scene.world is not None:
        scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value *= exposure
    names = list(anchors)
    cam = add_camera("camera", shot, anchors[names[0]], rng)
    scene.camera = cam
    if shot.cut_at is not None:
        second = add_camera("camera_after_cut", shot, anchors[names[1]], rng)
        scene.timeline_markers.new("shot_a", frame=1).camera = cam
        scene.timeline_markers.new("shot_b", frame=shot.cut_at + 1).camera = second
    r = scene.render
    r.use_motion_blur = shot.motion_blur
    if shot.motion_blur:
        r.motion_blur_shutter = 0.5
    scene.frame_start, scene.frame_end = 1, shot.frames
    return scene
