"""Seeded procedural scenes built like real interiors: a JSON-able description, then a Mitsuba
scene dict.

Generator g2 (replaces g1's boxes of floating primitives). From the sequence seed:
`architecture.plan` lays out a room (60% with a corridor or second room through a doorway) with
windows, reveals, frames and blinds, or an open courtyard with a colonnade; a lighting mode
(sun, overcast, evening, night) sets the sky, the sun (aimed through a window so it lands on
the floor) and which lamps are on; `_furnish` places furniture assembled from parts
(`furniture.py`) against walls and in groups, pictures on walls, pendants under the ceiling,
props on tops, tiny bright LEDs; materials come by role (`materials.role_material`). Cameras
move like shots (`camera.animate`) inside the spaces and outside furniture; half of the
interiors have a moving object (a rolling ball or a sliding chair) whose per-frame transform
is in the description. `generate(seed, frames)` is pure numpy and deterministic; bump
GENERATOR_VERSION whenever its output for a seed changes (the data cache is keyed by it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import architecture, furniture, materials, meshes, textures
from .camera import Camera, animate

GENERATOR_VERSION = "g2"
Y_UP = np.array([0.0, 1.0, 0.0])
LIGHTING = ("sun", "overcast", "evening", "night")


# ---------------------------------------------------------------------------------------------
# Environment


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


def _window_sun(rng: np.random.Generator, layout: dict, low: bool) -> np.ndarray | None:
    """Direction to a sun that shines through a window of the main room onto its floor (or,
    `low`, a low evening sun), or None without windows."""
    wins = [o for o in layout["openings"] if o["kind"] == "window" and o.get("space") == 0]
    if not wins:
        return None
    o = wins[int(rng.integers(len(wins)))]
    ax = np.array([1.0, 0, 0]) if o["axis"] == "x" else np.array([0, 0, 1.0])
    inward = np.array([0, 0, o["inward"]]) if o["axis"] == "x" else np.array([o["inward"], 0, 0])
    x0, z0, x1, z1 = layout["spaces"][0]["rect"]
    depth = (z1 - z0) if o["axis"] == "x" else (x1 - x0)
    centre = (o["v"][0] + o["v"][1]) / 2
    if low:
        elevation = rng.uniform(3, 10)
    else:  # the patch through the window's centre lands on the floor within 85% of the depth
        lo = max(10.0, float(np.degrees(np.arctan2(centre, 0.85 * depth))))
        elevation = rng.uniform(lo, max(lo, 60.0))
    az = np.radians(rng.uniform(-45, 45))
    el = np.radians(elevation)
    to_sun = np.cos(el) * (-np.cos(az) * inward + np.sin(az) * ax) + np.sin(el) * Y_UP
    return to_sun / np.linalg.norm(to_sun)


def _environment(rng: np.random.Generator, layout: dict, mode: str) -> dict:
    scale = {
        "sun": (0.3, 1.5),
        "overcast": (0.5, 2.0),
        "evening": (0.02, 0.12),
        "night": (0.002, 0.01),
    }
    env: dict = {
        "kind": "sky",
        "seed": int(rng.integers(2**31)),
        "scale": float(rng.uniform(*scale[mode])),
        "overcast": mode == "overcast",
        "clouds": float(rng.uniform(0, 0.7)) if rng.random() < 0.5 else 0.0,
    }
    if mode in ("sun", "evening"):
        if layout["kind"] == "courtyard":
            el, az = np.radians(rng.uniform(15, 65)), rng.uniform(0, 2 * np.pi)
            to_sun = np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
        else:
            to_sun = _window_sun(rng, layout, low=mode == "evening")
        if to_sun is not None and (mode == "sun" or rng.random() < 0.5):
            kelvin = rng.uniform(4500, 6500) if mode == "sun" else rng.uniform(2500, 3500)
            env["sun"] = {
                "to_sun": to_sun.tolist(),
                "irradiance": float(
                    env["scale"] * rng.uniform(15, 40) * (1 if mode == "sun" else 8)
                ),
                "color": materials.blackbody_rgb(float(kelvin)).tolist(),
            }
        elif to_sun is not None:
            env["glow_dir"] = to_sun.tolist()
    return env


def sun_patches(desc: dict) -> list[np.ndarray]:
    """Where the sun comes in: for each window of the main room that a ray from its centre
    towards the sun gets out through (past the reveal), the floor point that ray reaches
    inside the room, or None when it lands on a wall (a low sun)."""
    sun = desc["environment"].get("sun")
    if sun is None or desc["layout"]["kind"] == "courtyard" or sun["to_sun"][1] <= 0:
        return []
    d = np.asarray(sun["to_sun"])
    x0, z0, x1, z1 = desc["layout"]["spaces"][0]["rect"]
    out = []
    for o in desc["layout"]["openings"]:
        if o["kind"] != "window" or o.get("space") != 0:
            continue
        along = d[0] if o["axis"] == "x" else d[2]
        away = -o["inward"] * (d[2] if o["axis"] == "x" else d[0])
        if away <= 0:
            continue
        s = architecture.WALL / away  # distance to the outer face of the wall
        if abs(s * along) > (o["u"][1] - o["u"][0]) / 2 or s * d[1] > (o["v"][1] - o["v"][0]) / 2:
            continue
        u, v = (o["u"][0] + o["u"][1]) / 2, (o["v"][0] + o["v"][1]) / 2
        plane = o["planes"][0]
        p = np.array([u, v, plane]) if o["axis"] == "x" else np.array([plane, v, u])
        hit = p - d * (v / d[1])  # follow the sunlight from the window centre to the floor
        out.append(hit if x0 < hit[0] < x1 and z0 < hit[2] < z1 else None)
    return out


def sun_enters(desc: dict) -> bool:
    """The sun shines into the main room through a window, and with a high sun ("sun"
    lighting) its patch lands on the room's floor. Courtyards: any sun."""
    if desc["layout"]["kind"] == "courtyard":
        return "sun" in desc["environment"]
    patches = sun_patches(desc)
    if desc["lighting"] == "sun":
        return any(p is not None for p in patches)
    return bool(patches)


# ---------------------------------------------------------------------------------------------
# Materials


WALL_ROLES = ("paint", "paint", "wallpaper", "wall_tiles", "brick")
FLOOR_ROLES = ("floor_wood", "floor_wood", "floor_tiles", "carpet", "stone")
PIECE_ROLES = ("wood", "fabric", "metal", "glass", "ceramic", "paper", "dark", "leaf",
               "carpet", "stone")


def _materials(rng: np.random.Generator, layout: dict) -> tuple[list[dict], dict, dict]:
    """Material list, surface key -> index (architecture) and role -> indices (furniture).
    Interiors reuse materials, and every distinct BSDF is one more callee in Mitsuba's JIT
    kernel, so the palette stays at 1-2 materials per role."""
    mats: list[dict] = []

    def add(m: dict) -> int:
        mats.append(m)
        return len(mats) - 1

    palette = {r: [add(materials.role_material(rng, r))] for r in PIECE_ROLES}
    for r in ("fabric", "ceramic", "paper", "wood"):
        if rng.random() < 0.5:
            palette[r].append(add(materials.role_material(rng, r)))
    surf: dict[str, int] = {}
    yard = layout["kind"] == "courtyard"
    for i, _ in enumerate(layout["spaces"]):
        wall_role = str(rng.choice(("paint", "brick", "stone") if yard else WALL_ROLES))
        surf[f"wall{i}"] = add(materials.role_material(rng, wall_role))
        surf[f"floor{i}"] = add(
            materials.role_material(rng, "stone" if yard else str(rng.choice(FLOOR_ROLES)))
        )
        surf[f"ceiling{i}"] = add(materials.role_material(rng, "ceiling"))
    surf["reveal"] = surf["wall0"]
    surf["frame"] = add(materials.role_material(rng, str(rng.choice(["paint", "wood", "metal"]))))
    surf["blind"] = add(materials.role_material(rng, str(rng.choice(["paint", "metal", "wood"]))))
    surf["stone"] = palette["stone"][0]
    surf["dark"] = add({"kind": "plastic", "color": [0.02, 0.025, 0.03]})  # facade glass
    surf["metal"] = palette["metal"][0]
    surf["ground"] = add(
        {"kind": "diffuse", "color": textures.random_color(rng, 0.1, 0.3).tolist()}
    )
    surf["bulb_off"] = add({"kind": "diffuse", "color": [0.8, 0.8, 0.8]})
    return mats, surf, palette


# ---------------------------------------------------------------------------------------------
# Furniture


def _transform(theta: float, pos) -> np.ndarray:
    """Yaw `theta` about +Y (local +Z turns to (sin, 0, cos)), then translate to `pos`."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, 0, s, pos[0]], [0, 1, 0, pos[1]], [-s, 0, c, pos[2]], [0, 0, 0, 1.0]])


def _aabb(fw: float, fd: float, theta: float, x: float, z: float) -> list[float]:
    c, s = abs(np.cos(theta)), abs(np.sin(theta))
    wx, wz = c * fw + s * fd, s * fw + c * fd
    return [x - wx / 2, z - wz / 2, x + wx / 2, z + wz / 2]


def _overlap(a: list[float], b: list[float], margin: float = 0.0) -> bool:
    return (
        a[0] < b[2] + margin
        and b[0] < a[2] + margin
        and a[1] < b[3] + margin
        and b[1] < a[3] + margin
    )


def _within(r: list[float], space: dict, margin: float = 0.0) -> bool:
    x0, z0, x1, z1 = space["rect"]
    return (
        r[0] >= x0 + margin and r[1] >= z0 + margin and r[2] <= x1 - margin and r[3] <= z1 - margin
    )


class _Furnisher:
    """Places pieces without overlaps; records blockers (boxes the camera must stay out of)."""

    def __init__(self, rng: np.random.Generator, layout: dict, palette: dict, mode: str):
        self.rng, self.layout, self.palette, self.mode = rng, layout, palette, mode
        self.pieces: list[dict] = []
        self.blockers: list[dict] = []  # {"rect": [x0, z0, x1, z1], "y": [y0, y1]}
        self.tops: list[tuple[list[float], float]] = []  # surfaces props can stand on

    def add(self, kind: str, params: dict, m: np.ndarray, light: dict | None = None) -> dict:
        roles = {r for r, _ in furniture.parts(kind, params) if r != "bulb"}
        mats = {r: int(self.rng.choice(self.palette[r])) for r in sorted(roles)}
        piece = {"kind": kind, "params": params, "transform": m.tolist(), "materials": mats}
        if light is not None:
            piece["light"] = light
        self.pieces.append(piece)
        return piece

    def free(self, rect: list[float], skip: int = 0) -> bool:
        return not any(
            _overlap(rect, b["rect"], 0.05) for b in self.blockers[skip:] if b["y"][0] < 0.5
        )

    def lamp_light(self, force: bool = False) -> dict:
        on = force or self.mode in ("evening", "night") or self.rng.random() < 0.15
        return {
            "power": float(np.exp(self.rng.uniform(np.log(30), np.log(200)))),
            "color": materials.blackbody_rgb(float(self.rng.uniform(2600, 4200))).tolist(),
            "on": bool(on),
        }

    def on_wall(self, si: int, kind: str, params: dict | None = None, light=None) -> dict | None:
        """Stand a piece with its back to a wall, clear of doors (and of windows if taller
        than the sill)."""
        rng, space = self.rng, self.layout["spaces"][si]
        params = params or furniture.draw(kind, rng)
        fw, fd, fh = furniture.footprint(kind, params)
        for _ in range(30):
            side = str(rng.choice(list(architecture.SIDES)))
            axis, idx, inward = architecture.SIDES[side]
            lo, hi = architecture.wall_span(space["rect"], side)
            if hi - lo < fw + 0.2:
                continue
            u = rng.uniform(lo + fw / 2 + 0.05, hi - fw / 2 - 0.05)
            plane = space["rect"][idx]
            clash = False
            for o in self.layout["openings"]:
                if o["axis"] != axis or not any(abs(p - plane) < 1e-6 for p in o["planes"]):
                    continue
                pad = 0.5 if o["kind"] == "door" else 0.05
                if u - fw / 2 < o["u"][1] + pad and u + fw / 2 > o["u"][0] - pad:
                    clash |= o["kind"] == "door" or fh > o["v"][0] - 0.05
            if clash:
                continue
            n = np.array([0, 0, inward]) if axis == "x" else np.array([inward, 0, 0])
            theta = float(np.arctan2(n[0], n[2]))
            on_plane = np.array([u, 0, plane]) if axis == "x" else np.array([plane, 0, u])
            c = on_plane + n * (fd / 2 + 0.02)
            rect = _aabb(fw, fd, theta, c[0], c[2])
            if not _within(rect, space, 0.01) or not self.free(rect):
                continue
            piece = self.add(kind, params, _transform(theta, c), light)
            self.blockers.append({"rect": rect, "y": [0.0, fh]})
            if kind == "cabinet":
                self.tops.append((rect, fh))
            piece["wall"] = [side, float(u), float(theta)]
            return piece
        return None

    def group(self, si: int) -> None:
        """A dining table with chairs around it (and a rug), in the open floor."""
        rng, space = self.rng, self.layout["spaces"][si]
        t = furniture.draw("table", rng)
        fw, fd, fh = furniture.footprint("table", t)
        for _ in range(30):
            x0, z0, x1, z1 = space["rect"]
            if x1 - x0 < fw + 2.0 or z1 - z0 < fd + 2.0:
                return
            c = np.array(
                [
                    rng.uniform(x0 + fw / 2 + 0.8, x1 - fw / 2 - 0.8),
                    0,
                    rng.uniform(z0 + fd / 2 + 0.8, z1 - fd / 2 - 0.8),
                ]
            )
            theta = float(rng.choice([0, np.pi / 2]) + rng.normal(0, 0.05))
            outer = _aabb(fw + 1.2, fd + 1.2, theta, c[0], c[2])
            if not _within(outer, space, 0.1) or not self.free(outer):
                continue
            if rng.random() < 0.5:
                rug = furniture.draw("rug", rng)
                rug["w"], rug["d"] = fw + rng.uniform(0.8, 1.6), fd + rng.uniform(0.8, 1.6)
                self.add("rug", rug, _transform(theta, c))
            self.add("table", t, _transform(theta, c))
            rect = _aabb(fw, fd, theta, c[0], c[2])
            self.blockers.append({"rect": rect, "y": [0.0, fh]})
            self.tops.append((rect, fh))
            if fh < 0.55:  # a coffee table: no chairs
                return
            chair = furniture.draw("chair", rng)
            cw = furniture.footprint("chair", chair)[0]
            per_side = max(1, int(fw / (cw + 0.25)))
            seats = [
                (x, side)
                for side in (-1, 1)
                for x in np.linspace(-fw / 2, fw / 2, per_side + 2)[1:-1]
            ]
            seats = [s for s in seats if rng.random() < 0.8]
            for x, side in seats:
                pull = rng.uniform(0.0, 0.25)
                local = np.array([x, 0, side * (fd / 2 + cw / 2 - 0.1 + pull)])
                pos = _transform(theta, c)[:3, :3] @ local + c
                phi = theta + (np.pi if side > 0 else 0.0) + rng.normal(0, 0.12)
                self.add("chair", chair, _transform(phi, pos))
                self.blockers.append({"rect": _aabb(cw, cw, phi, pos[0], pos[2]), "y": [0.0, 0.95]})
            return

    def picture(self, si: int) -> None:
        rng, space = self.rng, self.layout["spaces"][si]
        p = furniture.draw("picture", rng)
        w, h = p["w"] + 2 * p["frame"], p["h"] + 2 * p["frame"]
        for _ in range(20):
            side = str(rng.choice(list(architecture.SIDES)))
            axis, idx, inward = architecture.SIDES[side]
            lo, hi = architecture.wall_span(space["rect"], side)
            if hi - lo < w + 0.4:
                continue
            u, y = rng.uniform(lo + w / 2 + 0.2, hi - w / 2 - 0.2), rng.uniform(1.3, 1.8)
            if y + h / 2 > space["h"] - 0.1:
                continue
            plane = space["rect"][idx]
            if any(
                o["axis"] == axis
                and any(abs(q - plane) < 1e-6 for q in o["planes"])
                and u - w / 2 < o["u"][1] + 0.1
                and u + w / 2 > o["u"][0] - 0.1
                for o in self.layout["openings"]
            ):
                continue
            n = np.array([0, 0, inward]) if axis == "x" else np.array([inward, 0, 0])
            on_plane = np.array([u, y, plane]) if axis == "x" else np.array([plane, y, u])
            strip = _aabb(w, 0.8, float(np.arctan2(n[0], n[2])), *(on_plane + n * 0.4)[[0, 2]])
            if any(_overlap(strip, b["rect"]) and b["y"][1] > y - h / 2 for b in self.blockers):
                continue
            self.add("picture", p, _transform(float(np.arctan2(n[0], n[2])), on_plane + n * 0.002))
            return

    def pendant(self, si: int, force_on: bool = False) -> None:
        rng, space = self.rng, self.layout["spaces"][si]
        p = furniture.draw("pendant", rng)
        p["drop"] = min(p["drop"], space["h"] - 2.0)
        if p["drop"] < 0.2:
            p["drop"] = 0.2
        x0, z0, x1, z1 = space["rect"]
        over = [t for t in self.tops if _within(t[0], space)]
        if over and rng.random() < 0.6:
            r = over[int(rng.integers(len(over)))][0]
            x, z = (r[0] + r[2]) / 2, (r[1] + r[3]) / 2
        else:
            mx, mz = min(0.7, (x1 - x0) / 2 - 0.05), min(0.7, (z1 - z0) / 2 - 0.05)
            x, z = rng.uniform(x0 + mx, x1 - mx), rng.uniform(z0 + mz, z1 - mz)
        self.add("pendant", p, _transform(0.0, [x, space["h"], z]), self.lamp_light(force_on))
        r = p["shade"] + 0.35
        self.blockers.append(
            {
                "rect": [x - r, z - r, x + r, z + r],
                "y": [space["h"] - p["drop"] - p["shade"] * 1.2, space["h"]],
            }
        )

    def props(self) -> None:
        """Vases, bowls, balls and tiny bright LEDs on tables and cabinets."""
        rng = self.rng
        for rect, h in self.tops:
            for _ in range(int(rng.integers(0, 4))):
                kind = str(rng.choice(["vase", "bowl", "ball", "led"], p=[0.35, 0.25, 0.2, 0.2]))
                p = furniture.draw(kind, rng)
                x = rng.uniform(rect[0] + 0.15, max(rect[0] + 0.15, rect[2] - 0.15))
                z = rng.uniform(rect[1] + 0.15, max(rect[1] + 0.15, rect[3] - 0.15))
                light = None
                if kind == "led":
                    tint = materials.blackbody_rgb(float(rng.uniform(2700, 6500)))
                    if rng.random() < 0.3:
                        tint = textures.random_color(rng, 0.2, 1.0) * 2
                    light = {
                        "radiance": float(np.exp(rng.uniform(np.log(200), np.log(5000)))),
                        "color": tint.tolist(),
                        "on": True,
                    }
                self.add(kind, p, _transform(rng.uniform(0, 2 * np.pi), [x, h, z]), light)


def _furnish(rng: np.random.Generator, layout: dict, palette: dict, mode: str) -> _Furnisher:
    f = _Furnisher(rng, layout, palette, mode)
    if layout["kind"] == "courtyard":
        for x, z in architecture.column_positions(layout):
            r = layout["colonnade"]["column"]["r"] * 1.3
            f.blockers.append({"rect": [x - r, z - r, x + r, z + r], "y": [0.0, 10.0]})
        if rng.random() < 0.5:
            f.group(0)
        for kind, n in (("bench", int(rng.integers(1, 4))), ("plant", int(rng.integers(2, 7)))):
            for _ in range(n):
                p = furniture.draw(kind, rng)
                if kind == "plant":
                    p["h"], p["pot"] = p["h"] * 1.5, p["pot"] * 1.8
                f.on_wall(0, kind, p)
        f.props()
        return f
    for si, space in enumerate(layout["spaces"]):
        if space["kind"] == "corridor":
            for kind in rng.choice(
                ["cabinet", "plant", "bookcase", "picture"], int(rng.integers(1, 4))
            ):
                f.picture(si) if kind == "picture" else f.on_wall(si, str(kind))
            f.pendant(si)
            continue
        big = ["sofa", "bed", "bookcase", "bookcase", "cabinet", "cabinet"]
        for kind in rng.choice(big, int(rng.integers(1, 4)), replace=False):
            f.on_wall(si, str(kind))
        if rng.random() < 0.8:
            f.group(si)
        for kind in ("plant", "plant", "floor_lamp"):
            if rng.random() < 0.5:
                f.on_wall(si, kind, light=f.lamp_light() if kind == "floor_lamp" else None)
        for _ in range(int(rng.integers(1, 5))):
            f.picture(si)
        for _ in range(int(rng.integers(1, 3))):
            f.pendant(si)
    if mode in ("evening", "night") and not any(
        "light" in p and p["light"]["on"] and p["kind"] != "led" for p in f.pieces
    ):
        f.pendant(0, force_on=True)
    f.props()
    return f


def camera_clear(desc: dict, points: np.ndarray) -> np.ndarray:
    """Which points (N, 3) are valid camera positions: inside a space (0.35 m from walls,
    floor and ceiling) and 0.3 m away from every piece of furniture and lamp."""
    ok = architecture.inside(desc["layout"], points, 0.35)
    for b in desc["blockers"]:
        x0, z0, x1, z1 = b["rect"]
        m = 0.3
        ok &= ~(
            (points[:, 0] > x0 - m)
            & (points[:, 0] < x1 + m)
            & (points[:, 2] > z0 - m)
            & (points[:, 2] < z1 + m)
            & (points[:, 1] > b["y"][0] - m)
            & (points[:, 1] < b["y"][1] + m)
        )
    return ok


# ---------------------------------------------------------------------------------------------
# Moving objects


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _mover(rng: np.random.Generator, desc: dict, f: _Furnisher, cams: list[Camera]) -> dict | None:
    """A ball rolling or a chair sliding across the floor in view of the first frame, clear of
    furniture, walls and every camera position."""
    kind = "ball" if rng.random() < 0.6 else "chair"
    p = furniture.draw(kind, rng)
    if kind == "ball":
        p["r"] = float(rng.uniform(0.08, 0.2))
    fw, fd, _ = furniture.footprint(kind, p)
    rad = max(fw, fd) / 2
    left, _, fwd = cams[0].basis()
    flat = np.array([fwd[0], 0, fwd[2]]) / max(np.hypot(fwd[0], fwd[2]), 1e-6)
    side = np.array([left[0], 0, left[2]]) / max(np.hypot(left[0], left[2]), 1e-6)
    n = len(cams)
    for _ in range(40):
        start = (
            np.asarray(cams[0].origin) * [1, 0, 1]
            + flat * rng.uniform(1.5, 3.5)
            + side * rng.uniform(-1, 1)
        )
        a = rng.uniform(0, 2 * np.pi)
        v = np.array([np.cos(a), 0, np.sin(a)]) * rng.uniform(0.02, 0.07)
        spin = rng.uniform(-0.06, 0.06)
        theta0 = rng.uniform(0, 2 * np.pi)
        frames, ok = [], True
        for k in range(n):
            pos = start + v * k
            rect = [pos[0] - rad, pos[2] - rad, pos[0] + rad, pos[2] + rad]
            si = architecture.space_of(desc["layout"], pos)
            cam = np.asarray(cams[k].origin)
            if si < 0 or not _within(rect, desc["layout"]["spaces"][si], 0.05) or not f.free(rect):
                ok = False
                break
            if np.hypot(*(cam - pos)[[0, 2]]) < rad + 0.6:
                ok = False
                break
            if kind == "ball":  # rolling without slipping: angle = distance / radius
                r = p["r"]
                m = np.eye(4)
                m[:3, :3] = _rotation(np.cross(Y_UP, v), np.linalg.norm(v) * k / r)
                centre = np.eye(4)
                centre[:3, 3] = pos + [0, r, 0]
                back = np.eye(4)
                back[1, 3] = -r
                frames.append((centre @ m @ back).tolist())
            else:
                frames.append(_transform(theta0 + spin * k, pos).tolist())
        if ok:
            piece = {"kind": kind, "params": p, "frames": frames, "transform": frames[0]}
            roles = {r for r, _ in furniture.parts(kind, p)}
            piece["materials"] = {r: int(rng.choice(f.palette[r])) for r in sorted(roles)}
            return piece
    return None


# ---------------------------------------------------------------------------------------------
# Scene


def generate(seed: int, n_frames: int, attempt: int = 0) -> dict:
    """The full, JSON-able description of sequence `seed`; `attempt` > 0 draws a replacement
    when the renderer rejects a scene (blocked or black)."""
    rng = np.random.default_rng([seed, attempt, 0x5CE7E2])
    courtyard = bool(rng.random() < 0.2)
    layout = architecture.plan(rng, courtyard)
    if courtyard:
        mode = str(rng.choice(["sun", "overcast"], p=[0.8, 0.2]))
    else:
        mode = str(rng.choice(LIGHTING, p=[0.45, 0.15, 0.25, 0.15]))
    architecture.add_blinds(rng, layout, 0.45 if mode == "sun" else 0.15)
    mats, surf, palette = _materials(rng, layout)
    env = _environment(rng, layout, mode)
    f = _furnish(rng, layout, palette, mode)
    desc = {
        "generator": GENERATOR_VERSION,
        "seed": seed,
        "attempt": attempt,
        "layout": layout,
        "lighting": mode,
        "environment": env,
        "materials": mats,
        "surfaces": surf,
        "pieces": f.pieces,
        "blockers": f.blockers,
    }
    spaces = layout["spaces"]
    yard = layout["kind"] == "courtyard"

    patch = [p for p in sun_patches(desc) if p is not None]
    # Shots start in the annex only where light reaches it directly (a window, lamps on):
    # a windowless corridor in daylight is lit through the door alone, near black.
    lit = [0] + [
        i
        for i in range(1, len(spaces))
        if mode in ("evening", "night")
        or any(o["kind"] == "window" and o.get("space") == i for o in layout["openings"])
    ]

    def start(g: np.random.Generator) -> np.ndarray:
        """Eye height; 60% of shots stand near a wall and look across the space."""
        si = 0 if len(lit) == 1 or g.random() < 0.8 else int(g.choice(lit[1:]))
        x0, z0, x1, z1 = spaces[si]["rect"]
        p = np.array([g.uniform(x0 + 0.4, x1 - 0.4), 0, g.uniform(z0 + 0.4, z1 - 0.4)])
        if g.random() < 0.6:
            k = int(g.integers(4))
            off = g.uniform(0.45, 1.2)
            p[[0, 2][k % 2]] = [x0, z0, x1, z1][k] + (off if k < 2 else -off)
        p[1] = g.uniform(1.2, 1.8) if yard else g.uniform(1.0, 1.7)
        return p

    def target(g: np.random.Generator, s: np.ndarray) -> np.ndarray:
        """The sun patch (35%, sunny rooms), a piece of furniture in the same space (65%) or
        any point of it."""
        si = max(architecture.space_of(layout, s), 0)
        x0, z0, x1, z1 = spaces[si]["rect"]
        near = [
            np.asarray(p["transform"])[:3, 3]
            for p in f.pieces
            if p["kind"] not in ("pendant", "led", "rug")
            and architecture.space_of(layout, np.asarray(p["transform"])[:3, 3]) == si
        ]
        if patch and si == 0 and g.random() < 0.35:  # the sun patch: sharp-edged sun patterns
            return patch[int(g.integers(len(patch)))] + [g.normal(0, 0.3), 0, g.normal(0, 0.3)]
        if near and g.random() < 0.65:
            c = near[int(g.integers(len(near)))]
            return c + [g.normal(0, 0.2), g.uniform(0.2, 0.8), g.normal(0, 0.2)]
        y = g.uniform(0.5, 4.0) if yard else g.uniform(0.3, 1.6)
        return np.array([g.uniform(x0 + 0.2, x1 - 0.2), y, g.uniform(z0 + 0.2, z1 - 0.2)])

    shot = animate(
        rng,
        inside=lambda p: camera_clear(desc, p),
        sample_point=start,
        sample_target=target,
        n_frames=n_frames,
    )
    cams = shot["frames"]
    movers = []
    if rng.random() < 0.5:
        m = _mover(rng, desc, f, cams)
        if m is not None:
            movers.append(m)
    desc.update(
        {
            "movers": movers,
            "cameras": [c.as_dict() for c in cams],
            "shots": shot["shots"],
            "cuts": shot["cuts"],
        }
    )
    return desc


# ---------------------------------------------------------------------------------------------
# Locked-off shots (issue 24)

# A locked-off sequence renders one reference, for frame 0, and every frame uses it (the true
# image is constant): it gets this many times the reference spp. Both back ends read it.
LOCKED_OFF_REFERENCE_SCALE = 4


def locked_off(desc: dict) -> dict:
    """The description with every frame given the first frame's camera and object poses, no
    cuts and one shot: the true image is constant, so frame-to-frame change in a denoised
    output is flicker (issue 24's stability measure). `desc` itself is left as it was."""
    n = len(desc["cameras"])
    out = dict(desc)
    out["cameras"] = [desc["cameras"][0]] * n
    out["movers"] = [{**m, "frames": [m["frames"][0]] * n} for m in desc["movers"]]
    out["cuts"], out["shots"] = [], desc["shots"][:1]
    return out


def summary(desc: dict) -> dict:
    """Short, human-readable digest of a description for the manifest."""
    layout = desc["layout"]
    kinds: dict[str, int] = {}
    for p in desc["pieces"]:
        kinds[p["kind"]] = kinds.get(p["kind"], 0) + 1
    lamps = [p for p in desc["pieces"] if "light" in p]
    return {
        "layout": layout["kind"],
        "spaces": [s["kind"] for s in layout["spaces"]],
        "windows": sum(o["kind"] == "window" for o in layout["openings"]),
        "blinds": sum(bool(o.get("blind")) for o in layout["openings"]),
        "doors": sum(o["kind"] == "door" for o in layout["openings"]),
        "lighting": desc["lighting"],
        "sun": "sun" in desc["environment"],
        "lights_on": sum(p["light"]["on"] for p in lamps),
        "pieces": kinds,
        "movers": [m["kind"] for m in desc["movers"]],
        "materials": len(desc["materials"]),
        "shots": desc["shots"],
    }


# ---------------------------------------------------------------------------------------------
# Mitsuba


def _emitter_rgb(color: list[float], scale: float) -> dict:
    return {"type": "rgb", "value": (np.asarray(color) * scale).tolist()}


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
