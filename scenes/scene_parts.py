"""A scene description's geometry and emitters as both renderers build them (`mitsuba_scene.py`,
`cycles_scene.py`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import architecture, furniture, meshes
from .architecture import Y_UP


def _bulb_radiance(piece: dict, mesh: meshes.MeshData) -> float:
    light = piece["light"]
    if "radiance" in light:
        return light["radiance"]
    p = mesh.positions
    area = float(
        np.linalg.norm(
            np.cross(*(p[mesh.faces[:, 1:]] - p[mesh.faces[:, :1]]).transpose(1, 0, 2)), axis=-1
        ).sum()
        / 2
    )
    return light["power"] / (np.pi * area)


def mover_meshes(desc: dict) -> list[tuple[str, meshes.MeshData, list[np.ndarray]]]:
    """(shape name, object-space mesh, per-frame 4x4 transforms) of every moving part."""
    out = []
    for j, piece in enumerate(desc["movers"]):
        by_role: dict[str, list] = {}
        for role, m in furniture.parts(piece["kind"], piece["params"]):
            by_role.setdefault(role, []).append(m)
        frames = [np.asarray(f) for f in piece["frames"]]
        for role, ms in sorted(by_role.items()):
            out.append((f"mover{j}_{role}", meshes.merge(ms), frames))
    return out


@dataclass
class SceneParts:
    """What both renderers build from a description: static geometry merged per material
    index, moving parts (object-space mesh, per-frame 4x4, material index), lit bulbs (placed
    mesh, linear-RGB radiance) and the ground plane. One place, so the Mitsuba and Cycles
    scenes hold the same triangles, materials and emitters."""

    static: dict[int, meshes.MeshData]
    movers: list[tuple[str, meshes.MeshData, list[np.ndarray], int]]
    bulbs: list[tuple[meshes.MeshData, list[float]]]


def scene_parts(desc: dict) -> SceneParts:
    surf = desc["surfaces"]
    groups: dict[int, list[meshes.MeshData]] = {}
    for key, m in architecture.meshes_of(desc["layout"]):
        groups.setdefault(surf[key], []).append(m)
    ground = architecture.quad([0, -0.02, 0], [1, 0, 0], [0, 0, 1], Y_UP, [-200, 200, -200, 200])
    groups.setdefault(surf["ground"], []).append(ground)
    bulbs: list[tuple[meshes.MeshData, list[float]]] = []
    for piece in desc["pieces"]:
        m4 = np.asarray(piece["transform"])
        for role, m in furniture.parts(piece["kind"], piece["params"]):
            m = m.transformed(m4)
            if role == "bulb" and piece["light"]["on"]:
                rgb = np.asarray(piece["light"]["color"]) * _bulb_radiance(piece, m)
                bulbs.append((m, rgb.tolist()))
            else:
                idx = surf["bulb_off"] if role == "bulb" else piece["materials"][role]
                groups.setdefault(idx, []).append(m)
    movers = []
    for name, mesh, frames in mover_meshes(desc):
        j, role = name[5:].split("_", 1)
        movers.append((name, mesh, frames, desc["movers"][int(j)]["materials"][role]))
    static = {idx: meshes.merge(ms) for idx, ms in sorted(groups.items())}
    return SceneParts(static, movers, bulbs)


BULB_REFLECTANCE = 0.8  # the diffuse grey of a lit bulb's surface (both renderers)
