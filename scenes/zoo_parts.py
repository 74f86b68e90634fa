"""Blender building blocks of the zoo's sets (scenes/zoo_scene.py): primitives and meshes written
here, Principled materials over Blender's procedural textures and the photos of zoo_assets, and
the lights (bundled HDR environments, the Nishita sky, sun and area lamps). Blender's world is
z up; sizes are metres.
"""

from __future__ import annotations

import math

import bpy  # only in the Cycles venv
import numpy as np
from mathutils import Euler, Vector

from . import zoo_assets

# ---------------------------------------------------------------------------------------------
# Geometry


def link(obj: bpy.types.Object) -> bpy.types.Object:
    bpy.context.scene.collection.objects.link(obj)
    return obj


def mesh(name: str, verts, faces, mat: bpy.types.Material, smooth: bool = False):
    data = bpy.data.meshes.new(name)
    data.from_pydata([tuple(map(float, v)) for v in verts], [], [tuple(f) for f in faces])
    data.update()
    if smooth:
        data.shade_smooth()
    data.materials.append(mat)
    return link(bpy.data.objects.new(name, data))


_BOX_FACES = ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))


def _box_verts(lo, hi) -> list[tuple[float, float, float]]:
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    return [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0),
            (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)]


def box(name: str, lo, hi, mat) -> bpy.types.Object:
    """An axis-aligned box from corner `lo` to corner `hi` (vertices in world metres, so
    object-space texture coordinates are metres)."""
    return boxes(name, [(lo, hi)], mat)


def boxes(name: str, corners, mat) -> bpy.types.Object:
    """Many axis-aligned boxes (lo, hi) as one mesh: fence pickets, book spines, comb teeth."""
    verts, faces = [], []
    for lo, hi in corners:
        faces += [tuple(len(verts) + i for i in f) for f in _BOX_FACES]
        verts += _box_verts(lo, hi)
    return mesh(name, verts, faces, mat)


def quad(name: str, corner, u, v, mat) -> bpy.types.Object:
    """A rectangle corner, corner+u, corner+u+v, corner+v, with UVs 0..1 over it."""
    c, u, v = (np.asarray(x, float) for x in (corner, u, v))
    obj = mesh(name, [c, c + u, c + u + v, c + v], [(0, 1, 2, 3)], mat)
    uv = obj.data.uv_layers.new(name="UVMap")
    uv.data.foreach_set("uv", [0, 0, 1, 0, 1, 1, 0, 1])
    return obj


def sphere(name: str, center, radius: float, mat) -> bpy.types.Object:
    bpy.ops.mesh.primitive_uv_sphere_add(segments=48, ring_count=24, radius=radius,
                                         location=center)
    obj = bpy.context.active_object
    obj.name = name
    obj.data.shade_smooth()
    obj.data.materials.append(mat)
    return obj


def suzanne(name: str, center, size: float, yaw_deg: float, mat) -> bpy.types.Object:
    """Blender's monkey head, subdivided once and smooth."""
    bpy.ops.mesh.primitive_monkey_add(size=size, location=center,
                                      rotation=(0.0, 0.0, math.radians(yaw_deg)))
    obj = bpy.context.active_object
    obj.name = name
    mod = obj.modifiers.new("subdivision", "SUBSURF")
    mod.levels = mod.render_levels = 1
    obj.data.shade_smooth()
    obj.data.materials.append(mat)
    return obj


def cylinder(name: str, center, radius: float, depth: float, mat) -> bpy.types.Object:
    bpy.ops.mesh.primitive_cylinder_add(vertices=32, radius=radius, depth=depth,
                                        location=center)
    obj = bpy.context.active_object
    obj.name = name
    obj.data.materials.append(mat)
    return obj


def leaves(name: str, center, radius, count: int, leaf: float, rng, mat):
    """Foliage: `count` small leaf quads (`leaf` m long) at random points and orientations in
    an ellipsoid of semi-axes `radius`, one mesh: geometry finer than a pixel at a few metres."""
    c, r = np.asarray(center, float), np.asarray(radius, float)
    p = rng.normal(size=(count, 3))
    p = p / np.linalg.norm(p, axis=1, keepdims=True) * rng.uniform(0, 1, (count, 1)) ** (1 / 3)
    p = c + p * r
    a, b = rng.normal(size=(count, 3)), rng.normal(size=(count, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b -= (b * a).sum(1, keepdims=True) * a
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    a, b = a * leaf / 2, b * leaf / 4
    verts = np.concatenate([p - a, p - b, p + a, p + b], 1).reshape(-1, 3)
    faces = [(4 * i, 4 * i + 1, 4 * i + 2, 4 * i + 3) for i in range(count)]
    return mesh(name, verts, faces, mat)


def rods(name: str, segments, radius: float, mat, sides: int = 6) -> bpy.types.Object:
    """Thin round bars (cables, branches, posts of a railing) from point pairs, one mesh of
    `sides`-gon prisms: geometry a pixel or less wide at the shots' distances."""
    verts, faces = [], []
    ring = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    for p0, p1 in segments:
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        axis = (p1 - p0) / max(np.linalg.norm(p1 - p0), 1e-9)
        a = np.cross(axis, (0.0, 0.0, 1.0) if abs(axis[2]) < 0.9 else (1.0, 0.0, 0.0))
        a /= np.linalg.norm(a)
        b = np.cross(axis, a)
        offsets = radius * (np.cos(ring)[:, None] * a + np.sin(ring)[:, None] * b)
        base = len(verts)
        verts += list(p0 + offsets) + list(p1 + offsets)
        faces += [(base + k, base + (k + 1) % sides, base + sides + (k + 1) % sides,
                   base + sides + k) for k in range(sides)]
    return mesh(name, verts, faces, mat)


def branches(origin, length: float, depth: int, rng, spread: float = 0.6) -> list:
    """Segments of a bare tree grown upward from `origin`: each branch splits in two to
    three shorter ones (0.6-0.8 of its length) turned by up to `spread` radians."""
    segments = []

    def grow(p, direction, size, level):
        end = p + direction * size
        segments.append((p, end))
        if level == 0:
            return
        for _ in range(int(rng.integers(2, 4))):
            d = direction + rng.normal(0.0, spread, 3)
            d[2] = abs(d[2]) * 0.7 + 0.2
            grow(end, d / np.linalg.norm(d), size * rng.uniform(0.6, 0.8), level - 1)

    grow(np.asarray(origin, float), np.array([0.0, 0.0, 1.0]), length, depth)
    return segments


def wireframe(obj: bpy.types.Object, thickness: float) -> bpy.types.Object:
    """Keep only `obj`'s edges, as bars `thickness` metres thick (Blender's Wireframe
    modifier): a rotating object made of lines a pixel or two wide."""
    mod = obj.modifiers.new("wireframe", "WIREFRAME")
    mod.thickness, mod.use_replace = thickness, True
    return obj


def spin(obj: bpy.types.Object, degrees_per_frame: float, frames: int = 40,
         axis: int = 2) -> bpy.types.Object:
    """Key a turn of `degrees_per_frame` about one axis on frames 0..frames (object motion in
    the Vector pass); the keys are made linear by the shot's camera set-up."""
    obj.rotation_mode = "XYZ"
    start = tuple(obj.rotation_euler)
    for t in range(frames + 1):
        rot = list(start)
        rot[axis] += math.radians(degrees_per_frame * t)
        obj.rotation_euler = rot
        obj.keyframe_insert("rotation_euler", frame=t)
    return linear_keys(obj)


def linear_keys(obj: bpy.types.Object) -> bpy.types.Object:
    """Linear keys with linear extrapolation, so the Vector pass of every keyed frame is the
    motion since the frame before."""
    anim = obj.animation_data
    if anim and anim.action:
        for curve in anim.action.fcurves:
            curve.extrapolation = "LINEAR"
            for key in curve.keyframe_points:
                key.interpolation = "LINEAR"
    return obj


# ---------------------------------------------------------------------------------------------
# Materials


class Material:
    """A Principled BSDF material under construction; `color`, `roughness` and `bump` take a
    plain value or a texture output."""

    def __init__(self, name: str) -> None:
        self.mat = bpy.data.materials.new(name)
        self.mat.use_nodes = True
        self.tree = self.mat.node_tree
        self.nodes, self.links = self.tree.nodes, self.tree.links
        self.bsdf = self.nodes["Principled BSDF"]

    def node(self, kind: str, **inputs):
        n = self.nodes.new(kind)
        for k, v in inputs.items():
            n.inputs[k].default_value = v
        return n

    def coords(self, scale: float, uv: bool = False, wall: bool = False):
        """Texture coordinates: object-space metres times `scale` (so `scale` repeats per
        metre), or the mesh UVs; `wall` maps a vertical wall of either axis to (x + y, z), so
        a 2-D pattern (brick courses) runs horizontally on every wall."""
        tc = self.node("ShaderNodeTexCoord")
        mapping = self.node("ShaderNodeMapping")
        mapping.inputs["Scale"].default_value = (scale,) * 3
        source = tc.outputs["UV" if uv else "Object"]
        if wall:
            split, along, joined = (self.node("ShaderNodeSeparateXYZ"),
                                    self.node("ShaderNodeMath"), self.node("ShaderNodeCombineXYZ"))
            self.links.new(source, split.inputs["Vector"])
            self.links.new(split.outputs["X"], along.inputs[0])
            self.links.new(split.outputs["Y"], along.inputs[1])  # Math defaults to ADD
            self.links.new(along.outputs["Value"], joined.inputs["X"])
            self.links.new(split.outputs["Z"], joined.inputs["Y"])
            source = joined.outputs["Vector"]
        self.links.new(source, mapping.inputs["Vector"])
        return mapping.outputs["Vector"]

    def photo(self, name: str, scale: float, uv: bool = False, tint=(1, 1, 1), box=True):
        """One of zoo_assets' photos, repeated `scale` times a metre (box projection on
        object coordinates), or once over the UVs; grey photos are tinted."""
        tex = self.node("ShaderNodeTexImage")
        tex.image = bpy.data.images.load(str(zoo_assets.photo(name)), check_existing=True)
        tex.interpolation, tex.extension = "Cubic", "REPEAT"
        if box and not uv:
            tex.projection, tex.projection_blend = "BOX", 0.15
        self.links.new(self.coords(scale, uv), tex.inputs["Vector"])
        mix = self.node("ShaderNodeMix")
        mix.data_type, mix.blend_type = "RGBA", "MULTIPLY"
        mix.inputs["Factor"].default_value = 1.0
        self.links.new(tex.outputs["Color"], mix.inputs["A"])
        mix.inputs["B"].default_value = (*tint, 1.0)
        return mix.outputs["Result"]

    def procedural(self, kind: str, scale: float, wall: bool = False, **settings):
        """Blender's procedural textures at a fine scale: brick (mortar lines), wave (a
        woven-fabric stripe), checker (tiles), noise (grain)."""
        node = self.node({"brick": "ShaderNodeTexBrick", "wave": "ShaderNodeTexWave",
                          "checker": "ShaderNodeTexChecker",
                          "noise": "ShaderNodeTexNoise"}[kind])
        for k, v in settings.items():
            if k in node.inputs:
                node.inputs[k].default_value = v
            else:
                setattr(node, k, v)
        self.links.new(self.coords(scale, wall=wall), node.inputs["Vector"])
        return node.outputs["Color"]

    def set(self, **inputs) -> Material:
        for k, v in inputs.items():
            if isinstance(v, bpy.types.NodeSocket):
                self.links.new(v, self.bsdf.inputs[k])
            else:
                self.bsdf.inputs[k].default_value = (*v, 1.0) if k in (
                    "Base Color", "Emission Color") else v
        return self

    def bump(self, height, strength: float = 0.3) -> Material:
        b = self.node("ShaderNodeBump", Strength=strength)
        self.links.new(height, b.inputs["Height"])
        self.links.new(b.outputs["Normal"], self.bsdf.inputs["Normal"])
        return self


def plain(name: str, rgb, roughness: float = 0.5, **more) -> bpy.types.Material:
    return Material(name).set(**{"Base Color": rgb, "Roughness": roughness, **more}).mat


def photo_material(name: str, photo: str, scale: float, tint=(1, 1, 1), roughness=0.7,
                   uv: bool = False, bump: float = 0.0) -> bpy.types.Material:
    m = Material(name)
    color = m.photo(photo, scale, uv=uv, tint=tint)
    m.set(**{"Base Color": color, "Roughness": roughness})
    if bump:
        m.bump(color, bump)
    return m.mat


def fabric(name: str, rgb, period_m: float) -> bpy.types.Material:
    """Woven fabric: two crossed sets of wave bands repeating every `period_m` metres (a few
    pixels at the shot's distance), as base colour and bump; rough."""
    m = Material(name)
    scale = 2 * math.pi / 10 / period_m  # Blender's wave bands: sin(10 (x + y + z) Scale)
    warp = m.procedural("wave", scale, wave_type="BANDS", bands_direction="X",
                        Scale=1.0, Distortion=1.5, Detail=4.0)
    weft = m.procedural("wave", scale, wave_type="BANDS", bands_direction="Y",
                        Scale=1.0, Distortion=1.5, Detail=4.0)
    mix = m.node("ShaderNodeMix")
    mix.data_type, mix.blend_type = "RGBA", "MULTIPLY"
    mix.inputs["Factor"].default_value = 1.0
    m.links.new(warp, mix.inputs["A"])
    m.links.new(weft, mix.inputs["B"])
    tint = m.node("ShaderNodeMix")
    tint.data_type, tint.blend_type = "RGBA", "MIX"
    tint.inputs["A"].default_value = (*(0.35 * np.asarray(rgb)), 1.0)
    tint.inputs["B"].default_value = (*rgb, 1.0)
    m.links.new(mix.outputs["Result"], tint.inputs["Factor"])
    m.set(**{"Base Color": tint.outputs["Result"], "Roughness": 0.9})
    return m.bump(mix.outputs["Result"], 0.4).mat


def brick_wall(name: str, rgb, brick_m: float = 0.22,
               mortar=(0.55, 0.53, 0.5)) -> bpy.types.Material:
    """Blender's brick texture with bricks `brick_m` long and a quarter as tall (real brick
    proportions): a pixel or two per course at the shots' distances."""
    m = Material(name)
    color = m.procedural("brick", 0.5 / brick_m, wall=True, Color1=(*rgb, 1.0),
                         Color2=(*(0.7 * np.asarray(rgb)), 1.0), Mortar=(*mortar, 1.0),
                         offset=0.5, squash=1.0, Scale=1.0,
                         **{"Mortar Size": 0.012, "Bias": 0.1, "Brick Width": 0.5,
                            "Row Height": 0.13})
    m.set(**{"Base Color": color, "Roughness": 0.85})
    return m.bump(color, 0.5).mat


def leaf_material(name: str, rgb) -> bpy.types.Material:
    m = Material(name)
    m.set(**{"Base Color": rgb, "Roughness": 0.45, "Subsurface Weight": 0.0,
             "Transmission Weight": 0.25})
    return m.mat


def glass(name: str) -> bpy.types.Material:
    return plain(name, (1.0, 1.0, 1.0), 0.0, **{"Transmission Weight": 1.0, "IOR": 1.5})


def metal(name: str, rgb, roughness: float) -> bpy.types.Material:
    return plain(name, rgb, roughness, Metallic=1.0)


# ---------------------------------------------------------------------------------------------
# Lights


def world_hdri(environment: str, strength: float, yaw_deg: float = 0.0) -> None:
    """One of Blender's bundled environments (studiolights/world/<name>.exr)."""
    world = bpy.data.worlds.new(environment)
    world.use_nodes = True
    nodes, links = world.node_tree.nodes, world.node_tree.links
    folder = bpy.utils.system_resource("DATAFILES", path="studiolights/world")
    path = f"{folder}/{environment}.exr"
    tex = nodes.new("ShaderNodeTexEnvironment")
    tex.image = bpy.data.images.load(path, check_existing=True)
    mapping, coords = nodes.new("ShaderNodeMapping"), nodes.new("ShaderNodeTexCoord")
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(yaw_deg))
    links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
    links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    nodes["Background"].inputs["Strength"].default_value = strength
    links.new(tex.outputs["Color"], nodes["Background"].inputs["Color"])
    bpy.context.scene.world = world


def world_sky(elevation_deg: float, azimuth_deg: float, strength: float) -> None:
    """Blender's physical (Nishita) sky without its sun disc; the sun is a lamp (sun())."""
    world = bpy.data.worlds.new("sky")
    world.use_nodes = True
    nodes = world.node_tree.nodes
    sky = nodes.new("ShaderNodeTexSky")
    sky.sky_type, sky.sun_disc = "NISHITA", False
    sky.sun_elevation, sky.sun_rotation = math.radians(elevation_deg), math.radians(azimuth_deg)
    nodes["Background"].inputs["Strength"].default_value = strength
    world.node_tree.links.new(sky.outputs["Color"], nodes["Background"].inputs["Color"])
    bpy.context.scene.world = world


def sun(elevation_deg: float, azimuth_deg: float, strength: float, rgb=(1.0, 0.95, 0.88)):
    light = bpy.data.lights.new("sun", "SUN")
    light.energy, light.color, light.angle = strength, rgb, math.radians(0.53)
    obj = bpy.data.objects.new("sun", light)
    # a sun shines along its local -z: tilt it from the zenith down to the elevation
    obj.rotation_euler = Euler((math.radians(90 - elevation_deg), 0.0,
                                math.radians(azimuth_deg + 90)), "XYZ")
    return link(obj)


def point(name: str, location, watts: float, radius: float = 0.01, rgb=(1.0, 0.9, 0.75)):
    """A small bright bulb: through glass it casts caustics a path tracer finds only by chance
    (fireflies at every spp a farm renders)."""
    light = bpy.data.lights.new(name, "POINT")
    light.energy, light.color, light.shadow_soft_size = watts, rgb, radius
    obj = link(bpy.data.objects.new(name, light))
    obj.location = location
    return obj


def area(name: str, location, target, size: float, watts: float, rgb=(1.0, 0.92, 0.82)):
    light = bpy.data.lights.new(name, "AREA")
    light.energy, light.size, light.color = watts, size, rgb
    obj = link(bpy.data.objects.new(name, light))
    obj.location = location
    obj.rotation_euler = (Vector(target) - Vector(location)).to_track_quat("-Z", "Y").to_euler()
    return obj
