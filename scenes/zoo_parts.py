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


def box(name: str, lo, hi, mat) -> bpy.types.Object:
    """An axis-aligned box from corner `lo` to corner `hi` (vertices in world metres, so
    object-space texture coordinates are metres)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0),
         (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)]
    f = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    return mesh(name, v, f, mat)


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


def area(name: str, location, target, size: float, watts: float, rgb=(1.0, 0.92, 0.82)):
    light = bpy.data.lights.new(name, "AREA")
    light.energy, light.size, light.color = watts, size, rgb
    obj = link(bpy.data.objects.new(name, light))
    obj.location = location
    obj.rotation_euler = (Vector(target) - Vector(location)).to_track_quat("-Z", "Y").to_euler()
    return obj
