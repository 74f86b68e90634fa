"""Furniture and props assembled from parts (numpy meshes), for generator g2.

A piece is `(kind, params)`: `draw(kind, rng)` draws the JSON-able params, `parts(kind, params)`
rebuilds the meshes, each tagged with the material role of that part ("wood", "metal",
"fabric", ...; see `materials.ROLES`) or "bulb" for a lamp's emitter. Local frame: the floor is
y = 0 (pendants hang from y = 0 downwards, pictures are centred in the XY plane facing +Z),
the piece is centred in x and z and its front faces +Z.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from . import meshes
from .meshes import MeshData, box_at, cylinder_at

Parts = list[tuple[str, MeshData]]


# How one parameter of a piece is drawn from the scene's generator.
Draw = Callable[[np.random.Generator], float | int | bool | str]


def _uniform(lo: float, hi: float) -> Draw:
    return lambda rng: float(rng.uniform(lo, hi))


def _integer(lo: int, hi: int) -> Draw:
    """An int in [lo, hi)."""
    return lambda rng: int(rng.integers(lo, hi))


def _one_of(*options: str) -> Draw:
    """One of `options` (one listed twice is twice as likely)."""
    return lambda rng: str(rng.choice(options))


def _chance(p: float) -> Draw:
    """True with probability `p`."""
    return lambda rng: bool(rng.random() < p)


def _seed(rng: np.random.Generator) -> int:
    """The seed of a piece's own generator (its books, its leaves)."""
    return int(rng.integers(2**31))


def _legs(w: float, d: float, h: float, leg: float, inset: float, round_: bool) -> list:
    out = []
    for sx in (-1, 1):
        for sz in (-1, 1):
            x, z = sx * (w / 2 - inset), sz * (d / 2 - inset)
            if round_:
                out.append(cylinder_at(leg / 2, h, (x, 0, z)))
            else:
                out.append(box_at((leg, h, leg), (x, h / 2, z)))
    return out


def _yaw(mesh: MeshData, angle: float, shift=(0.0, 0.0, 0.0)) -> MeshData:
    c, s = np.cos(angle), np.sin(angle)
    m = np.array([[c, 0, s, shift[0]], [0, 1, 0, shift[1]], [-s, 0, c, shift[2]], [0, 0, 0, 1]])
    return mesh.transformed(m)


# ---------------------------------------------------------------------------------------------
# Parameters


# Each piece's parameters (sizes in metres, part materials as roles) and how each is drawn,
# in drawing order: they take turns on the scene's generator, so reordering a piece's entries
# (or adding one) changes every scene that has that piece.
_PARAMS: dict[str, dict[str, Draw]] = {
    "table": {
        "w": _uniform(0.8, 1.8), "d": _uniform(0.6, 1.0), "h": _uniform(0.42, 0.78),
        "top": _uniform(0.02, 0.05), "leg": _uniform(0.03, 0.07), "round": _chance(0.3),
        "top_role": _one_of("wood", "wood", "glass", "stone"),
        "leg_role": _one_of("wood", "metal"),
    },
    "chair": {
        "w": _uniform(0.4, 0.5), "seat": _uniform(0.42, 0.48), "back": _uniform(0.35, 0.5),
        "leg": _uniform(0.02, 0.04), "slats": _integer(0, 5),
        "seat_role": _one_of("wood", "fabric"), "leg_role": _one_of("wood", "metal"),
    },
    "bookcase": {
        "w": _uniform(0.6, 1.6), "h": _uniform(1.0, 2.2), "d": _uniform(0.25, 0.4),
        "boards": _integer(3, 7), "seed": _seed,
    },
    "sofa": {
        "w": _uniform(1.5, 2.4), "d": _uniform(0.8, 1.0), "arm": _uniform(0.12, 0.25),
        "cushions": _integer(2, 4),
    },
    "bed": {"w": _uniform(1.0, 1.8), "l": _uniform(2.0, 2.15), "pillows": _integer(1, 3)},
    "cabinet": {
        "w": _uniform(0.8, 1.8), "h": _uniform(0.5, 0.9), "d": _uniform(0.4, 0.5),
        "doors": _integer(2, 5),
    },
    "plant": {
        "h": _uniform(0.4, 1.6), "pot": _uniform(0.1, 0.22), "leaves": _integer(12, 40),
        "seed": _seed,
    },
    "floor_lamp": {
        "h": _uniform(1.3, 1.8), "shade": _uniform(0.15, 0.25), "bulb": _uniform(0.02, 0.04),
    },
    "pendant": {
        "drop": _uniform(0.5, 1.1), "shade": _uniform(0.12, 0.3),
        "shape": _one_of("cone", "dome", "drum"), "bulb": _uniform(0.02, 0.04),
        "shade_role": _one_of("metal", "ceramic", "fabric"),
    },
    "picture": {
        "w": _uniform(0.3, 1.2), "h": _uniform(0.3, 1.0), "frame": _uniform(0.015, 0.06),
        "frame_role": _one_of("wood", "metal", "dark"),
    },
    "rug": {"w": _uniform(1.2, 3.0), "d": _uniform(0.8, 2.0)},
    "railing": {
        "l": _uniform(1.5, 4.0), "h": _uniform(0.85, 1.05), "gap": _uniform(0.1, 0.16),
        "bar": _uniform(0.008, 0.015), "role": _one_of("metal", "wood"),
    },
    "bench": {"w": _uniform(1.2, 2.0), "slats": _integer(3, 7)},
    "column": {"r": _uniform(0.14, 0.3), "h": _uniform(3.0, 4.0)},
    "vase": {
        "h": _uniform(0.15, 0.45), "r": _uniform(0.05, 0.12), "bulge": _uniform(0.6, 1.6),
        "role": _one_of("glass", "glass", "ceramic", "metal"),
    },
    "bowl": {"r": _uniform(0.08, 0.18), "role": _one_of("ceramic", "metal", "glass")},
    "ball": {"r": _uniform(0.06, 0.2), "role": _one_of("metal", "ceramic", "glass")},
    # a tiny very bright emitter: fireflies in glossy surfaces
    "led": {"r": _uniform(0.004, 0.012)},
}


def draw(kind: str, rng: np.random.Generator) -> dict:
    """Random parameters of a piece (sizes in metres, part materials as roles)."""
    if kind not in _PARAMS:
        raise ValueError(f"unknown piece {kind!r}")
    return {name: draw_one(rng) for name, draw_one in _PARAMS[kind].items()}


# ---------------------------------------------------------------------------------------------
# Meshes


def parts(kind: str, p: dict) -> Parts:
    """The meshes of piece `kind`, each tagged with its material role."""
    return _BUILDERS[kind](p)


def _table(p: dict) -> Parts:
    w, d, h, top = p["w"], p["d"], p["h"], p["top"]
    if p["round"]:
        r = min(w, d) / 2 + 0.15
        out = [(p["top_role"], cylinder_at(r, top, (0, h - top, 0)))]
        out.append((p["leg_role"], cylinder_at(p["leg"], h - top, (0, 0, 0))))
        out.append((p["leg_role"], cylinder_at(r * 0.45, 0.03, (0, 0, 0))))
        return out
    out = [(p["top_role"], box_at((w, top, d), (0, h - top / 2, 0)))]
    legs = _legs(w, d, h - top, p["leg"], p["leg"], p["leg_role"] == "metal")
    return out + [(p["leg_role"], m) for m in legs]


def _chair(p: dict) -> Parts:
    w, s, leg = p["w"], p["seat"], p["leg"]
    t = 0.04
    out = [(p["seat_role"], box_at((w, t, w), (0, s - t / 2, 0)))]
    round_ = p["leg_role"] == "metal"
    out += [(p["leg_role"], m) for m in _legs(w, w, s - t, leg, leg, round_)]
    z = -w / 2 + leg / 2
    for sx in (-1, 1):  # back uprights continue the rear legs
        out.append(
            (
                p["leg_role"],
                box_at((leg, p["back"], leg), (sx * (w / 2 - leg), s + p["back"] / 2, z)),
            )
        )
    if p["slats"] == 0:
        out.append(
            (
                p["seat_role"],
                box_at((w - 2 * leg, p["back"] * 0.5, 0.02), (0, s + p["back"] * 0.7, z)),
            )
        )
    else:
        for i in range(p["slats"]):  # thin vertical slats: fine shadows and gaps
            x = (i + 0.5) / p["slats"] * (w - 2 * leg) - (w / 2 - leg)
            out.append(
                (p["leg_role"], box_at((0.015, p["back"], 0.015), (x, s + p["back"] / 2, z)))
            )
        out.append((p["leg_role"], box_at((w, 0.04, 0.025), (0, s + p["back"], z))))
    return out


def _bookcase(p: dict) -> Parts:
    w, h, d, n = p["w"], p["h"], p["d"], p["boards"]
    b = 0.025
    out = [("wood", box_at((b, h, d), (sx * (w - b) / 2, h / 2, 0))) for sx in (-1, 1)]
    out.append(("wood", box_at((w, h, 0.01), (0, h / 2, -d / 2 + 0.005))))
    rng = np.random.default_rng(p["seed"])
    gap = (h - b) / (n - 1)
    for i in range(n):
        y = b / 2 + i * gap
        out.append(("wood", box_at((w - 2 * b, b, d), (0, y, 0))))
        if i == n - 1 or rng.random() < 0.2:
            continue
        x = -w / 2 + b
        while True:  # a row of books of random size, some missing
            bw = rng.uniform(0.015, 0.05)
            bh = min(gap - b - 0.01, rng.uniform(0.15, 0.32))
            if x + bw > w / 2 - b or bh < 0.08:
                break
            if rng.random() < 0.85:
                bd = d * rng.uniform(0.6, 0.9)
                role = str(rng.choice(["fabric", "ceramic", "paper"]))
                out.append(
                    (
                        role,
                        box_at(
                            (bw, bh, bd), (x + bw / 2, y + b / 2 + bh / 2, -d / 2 + bd / 2 + 0.01)
                        ),
                    )
                )
            x += bw + 0.002
    return out


def _sofa(p: dict) -> Parts:
    w, d, a = p["w"], p["d"], p["arm"]
    seat, leg = 0.42, 0.08
    out = [("fabric", box_at((w, 0.2, d), (0, leg + 0.1, 0)))]
    out += [("wood", m) for m in _legs(w, d, leg, 0.04, 0.06, False)]
    for sx in (-1, 1):
        out.append(
            (
                "fabric",
                meshes.rounded_box((a, 0.62 - leg, d), 0.05).transformed(
                    _at(sx * (w - a) / 2, leg + (0.62 - leg) / 2, 0)
                ),
            )
        )
    n = p["cushions"]
    cw = (w - 2 * a) / n
    for i in range(n):
        x = -w / 2 + a + cw * (i + 0.5)
        out.append(
            (
                "fabric",
                meshes.rounded_box((cw - 0.01, 0.14, d - 0.2), 0.05).transformed(
                    _at(x, seat - 0.02, 0.08)
                ),
            )
        )
        out.append(
            (
                "fabric",
                meshes.rounded_box((cw - 0.01, 0.45, 0.18), 0.06).transformed(
                    _at(x, seat + 0.2, -d / 2 + 0.1)
                ),
            )
        )
    return out


def _at(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def _bed(p: dict) -> Parts:
    w, length = p["w"], p["l"]
    out = [("wood", box_at((w + 0.06, 0.3, length), (0, 0.15, 0)))]
    out.append(("wood", box_at((w + 0.06, 1.0, 0.05), (0, 0.5, -length / 2))))
    out.append(
        ("fabric", meshes.rounded_box((w, 0.2, length - 0.06), 0.06).transformed(_at(0, 0.4, 0.02)))
    )
    out.append(
        (
            "paper",
            meshes.rounded_box((w + 0.04, 0.05, length * 0.6), 0.02).transformed(
                _at(0, 0.5, length * 0.18)
            ),
        )
    )
    n = p["pillows"]
    for i in range(n):
        x = (i + 0.5) / n * w - w / 2
        out.append(
            (
                "fabric",
                meshes.rounded_box((w / n - 0.08, 0.12, 0.38), 0.05).transformed(
                    _at(x, 0.55, -length / 2 + 0.3)
                ),
            )
        )
    return out


def _cabinet(p: dict) -> Parts:
    w, h, d = p["w"], p["h"], p["d"]
    leg = 0.1
    out = [("wood", box_at((w, h - leg, d), (0, leg + (h - leg) / 2, 0)))]
    out += [("metal", m) for m in _legs(w, d, leg, 0.025, 0.05, True)]
    for i in range(p["doors"]):  # handles: thin metal bars on the front
        x = (i + 0.5) / p["doors"] * w - w / 2
        out.append(("metal", box_at((0.01, 0.12, 0.02), (x, leg + (h - leg) * 0.7, d / 2 + 0.01))))
    return out


def _plant(p: dict) -> Parts:
    rng = np.random.default_rng(p["seed"])
    r, h = p["pot"], p["h"]
    ph = r * 1.2
    out = [("ceramic", meshes.lathe([r * 0.7, r, r * 1.05], [0, ph * 0.9, ph]))]
    out.append(("dark", cylinder_at(r * 0.98, 0.01, (0, ph * 0.85, 0))))
    for _ in range(p["leaves"]):  # stems from the pot with one leaf each: thin geometry
        yaw = rng.uniform(0, 2 * np.pi)
        tilt = rng.uniform(0.05, 0.6)
        length = rng.uniform(0.4, 1.0) * (h - ph)
        tip = (
            np.array([np.sin(tilt) * np.cos(yaw), np.cos(tilt), np.sin(tilt) * np.sin(yaw)])
            * length
        )
        stem = meshes.cylinder(0.004, 1.0, cols=6, caps=False)
        out.append(("leaf", stem.transformed(_segment(np.array([0, ph * 0.85, 0]), tip))))
        lf = meshes.leaf(rng.uniform(0.1, 0.25) * max(h, 0.6), rng.uniform(0.03, 0.08))
        out.append(
            (
                "leaf",
                _yaw(
                    _tilted(lf, rng.uniform(-0.6, 0.3)), -yaw, (tip[0], ph * 0.85 + tip[1], tip[2])
                ),
            )
        )
    return out


def _tilted(m: MeshData, angle: float) -> MeshData:
    c, s = np.cos(angle), np.sin(angle)
    return m.transformed(np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))


def _segment(a: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Map the unit Y-cylinder (centred, height 1) onto the segment a -> a + d."""
    length = float(np.linalg.norm(d))
    y = d / length
    x = np.cross(y, [0, 0, 1.0]) if abs(y[2]) < 0.9 else np.cross(y, [1.0, 0, 0])
    x /= np.linalg.norm(x)
    z = np.cross(x, y)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y * length, z, a + d / 2
    return m


def _shade(shape: str, r: float) -> MeshData:
    """An open lamp shade hanging below y = 0 (its top rim at y = 0)."""
    if shape == "cone":
        return meshes.lathe([r * 0.25, r], [0, -r * 0.9])
    if shape == "dome":
        a = np.linspace(0.15, np.pi / 2, 8)
        return meshes.lathe(list(np.sin(a) * r), list((np.cos(a) - 1) * r * 0.8))
    return meshes.lathe([r, r], [0, -r * 1.1])


def _pendant(p: dict) -> Parts:
    r, drop = p["shade"], p["drop"]
    out = [
        ("dark", meshes.cylinder(0.005, drop, cols=6, caps=False).transformed(_at(0, -drop / 2, 0)))
    ]
    out.append((p["shade_role"], _shade(p["shape"], r).transformed(_at(0, -drop, 0))))
    out.append(
        ("bulb", meshes.uv_sphere(p["bulb"], 10, 20).transformed(_at(0, -drop - r * 0.35, 0)))
    )
    return out


def _floor_lamp(p: dict) -> Parts:
    h, r = p["h"], p["shade"]
    out = [
        ("metal", cylinder_at(0.15, 0.03, (0, 0, 0))),
        ("metal", cylinder_at(0.012, h, (0, 0, 0))),
    ]
    out.append(("fabric", meshes.lathe([r * 0.6, r], [h + r * 0.7, h - 0.05])))
    out.append(("bulb", meshes.uv_sphere(p["bulb"], 10, 20).transformed(_at(0, h + 0.05, 0))))
    return out


def _picture(p: dict) -> Parts:
    w, h, f = p["w"], p["h"], p["frame"]
    pic = meshes.quad(w, h)
    pic = meshes.MeshData(pic.positions, pic.normals, pic.uvs / [w, h], pic.faces)  # 0..1
    out = [("paper", pic.transformed(_at(0, 0, 0.005)))]
    for sx in (-1, 1):
        out.append((p["frame_role"], box_at((f, h + 2 * f, 0.03), (sx * (w + f) / 2, 0, 0.015))))
    for sy in (-1, 1):
        out.append((p["frame_role"], box_at((w, f, 0.03), (0, sy * (h + f) / 2, 0.015))))
    return out


def _rug(p: dict) -> Parts:
    return [("carpet", box_at((p["w"], 0.012, p["d"]), (0, 0.006, 0)))]


def _railing(p: dict) -> Parts:
    n = max(2, int(p["l"] / p["gap"]) + 1)
    out = [(p["role"], box_at((p["l"], 0.04, 0.05), (0, p["h"], 0)))]
    out.append((p["role"], box_at((p["l"], 0.02, 0.02), (0, 0.1, 0))))
    for i in range(n):  # balusters: thin bars, sub-pixel at a few metres
        x = -p["l"] / 2 + i * p["l"] / (n - 1)
        out.append((p["role"], cylinder_at(p["bar"], p["h"], (x, 0, 0))))
    return out


def _bench(p: dict) -> Parts:
    w, n = p["w"], p["slats"]
    out = []
    for i in range(n):
        z = (i + 0.5) / n * 0.42 - 0.21
        out.append(("wood", box_at((w, 0.03, 0.42 / n - 0.015), (0, 0.44, z))))
    for sx in (-1, 1):
        out.append(("metal", box_at((0.05, 0.43, 0.4), (sx * (w / 2 - 0.15), 0.215, 0))))
    return out


def _column(p: dict) -> Parts:
    r, h = p["r"], p["h"]
    out = [("stone", cylinder_at(r, h - 0.3, (0, 0.15, 0)))]
    out.append(("stone", box_at((2.6 * r, 0.15, 2.6 * r), (0, 0.075, 0))))
    out.append(("stone", box_at((2.6 * r, 0.15, 2.6 * r), (0, h - 0.075, 0))))
    return out


def _vase(p: dict) -> Parts:
    r, h, b = p["r"], p["h"], p["bulge"]
    prof = [r * 0.6, r * b, r * 0.9, r * 0.45, r * 0.6]
    ys = [0, h * 0.35, h * 0.6, h * 0.85, h]
    return [(p["role"], meshes.lathe(prof, ys))]


def _bowl(p: dict) -> Parts:
    r = p["r"]
    a = np.linspace(0.2, np.pi / 2, 8)
    return [(p["role"], meshes.lathe(list(np.sin(a) * r), list((1 - np.cos(a)) * r * 0.6)))]


def _ball(p: dict) -> Parts:
    return [(p["role"], meshes.uv_sphere(p["r"], 16, 32).transformed(_at(0, p["r"], 0)))]


def _led(p: dict) -> Parts:
    return [("bulb", meshes.uv_sphere(p["r"], 8, 16).transformed(_at(0, p["r"], 0)))]


_BUILDERS = {
    "table": _table,
    "chair": _chair,
    "bookcase": _bookcase,
    "sofa": _sofa,
    "bed": _bed,
    "cabinet": _cabinet,
    "plant": _plant,
    "floor_lamp": _floor_lamp,
    "pendant": _pendant,
    "picture": _picture,
    "rug": _rug,
    "railing": _railing,
    "bench": _bench,
    "column": _column,
    "vase": _vase,
    "bowl": _bowl,
    "ball": _ball,
    "led": _led,
}
KINDS = tuple(_BUILDERS)


def footprint(kind: str, p: dict) -> tuple[float, float, float]:
    """(width x, depth z, height) of the piece's bounding box in its local frame."""
    pos = np.concatenate([m.positions for _, m in parts(kind, p)])
    lo, hi = pos.min(0), pos.max(0)
    return float(hi[0] - lo[0]), float(hi[2] - lo[2]), float(hi[1] - lo[1])
