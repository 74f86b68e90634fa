"""Build a training-corpus shot in Blender from its stored description (scenes/corpus_shots.py
draws it; the manifest keeps it, so a resumed render builds the scene it started). Every part is
made of zoo_parts' blocks (primitives, Principled materials over Blender's procedural textures
and the zoo's photos, bundled HDRIs, the Nishita sky, sun, area and point lamps); the camera
work is keyed by the zoo's own camera code (zoo_scene.add_camera). No zoo set is built.

Blender's world is z up, sizes are metres; every emitter is scaled by `exposure`.
"""

from __future__ import annotations

import math

import bpy  # only in the Cycles venv
import numpy as np

from . import zoo_parts as zp
from .corpus_shots import CorpusShot
from .zoo_scene import add_camera

# ---------------------------------------------------------------------------------------------
# Materials from their descriptions


def _tinted(m: zp.Material, color, rgb):
    mix = m.node("ShaderNodeMix")
    mix.data_type, mix.blend_type = "RGBA", "MULTIPLY"
    mix.inputs["Factor"].default_value = 1.0
    m.links.new(color, mix.inputs["A"])
    mix.inputs["B"].default_value = (*rgb, 1.0)
    return mix.outputs["Result"]


def material(d: dict, name: str, exposure: float = 1.0) -> bpy.types.Material:
    """A Blender material for a surface description (corpus_parts.surface and the parts' own:
    leaf, emissive)."""
    kind = d["kind"]
    if kind == "plain":
        return zp.plain(name, d["rgb"], d["roughness"])
    if kind == "metal":
        return zp.metal(name, d["rgb"], d["roughness"])
    if kind == "glass":
        return zp.plain(name, (1.0, 1.0, 1.0), d["roughness"],
                        **{"Transmission Weight": 1.0, "IOR": 1.5})
    if kind == "photo":
        return zp.photo_material(name, d["photo"], d["scale"], tint=d["tint"],
                                 roughness=d["roughness"], uv=d.get("uv", False),
                                 bump=d.get("bump", 0.0))
    if kind == "fabric":
        return zp.fabric(name, d["rgb"], d["period"])
    if kind == "brick":
        return zp.brick_wall(name, d["rgb"], d["brick_m"])
    if kind == "leaf":
        return zp.leaf_material(name, d["rgb"])
    if kind == "emissive":
        return zp.plain(name, (0.8, 0.8, 0.8), 0.5, **{"Emission Color": d["rgb"],
                                                     "Emission Strength": d["strength"] * exposure})
    m = zp.Material(name)
    if kind == "checker":
        color = m.procedural("checker", d["scale"], Color1=(*d["rgb"], 1.0),
                             Color2=(*d["rgb2"], 1.0), Scale=1.0)
    elif kind == "noise":
        color = _tinted(m, m.procedural("noise", d["scale"], Scale=1.0, Detail=8.0), d["rgb"])
    elif kind == "wood":
        color = _tinted(m, m.procedural("wave", d["scale"], wave_type="RINGS", Distortion=6.0,
                                        Detail=6.0), d["rgb"])
    else:
        raise ValueError(f"no material kind {kind!r}")
    m.set(**{"Base Color": color, "Roughness": d["roughness"]})
    return m.bump(color, 0.2).mat


# ---------------------------------------------------------------------------------------------
# Stage geometry


def _wall(name: str, origin, along, length: float, height: float, window: dict | None, mat):
    """A wall from `origin` along the unit vector `along` (horizontal), with one window cut."""
    o, a, up = np.asarray(origin, float), np.asarray(along, float), np.array((0.0, 0.0, 1.0))
    if window is None:
        zp.quad(name, o, a * length, up * height, mat)
        return
    a0 = window["center"] * length - window["width"] / 2
    a1, z0, z1 = a0 + window["width"], window["z0"], window["z1"]
    for i, (s0, s1, t0, t1) in enumerate(((0, a0, 0, height), (a1, length, 0, height),
                                          (a0, a1, 0, z0), (a0, a1, z1, height))):
        zp.quad(f"{name}{i}", o + a * s0 + up * t0, a * (s1 - s0), up * (t1 - t0), mat)


def _room(p: dict, name: str, exposure: float) -> None:
    (w, d, h), y0 = p["size"], p["y0"]
    wall, floor = material(p["wall"], f"{name}_wall"), material(p["floor"], f"{name}_floor")
    zp.quad(f"{name}_floor", (-w / 2, y0, 0), (w, 0, 0), (0, d, 0), floor)
    zp.quad(f"{name}_ceiling", (-w / 2, y0, h), (0, d, 0), (w, 0, 0),
            material(p["ceiling"], f"{name}_ceiling"))
    windows = {win["wall"]: win for win in p["windows"]}
    for side, origin, along, length in (("south", (-w / 2, y0, 0), (1, 0, 0), w),
                                        ("north", (-w / 2, y0 + d, 0), (1, 0, 0), w),
                                        ("west", (-w / 2, y0, 0), (0, 1, 0), d),
                                        ("east", (w / 2, y0, 0), (0, 1, 0), d)):
        _wall(f"{name}_{side}", origin, along, length, h, windows.get(side), wall)


def _ground(p: dict, name: str, exposure: float) -> None:
    zp.quad(name, (-80, -40, 0), (160, 0, 0), (0, 160, 0), material(p["material"], name))


def _facades(p: dict, name: str, exposure: float) -> None:
    """A row of houses `y` metres away with dark panes: the distant background."""
    rng = np.random.default_rng(p["seed"])
    wall = material(p["material"], name)
    panes = zp.plain(f"{name}_panes", (0.04, 0.05, 0.06), 0.05)
    x, y = -60.0, p["y"]
    while x < 60.0:
        w, h = rng.uniform(5, 10), rng.uniform(5, 14)
        zp.box(f"{name}{int(x)}", (x, y, 0.0), (x + w, y + 6.0, h), wall)
        zp.boxes(f"{name}_windows{int(x)}",
                 [((x + 0.8 + 1.8 * c, y - 0.02, 1.0 + 2.6 * r),
                   (x + 1.8 + 1.8 * c, y, 2.4 + 2.6 * r))
                  for r in range(int(h // 2.6)) for c in range(int(w // 1.8) - 1)], panes)
        x += w + rng.uniform(0.2, 2.0)


def _box(p: dict, name: str, exposure: float) -> None:
    zp.box(name, p["lo"], p["hi"], material(p["material"], name))


def _poster(p: dict, name: str, exposure: float) -> None:
    x, y, z = p["corner"]
    zp.quad(name, (x, y, z), (p["width"], 0, 0), (0, 0, p["height"]),
            zp.photo_material(name, p["photo"], 1.0, uv=True, roughness=0.4))


# ---------------------------------------------------------------------------------------------
# Props


def _ball(p: dict, name: str, exposure: float) -> None:
    zp.sphere(name, p["center"], p["radius"], material(p["material"], name))


def _head(p: dict, name: str, exposure: float) -> None:
    cx, cy, cz = p["center"]
    size = p["size"]
    if p["plinth"] > 0:
        top = cz - 0.45 * size
        zp.box(f"{name}_plinth", (cx - 0.35 * size, cy - 0.35 * size, top - p["plinth"]),
               (cx + 0.35 * size, cy + 0.35 * size, top),
               material(p["plinth_material"], f"{name}_plinth"))
    head = zp.suzanne(name, p["center"], size, p["yaw"], material(p["material"], name))
    if p["spin"]:
        zp.spin(head, p["spin"])


def _wire(p: dict, name: str, exposure: float) -> None:
    r = p["radius"]
    if p["shape"] == "ico":
        bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2, radius=r, location=p["center"],
                                              rotation=p["tilt"])
    else:
        bpy.ops.mesh.primitive_torus_add(major_radius=r, minor_radius=0.28 * r,
                                         location=p["center"], rotation=p["tilt"])
    obj = bpy.context.active_object
    obj.name = name
    obj.data.materials.append(material(p["material"], name))
    zp.wireframe(obj, p["thickness"])
    if p["spin"]:
        zp.spin(obj, p["spin"], axis=p["axis"])


def _column(p: dict, name: str, exposure: float) -> None:
    zp.cylinder(name, p["center"], p["radius"], p["height"], material(p["material"], name))


def _foliage(p: dict, name: str, exposure: float) -> None:
    zp.leaves(name, p["center"], p["radius"], p["count"], p["leaf"],
              np.random.default_rng(p["seed"]), zp.leaf_material(name, p["rgb"]))


def _sign(p: dict, name: str, exposure: float) -> None:
    _poster(p, name, exposure)
    x, y, z = p["corner"]
    if p["post"] > 0:
        zp.rods(f"{name}_post", [((x + p["width"] / 2, y + 0.02, z - p["post"]),
                                  (x + p["width"] / 2, y + 0.02, z))], 0.02,
                material(p["material"], f"{name}_post"))


def _shelf(p: dict, name: str, exposure: float) -> None:
    """Boards full of book spines 1.2-3.5 cm thick: thin vertical detail."""
    rng = np.random.default_rng(p["seed"])
    x0, y, z0 = p["corner"]
    width = p["width"]
    boards, spines = [], [[] for _ in range(6)]
    for k in range(p["levels"]):
        z = z0 + 0.05 + 0.42 * k
        boards.append(((x0, y, z - 0.025), (x0 + width, y + 0.3, z)))
        x = x0 + 0.02
        while x < x0 + width - 0.05:
            thick = rng.uniform(0.012, 0.035)
            if rng.random() > 0.05:  # else a gap
                spines[int(rng.integers(6))].append(
                    ((x, y + rng.uniform(0.0, 0.06), z), (x + thick, y + 0.28,
                                                          z + rng.uniform(0.22, 0.36))))
            x += thick + 0.001
    zp.boxes(f"{name}_boards", boards, material(p["material"], f"{name}_boards"))
    for k, group in enumerate(spines):
        if group:
            zp.boxes(f"{name}_spines{k}", group,
                     zp.plain(f"{name}_spine{k}", rng.uniform(0.05, 0.8, 3), 0.55))


def _leds(p: dict, name: str, exposure: float) -> None:
    mat = material({"kind": "emissive", "rgb": p["rgb"], "strength": p["strength"]}, name,
                   exposure)
    for k, (x, y, z) in enumerate(p["points"]):
        zp.sphere(f"{name}{k}", (x, y, z + p["radius"]), p["radius"], mat)


def _roller(p: dict, name: str, exposure: float, frames: int) -> None:
    """A ball rolling without slipping: `step` metres a frame, keyed on Blender's frames."""
    ball = zp.sphere(name, p["center"], p["radius"], material(p["material"], name))
    step = np.asarray(p["step"], float)
    axis = np.cross((0.0, 0.0, 1.0), step)
    turn = np.linalg.norm(step) / p["radius"]
    ball.rotation_mode = "AXIS_ANGLE"
    for t in range(-1, frames + 1):
        ball.location = tuple(np.asarray(p["center"]) + step * t)
        ball.rotation_axis_angle = (turn * t, *(axis / max(np.linalg.norm(axis), 1e-9)))
        ball.keyframe_insert("location", frame=t + 1)
        ball.keyframe_insert("rotation_axis_angle", frame=t + 1)
    zp.linear_keys(ball)


def _tree(p: dict, name: str, exposure: float) -> None:
    zp.rods(name, zp.branches(p["origin"], p["length"], p["depth"],
                              np.random.default_rng(p["seed"])), p["radius"],
            material(p["material"], name))


def _page(p: dict, name: str, exposure: float) -> None:
    c, t = np.asarray(p["corner"], float), p["turn"]
    u = p["width"] * np.array((math.cos(t), math.sin(t), 0.0))
    v = p["depth"] * np.array((-math.sin(t), math.cos(t), 0.0))
    zp.quad(name, c, u, v, zp.photo_material(name, p["photo"], 1.0, uv=True, roughness=0.85))


def _comb(p: dict, name: str, exposure: float) -> None:
    x, y, z = p["corner"]
    pitch = p["tooth"] + p["gap"]
    teeth = [((x + k * pitch, y, z), (x + k * pitch + p["tooth"], y + 0.004, z + p["height"]))
             for k in range(p["teeth"])]
    teeth.append(((x, y, z + p["height"]), (x + p["teeth"] * pitch, y + 0.004,
                                            z + p["height"] + 0.012)))
    zp.boxes(name, teeth, material(p["material"], name))


def _pencils(p: dict, name: str, exposure: float) -> None:
    rng = np.random.default_rng(p["seed"])
    base = np.asarray(p["base"], float)
    tips = [base + (0, 0, p["length"]) + rng.normal(0, 0.15 * p["length"], 3)
            for _ in range(p["count"])]
    zp.rods(name, [(base, tip) for tip in tips], p["radius"], zp.plain(name, p["rgb"], 0.5))


def _fence(p: dict, name: str, exposure: float) -> None:
    y, span, w = p["y"], p["span"], p["width"]
    mat = material(p["material"], name)
    xs = np.arange(-span, span, w + p["gap"])
    zp.boxes(name, [((x, y, 0.0), (x + w, y + 0.02, p["height"])) for x in xs], mat)
    zp.boxes(f"{name}_rails", [((-span, y + 0.02, z), (span, y + 0.05, z + 0.06))
                               for z in (0.2, 0.7 * p["height"])], mat)


def _railing(p: dict, name: str, exposure: float) -> None:
    y, x0, span, r, top = p["y"], p["x"], p["span"], p["radius"], p["height"]
    mat = material(p["material"], name)
    xs = np.arange(x0 - span, x0 + span, p["spacing"])
    zp.rods(name, [((x, y, 0.0), (x, y, top)) for x in xs], r, mat)
    zp.rods(f"{name}_rails", [((x0 - span, y, z), (x0 + span, y, z)) for z in (0.1, top)],
            2.5 * r, mat)


def _bars(p: dict, name: str, exposure: float) -> None:
    x0, span = p["x"], p["span"]
    xs = np.arange(x0 - span / 2, x0 + span / 2, p["spacing"])
    zp.rods(name, [((x, p["y"], 0.0), (x, p["y"], p["height"])) for x in xs], p["radius"],
            material(p["material"], name))


def _cables(p: dict, name: str, exposure: float) -> None:
    y, z = p["y"], p["z"]
    zp.rods(name, [((-40.0, y + k, z + 0.3 * k), (40.0, y + k + 2.0, z + 0.3 * k + p["sag"]))
                   for k in range(p["count"])], p["radius"], material(p["material"], name))


def _trees(p: dict, name: str, exposure: float) -> None:
    rng = np.random.default_rng(p["seed"])
    segments = [s for o in p["origins"] for s in zp.branches(o, p["length"], p["depth"], rng)]
    zp.rods(name, segments, p["radius"], material(p["material"], name))


PARTS = {"room": _room, "ground": _ground, "facades": _facades, "box": _box, "poster": _poster,
         "ball": _ball, "head": _head, "wire": _wire, "column": _column, "foliage": _foliage,
         "sign": _sign, "shelf": _shelf, "leds": _leds, "tree": _tree, "page": _page,
         "comb": _comb, "pencils": _pencils, "fence": _fence, "railing": _railing,
         "bars": _bars, "cables": _cables, "trees": _trees}


# ---------------------------------------------------------------------------------------------
# Lights and the scene


def _lights(desc: dict) -> None:
    env = desc["environment"]
    if env["kind"] == "hdri":
        zp.world_hdri(env["name"], env["strength"], env["yaw"])
    else:
        zp.world_sky(env["elevation"], env["azimuth"], env["strength"])
        zp.sun(env["elevation"], env["azimuth"], env["sun"])
    for k, light in enumerate(desc["lights"]):
        loc = light["location"]
        if light["kind"] == "point":
            zp.point(f"bulb{k}", loc, light["watts"], light["radius"])
        else:
            target = light.get("target", (loc[0], loc[1], loc[2] - 1.0))
            zp.area(f"panel{k}", loc, target, light["size"], light["watts"])


def build(shot: CorpusShot, desc: dict, exposure: float = 1.0) -> bpy.types.Scene:
    """An empty Blender with the described stage, props and lights (emitters scaled by
    `exposure`) and the shot's camera(s); a cut switches camera through timeline markers."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    for k, part in enumerate((*desc["shell"], *desc["props"])):
        name = f"{part['kind']}{k}"
        if part["kind"] == "roller":
            _roller(part, name, exposure, shot.frames)
        else:
            PARTS[part["kind"]](part, name, exposure)
    _lights(desc)
    for light in bpy.data.lights:
        light.energy *= exposure
    scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value *= exposure
    camera_shot, rng = shot.camera_shot(), np.random.default_rng([shot.seed, 5])
    cams = []
    for k, a in enumerate(desc["anchors"]):
        cam = add_camera(f"camera{k}", camera_shot, (a["eye"], a["target"], a["fov"]), rng)
        if shot.dof:
            cam.data.dof.aperture_fstop = shot.fstop
        cams.append(cam)
    scene.camera = cams[0]
    if shot.cut_at is not None:
        scene.timeline_markers.new("shot_a", frame=1).camera = cams[0]
        scene.timeline_markers.new("shot_b", frame=shot.cut_at + 1).camera = cams[1]
    scene.render.use_motion_blur = shot.motion_blur
    if shot.motion_blur:
        scene.render.motion_blur_shutter = 0.5
    scene.frame_start, scene.frame_end = 1, shot.frames
    return scene
