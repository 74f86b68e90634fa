"""The Cycles back end of the g2 scene description: the same triangles, materials, lamps, sky,
sun, moving objects and cameras as the Mitsuba scene (`scene_parts.scene_parts`), built as a
Blender scene through `bpy` (Blender 4.5 LTS as a Python module, the `cycles` extra).

World coordinates are the description's (y up); Blender does not care which way is up except
for the environment texture, whose bitmap is resampled into Blender's z-up equirectangular
parameterisation here. How each material and light maps (exactly or approximately) is listed in
docs/data.md, "Cycles back end"; the short form is beside each builder below.
"""

from __future__ import annotations

import math

import bpy  # only in the Cycles venv (extra `cycles`); never imported by serving or tests
import numpy as np
from mathutils import Matrix

from . import materials
from .camera import Camera
from .environment import sky_bitmap
from .meshes import MeshData
from .scene_parts import BULB_REFLECTANCE, scene_parts

# Mitsuba's `plastic`/`roughplastic` default interior IOR (polypropylene).
PLASTIC_IOR = 1.49
SKY_WIDTH = 1024  # Blender-side equirectangular width (resampled from the Mitsuba bitmap)


# ---------------------------------------------------------------------------------------------
# Images


def _image(name: str, pixels: np.ndarray, color: bool) -> bpy.types.Image:
    """A float image from (H, W, 3) or (H, W) pixels; row 0 of `pixels` is Blender's bottom
    row, so v = 0 samples row 0 as in Mitsuba's bitmap lookup."""
    h, w = pixels.shape[:2]
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = pixels if pixels.ndim == 3 else pixels[..., None]
    img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    img.colorspace_settings.name = "Linear Rec.709" if color else "Non-Color"
    img.pixels.foreach_set(rgba.ravel())
    img.pack()  # keeps the generated pixels with the scene (no file behind them)
    return img


def sky_pixels(env: dict, width: int = SKY_WIDTH) -> np.ndarray:
    """The description's sky in Cycles' equirectangular mapping (z up: u = 0.5 - atan2(y, x) /
    2pi, v = 0.5 + asin(z) / pi, image row 0 at v = 0), resampled bilinearly from the Mitsuba
    bitmap (y up: u = atan2(x, -z) / 2pi, v = acos(y) / pi, row 0 at v = 0)."""
    src = sky_bitmap(env, width)
    h = width // 2
    u, v = np.meshgrid((np.arange(width) + 0.5) / width, (np.arange(h) + 0.5) / h)
    phi, el = (0.5 - u) * 2 * np.pi, (v - 0.5) * np.pi
    d = np.stack([np.cos(el) * np.cos(phi), np.cos(el) * np.sin(phi), np.sin(el)], -1)
    # Blender world axes are the description's: x, y (up), z.
    mu = (np.arctan2(d[..., 0], -d[..., 2]) / (2 * np.pi)) % 1.0
    mv = np.arccos(np.clip(d[..., 1], -1, 1)) / np.pi
    sh, sw = src.shape[:2]
    x, y = mu * sw - 0.5, mv * sh - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    xa, xb = x0 % sw, (x0 + 1) % sw  # wraps around in longitude
    ya, yb = np.clip(y0, 0, sh - 1), np.clip(y0 + 1, 0, sh - 1)
    top = src[ya, xa] * (1 - fx) + src[ya, xb] * fx
    bottom = src[yb, xa] * (1 - fx) + src[yb, xb] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Materials


class _Nodes:
    """A material's node tree under construction."""

    def __init__(self, name: str) -> None:
        self.mat = bpy.data.materials.new(name)
        self.mat.use_nodes = True
        self.tree = self.mat.node_tree
        self.tree.nodes.clear()

    def new(self, kind: str, **inputs):
        node = self.tree.nodes.new(kind)
        for key, value in inputs.items():
            node.inputs[key].default_value = value
        return node

    def link(self, out, into) -> None:
        self.tree.links.new(out, into)

    def texture(self, pixels: np.ndarray, tiling: float, color: bool, name: str):
        """Image texture on the mesh UVs scaled by `tiling` (Mitsuba's to_uv), bilinear, repeat."""
        uv = self.new("ShaderNodeTexCoord")
        mapping = self.new("ShaderNodeMapping")
        mapping.inputs["Scale"].default_value = (tiling, tiling, 1.0)
        self.link(uv.outputs["UV"], mapping.inputs["Vector"])
        tex = self.new("ShaderNodeTexImage")
        tex.image = _image(name, pixels, color)
        tex.interpolation, tex.extension = "Linear", "REPEAT"
        self.link(mapping.outputs["Vector"], tex.inputs["Vector"])
        return tex.outputs["Color"]

    def output(self, shader) -> bpy.types.Material:
        out = self.new("ShaderNodeOutputMaterial")
        self.link(shader, out.inputs["Surface"])
        return self.mat


def _rgba(rgb) -> tuple[float, float, float, float]:
    return (*map(float, rgb), 1.0)


def _roughness(alpha: float) -> float:
    """Principled/Glass roughness r has GGX alpha = r^2 (Mitsuba's alpha is the lobe width)."""
    return math.sqrt(alpha)


def material(mat: dict, name: str) -> bpy.types.Material:
    """A Cycles material for a description (see the module docstring for how exact)."""
    n = _Nodes(name)
    kind = mat["kind"]
    if kind in ("diffuse", "plastic", "roughplastic"):
        color = (
            n.texture(materials.texture_pixels(mat["texture"], True), mat["texture"]["tiling"],
                      True, f"{name}.tex")
            if "texture" in mat
            else None
        )
        if kind == "diffuse":  # Lambertian: exact
            shader = n.new("ShaderNodeBsdfDiffuse", Roughness=0.0)
        else:  # a dielectric coat over a diffuse base: approximate (Principled, GGX)
            rough = _roughness(mat["alpha"]) if kind == "roughplastic" else 0.0
            shader = n.new("ShaderNodeBsdfPrincipled", Roughness=rough, IOR=PLASTIC_IOR)
            shader.inputs["Metallic"].default_value = 0.0
        slot = shader.inputs["Color" if kind == "diffuse" else "Base Color"]
        slot.default_value = _rgba(mat["color"])
        if color is not None:
            n.link(color, slot)
    elif kind in ("conductor", "roughconductor"):  # F82 metal from the reflectance: approximate
        shader = n.new("ShaderNodeBsdfPrincipled", Metallic=1.0)
        shader.inputs["Base Color"].default_value = _rgba(materials.METALS[mat["metal"]])
        shader.inputs["Roughness"].default_value = (
            _roughness(mat["alpha"]) if kind == "roughconductor" else 0.0
        )
        if "alpha_texture" in mat:
            rough = np.sqrt(materials.roughness_pixels(mat))
            tex = n.texture(rough, mat["alpha_texture"]["tiling"], False, f"{name}.rough")
            n.link(tex, shader.inputs["Roughness"])
    elif kind == "thindielectric":  # Fresnel-weighted mirror over straight transmission
        fresnel = n.new("ShaderNodeFresnel", IOR=mat["ior"])
        mirror = n.new("ShaderNodeBsdfGlossy", Roughness=0.0)
        through = n.new("ShaderNodeBsdfTransparent", Color=_rgba(mat["tint"]))
        mix = n.new("ShaderNodeMixShader")
        n.link(fresnel.outputs["Fac"], mix.inputs["Fac"])
        n.link(through.outputs[0], mix.inputs[1])
        n.link(mirror.outputs[0], mix.inputs[2])
        return n.output(mix.outputs[0])
    else:  # dielectric, roughdielectric: Glass BSDF (its colour tints reflection too)
        rough = _roughness(mat["alpha"]) if kind == "roughdielectric" else 0.0
        shader = n.new("ShaderNodeBsdfGlass", IOR=mat["ior"], Roughness=rough)
        shader.inputs["Color"].default_value = _rgba(mat["tint"])
        return n.output(shader.outputs[0])
    if "bump" in mat:  # Mitsuba's bumpmap height (scale x 0.02 m per unit): approximate
        spec = mat["bump"]
        height = n.texture(materials.texture_pixels(spec, False), spec["tiling"], False,
                           f"{name}.bump")
        bump = n.new("ShaderNodeBump", Strength=1.0, Distance=spec["scale"] * 0.02)
        n.link(height, bump.inputs["Height"])
        n.link(bump.outputs["Normal"], shader.inputs["Normal"])
    return n.output(shader.outputs[0])


def emitter_material(rgb: list[float], name: str) -> bpy.types.Material:
    """A lit bulb: uniform emission of radiance `rgb` (Cycles' emission strength is radiance)
    plus the grey diffuse surface Mitsuba gives it. Exact for closed bulbs (Mitsuba emits from
    the front side only; the back faces inwards)."""
    n = _Nodes(name)
    peak = max(max(rgb), 1e-12)
    emit = n.new("ShaderNodeEmission", Strength=peak)
    emit.inputs["Color"].default_value = _rgba(np.asarray(rgb) / peak)
    grey = n.new("ShaderNodeBsdfDiffuse", Roughness=0.0)
    grey.inputs["Color"].default_value = _rgba([BULB_REFLECTANCE] * 3)
    add = n.new("ShaderNodeAddShader")
    n.link(emit.outputs[0], add.inputs[0])
    n.link(grey.outputs[0], add.inputs[1])
    return n.output(add.outputs[0])


# ---------------------------------------------------------------------------------------------
# Geometry, lights, camera


def mesh_object(name: str, mesh: MeshData, mat: bpy.types.Material) -> bpy.types.Object:
    """A Blender mesh with the description's vertices, UVs and (custom split) normals."""
    me = bpy.data.meshes.new(name)
    faces = np.ascontiguousarray(mesh.faces, np.int32)
    me.vertices.add(len(mesh.positions))
    me.vertices.foreach_set("co", np.ascontiguousarray(mesh.positions, np.float32).ravel())
    me.loops.add(faces.size)
    me.loops.foreach_set("vertex_index", faces.ravel())
    me.polygons.add(len(faces))
    me.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
    uv = me.uv_layers.new(name="UVMap")
    uv.data.foreach_set("uv", np.ascontiguousarray(mesh.uvs[faces.ravel()], np.float32).ravel())
    me.update()
    me.polygons.foreach_set("use_smooth", np.ones(len(faces), bool))
    me.normals_split_custom_set_from_vertices(np.ascontiguousarray(mesh.normals, np.float32))
    me.materials.append(mat)
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _matrix(m4: np.ndarray) -> Matrix:
    """A mathutils matrix from a row-major 4x4 (a plain nested list is read column-major)."""
    return Matrix([list(map(float, row)) for row in np.asarray(m4)])


def _keyframe_matrix(obj: bpy.types.Object, m4: np.ndarray, frame: int) -> None:
    obj.matrix_world = _matrix(m4)
    obj.keyframe_insert("location", frame=frame)
    obj.keyframe_insert("rotation_quaternion", frame=frame)
    obj.keyframe_insert("scale", frame=frame)


def _linear_keys(obj: bpy.types.Object) -> None:
    """Linear between keys: every frame is keyed, so motion vectors to frame t-1 are exact."""
    for anim in (obj.animation_data, getattr(obj.data, "animation_data", None)):
        if anim is None or anim.action is None:
            continue
        for curve in anim.action.fcurves:
            for key in curve.keyframe_points:
                key.interpolation = "LINEAR"


def blender_frame(t: int) -> int:
    """Scene frame of description frame t (Blender numbers frames from 1, as farms do)."""
    return t + 1


def camera_matrix(cam: Camera) -> np.ndarray:
    """Blender camera-to-world: it looks along local -z with local +y up and +x right; the
    description's camera has columns (left, up, forward, origin)."""
    left, up, fwd = cam.basis()
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = -left, up, -fwd, cam.origin
    return m


def add_camera(cameras: list[Camera]) -> bpy.types.Object:
    data = bpy.data.cameras.new("camera")
    data.sensor_fit = "HORIZONTAL"
    data.clip_start = 0.01
    obj = bpy.data.objects.new("camera", data)
    obj.rotation_mode = "QUATERNION"
    bpy.context.scene.collection.objects.link(obj)
    for t, cam in enumerate(cameras):
        _keyframe_matrix(obj, camera_matrix(cam), blender_frame(t))
        data.angle = math.radians(cam.fov_x)  # horizontal field of view (sensor fit)
        data.keyframe_insert("lens", frame=blender_frame(t))
    _linear_keys(obj)
    bpy.context.scene.camera = obj
    return obj


def add_sun(sun: dict, exposure: float) -> None:
    """Mitsuba's `directional` light: a Blender sun of angle 0 whose strength is the irradiance
    (exact)."""
    color = np.asarray(sun["color"], np.float64)
    peak = float(color.max())
    light = bpy.data.lights.new("sun", "SUN")
    light.energy = sun["irradiance"] * peak * exposure
    light.color = (color / peak).tolist()
    light.angle = 0.0
    obj = bpy.data.objects.new("sun", light)
    z = np.asarray(sun["to_sun"], np.float64)  # the light shines along its local -z
    x = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = x, np.cross(z, x), z
    obj.matrix_world = _matrix(m)
    bpy.context.scene.collection.objects.link(obj)


def add_world(env: dict, exposure: float) -> None:
    """The procedural sky as an environment texture (bilinear resampling: approximate to the
    bitmap's resolution)."""
    world = bpy.data.worlds.new("sky")
    world.use_nodes = True
    nodes = world.node_tree.nodes
    tex = nodes.new("ShaderNodeTexEnvironment")
    tex.image = _image("sky", sky_pixels(env), True)
    tex.interpolation = "Linear"
    background = nodes["Background"]
    background.inputs["Strength"].default_value = exposure
    world.node_tree.links.new(tex.outputs["Color"], background.inputs["Color"])
    bpy.context.scene.world = world


def build_scene(desc: dict, exposure: float = 1.0) -> bpy.types.Scene:
    """An empty Blender, then the description's scene with every emitter scaled by `exposure`
    (so the render is already exposed, and Cycles' indirect clamp acts on exposed values)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    mats = desc["materials"]
    parts = scene_parts(desc)
    made: dict[int, bpy.types.Material] = {}

    def mat_of(idx: int) -> bpy.types.Material:
        if idx not in made:
            made[idx] = material(mats[idx], f"mat{idx:02d}")
        return made[idx]

    for idx, mesh in parts.static.items():
        mesh_object(f"mat{idx:02d}", mesh, mat_of(idx))
    for name, mesh, frames, idx in parts.movers:
        obj = mesh_object(name, mesh, mat_of(idx))
        obj.rotation_mode = "QUATERNION"
        for t, m4 in enumerate(frames):
            _keyframe_matrix(obj, np.asarray(m4), blender_frame(t))
        _linear_keys(obj)
    for k, (mesh, rgb) in enumerate(parts.bulbs):
        scaled = (np.asarray(rgb) * exposure).tolist()
        mesh_object(f"bulb{k:02d}", mesh, emitter_material(scaled, f"bulb{k:02d}"))
    env = desc["environment"]
    add_world(env, exposure)
    if "sun" in env:
        add_sun(env["sun"], exposure)
    cams = [Camera(**c) for c in desc["cameras"]]
    add_camera(cams)
    scene.frame_start, scene.frame_end = blender_frame(0), blender_frame(len(cams) - 1)
    return scene
