"""Seeded procedural scenes: a JSON-able description, then a Mitsuba scene dict.

Adapted from Isik et al. 2021, 4.1 (itself after Gharbi et al. 2019) to what we can build
without assets: a box or L-shaped room (sometimes with windows, an open wall or a skylight onto
a procedural sky with sun), 10-40 procedural objects with random rigid transforms placed so the
camera is not blocked, randomised BSDFs with numpy textures, and a random mix of area, point,
spot and emissive-object lights. `generate(seed)` is pure numpy and deterministic; bump
GENERATOR_VERSION whenever its output for a seed changes (the data cache is keyed by it).
"""

from __future__ import annotations

import json

import numpy as np

from . import materials, meshes, textures
from .camera import animate

GENERATOR_VERSION = "g1"
Y_UP = np.array([0.0, 1.0, 0.0])


# ---------------------------------------------------------------------------------------------
# Room


def _inside_rects(points: np.ndarray, rects: list[list[float]], margin: float) -> np.ndarray:
    """Which points (N, 3) lie in the union of floor rectangles shrunk by `margin` (XZ)."""
    x, z = points[:, 0], points[:, 2]
    ok = np.zeros(len(points), bool)
    for x0, z0, x1, z1 in rects:
        ok |= (x > x0 + margin) & (x < x1 - margin) & (z > z0 + margin) & (z < z1 - margin)
    return ok


def _room(rng: np.random.Generator, open_env: bool) -> dict:
    w, d, h = rng.uniform(4, 10), rng.uniform(4, 10), rng.uniform(2.5, 4.0)
    if rng.random() < 0.35:  # L-shape: one corner of the box removed
        w1, d1 = w * rng.uniform(0.4, 0.7), d * rng.uniform(0.4, 0.7)
        outline = [(0, 0), (w, 0), (w, d1), (w1, d1), (w1, d), (0, d)]
        rects = [(0, 0, w, d1), (0, d1, w1, d)]
    else:
        outline = [(0, 0), (w, 0), (w, d), (0, d)]
        rects = [(0, 0, w, d)]
    cx, cz = w / 2, d / 2
    outline = [[x - cx, z - cz] for x, z in outline]
    rects = [[x0 - cx, z0 - cz, x1 - cx, z1 - cz] for x0, z0, x1, z1 in rects]

    walls = []
    opened = False
    for a, b in zip(outline, outline[1:] + outline[:1], strict=True):
        length = float(np.hypot(b[0] - a[0], b[1] - a[1]))
        wall: dict = {"a": a, "b": b, "length": length, "holes": []}
        if open_env and not opened and length > 3 and rng.random() < 0.12:
            wall["open"] = True  # the whole wall is missing: a terrace or a loggia
            opened = True
        elif open_env and length > 1.6:
            for _ in range(int(rng.integers(0, 3))):
                ww = rng.uniform(0.6, min(2.5, length / 2 - 0.2))
                u0 = rng.uniform(0.2, length - ww - 0.2)
                v0 = rng.uniform(0.3, 1.2)
                v1 = min(h - 0.2, v0 + rng.uniform(0.8, 2.0))
                hole = [u0, u0 + ww, v0, v1]
                if all(hole[0] > o[1] + 0.2 or hole[1] < o[0] - 0.2 for o in wall["holes"]):
                    wall["holes"].append(hole)
        walls.append(wall)
    skylight = None
    if open_env and rng.random() < 0.25:
        x0, z0, x1, z1 = rects[0]
        sw, sd = rng.uniform(0.6, (x1 - x0) / 2), rng.uniform(0.6, (z1 - z0) / 2)
        sx, sz = rng.uniform(x0 + 0.3, x1 - sw - 0.3), rng.uniform(z0 + 0.3, z1 - sd - 0.3)
        skylight = [sx, sx + sw, sz, sz + sd]
    if open_env and not opened and not skylight and not any(w["holes"] for w in walls):
        walls[int(np.argmax([w["length"] for w in walls]))]["holes"].append(
            [0.5, 2.0, 0.8, min(h - 0.2, 2.2)]
        )  # an open room always has at least one window
    wall_kind = str(rng.choice(["diffuse", "diffuse", "roughplastic"]))
    room: dict = {
        "height": h,
        "outline": outline,
        "rects": rects,
        "walls": walls,
        "skylight": skylight,
        "floor": materials.random_material(
            rng,
            str(rng.choice(["diffuse", "roughplastic", "roughplastic", "plastic"])),
            ("wood", "checker", "bricks", "noise", "stripes"),
            texture_prob=0.85,
        ),
        "wall": materials.random_material(
            rng, wall_kind, ("noise", "stripes", "bricks", "text", "checker", "wood"), 0.7
        ),
        "ceiling": {"kind": "diffuse", "color": [float(rng.uniform(0.5, 0.85))] * 3},
    }
    # Bump maps on the big room quads produced NaN radiance in Mitsuba (seen on ~0.2% of
    # samples), so rooms stay flat; objects keep theirs.
    room["floor"].pop("bump", None)
    room["wall"].pop("bump", None)
    return room


def _split_rect(u0: float, u1: float, v0: float, v1: float, holes: list) -> list[list[float]]:
    """Cover [u0,u1]x[v0,v1] minus non-overlapping holes with rectangles (columns)."""
    out, cursor = [], u0
    for h0, h1, g0, g1 in sorted(holes):
        out.append([cursor, h0, v0, v1])
        out += [[h0, h1, v0, g0], [h0, h1, g1, v1]]
        cursor = h1
    out.append([cursor, u1, v0, v1])
    return [r for r in out if r[1] - r[0] > 1e-6 and r[3] - r[2] > 1e-6]


def _quad_mesh(origin, du, dv, normal, rect: list[float]) -> meshes.MeshData:
    """A quad origin + u*du + v*dv over rect [u0,u1,v0,v1], UVs in metres."""
    u0, u1, v0, v1 = rect
    corners = [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
    pos = np.array([np.add(origin, np.multiply(du, u) + np.multiply(dv, v)) for u, v in corners])
    m = meshes.MeshData(
        pos.astype(np.float32),
        np.tile(np.asarray(normal, np.float32), (4, 1)),
        np.array(corners, np.float32),
        np.array([[0, 1, 2], [0, 2, 3]], np.uint32),
    )
    return meshes.orient(m)


def room_meshes(room: dict) -> dict[str, meshes.MeshData]:
    h = room["height"]
    walls = []
    for wall in room["walls"]:
        if wall.get("open"):
            continue
        a, b = np.array(wall["a"]), np.array(wall["b"])
        e = (b - a) / wall["length"]
        n2 = np.array([-e[1], e[0]])
        mid = (a + b) / 2 + n2 * 0.01
        if not _inside_rects(np.array([[mid[0], 0, mid[1]]]), room["rects"], 0.0)[0]:
            n2 = -n2  # normal must face into the room
        pieces = _split_rect(0, wall["length"], 0, h, wall["holes"])
        for r in pieces:
            walls.append(_quad_mesh([a[0], 0, a[1]], [e[0], 0, e[1]], Y_UP, [n2[0], 0, n2[1]], r))
    floor, ceiling = [], []
    for i, (x0, z0, x1, z1) in enumerate(room["rects"]):
        floor.append(_quad_mesh([0, 0, 0], [1, 0, 0], [0, 0, 1], Y_UP, [x0, x1, z0, z1]))
        holes = [room["skylight"]] if room["skylight"] and i == 0 else []
        for r in _split_rect(x0, x1, z0, z1, holes):
            ceiling.append(_quad_mesh([0, h, 0], [1, 0, 0], [0, 0, 1], -Y_UP, r))
    return {
        "walls": meshes.merge(walls),
        "floor": meshes.merge(floor),
        "ceiling": meshes.merge(ceiling),
    }


# ---------------------------------------------------------------------------------------------
# Environment


def _environment(rng: np.random.Generator, room: dict | None, kind: str) -> dict:
    if kind == "closed":
        return {"kind": "closed"}
    if kind == "constant":
        tint = 1 - 0.3 * rng.random(3)
        return {"kind": "constant", "radiance": (tint * rng.uniform(0.3, 2.0)).tolist()}
    env: dict = {
        "kind": "sky",
        "seed": int(rng.integers(2**31)),
        "scale": float(rng.uniform(0.3, 1.5)),
        "overcast": bool(rng.random() < 0.2),
        "clouds": float(rng.uniform(0, 0.7)) if rng.random() < 0.5 else 0.0,
    }
    # Aim the sun through an opening so it actually reaches the interior most of the time.
    openings = []
    for wall in room["walls"] if room else []:
        if wall.get("open") or wall["holes"]:
            a, b = np.array(wall["a"]), np.array(wall["b"])
            e = (b - a) / wall["length"]
            n2 = np.array([-e[1], e[0]])
            mid = (a + b) / 2 + n2 * 0.01
            if _inside_rects(np.array([[mid[0], 0, mid[1]]]), room["rects"], 0.0)[0]:
                n2 = -n2  # outward
            openings.append((np.array([n2[0], 0, n2[1]]), np.array([e[0], 0, e[1]])))
    elevation = np.radians(rng.uniform(8, 60))
    if room and room["skylight"] and (not openings or rng.random() < 0.5):
        elevation = np.radians(rng.uniform(45, 85))
        out, along = np.array([1.0, 0, 0]), np.array([0, 0, 1.0])
    elif openings:
        out, along = openings[int(rng.integers(len(openings)))]
    else:
        out, along = np.array([1.0, 0, 0]), np.array([0, 0, 1.0])
    azimuth = np.radians(rng.uniform(-55, 55))
    to_sun = np.cos(elevation) * (np.cos(azimuth) * out + np.sin(azimuth) * along)
    to_sun = to_sun + np.sin(elevation) * Y_UP
    if not env["overcast"] and rng.random() < 0.85:
        env["sun"] = {
            "to_sun": (to_sun / np.linalg.norm(to_sun)).tolist(),
            "irradiance": float(env["scale"] * rng.uniform(8, 40)),
            "color": materials.blackbody_rgb(float(rng.uniform(3500, 6500))).tolist(),
        }
    else:
        env["glow_dir"] = (to_sun / np.linalg.norm(to_sun)).tolist()
    return env


def sky_bitmap(env: dict, width: int = 256) -> np.ndarray:
    """Equirectangular linear-RGB sky (H = W/2) in Mitsuba's envmap parameterisation:
    u = atan2(d.x, -d.z) / 2pi, v = acos(d.y) / pi."""
    rng = np.random.default_rng(env["seed"])
    h = width // 2
    u, v = np.meshgrid((np.arange(width) + 0.5) / width, (np.arange(h) + 0.5) / h)
    theta, phi = v * np.pi, u * 2 * np.pi
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
    el = np.arcsin(np.clip(d[..., 1], -1, 1))
    zenith = np.array([0.12, 0.25, 0.75]) * rng.uniform(0.7, 1.3, 3)
    horizon = np.array([0.75, 0.85, 1.0]) * rng.uniform(0.8, 1.1, 3)
    ground = textures.random_color(rng, 0.1, 0.35)
    t = np.exp(-np.maximum(el, 0) / rng.uniform(0.15, 0.4))[..., None]
    sky = zenith * (1 - t) + horizon * t
    if env["overcast"]:  # CIE overcast sky: zenith three times the horizon
        sky = np.full_like(sky, 0.8) * ((1 + 2 * np.sin(np.maximum(el, 0))) / 3)[..., None]
    if env["clouds"] > 0:
        noise = textures.value_noise(rng, width, octaves=6)[:h]
        cover = np.clip((noise - (1 - env["clouds"])) * 3, 0, 1)[..., None] * (el > 0)[..., None]
        sky = sky * (1 - cover) + 0.9 * cover
    sun_dir = env.get("sun", {}).get("to_sun") or env.get("glow_dir")
    if sun_dir is not None:  # aureole around the sun; the disc itself is a directional light
        c = np.sum(d * np.asarray(sun_dir), -1)
        sky = sky + (2.0 * np.exp((c - 1) / 0.01) + 0.4 * np.exp((c - 1) / 0.15))[..., None]
    fade = np.clip(el / 0.03 + 1, 0, 1)[..., None]  # soft horizon into the ground colour
    sky = sky * fade + ground * 0.5 * (1 - fade)
    return (sky * env["scale"]).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Objects and lights

SHAPES = (
    "sphere",
    "box",
    "rounded_box",
    "cylinder",
    "torus",
    "heightfield",
    "slats",
    "rods",
    "table",
    "shelf",
)
SHAPE_WEIGHTS = (0.13, 0.1, 0.13, 0.1, 0.1, 0.07, 0.12, 0.11, 0.08, 0.06)


def _shape_params(rng: np.random.Generator, shape: str, r: float) -> dict:
    if shape == "sphere":
        return {"radius": r}
    if shape in ("box", "rounded_box"):
        dims = (rng.uniform(0.25, 1.0, 3) * r * 1.15).tolist()
        return {"size": dims, "radius": float(rng.uniform(0.05, 0.4) * min(dims))}
    if shape == "cylinder":
        return {
            "radius": float(r * rng.uniform(0.2, 0.7)),
            "height": float(r * rng.uniform(0.5, 1.9)),
        }
    if shape == "torus":
        return {"major": float(r * 0.75), "minor": float(r * 0.75 * rng.uniform(0.1, 0.45))}
    if shape == "heightfield":
        return {
            "size": float(1.4 * r),
            "amplitude": float(r * rng.uniform(0.1, 0.5)),
            "seed": int(rng.integers(2**31)),
        }
    if shape == "slats":
        count = int(rng.integers(4, 16))
        width = 1.6 * r / count * rng.uniform(0.3, 0.8)
        return {
            "count": count,
            "length": float(1.6 * r),
            "width": float(width),
            "thickness": float(rng.uniform(0.005, 0.03)),
            "gap": float((1.6 * r - count * width) / max(count - 1, 1)),
        }
    if shape == "table":
        return {
            "width": float(2 * r * rng.uniform(0.6, 1.0)),
            "depth": float(2 * r * rng.uniform(0.4, 0.8)),
            "height": float(rng.uniform(0.4, 1.0)),
            "top": float(rng.uniform(0.02, 0.06)),
            "leg": float(rng.uniform(0.015, 0.05)),
        }
    if shape == "shelf":
        return {
            "width": float(2 * r),
            "height": float(rng.uniform(0.8, 2.2)),
            "depth": float(rng.uniform(0.2, 0.45)),
            "boards": int(rng.integers(3, 7)),
            "board": float(rng.uniform(0.015, 0.04)),
        }
    count = int(rng.integers(3, 14))
    return {
        "count": count,
        "length": float(1.8 * r),
        "radius": float(rng.uniform(0.004, 0.02)),
        "gap": float(1.6 * r / count),
    }


def shape_mesh(shape: str, p: dict) -> meshes.MeshData:
    if shape == "sphere":
        return meshes.uv_sphere(p["radius"])
    if shape == "box":
        return meshes.box(tuple(p["size"]))
    if shape == "rounded_box":
        return meshes.rounded_box(tuple(p["size"]), p["radius"])
    if shape == "cylinder":
        return meshes.cylinder(p["radius"], p["height"])
    if shape == "torus":
        return meshes.torus(p["major"], p["minor"])
    if shape == "heightfield":
        field = textures.value_noise(np.random.default_rng(p["seed"]), 64, octaves=4)
        return meshes.heightfield(
            np.pad(field, ((0, 1), (0, 1)), mode="wrap"), (p["size"],) * 2, p["amplitude"]
        )
    if shape == "slats":
        return meshes.slats(p["count"], p["length"], p["width"], p["thickness"], p["gap"])
    if shape == "table":
        return meshes.table(p["width"], p["depth"], p["height"], p["top"], p["leg"])
    if shape == "shelf":
        return meshes.shelf(p["width"], p["height"], p["depth"], p["boards"], p["board"])
    return meshes.rods(p["count"], p["length"], p["radius"], p["gap"])


def _random_rotation(rng: np.random.Generator, upright: bool) -> np.ndarray:
    if upright:  # yaw only, as if standing on the floor
        a = rng.uniform(0, 2 * np.pi)
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _blocks_camera(center: np.ndarray, r: float, cams: list) -> bool:
    for cam in cams:
        o = np.asarray(cam.origin)
        dist = np.linalg.norm(center - o)
        if dist < r + 0.4:
            return True
        left, up, fwd = cam.basis()
        ahead = np.dot(center - o, fwd)
        # In front and wider than ~40% of the view: would hide the scene.
        if ahead > 0 and r / dist > 0.4 * np.tan(np.radians(cam.fov_x) / 2):
            return True
    return False


def _place_objects(rng: np.random.Generator, room: dict, cams: list, count: int) -> list[dict]:
    objects: list[dict] = []
    h = room["height"]
    # A per-scene palette: interiors reuse materials, and every distinct BSDF is one more
    # callee in Mitsuba's JIT kernel (40 distinct ones took ~4x longer to compile than 6).
    palette = [materials.random_material(rng) for _ in range(int(rng.integers(5, 11)))]
    for _ in range(count * 20):
        if len(objects) == count:
            break
        shape = str(rng.choice(SHAPES, p=np.asarray(SHAPE_WEIGHTS) / sum(SHAPE_WEIGHTS)))
        r = float(np.exp(rng.uniform(np.log(0.15), np.log(1.1))))
        params = _shape_params(rng, shape, r)
        upright = shape in ("table", "shelf") or rng.random() < 0.5
        rot = _random_rotation(rng, upright)
        if rng.random() < 0.65:  # somewhere in view of a random frame
            cam = cams[int(rng.integers(len(cams)))]
            left, up, fwd = cam.basis()
            tan_x = np.tan(np.radians(cam.fov_x) / 2)
            sx, sy = rng.uniform(-1, 1) * tan_x, rng.uniform(-0.75, 0.75) * tan_x
            center = np.asarray(cam.origin) + (fwd - sx * left + sy * up) * rng.uniform(1.2, 6.0)
        else:
            x0, z0, x1, z1 = room["rects"][int(rng.integers(len(room["rects"])))]
            center = np.array([rng.uniform(x0, x1), rng.uniform(0, h), rng.uniform(z0, z1)])
        mesh = shape_mesh(shape, params)
        if upright or center[1] < r:  # rest on the floor
            center[1] = -float((mesh.positions @ rot.T)[:, 1].min())
        center[1] = min(center[1], h - 0.5 * r)
        if not _inside_rects(center[None], room["rects"], min(r, 0.3))[0]:
            continue
        if _blocks_camera(center, r, cams):
            continue
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = rot, center
        objects.append(
            {
                "shape": shape,
                "params": params,
                "transform": m.tolist(),
                "radius": r,
                "material": palette[int(rng.integers(len(palette)))],
            }
        )
    return objects


def _light_color(rng: np.random.Generator) -> list[float]:
    if rng.random() < 0.15:  # coloured gels and LEDs
        return (textures.random_color(rng, 0.2, 1.0) * 2).tolist()
    return materials.blackbody_rgb(float(rng.uniform(2700, 7000))).tolist()


def _random_point(rng: np.random.Generator, room: dict, margin: float, y0: float, y1: float):
    areas = [(x1 - x0) * (z1 - z0) for x0, z0, x1, z1 in room["rects"]]
    x0, z0, x1, z1 = room["rects"][int(rng.choice(len(areas), p=np.divide(areas, sum(areas))))]
    return np.array(
        [
            rng.uniform(x0 + margin, x1 - margin),
            rng.uniform(y0, y1),
            rng.uniform(z0 + margin, z1 - margin),
        ]
    )


def _lights(rng: np.random.Generator, room: dict, env: dict, cams: list) -> list[dict]:
    h = room["height"]
    power = lambda: float(np.exp(rng.uniform(np.log(20), np.log(400))))  # noqa: E731
    lights: list[dict] = []
    if env["kind"] == "closed" and rng.random() < 0.1:
        # A single small light: hard, caustic-like noise everywhere.
        p = _random_point(rng, room, 0.5, 0.5, h - 0.3)
        if rng.random() < 0.5:
            return [
                {
                    "kind": "point",
                    "position": p.tolist(),
                    "power": power(),
                    "color": _light_color(rng),
                }
            ]
        return [
            {
                "kind": "sphere",
                "position": p.tolist(),
                "radius": float(rng.uniform(0.01, 0.04)),
                "power": power(),
                "color": _light_color(rng),
            }
        ]
    interior = env["kind"] == "closed" or rng.random() < 0.5
    counts = {
        k: int(rng.integers(0, n + 1)) * interior
        for k, n in (("rect", 3), ("sphere", 2), ("point", 2), ("spot", 2))
    }
    counts["emissive"] = int(rng.integers(0, 4))
    if (
        env["kind"] == "closed"
        and counts["rect"] + counts["sphere"] + counts["point"] + counts["spot"] == 0
    ):
        counts["rect"] = 1
    for _ in range(counts["rect"]):
        p = _random_point(rng, room, 0.6, h - 0.001, h - 0.001)
        lights.append(
            {
                "kind": "rect",
                "position": p.tolist(),
                "size": rng.uniform(0.2, 1.5, 2).tolist(),
                "yaw": float(rng.uniform(0, np.pi)),
                "power": power(),
                "color": _light_color(rng),
            }
        )
    for _ in range(counts["sphere"]):
        lights.append(
            {
                "kind": "sphere",
                "position": _random_point(rng, room, 0.5, 0.3, h - 0.3).tolist(),
                "radius": float(rng.uniform(0.03, 0.2)),
                "power": power(),
                "color": _light_color(rng),
            }
        )
    for _ in range(counts["point"]):
        lights.append(
            {
                "kind": "point",
                "position": _random_point(rng, room, 0.5, 0.3, h - 0.2).tolist(),
                "power": power() * 0.5,
                "color": _light_color(rng),
            }
        )
    for _ in range(counts["spot"]):
        p = _random_point(rng, room, 0.5, h * 0.6, h - 0.1)
        lights.append(
            {
                "kind": "spot",
                "position": p.tolist(),
                "target": _random_point(rng, room, 0.5, 0, h * 0.5).tolist(),
                "cutoff": float(rng.uniform(15, 60)),
                "power": power(),
                "color": _light_color(rng),
            }
        )
    for _ in range(counts["emissive"]):
        # Small very bright objects: their reflections in glossy surfaces make fireflies.
        for _ in range(50):
            p = _random_point(rng, room, 0.4, 0.05, h - 0.1)
            if not _blocks_camera(p, 0.15, cams):
                break
        lights.append(
            {
                "kind": "emissive",
                "shape": str(rng.choice(["sphere", "box", "torus"])),
                "position": p.tolist(),
                "size": float(rng.uniform(0.02, 0.1)),
                "radiance": float(np.exp(rng.uniform(np.log(5), np.log(300)))),
                "color": _light_color(rng),
            }
        )
    return lights


def generate(seed: int, n_frames: int, attempt: int = 0) -> dict:
    """The full, JSON-able description of sequence `seed` (room, env, objects, lights, cameras);
    `attempt` > 0 draws a replacement when the renderer rejects a scene (blocked or black)."""
    rng = np.random.default_rng([seed, attempt, 0x5CE7E])
    env_kind = str(rng.choice(["closed", "sky", "constant"], p=[0.35, 0.5, 0.15]))
    room = _room(rng, open_env=env_kind != "closed")
    env = _environment(rng, room, env_kind)
    h = room["height"]
    shot = animate(
        rng,
        inside=lambda p: (
            _inside_rects(p, room["rects"], 0.35) & (p[:, 1] > 0.25) & (p[:, 1] < h - 0.25)
        ),
        sample_point=lambda g: _random_point(g, room, 0.5, 0.3, h - 0.4),
        n_frames=n_frames,
    )
    cams = shot["frames"]
    objects = _place_objects(rng, room, cams, int(rng.integers(10, 41)))
    lights = _lights(rng, room, env, cams)
    return {
        "generator": GENERATOR_VERSION,
        "seed": seed,
        "attempt": attempt,
        "room": room,
        "environment": env,
        "objects": objects,
        "lights": lights,
        "cameras": [c.as_dict() for c in cams],
        "shots": shot["shots"],
        "cuts": shot["cuts"],
    }


def summary(desc: dict) -> dict:
    """Short, human-readable digest of a description for the manifest."""
    count = lambda items, key: {k: sum(i[key] == k for i in items) for k in {i[key] for i in items}}  # noqa: E731
    return {
        "room": "L" if len(desc["room"]["rects"]) > 1 else "box",
        "environment": desc["environment"]["kind"],
        "sun": "sun" in desc["environment"],
        "objects": count(desc["objects"], "shape"),
        "materials": count([o["material"] for o in desc["objects"]], "kind"),
        "lights": count(desc["lights"], "kind"),
        "shots": desc["shots"],
    }


# ---------------------------------------------------------------------------------------------
# Mitsuba


def _emitter_rgb(color: list[float], scale: float) -> dict:
    return {"type": "rgb", "value": (np.asarray(color) * scale).tolist()}


def build(desc: dict) -> tuple[dict, dict[str, list[float]]]:
    """Mitsuba scene dict without sensor and integrator, plus per-shape albedo overrides
    (shape id -> RGB) for surfaces whose Mitsuba albedo AOV is not a reflectance."""
    import mitsuba as mi

    scene: dict = {"type": "scene"}
    overrides: dict[str, list[float]] = {}
    room = desc["room"]
    parts = room_meshes(room)
    for name, mat in (
        ("walls", room["wall"]),
        ("floor", room["floor"]),
        ("ceiling", room["ceiling"]),
    ):
        if len(parts[name].faces):
            scene[name] = meshes.to_mitsuba(
                parts[name], name, mi.load_dict(materials.bsdf_dict(mat))
            )
    env = desc["environment"]
    if env["kind"] != "closed":
        ground = _quad_mesh([0, -0.02, 0], [1, 0, 0], [0, 0, 1], Y_UP, [-100, 100, -100, 100])
        gmat = {"kind": "diffuse", "color": [0.2, 0.18, 0.15]}
        scene["ground"] = meshes.to_mitsuba(
            ground, "ground", mi.load_dict(materials.bsdf_dict(gmat))
        )
    if env["kind"] == "constant":
        scene["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": env["radiance"]}}
    elif env["kind"] == "sky":
        scene["env"] = {"type": "envmap", "bitmap": mi.Bitmap(sky_bitmap(env))}
        if "sun" in env:
            sun = env["sun"]
            scene["sun"] = {
                "type": "directional",
                "direction": (-np.asarray(sun["to_sun"])).tolist(),
                "irradiance": _emitter_rgb(sun["color"], sun["irradiance"]),
            }
    bsdfs: dict[str, object] = {}  # one BSDF instance per palette entry, shared by its objects
    for i, obj in enumerate(desc["objects"]):
        mesh = shape_mesh(obj["shape"], obj["params"]).transformed(np.asarray(obj["transform"]))
        name = f"object_{i:02d}"
        key = json.dumps(obj["material"], sort_keys=True)
        if key not in bsdfs:
            bsdfs[key] = mi.load_dict(materials.bsdf_dict(obj["material"]))
        scene[name] = meshes.to_mitsuba(mesh, name, bsdfs[key])
        albedo = materials.albedo_of(obj["material"])
        if albedo is not None:
            overrides[name] = albedo
    for i, light in enumerate(desc["lights"]):
        scene[f"light_{i:02d}"] = _light_dict(light, f"light_{i:02d}")
    return scene, overrides


def _light_dict(light: dict, name: str):
    import mitsuba as mi

    kind, pos = light["kind"], light["position"]
    dark = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.05}}
    if kind == "rect":
        sx, sy = light["size"]
        to_world = (
            mi.ScalarTransform4f()
            .translate(pos)
            .rotate([0, 1, 0], np.degrees(light["yaw"]))
            .rotate([1, 0, 0], 90)
            .scale([sx / 2, sy / 2, 1])
        )  # +Z normal turned down
        radiance = light["power"] / (np.pi * sx * sy)
        return {
            "type": "rectangle",
            "to_world": to_world,
            "bsdf": dark,
            "emitter": {"type": "area", "radiance": _emitter_rgb(light["color"], radiance)},
        }
    if kind == "sphere":
        r = light["radius"]
        radiance = light["power"] / (np.pi * 4 * np.pi * r * r)
        return {
            "type": "sphere",
            "center": pos,
            "radius": r,
            "bsdf": dark,
            "emitter": {"type": "area", "radiance": _emitter_rgb(light["color"], radiance)},
        }
    if kind == "point":
        return {
            "type": "point",
            "position": pos,
            "intensity": _emitter_rgb(light["color"], light["power"] / (4 * np.pi)),
        }
    if kind == "spot":
        return {
            "type": "spot",
            "cutoff_angle": light["cutoff"],
            "beam_width": light["cutoff"] * 0.75,
            "to_world": mi.ScalarTransform4f().look_at(
                origin=pos, target=light["target"], up=[0, 1, 0.01]
            ),
            "intensity": _emitter_rgb(light["color"], light["power"] / (2 * np.pi)),
        }
    s = light["size"]
    mesh = {
        "sphere": lambda: meshes.uv_sphere(s, 12, 24),
        "box": lambda: meshes.box((s * 1.6,) * 3),
        "torus": lambda: meshes.torus(s, s * 0.3, 12, 24),
    }[light["shape"]]()
    m = np.eye(4)
    m[:3, 3] = pos
    emitter = mi.load_dict(
        {"type": "area", "radiance": _emitter_rgb(light["color"], light["radiance"])}
    )
    return meshes.to_mitsuba(mesh.transformed(m), name, mi.load_dict(dark), emitter)
