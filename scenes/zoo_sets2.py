"""The sets of zoo round 2 (scenes/zoo_shots.py): content a reprojected history finds hard.
Thin geometry in front of a distant background (pickets, railings, cables, bare branches, book
spines, comb teeth), wireframe objects that turn, a defocused foreground near the lens, caustics
of a small bright bulb through glass. Each set returns camera anchors {name: (eye, target,
fov)} as zoo_scene's sets do; the camera work (truck, orbit, locked) is the shot's.

Blender's world is z up; sizes are metres. Written from zoo_parts' building blocks only.
"""

from __future__ import annotations

import bpy  # only in the Cycles venv
import numpy as np

from .zoo_parts import (
    Material,
    area,
    box,
    boxes,
    branches,
    glass,
    leaf_material,
    leaves,
    metal,
    photo_material,
    plain,
    point,
    quad,
    rods,
    sphere,
    spin,
    sun,
    wireframe,
    world_hdri,
    world_sky,
)

Anchor = tuple[tuple[float, float, float], tuple[float, float, float], float]


def _emissive(name: str, rgb, strength: float) -> bpy.types.Material:
    return plain(name, (0.8, 0.8, 0.8), 0.5, **{"Emission Color": rgb,
                                              "Emission Strength": strength})


def set_yard(rng, v: dict) -> dict[str, Anchor]:
    """A back yard: a picket fence (or a metal railing) 3 m from the camera, cables strung
    behind it, bare trees, a near post, and house facades 40 m away under sky and sun."""
    elevation = v.get("sun_elevation", 38.0)
    quad("lawn", (-60, -10, 0), (120, 0, 0), (0, 90, 0),
         photo_material("lawn", "grass", 2.0, tint=(0.32, 0.5, 0.18), bump=0.2))
    paint = plain("fence_paint", (0.85, 0.84, 0.8), 0.5)
    if v.get("railing"):
        xs = np.arange(-9.0, 9.0, 0.11)  # balusters 12 mm round, 11 cm apart
        rods("balusters", [((x, 2.6, 0.0), (x, 2.6, 1.0)) for x in xs], 0.006,
             metal("iron", (0.2, 0.2, 0.22), 0.35))
        rods("handrail", [((-9.0, 2.6, 1.0), (9.0, 2.6, 1.0)),
                          ((-9.0, 2.6, 0.1), (9.0, 2.6, 0.1))], 0.02,
             metal("iron_rail", (0.2, 0.2, 0.22), 0.35))
    else:
        xs = np.arange(-9.0, 9.0, 0.12)  # pickets 3.5 cm wide, gaps 8.5 cm
        boxes("pickets", [((x, 3.0, 0.0), (x + 0.035, 3.02, 1.0 + 0.05 * (k % 2)))
                          for k, x in enumerate(xs)], paint)
        boxes("fence_rails", [((-9.0, 3.02, z), (9.0, 3.05, z + 0.06)) for z in (0.2, 0.75)],
              paint)
    cable = plain("cable", (0.05, 0.05, 0.05), 0.4)
    rods("cables", [((-30.0, 9.0 + k, 4.2 + 0.35 * k), (30.0, 11.0 + k, 3.9 + 0.3 * k))
                    for k in range(4)], 0.006, cable)
    bark = plain("bark", (0.22, 0.17, 0.12), 0.9)
    for k, (x, y) in enumerate(((2.0, 7.0), (-3.5, 11.0), (6.0, 15.0))):
        rods(f"tree{k}", branches((x, y, 0.0), 1.6, 5, rng), 0.03 - 0.005 * k, bark)
    box("near_post", (0.7, 1.1, 0.0), (0.76, 1.16, 1.6), plain("post", (0.35, 0.25, 0.15), 0.8))
    brick = photo_material("facades", "brick", 2.0, tint=(0.75, 0.45, 0.32), bump=0.3)
    windows = plain("panes", (0.04, 0.05, 0.06), 0.05)
    x = -45.0
    while x < 45.0:
        w, h = rng.uniform(6, 10), rng.uniform(7, 13)
        box(f"house{int(x)}", (x, 40.0, 0.0), (x + w, 46.0, h), brick)
        boxes(f"windows{int(x)}", [((x + 0.8 + 1.8 * c, 39.98, 1.0 + 2.6 * r),
                                    (x + 1.8 + 1.8 * c, 40.0, 2.4 + 2.6 * r))
                                   for r in range(int(h // 2.6)) for c in range(int(w // 1.8) - 1)],
              windows)
        x += w + 0.3
    world_sky(elevation, v.get("sun_azimuth", 140.0), 0.3)
    sun(elevation, v.get("sun_azimuth", 140.0), 4.0)
    return {"main": ((-0.5, -1.0, 1.15), (-0.5, 30.0, 2.0), 60.0),
            "wide": ((3.0, -2.0, 1.6), (-2.0, 20.0, 2.5), 70.0)}


def set_studio(rng, v: dict) -> dict[str, Anchor]:
    """A dark studio: a rack of thin bars before a far wall, a wireframe icosphere and torus
    turning `spin` degrees a frame, a glass ball and a chrome one under a small bright bulb
    (caustics, fireflies), a few LEDs; a dim environment and one soft panel."""
    w, d, h = 6.0, 7.0, 3.2
    floor = Material("floor").set(**{"Base Color": (0.08, 0.08, 0.09), "Roughness": 0.08}).mat
    walls = plain("walls", (0.12, 0.12, 0.13), 0.8)
    y0 = -2.0  # the room runs y0..d: the camera (y = -0.4) stands inside it
    for name, c, u, vv in (("floor", (0, y0, 0), (w, 0, 0), (0, d - y0, 0)),
                           ("ceiling", (0, y0, h), (0, d - y0, 0), (w, 0, 0)),
                           ("wall_w", (0, y0, 0), (0, d - y0, 0), (0, 0, h)),
                           ("wall_e", (w, y0, 0), (0, 0, h), (0, d - y0, 0)),
                           ("wall_n", (0, d, 0), (w, 0, 0), (0, 0, h)),
                           ("wall_s", (0, y0, 0), (0, 0, h), (w, 0, 0))):
        quad(name, c, u, vv, floor if name == "floor" else walls)
    quad("backdrop", (0.5, d - 0.05, 0.3), (5.0, 0, 0), (0, 0, 2.2),
         photo_material("backdrop", "astronaut", 1.0, uv=True, roughness=0.6))
    rods("bar_rack", [((x, 4.2, 0.0), (x, 4.2, 2.2)) for x in np.arange(0.6, 5.4, 0.09)],
         0.005, metal("steel_bars", (0.75, 0.75, 0.78), 0.25))
    turn = float(v.get("spin", 4.0))
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2, radius=0.5, location=(2.3, 2.7, 0.9))
    ico = bpy.context.active_object
    ico.name = "wire_ico"
    ico.data.materials.append(metal("chrome_wire", (0.9, 0.9, 0.92), 0.15))
    spin(wireframe(ico, 0.012), turn)
    bpy.ops.mesh.primitive_torus_add(major_radius=0.35, minor_radius=0.1,
                                     location=(3.9, 3.0, 0.75), rotation=(1.2, 0.0, 0.3))
    torus = bpy.context.active_object
    torus.name = "wire_torus"
    torus.data.materials.append(metal("copper_wire", (0.95, 0.6, 0.45), 0.2))
    spin(wireframe(torus, 0.01), -1.5 * turn, axis=0)
    sphere("glass_ball", (3.1, 1.9, 0.25), 0.25, glass("glass"))
    sphere("chrome_ball", (1.6, 1.7, 0.15), 0.15, metal("chrome", (0.92, 0.92, 0.92), 0.03))
    point("bulb", (3.2, 1.8, 1.3), 80.0, 0.005)
    for k, (x, y) in enumerate(((1.0, 3.3), (4.6, 2.2), (2.8, 3.6))):
        sphere(f"led{k}", (x, y, 0.012), 0.012, _emissive(f"led{k}", (1.0, 0.3 + 0.3 * k, 0.2),
                                                          400.0))
    world_hdri(v.get("environment", "interior"), 0.08)
    area("panel", (1.0, 1.0, h - 0.05), (2.5, 2.5, 0.0), 1.0, 60.0)
    return {"main": ((3.0, -0.4, 1.35), (3.0, 2.6, 0.65), 55.0),
            "low": ((5.2, 0.4, 0.6), (2.5, 2.8, 0.6), 50.0)}


_SPINE_COLOURS = ((0.55, 0.1, 0.08), (0.1, 0.2, 0.45), (0.12, 0.35, 0.15), (0.7, 0.6, 0.4),
                  (0.2, 0.15, 0.1), (0.75, 0.72, 0.65), (0.4, 0.1, 0.35), (0.05, 0.05, 0.05))


def set_library(rng, v: dict) -> dict[str, Anchor]:
    """A long library wall of shelves full of thin book spines 3.6 m from the camera, a table
    of combs or pencil cups at 2 m, potted plants 0.5-0.7 m from the lens (defocused by the
    shot's f/2), photo posters, ceiling panels and a window's environment."""
    w, d, h = 12.0, 4.0, 2.9
    wood = Material("shelf_wood")
    wood.set(**{"Base Color": wood.procedural("wave", 5.0, wave_type="RINGS", Distortion=5.0,
                                             Detail=5.0), "Roughness": 0.45})
    plaster = plain("plaster", (0.75, 0.73, 0.7), 0.85)
    for name, c, u, vv, m in (
            ("floor", (0, -2, 0), (w, 0, 0), (0, d + 2, 0),
             photo_material("boards", "gravel", 0.8, tint=(0.45, 0.32, 0.2), roughness=0.35)),
            ("ceiling", (0, -2, h), (0, d + 2, 0), (w, 0, 0), plaster),
            ("wall_n", (0, d, 0), (w, 0, 0), (0, 0, h), plaster)):
        quad(name, c, u, vv, m)
    shelves = [((0.2, 3.55, z), (w - 0.2, 3.95, z + 0.025)) for z in np.arange(0.1, 2.4, 0.42)]
    boxes("shelves", shelves, wood.mat)
    spines: list[list] = [[] for _ in _SPINE_COLOURS]
    for z in np.arange(0.125, 2.2, 0.42):
        x = 0.25
        while x < w - 0.3:
            thick = rng.uniform(0.012, 0.035)
            if rng.random() < 0.04:  # a gap, a leaning book's space
                x += rng.uniform(0.05, 0.15)
                continue
            spines[int(rng.integers(len(spines)))].append(
                ((x, rng.uniform(3.6, 3.68), z), (x + thick, 3.9, z + rng.uniform(0.24, 0.36))))
            x += thick + 0.001
    for k, group in enumerate(spines):
        boxes(f"spines{k}", group, plain(f"spine{k}", _SPINE_COLOURS[k], 0.55))
    box("table", (1.5, 1.8, 0.72), (10.5, 2.4, 0.76), wood.mat)
    teeth = []
    if v.get("combs"):  # combs standing on edge: teeth 1.5 mm wide, 3 mm apart
        for cx in np.arange(1.8, 10.2, 0.45):
            teeth += [((cx + k * 0.003, 2.1, 0.76), (cx + k * 0.003 + 0.0015, 2.104, 0.86))
                      for k in range(60)]
            teeth.append(((cx, 2.1, 0.86), (cx + 0.18, 2.104, 0.89)))
        boxes("combs", teeth, plain("horn", (0.15, 0.1, 0.06), 0.3))
    else:  # pencil cups of thin rods
        pencils = []
        for cx in np.arange(1.9, 10.2, 0.6):
            for _ in range(14):
                top = np.array((cx, 2.1, 0.95)) + rng.normal(0, 0.025, 3)
                pencils.append(((cx, 2.1, 0.76), tuple(top)))
        rods("pencils", pencils, 0.0035, plain("pencil", (0.9, 0.7, 0.1), 0.5))
    for k, name in enumerate(("coffee", "chelsea", "page")):
        quad(f"poster{k}", (2.0 + 3.5 * k, 3.52, 2.45), (0.8, 0, 0), (0, 0, 0.4),
             photo_material(f"poster{k}", name, 1.0, uv=True, roughness=0.4))
    eye_x = 6.0
    for k, dx in enumerate((-2.4, -1.2, 0.2, 1.3, 2.5)):  # plants along the truck, near the lens
        c = (eye_x + dx, 0.55 + 0.1 * (k % 2), 1.05 + 0.1 * (k % 3))
        leaves(f"plant{k}", c, (0.25, 0.12, 0.3), 900, 0.07, rng,
               leaf_material(f"plant_leaf{k}", (0.08, 0.25 + 0.03 * k, 0.05)))
    for k in range(3):
        area(f"ceiling_panel{k}", (2.0 + 4.0 * k, 1.5, h - 0.05), (2.0 + 4.0 * k, 2.5, 0.0),
             1.2, 250.0)
    world_hdri(v.get("environment", "courtyard"), 0.8)
    return {"main": ((eye_x, 0.0, 1.3), (eye_x, 3.6, 1.05), 60.0),
            "side": ((1.0, 0.2, 1.5), (6.0, 3.6, 1.0), 65.0)}


SETS = {"yard": set_yard, "studio": set_studio, "library": set_library}
