"""A scene description as a Mitsuba scene: the variant, the scene dict (`build`), and what
changes per frame (the camera and the moving parts, `set_frame`). Mitsuba is imported where it
is used: the description side of the generator needs numpy alone.
"""

from __future__ import annotations

import glob
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import materials, meshes
from .camera import Camera
from .environment import sky_bitmap
from .scene_parts import BULB_REFLECTANCE, mover_meshes, scene_parts


def _find_llvm() -> str | None:
    # drjit needs LLVM >= 16 here (14/15 fail); prefer the newest found.
    cands = glob.glob("/usr/lib/x86_64-linux-gnu/libLLVM-*.so") + glob.glob(
        "/usr/lib/llvm-*/lib/libLLVM*.so*"
    )

    def version(p: str) -> int:
        digits = "".join(ch if ch.isdigit() else " " for ch in Path(p).name).split()
        return int(digits[0]) if digits else 0

    good = [p for p in cands if version(p) >= 16]
    return max(good, key=version) if good else None


def set_variant(name: str = "auto") -> str:
    """Activate `llvm_ad_rgb` when a usable LLVM exists (about 2x faster here), else
    `scalar_rgb`. Returns the active variant."""
    if name in ("auto", "llvm_ad_rgb") and "DRJIT_LIBLLVM_PATH" not in os.environ:
        lib = _find_llvm()
        if lib:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    import mitsuba as mi

    if name != "auto":
        mi.set_variant(name)
        return name
    try:
        mi.set_variant("llvm_ad_rgb")
        import drjit as dr

        dr.eval(dr.llvm.Float(1.0) + 1.0)  # fails here when the LLVM library is unusable
        return "llvm_ad_rgb"
    except Exception:  # noqa: BLE001 - any backend failure means: use the CPU scalar variant
        mi.set_variant("scalar_rgb")
        return "scalar_rgb"


def _emitter_rgb(color: list[float], scale: float) -> dict:
    return {"type": "rgb", "value": (np.asarray(color) * scale).tolist()}


def build(desc: dict) -> tuple[dict, dict[str, list[float]]]:
    """Mitsuba scene dict without sensor and integrator, plus per-shape albedo overrides
    (shape id -> RGB) for surfaces whose Mitsuba albedo AOV is not a reflectance. Static
    geometry is merged into one mesh per material (fewer shapes, one BSDF instance each)."""
    import mitsuba as mi

    mats = desc["materials"]
    parts = scene_parts(desc)
    scene: dict = {"type": "scene"}
    overrides: dict[str, list[float]] = {}
    bsdfs: dict[int, object] = {}

    def bsdf(idx: int):
        if idx not in bsdfs:
            bsdfs[idx] = mi.load_dict(materials.bsdf_dict(mats[idx]))
        return bsdfs[idx]

    def add(name: str, mesh: meshes.MeshData, idx: int) -> None:
        scene[name] = meshes.to_mitsuba(mesh, name, bsdf(idx))
        albedo = materials.albedo_of(mats[idx])
        if albedo is not None:
            overrides[name] = albedo

    for idx, mesh in parts.static.items():
        add(f"mat{idx:02d}", mesh, idx)
    for name, mesh, frames, idx in parts.movers:
        add(name, mesh.transformed(frames[0]), idx)
    grey = {"type": "diffuse", "reflectance": {"type": "rgb", "value": BULB_REFLECTANCE}}
    dark = mi.load_dict(grey)
    for k, (mesh, rgb) in enumerate(parts.bulbs):
        emitter = mi.load_dict({"type": "area", "radiance": {"type": "rgb", "value": rgb}})
        scene[f"bulb{k:02d}"] = meshes.to_mitsuba(mesh, f"bulb{k:02d}", dark, emitter)
    env = desc["environment"]
    scene["env"] = {"type": "envmap", "bitmap": mi.Bitmap(sky_bitmap(env))}
    if "sun" in env:
        sun = env["sun"]
        scene["sun"] = {
            "type": "directional",
            "direction": (-np.asarray(sun["to_sun"])).tolist(),
            "irradiance": _emitter_rgb(sun["color"], sun["irradiance"]),
        }
    return scene, overrides


def shape_index(scene) -> dict[int, str]:
    """The per-sample shape channel's value -> shape id: the registry id in JIT variants, the
    1-based position in `scene.shapes()` in scalar ones (what the `aov` integrator writes)."""
    import mitsuba as mi

    shapes = scene.shapes()
    if mi.variant().startswith("scalar"):
        return {i + 1: s.id() for i, s in enumerate(shapes)}
    import drjit as dr

    ids = np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shapes)))
    return {int(i): s.id() for i, s in zip(ids, shapes, strict=True)}


@dataclass
class Mover:
    """A moving part: its shape-channel value, Mitsuba id, object-space mesh, per-frame 4x4."""

    key: int
    name: str
    mesh: object
    frames: list[np.ndarray]


def movers_of(scene, desc: dict) -> list[Mover]:
    names = {name: key for key, name in shape_index(scene).items()}
    return [Mover(names[n], n, m, f) for n, m, f in mover_meshes(desc) if n in names]


def set_frame(scene, cam: Camera, movers: list[Mover], t: int) -> None:
    """Camera and moving objects of frame t (one parameter update: one BVH rebuild)."""
    import mitsuba as mi

    params = mi.traverse(scene)
    params["sensor.to_world"] = mi.Transform4f(cam.to_world())
    params["sensor.x_fov"] = cam.fov_x
    for m in movers:
        placed = m.mesh.transformed(m.frames[t])
        params[f"{m.name}.vertex_positions"] = np.ascontiguousarray(placed.positions).ravel()
        params[f"{m.name}.vertex_normals"] = np.ascontiguousarray(placed.normals).ravel()
    params.update()
