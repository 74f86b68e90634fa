"""The random parts of a training-corpus scene (scenes/corpus_shots.py): surfaces, stages (their
geometry, lights, environment and camera anchors), props and thin geometry, each drawn as a
JSON-able dict that scenes/corpus_scene.py builds in Blender from zoo_parts' blocks. Pure numpy;
every size is metres, a stage's props scale with it (a still life is a quarter of a room).
"""

from __future__ import annotations

import numpy as np

HDRIS = ("city", "courtyard", "forest", "interior", "night", "studio", "sunrise", "sunset")
OUTDOOR_HDRIS = ("city", "courtyard", "forest", "sunrise", "sunset")
PHOTOS = ("brick", "grass", "gravel", "page", "text", "astronaut", "coffee", "chelsea")
POSTERS = ("astronaut", "coffee", "chelsea", "page", "text")


def rounded(x) -> float | list[float]:
    """Rounded for the manifest; the builder reads the stored values, so what is stored is what
    is rendered."""
    if np.ndim(x):
        return [round(float(v), 4) for v in np.ravel(x)]
    return round(float(x), 4)


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return rounded(rng.uniform(lo, hi))


def pick(rng: np.random.Generator, options, p=None) -> str:
    return str(options[int(rng.choice(len(options), p=p))])


# ---------------------------------------------------------------------------------------------
# Surfaces: JSON-able material descriptions corpus_scene turns into Blender materials


def _rgb(rng, lo=0.05, hi=0.85) -> list[float]:
    return rounded(rng.uniform(lo, hi, 3))


def surface(rng: np.random.Generator, role: str) -> dict:
    """A material for a role: wall, floor, ground, facade, cloth, prop (any textured or glossy
    one), glossy (metal, glass, polished)."""
    if role == "wall":
        kind = pick(rng, ("plain", "brick", "photo", "fabric", "checker"),
                     (0.35, 0.25, 0.15, 0.15, 0.10))
    elif role == "floor":
        kind = pick(rng, ("photo", "checker", "polished", "wood"), (0.35, 0.25, 0.2, 0.2))
    elif role == "ground":
        return {"kind": "photo", "photo": pick(rng, ("grass", "gravel", "brick")),
                "scale": _u(rng, 1.0, 3.0), "tint": _rgb(rng, 0.25, 0.75),
                "roughness": _u(rng, 0.6, 0.9), "bump": _u(rng, 0.1, 0.4)}
    elif role == "facade":
        kind = pick(rng, ("photo", "brick", "plain"), (0.45, 0.4, 0.15))
    elif role == "cloth":
        kind = pick(rng, ("fabric", "checker", "noise"), (0.6, 0.2, 0.2))
    elif role == "glossy":
        kind = pick(rng, ("metal", "glass", "polished"), (0.45, 0.3, 0.25))
    else:
        kind = pick(rng, ("plain", "metal", "glass", "photo", "fabric", "brick", "checker",
                           "noise", "wood", "polished"),
                     (0.14, 0.14, 0.08, 0.14, 0.1, 0.08, 0.08, 0.08, 0.08, 0.08))
    if kind == "plain":
        return {"kind": "plain", "rgb": _rgb(rng), "roughness": _u(rng, 0.3, 0.95)}
    if kind == "polished":
        return {"kind": "plain", "rgb": _rgb(rng, 0.02, 0.6), "roughness": _u(rng, 0.02, 0.2)}
    if kind == "metal":
        return {"kind": "metal", "rgb": _rgb(rng, 0.5, 0.98), "roughness": _u(rng, 0.02, 0.4)}
    if kind == "glass":
        rough = rng.uniform(0.05, 0.3) if rng.random() < 0.33 else 0.0
        return {"kind": "glass", "roughness": rounded(rough)}
    if kind == "photo":
        photo = pick(rng, ("brick", "gravel") if role in ("facade", "wall") else PHOTOS)
        return {"kind": "photo", "photo": photo, "scale": _u(rng, 0.8, 4.0),
                "tint": _rgb(rng, 0.4, 1.0), "roughness": _u(rng, 0.3, 0.9),
                "bump": rounded(rng.choice((0.0, rng.uniform(0.1, 0.5))))}
    if kind == "fabric":  # weave period 4-30 mm: a few pixels at the shots' distances
        return {"kind": "fabric", "rgb": _rgb(rng), "period": _u(rng, 0.004, 0.03)}
    if kind == "brick":
        return {"kind": "brick", "rgb": _rgb(rng, 0.25, 0.8), "brick_m": _u(rng, 0.06, 0.26)}
    if kind == "checker":  # tiles 1-15 cm
        return {"kind": "checker", "rgb": _rgb(rng), "rgb2": _rgb(rng, 0.02, 0.4),
                "scale": rounded(1.0 / rng.uniform(0.01, 0.15)), "roughness": _u(rng, 0.1, 0.8)}
    if kind == "noise":  # grain 0.5-3 cm
        return {"kind": "noise", "rgb": _rgb(rng), "scale": rounded(1.0 / rng.uniform(0.005, 0.03)),
                "roughness": _u(rng, 0.3, 0.9)}
    return {"kind": "wood", "rgb": _rgb(rng, 0.3, 0.8), "scale": _u(rng, 3.0, 12.0),
            "roughness": _u(rng, 0.15, 0.6)}


# ---------------------------------------------------------------------------------------------
# Environments and stages: each returns the stage's geometry, lights and camera anchors


def _environment(rng, outdoor: bool, dim: bool = False, sun_azimuth: float | None = None) -> dict:
    if dim:
        return {"kind": "hdri", "name": pick(rng, ("interior", "night", "studio")),
                "strength": _u(rng, 0.03, 0.15), "yaw": _u(rng, 0, 360)}
    if rng.random() < 0.55:
        az = rng.uniform(0, 360) if sun_azimuth is None else sun_azimuth
        return {"kind": "sky", "elevation": _u(rng, 6, 60), "azimuth": rounded(az),
                "strength": _u(rng, 0.2, 0.4), "sun": _u(rng, 2.5, 5.0)}
    names = OUTDOOR_HDRIS if outdoor else HDRIS
    return {"kind": "hdri", "name": pick(rng, names), "strength": _u(rng, 0.5, 1.6),
            "yaw": _u(rng, 0, 360)}


def _anchor(eye, target, fov) -> dict:
    return {"eye": rounded(eye), "target": rounded(target), "fov": rounded(fov)}


def _interior(rng) -> dict:
    w, d, h = rng.uniform(4.0, 9.0), rng.uniform(5.5, 10.0), rng.uniform(2.6, 3.4)
    walls = rng.choice(["north", "east", "west"], size=int(rng.integers(1, 3)), replace=False)
    windows = [{"wall": str(wall), "center": _u(rng, 0.3, 0.7),
                "width": _u(rng, 1.0, 2.4), "z0": _u(rng, 0.3, 1.0),
                "z1": rounded(h - rng.uniform(0.3, 0.7))} for wall in walls]
    az = {"north": 90.0, "east": 0.0, "west": 180.0}[str(walls[0])] + rng.uniform(-35, 35)
    shell = [{"kind": "room", "size": rounded((w, d, h)), "y0": -1.5, "windows": windows,
              "wall": surface(rng, "wall"), "floor": surface(rng, "floor"),
              "ceiling": {"kind": "plain", "rgb": _rgb(rng, 0.6, 0.9), "roughness": 0.9}}]
    lights = [{"kind": "area", "location": rounded((rng.uniform(-w / 3, w / 3),
                                                rng.uniform(0.5, d - 3), h - 0.05)),
               "size": _u(rng, 0.5, 1.5), "watts": _u(rng, 60, 300)}
              for _ in range(int(rng.choice((0, 1, 1, 2))))]
    if rng.random() < 0.3:
        lights.append({"kind": "point", "location": rounded((rng.uniform(-w / 3, w / 3),
                                                         rng.uniform(1.0, d - 3), h - 0.6)),
                       "watts": _u(rng, 20, 100), "radius": _u(rng, 0.01, 0.05)})
    eye = (rng.uniform(-w / 4, w / 4), -1.5 + rng.uniform(0.5, 1.0), rng.uniform(1.2, 1.7))
    target = (rng.uniform(-w / 4, w / 4), rng.uniform(2.5, d - 2.5), rng.uniform(0.5, 1.4))
    side = (rng.choice((-1, 1)) * w / 2.8, rng.uniform(0.2, 1.2), rng.uniform(1.3, 1.8))
    return {"shell": shell, "lights": lights, "floor_z": 0.0, "scale": 1.0, "props": (3, 9),
            "environment": _environment(rng, outdoor=False, sun_azimuth=az),
            "anchors": [_anchor(eye, target, rng.uniform(50, 75)),
                        _anchor(side, target, rng.uniform(50, 75))],
            "wall_y": d - 1.5 - 0.02, "half_width": w / 2}


def _exterior(rng) -> dict:
    far = rng.uniform(18.0, 45.0)
    shell = [{"kind": "ground", "material": surface(rng, "ground")},
             {"kind": "facades", "y": rounded(far), "material": surface(rng, "facade"),
              "seed": int(rng.integers(1 << 31))}]
    eye = (rng.uniform(-1, 1), 0.0, rng.uniform(1.2, 1.8))
    target = (rng.uniform(-1.5, 1.5), rng.uniform(4.0, 9.0), rng.uniform(0.6, 2.0))
    side = (rng.choice((-1, 1)) * rng.uniform(2.5, 4.5), rng.uniform(1.0, 3.0),
            rng.uniform(1.3, 2.2))
    return {"shell": shell, "lights": [], "floor_z": 0.0, "scale": 1.5, "props": (5, 12),
            "environment": _environment(rng, outdoor=True),
            "anchors": [_anchor(eye, target, rng.uniform(45, 75)),
                        _anchor(side, target, rng.uniform(45, 75))],
            "wall_y": None, "half_width": 6.0}


def _studio(rng) -> dict:
    w, d, h = rng.uniform(5.0, 7.0), rng.uniform(6.0, 8.0), rng.uniform(2.8, 3.4)
    dark = {"kind": "plain", "rgb": _rgb(rng, 0.04, 0.16), "roughness": _u(rng, 0.5, 0.9)}
    floor = {"kind": "plain", "rgb": _rgb(rng, 0.03, 0.12), "roughness": _u(rng, 0.03, 0.15)}
    shell = [{"kind": "room", "size": rounded((w, d, h)), "y0": -2.0, "windows": [], "wall": dark,
              "floor": floor, "ceiling": dark},
             {"kind": "poster", "photo": pick(rng, POSTERS),
              "corner": rounded((-w / 2 + 0.5, d - 2.05, 0.3)), "width": rounded(w - 1.0),
              "height": 2.2}]
    bulb = (rng.uniform(-1.0, 1.0), rng.uniform(1.5, 3.0), rng.uniform(0.8, 1.5))
    lights = [{"kind": "point", "location": rounded(bulb), "watts": _u(rng, 40, 120),
               "radius": _u(rng, 0.003, 0.01)}]
    if rng.random() < 0.5:
        lights.append({"kind": "area", "location": rounded((rng.uniform(-2, 2), 1.0, h - 0.05)),
                       "size": _u(rng, 0.6, 1.2), "watts": _u(rng, 30, 100)})
    eye = (rng.uniform(-0.8, 0.8), -1.4 + rng.uniform(0.0, 0.6), rng.uniform(1.0, 1.5))
    target = (rng.uniform(-0.5, 0.5), rng.uniform(2.2, 3.2), rng.uniform(0.4, 0.9))
    side = (rng.choice((-1, 1)) * w / 2.8, rng.uniform(-0.5, 0.8), rng.uniform(0.5, 1.3))
    return {"shell": shell, "lights": lights, "floor_z": 0.0, "scale": 0.8, "props": (3, 8),
            "environment": _environment(rng, outdoor=False, dim=True),
            "anchors": [_anchor(eye, target, rng.uniform(45, 65)),
                        _anchor(side, target, rng.uniform(45, 65))],
            "wall_y": None, "half_width": w / 2, "glass_under_bulb": rounded(bulb)}


def _stilllife(rng) -> dict:
    tw, td, top = rng.uniform(0.5, 0.8), rng.uniform(0.35, 0.5), 0.74
    shell = [{"kind": "ground", "material": surface(rng, "floor")},
             {"kind": "box", "lo": rounded((-tw, -td, top - 0.04)), "hi": rounded((tw, td, top)),
              "material": surface(rng, "cloth")}]
    if rng.random() < 0.6:
        shell.append({"kind": "box", "lo": [-3.0, 1.2, 0.0], "hi": [3.0, 1.3, 2.6],
                      "material": surface(rng, "wall")})
    lights = [{"kind": "area", "location": rounded((rng.uniform(-1.2, 1.2), rng.uniform(-1.2, -0.4),
                                               rng.uniform(1.4, 2.0))),
               "size": _u(rng, 0.5, 1.0), "watts": _u(rng, 40, 130),
               "target": rounded((0.0, 0.0, top))}]
    eye = (rng.uniform(-0.3, 0.3), -rng.uniform(0.6, 1.1), rng.uniform(0.95, 1.3))
    target = (rng.uniform(-0.1, 0.1), rng.uniform(-0.05, 0.15), top + 0.04)
    side = (rng.choice((-1, 1)) * rng.uniform(0.5, 0.8), -rng.uniform(0.3, 0.6),
            rng.uniform(0.9, 1.1))
    env = _environment(rng, outdoor=False)
    if env["kind"] == "sky":  # a still life is lit indoors
        env = {"kind": "hdri", "name": pick(rng, HDRIS), "strength": _u(rng, 0.5, 1.2),
               "yaw": _u(rng, 0, 360)}
    return {"shell": shell, "lights": lights, "floor_z": top, "scale": 0.25, "props": (4, 10),
            "environment": env,
            "anchors": [_anchor(eye, target, rng.uniform(35, 50)),
                        _anchor(side, target, rng.uniform(35, 50))],
            "wall_y": None, "half_width": tw, "table": (tw, td)}


STAGE_BUILDERS = {"interior": _interior, "exterior": _exterior, "studio": _studio,
                  "stilllife": _stilllife}


# ---------------------------------------------------------------------------------------------
# Props: placed around the first anchor's target, on the stage's floor (a still life: its table)

PROPS = {
    "interior": ("ball", "head", "wire", "crate", "column", "foliage", "sign", "shelf", "leds",
                 "roller", "tree"),
    "exterior": ("ball", "head", "crate", "column", "foliage", "foliage", "sign", "tree",
                 "roller", "leds"),
    "studio": ("ball", "head", "wire", "wire", "crate", "leds", "roller", "column"),
    "stilllife": ("ball", "head", "wire", "crate", "foliage", "page", "page", "comb", "pencils",
                  "leds", "roller"),
}
THIN = {"interior": ("bars", "railing", "fence"), "exterior": ("fence", "railing", "cables",
                                                                "trees", "bars"),
        "studio": ("bars",), "stilllife": ()}
THIN_P = {"interior": 0.35, "exterior": 0.75, "studio": 0.5, "stilllife": 0.0}
MOVING_PROPS = ("roller",)  # a locked-off shot keeps a constant image: none of these, no spin


def stage_spot(rng, st: dict, eye, target) -> list[float]:
    """A point on the stage's floor near the target, clear of the camera and the walls."""
    if "table" in st:
        tw, td = st["table"]
        return rounded((rng.uniform(-0.85, 0.85) * tw, rng.uniform(-0.85, 0.85) * td,
                        st["floor_z"]))
    reach = max(min(2.0, target[1] - eye[1] - 1.5), 0.3)
    x = target[0] + rng.uniform(-2.5, 2.5) * st["scale"]
    y = target[1] + rng.uniform(-reach, reach)
    x = float(np.clip(x, -st["half_width"] + 0.4, st["half_width"] - 0.4))
    if st["wall_y"] is not None:
        y = min(y, st["wall_y"] - 0.4)
    return rounded((x, y, st["floor_z"]))


def _spin(rng, moving: bool, p: float) -> float:
    if not moving or rng.random() >= p:
        return 0.0
    return rounded(rng.choice((-1, 1)) * rng.uniform(1.5, 6.0))


def draw_prop(rng, kind: str, p: list[float], s: float, moving: bool) -> dict:
    x, y, z = p
    seed = int(rng.integers(1 << 31))
    if kind == "ball":
        r = s * rng.uniform(0.12, 0.45)
        mat = surface(rng, "glossy" if rng.random() < 0.6 else "prop")
        return {"kind": "ball", "center": rounded((x, y, z + r)), "radius": rounded(r),
                "material": mat}
    if kind == "head":
        size, lift = s * rng.uniform(0.35, 0.8), s * rng.uniform(0.3, 1.0) * (rng.random() < 0.5)
        return {"kind": "head", "center": rounded((x, y, z + lift + 0.45 * size)),
                "size": rounded(size),
                "yaw": _u(rng, 0, 360), "plinth": rounded(lift),
                "material": surface(rng, "glossy" if rng.random() < 0.5 else "prop"),
                "plinth_material": surface(rng, "prop"), "spin": _spin(rng, moving, 0.4)}
    if kind == "wire":
        r = s * rng.uniform(0.25, 0.55)
        return {"kind": "wire", "shape": pick(rng, ("ico", "torus")), "radius": rounded(r),
                "center": rounded((x, y, z + r + s * rng.uniform(0.2, 0.8))),
                "thickness": rounded(s * rng.uniform(0.006, 0.015)),
                "tilt": rounded(rng.uniform(0, 1.5, 3)), "axis": int(rng.integers(3)),
                "material": surface(rng, "glossy"), "spin": _spin(rng, moving, 0.8)}
    if kind == "crate":
        half = s * rng.uniform(0.12, 0.45, 3)
        return {"kind": "box", "lo": rounded((x - half[0], y - half[1], z)),
                "hi": rounded((x + half[0], y + half[1], z + 2 * half[2])),
                "material": surface(rng, "prop")}
    if kind == "column":
        height = s * rng.uniform(0.8, 2.6)
        return {"kind": "column", "center": rounded((x, y, z + height / 2)),
                "height": rounded(height),
                "radius": rounded(s * rng.uniform(0.04, 0.2)), "material": surface(rng, "prop")}
    if kind == "foliage":
        r = s * rng.uniform(0.25, 0.8)
        return {"kind": "foliage", "center": rounded((x, y, z + r * rng.uniform(0.6, 1.4))),
                "radius": rounded((r, r * rng.uniform(0.7, 1.3), r * rng.uniform(0.6, 1.2))),
                "count": int(rng.uniform(800, 5000)), "leaf": rounded(s * rng.uniform(0.04, 0.1)),
                "rgb": rounded(rng.uniform((0.04, 0.15, 0.02), (0.2, 0.4, 0.1))),
                "seed": seed}
    if kind == "sign":
        w = s * rng.uniform(0.4, 1.2)
        h, bottom = w * rng.uniform(0.4, 1.0), s * rng.uniform(0.5, 1.5)
        return {"kind": "sign", "corner": rounded((x - w / 2, y, z + bottom)), "width": rounded(w),
                "height": rounded(h), "photo": pick(rng, ("text", "page", "text", *POSTERS)),
                "post": rounded(bottom), "material": surface(rng, "prop")}
    if kind == "shelf":
        return {"kind": "shelf", "corner": rounded((x - s, y, z)),
                "width": rounded(s * rng.uniform(1.0, 3.0)),
                "levels": int(rng.integers(2, 5)), "material": surface(rng, "prop"), "seed": seed}
    if kind == "leds":
        points = [_spot_near(rng, p, s) for _ in range(int(rng.integers(2, 7)))]
        return {"kind": "leds", "points": points,
                "radius": rounded(s * rng.uniform(0.006, 0.015)), "rgb": _rgb(rng, 0.2, 1.0),
                "strength": _u(rng, 200, 3000)}
    if kind == "roller":
        r, angle = s * rng.uniform(0.08, 0.25), rng.uniform(0, 2 * np.pi)
        step = s * rng.uniform(0.02, 0.07) * np.array((np.cos(angle), np.sin(angle), 0.0))
        return {"kind": "roller", "center": rounded((x, y, z + r)), "radius": rounded(r),
                "step": rounded(step), "material": surface(rng, "prop")}
    if kind == "tree":
        return {"kind": "tree", "origin": rounded(p), "length": rounded(s * rng.uniform(0.6, 1.6)),
                "depth": int(rng.integers(4, 6)), "radius": rounded(s * rng.uniform(0.008, 0.025)),
                "material": {"kind": "plain", "rgb": _rgb(rng, 0.1, 0.35), "roughness": 0.9},
                "seed": seed}
    if kind == "page":  # printed text lying flat: a page or a card on the table
        w = s * rng.uniform(0.6, 1.6)
        return {"kind": "page", "corner": rounded((x - w / 2, y - w / 4, z + 0.001)),
                "width": rounded(w),
                "depth": rounded(w * rng.uniform(0.4, 0.75)), "turn": _u(rng, -0.4, 0.4),
                "photo": pick(rng, ("text", "page"))}
    if kind == "comb":  # teeth 1-2 mm wide, 2-4 mm apart, standing on edge
        return {"kind": "comb", "corner": rounded((x, y, z)), "teeth": int(rng.integers(30, 70)),
                "tooth": _u(rng, 0.001, 0.002), "gap": _u(rng, 0.002, 0.004),
                "height": _u(rng, 0.04, 0.09), "material": surface(rng, "prop")}
    if kind == "pencils":
        return {"kind": "pencils", "base": rounded(p), "count": int(rng.integers(8, 17)),
                "length": _u(rng, 0.12, 0.2), "radius": 0.0035,
                "rgb": _rgb(rng, 0.3, 0.95), "seed": seed}
    raise ValueError(f"no prop {kind!r}")


def _spot_near(rng, p, s) -> list[float]:
    return rounded((p[0] + rng.uniform(-1, 1) * s, p[1] + rng.uniform(-1, 1) * s, p[2] + 0.001))


def draw_thin(rng, kind: str, st: dict, eye, target) -> dict:
    """Thin geometry between the camera and the background: pickets, balusters, bars, cables,
    bare trees (1-12 mm: a pixel or less at the shot's distance)."""
    span = min(st["half_width"], rng.uniform(3.0, 9.0))
    y = eye[1] + rng.uniform(1.2, max(target[1] - eye[1], 1.5) + 1.0)
    if st["wall_y"] is not None:
        y = min(y, st["wall_y"] - 0.3)
    material = surface(rng, "glossy" if rng.random() < 0.4 else "prop")
    if kind == "fence":
        return {"kind": "fence", "y": rounded(y), "span": rounded(span),
                "width": _u(rng, 0.02, 0.05),
                "gap": _u(rng, 0.04, 0.1), "height": _u(rng, 0.8, 1.4),
                "material": material}
    if kind in ("railing", "bars"):
        railing = kind == "railing"
        return {"kind": kind, "y": rounded(y),
                "span": rounded(span if railing else rng.uniform(1.5, 3.0)),
                "radius": _u(rng, 0.003, 0.008), "spacing": _u(rng, 0.05, 0.14),
                "height": _u(rng, 0.9, 1.1) if railing else _u(rng, 1.5, 2.5),
                "x": rounded(target[0]), "material": material}
    if kind == "cables":
        return {"kind": "cables", "y": rounded(y + rng.uniform(2, 10)),
                "count": int(rng.integers(2, 6)),
                "z": _u(rng, 3.0, 5.5), "radius": _u(rng, 0.004, 0.008),
                "sag": _u(rng, -0.5, 0.5), "material": {"kind": "plain", "rgb": [0.05] * 3,
                                                               "roughness": 0.4}}
    origins = [rounded((target[0] + rng.uniform(-6, 6), y + rng.uniform(2, 15), 0.0))
               for _ in range(int(rng.integers(1, 4)))]
    return {"kind": "trees", "origins": origins,
            "length": _u(rng, 1.2, 2.0), "depth": 5, "radius": _u(rng, 0.015, 0.03),
            "material": {"kind": "plain", "rgb": _rgb(rng, 0.12, 0.3), "roughness": 0.9},
            "seed": int(rng.integers(1 << 31))}


def posters(rng, st: dict, shell: dict) -> list[dict]:
    """Photos and printed text on the interior's far wall, clear of its windows."""
    w = shell["size"][0]
    blocked = [((win["center"] * w - w / 2) - win["width"] / 2 - 0.2,
                (win["center"] * w - w / 2) + win["width"] / 2 + 0.2)
               for win in shell["windows"] if win["wall"] == "north"]
    out = []
    for _ in range(int(rng.integers(0, 4))):
        pw = rng.uniform(0.5, 1.5)
        x0 = rng.uniform(-w / 2 + 0.2, w / 2 - 0.2 - pw)
        if any(x0 < b and x0 + pw > a for a, b in blocked):
            continue
        blocked.append((x0 - 0.1, x0 + pw + 0.1))
        out.append({"kind": "poster", "photo": pick(rng, POSTERS),
                    "corner": rounded((x0, st["wall_y"], rng.uniform(1.0, 1.6))),
                    "width": rounded(pw),
                    "height": rounded(pw * rng.uniform(0.4, 1.0))})
    return out


def near_foliage(rng, eye, target) -> dict:
    """Leaves 0.6-1.2 m from the lens, to one side: a foreground crossing the frame."""
    e, t = np.asarray(eye), np.asarray(target)
    fwd = (t - e) / np.linalg.norm(t - e)
    right = np.cross(fwd, (0.0, 0.0, 1.0))
    right /= np.linalg.norm(right)
    c = e + fwd * rng.uniform(0.6, 1.2) + right * rng.choice((-1, 1)) * rng.uniform(0.35, 0.7)
    c[2] += rng.uniform(-0.3, 0.1)
    return {"kind": "foliage", "center": rounded(c),
            "radius": rounded((rng.uniform(0.15, 0.3), 0.12,
                                                              rng.uniform(0.2, 0.35))),
            "count": int(rng.integers(600, 1200)), "leaf": _u(rng, 0.05, 0.08),
            "rgb": rounded((0.08, rng.uniform(0.2, 0.35), 0.05)),
            "seed": int(rng.integers(1 << 31)),
            "near": True}
